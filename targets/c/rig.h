/* Frame sets of a camera rig (PROTOCOL.md 4.2.1): collects the frames of one set for a
 * target that answers one ESTIMATE per set (CAP_FRAME_SETS). C99, libc only. */
#ifndef RIG_H
#define RIG_H

#include "hilp.h"

typedef struct {
    int open;            /* a set is being collected */
    uint64_t set_id;     /* frame_id of its camera 0: the ESTIMATE's frame_id */
    unsigned count;      /* its camera_count */
    uint32_t mask;       /* bit k: camera k came */
    int64_t sim_time;    /* ts1 of its first frame: every frame of the set carries it */
    int64_t first_mono_ns; /* CLOCK_MONOTONIC when its first frame came: the give-up deadline counts from here */
    int64_t last_t_rx;   /* receipt of its last frame to arrive (target clock): the ESTIMATE's t_rx */
    uint32_t vehicle_id;
    int dark;            /* some camera's centre is dark */
    int done_any;        /* a set was answered or given up ... */
    uint64_t done_last;  /* ... and this is the newest one's id */
} hil_rig;

enum { RIG_TOO_LATE, RIG_ADDED, RIG_COMPLETE, RIG_CONTRADICTS };

/* 1 when a set is open and `set_id` is a later one: the caller answers the open set
 * (given up) before adding the frame. */
int rig_later(const hil_rig *r, uint64_t set_id);

/* Adds camera f->camera_index of the set `set_id` (a frame whose header is h), received
 * at t_rx (target clock) and mono_ns (CLOCK_MONOTONIC), its centre dark or not.
 * Returns RIG_TOO_LATE (its set was answered already: drop it), RIG_ADDED, RIG_COMPLETE
 * (answer the set now), or RIG_CONTRADICTS (another camera_count, a camera twice, another
 * sim_time: e names the byte offset, 70, 69 or 32; the frame is dropped). */
int rig_add(hil_rig *r, uint64_t set_id, const hilp_header *h, const hilp_frame *f, int64_t t_rx, int64_t mono_ns,
            int dark, hilp_err *e);

/* 1 when every camera of the open set came. */
int rig_complete(const hil_rig *r);

/* The open set has been answered: nothing of it is taken any more. */
void rig_close(hil_rig *r);

/* The cameras of the open set that did not come, as text ("1, 3"), into out. */
void rig_missing(const hil_rig *r, char *out, size_t n);

#endif

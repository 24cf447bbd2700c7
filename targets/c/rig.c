/* Frame sets of a camera rig (PROTOCOL.md 4.2.1); see rig.h. */
#include "rig.h"

#include <stdio.h>
#include <string.h>

static uint32_t all_cameras(unsigned count) { return count >= 32 ? 0xFFFFFFFFu : (1u << count) - 1u; }

int rig_later(const hil_rig *r, uint64_t set_id) { return r->open && set_id > r->set_id; }

int rig_complete(const hil_rig *r) { return r->open && r->mask == all_cameras(r->count); }

void rig_close(hil_rig *r) {
    r->done_any = 1;
    r->done_last = r->set_id;
    r->open = 0;
}

static int contradicts(hilp_err *e, uint32_t offset, const char *text) {
    e->code = HILP_E_MALFORMED;
    e->offset = offset;
    snprintf(e->text, sizeof e->text, "%s (at byte offset %lu)", text, (unsigned long)offset);
    return RIG_CONTRADICTS;
}

int rig_add(hil_rig *r, uint64_t set_id, const hilp_header *h, const hilp_frame *f, int64_t t_rx, int64_t mono_ns,
            int dark, hilp_err *e) {
    unsigned count = f->camera_count ? f->camera_count : 1u;
    char text[160];
    if ((r->done_any && set_id <= r->done_last) || (r->open && set_id < r->set_id)) return RIG_TOO_LATE;
    if (!r->open) {
        memset(r, 0, offsetof(hil_rig, done_any));
        r->open = 1;
        r->set_id = set_id;
        r->count = count;
        r->sim_time = h->ts[1];
        r->first_mono_ns = mono_ns;
        r->vehicle_id = h->vehicle_id;
    }
    if (count != r->count) {
        snprintf(text, sizeof text, "camera_count %u in set %llu, whose first frame said %u", (unsigned)f->camera_count,
                 (unsigned long long)set_id, r->count);
        return contradicts(e, 70, text);
    }
    if (r->mask & (1u << f->camera_index)) {
        snprintf(text, sizeof text, "camera %u of set %llu came twice (frame_id %llu)", (unsigned)f->camera_index,
                 (unsigned long long)set_id, (unsigned long long)h->frame_id);
        return contradicts(e, 69, text);
    }
    if (h->ts[1] != r->sim_time) {
        snprintf(text, sizeof text, "sim_time %lld ns in set %llu, whose first frame said %lld: one capture instant "
                 "has one sim_time", (long long)h->ts[1], (unsigned long long)set_id, (long long)r->sim_time);
        return contradicts(e, 32, text);
    }
    r->mask |= 1u << f->camera_index;
    r->last_t_rx = t_rx;
    r->dark |= dark;
    return rig_complete(r) ? RIG_COMPLETE : RIG_ADDED;
}

void rig_missing(const hil_rig *r, char *out, size_t n) {
    size_t used = 0;
    out[0] = '\0';
    for (unsigned k = 0; k < r->count && used < n; k++)
        if (!(r->mask & (1u << k)))
            used += (size_t)snprintf(out + used, n - used, "%s%u", used ? ", " : "", k);
}

/* A reference AI target in C99 (libc and POSIX sockets only), written from
 * PROTOCOL.md: HELLO, FRAME -> ESTIMATE, clock sync, heartbeats, COMMAND, BYE and
 * the bad-message rules of section 8, over the local transport (the socket in
 * HIL_LOCAL_FD, section 10.1) or TCP (section 10.5). On TCP, t_rx and t2 are the
 * kernel's receive times (SO_TIMESTAMPNS), mapped onto the target's clock.
 *
 * The AI is deliberately trivial: STOP with full brake when the centre ninth of a
 * raw image is dark (mean luma below a threshold), otherwise SAFE at throttle 0.3.
 * A JPEG is not decoded (no library beyond libc): the protocol gives a target no way
 * to ask for raw frames, so the target uses the compressed size as a stand-in for
 * darkness (a dark, featureless picture compresses to few bytes per pixel). Use raw
 * frames (camera.encoding: raw) to exercise the real rule.
 *
 * Over TCP it serves harness after harness until SIGTERM or Ctrl-C (--once: one), with
 * one start-up line and one line per session on stderr; started by a harness (which
 * sets HIL_SESSION) it serves that one run. Each read stops at the end of the current
 * message, so every message is stamped with the arrival of its own last byte. With a
 * token in the environment (--token-env, default HIL_SESSION_TOKEN, which a harness
 * that starts the target sets) it announces CAP_AUTH and answers the harness's AUTH
 * challenge (PROTOCOL.md 4.8), so the harness knows this is its target.
 *
 * A camera rig (PROTOCOL.md 4.2.1): it announces CAP_CAMERAS and answers every camera of
 * a frame set, or with --frame-sets (CAP_FRAME_SETS) one ESTIMATE per set, whose
 * frame_id is the set id: STOP when any camera's centre is dark, SLOW when a camera is
 * missing (given up when a later set begins or 100 ms after the set's first frame),
 * else SAFE (rig.c collects the set).
 *
 *   hil_target [--transport local|tcp] [--listen HOST:PORT | --connect HOST:PORT]
 *              [--name NAME] [--clock monotonic|realtime] [--dark LUMA] [--token-env NAME]
 *              [--frame-sets] [--once | --keep-serving] [--verbose]
 */
#define _POSIX_C_SOURCE 200809L
#include "hilp.h"
#include "net.h"
#include "rig.h"

#include <errno.h>
#include <poll.h>
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/socket.h>
#include <sys/uio.h>
#include <time.h>
#include <unistd.h>

#if defined(SO_TIMESTAMPNS) && !defined(SCM_TIMESTAMPNS)
#define SCM_TIMESTAMPNS SO_TIMESTAMPNS /* the control message carries the option's number */
#endif

#define BUF_START (256u * 1024u)
#define HEARTBEAT_IDLE_NS 1000000000LL /* send a HEARTBEAT after 1 s without sending */
#define SET_TIMEOUT_NS 100000000LL /* give up a frame set 100 ms after its first frame */

static volatile sig_atomic_t g_term; /* SIGTERM or SIGINT: say BYE, serve no further run */

static void on_term(int sig) {
    (void)sig;
    g_term = 1;
}

typedef struct {
    int fd;
    clockid_t clock;
    uint8_t clock_id;
    const char *name;
    unsigned dark_luma;
    int verbose;
    int frame_sets; /* --frame-sets: one ESTIMATE per frame set (CAP_FRAME_SETS) */
    hil_rig rig;    /* the frame set being collected */
    unsigned last_camera; /* camera_index of the last FRAME */
    const uint8_t *token; /* the shared secret proven to the harness (AUTH), or NULL */
    size_t token_len;
    uint32_t vehicle_id; /* of the last FRAME, SYNC_REQUEST or AUTH challenge; 0 before */
    int stop;
    int harness_bye; /* the session ended by the harness's BYE, whose reason is below */
    char bye_reason[HILP_MAX_REASON + 1];
    int64_t last_send_ns;
    /* receive buffer: bytes [0, len) held, decoding from 0 */
    uint8_t *buf;
    size_t len, cap;
    int skipping; /* lost sync after a bad header: skip to the next magic silently */
    /* counters */
    unsigned long frames, estimates, dark, syncs, heartbeats, errors_sent, errors_received, bad, commands;
    unsigned long sets, sets_incomplete, frames_late; /* frame sets answered, of them incomplete; frames too late */
    unsigned long kernel_stamps; /* reads stamped with the kernel's receive time */
    uint8_t out[HILP_HEADER + 1100]; /* every message this target sends fits */
} session;

static int64_t clock_ns(clockid_t clock) {
    struct timespec ts;
    clock_gettime(clock, &ts);
    return (int64_t)ts.tv_sec * 1000000000LL + ts.tv_nsec;
}
static int64_t now_ns(const session *s) { return clock_ns(s->clock); }

/* Writes one whole message (loops on short writes); -1 when the peer is gone. */
static int send_msg(session *s, hilp_header *h) {
    size_t n = hilp_finish(s->out, h);
    size_t done = 0;
    while (done < n) {
        ssize_t w = send(s->fd, s->out + done, n - done, MSG_NOSIGNAL);
        if (w < 0 && errno == EINTR) continue;
        if (w <= 0) { s->stop = 1; return -1; }
        done += (size_t)w;
    }
    s->last_send_ns = now_ns(s);
    return 0;
}

static void header_init(hilp_header *h, uint8_t type, uint32_t vehicle_id) {
    memset(h, 0, sizeof *h);
    h->version = HILP_VERSION;
    h->type = type;
    h->vehicle_id = vehicle_id;
}

/* A text payload: u16 length at payload offset `at`, the text right after it. */
static size_t put_text(uint8_t *payload, size_t at, const char *text, size_t limit) {
    size_t n = strlen(text);
    if (n > limit) n = limit;
    hilp_put16(payload + at, (uint16_t)n);
    memcpy(payload + at + 2, text, n);
    return at + 2 + n;
}

static void send_error(session *s, uint16_t code, const char *text) {
    hilp_header h;
    header_init(&h, HILP_ERROR, s->vehicle_id);
    uint8_t *p = s->out + HILP_HEADER;
    hilp_put16(p, code);
    h.payload_len = (uint32_t)put_text(p, 2, text, HILP_MAX_ERROR);
    s->errors_sent++;
    send_msg(s, &h);
}

static void send_hello(session *s) {
    struct timespec res;
    clock_getres(s->clock, &res);
    hilp_header h;
    header_init(&h, HILP_HELLO, 0);
    uint8_t *p = s->out + HILP_HEADER;
    size_t n = strlen(s->name);
    if (n > HILP_MAX_NAME) n = HILP_MAX_NAME;
    p[0] = s->clock_id;
    p[1] = 0;
    hilp_put16(p + 2, (uint16_t)n);
    hilp_put32(p + 4, (uint32_t)(res.tv_sec * 1000000000L + res.tv_nsec));
    hilp_put32(p + 8, HILP_CAP_COMMANDS | HILP_CAP_CAMERAS | (s->frame_sets ? HILP_CAP_FRAME_SETS : 0u) |
                          (s->token ? HILP_CAP_AUTH : 0u));
    memcpy(p + 12, s->name, n);
    h.payload_len = (uint32_t)(12 + n);
    send_msg(s, &h);
}

/* The trivial AI: 1 when the picture's centre is dark. */
static int centre_is_dark(const session *s, const hilp_frame *f) {
    if (f->encoding == HILP_JPEG) /* opaque: few bytes per pixel stand in for dark */
        return (double)f->image_len < 0.03 * f->width * f->height;
    unsigned x0 = f->width / 3, x1 = f->width - f->width / 3, y0 = f->height / 3, y1 = f->height - f->height / 3;
    unsigned long long sum = 0, n = 0;
    int r = f->encoding == HILP_RGB8 ? 0 : 2, b = 2 - r;
    for (unsigned y = y0; y < y1; y++)
        for (unsigned x = x0; x < x1; x++) {
            const uint8_t *px = f->image + ((size_t)y * f->width + x) * 3u;
            sum += (77u * px[r] + 150u * px[1] + 29u * px[b]) >> 8;
            n++;
        }
    return n > 0 && sum < (unsigned long long)s->dark_luma * n;
}

/* One ESTIMATE: STOP when dark, else SLOW (a frame set missing a camera) or SAFE. */
static void send_estimate(session *s, uint32_t vehicle_id, uint64_t frame_id, int dark, int slow, int64_t t_rx,
                          int64_t t_start, int64_t t_end) {
    hilp_header h;
    header_init(&h, HILP_ESTIMATE, vehicle_id);
    h.frame_id = frame_id;
    uint8_t *p = s->out + HILP_HEADER;
    float steering = 0.0f, throttle = dark ? 0.0f : slow ? 0.1f : 0.3f, brake = dark ? 1.0f : 0.0f;
    uint32_t u;
    memset(p, 0, 16);
    p[0] = dark ? HILP_STOP : slow ? HILP_SLOW : HILP_SAFE;
    memcpy(&u, &steering, 4); hilp_put32(p + 4, u);
    memcpy(&u, &throttle, 4); hilp_put32(p + 8, u);
    memcpy(&u, &brake, 4); hilp_put32(p + 12, u);
    h.payload_len = 16;
    h.ts[0] = t_rx;
    h.ts[1] = t_start;
    h.ts[2] = t_end;
    h.ts[3] = now_ns(s); /* t_reply: handed to the transport right below */
    if (send_msg(s, &h) == 0) s->estimates++;
}

/* The open frame set's ESTIMATE (frame_id: the set id; t_rx: its last frame's). Each
 * camera's centre was measured as it came; the fusion is the stamped inference. */
static void answer_set(session *s, const char *given_up) {
    hil_rig *r = &s->rig;
    int complete = rig_complete(r);
    int64_t t_start = now_ns(s);
    int dark = r->dark;
    int64_t t_end = now_ns(s);
    s->sets++;
    s->sets_incomplete += (unsigned long)!complete;
    if (s->verbose && !complete) {
        char missing[160];
        rig_missing(r, missing, sizeof missing);
        fprintf(stderr, "hil_target: frame set %llu without camera(s) %s: %s\n", (unsigned long long)r->set_id,
                missing, given_up);
    }
    send_estimate(s, r->vehicle_id, r->set_id, dark, !complete, r->last_t_rx, t_start, t_end);
    rig_close(r);
}

static void on_frame(session *s, const uint8_t *m, const hilp_header *fh, int64_t t_rx) {
    hilp_frame f;
    hilp_frame_view(m, &f);
    s->frames++;
    s->vehicle_id = fh->vehicle_id;
    s->last_camera = f.camera_index;
    uint64_t set_id = fh->frame_id - f.camera_index; /* PROTOCOL.md 4.2.1; hilp_check_message saw index <= frame_id */
    if (s->frame_sets && rig_later(&s->rig, set_id)) answer_set(s, "a later set began");
    int64_t t_start = now_ns(s);
    int dark = centre_is_dark(s, &f);
    int64_t t_end = now_ns(s);
    s->dark += (unsigned long)dark;
    if (!s->frame_sets || f.camera_count == 0) { /* one ESTIMATE per FRAME */
        send_estimate(s, fh->vehicle_id, fh->frame_id, dark, 0, t_rx, t_start, t_end);
        return;
    }
    hilp_err e;
    switch (rig_add(&s->rig, set_id, fh, &f, t_rx, clock_ns(CLOCK_MONOTONIC), dark, &e)) {
    case RIG_TOO_LATE: s->frames_late++; break;
    case RIG_CONTRADICTS:
        s->bad++;
        send_error(s, e.code, e.text);
        break;
    case RIG_COMPLETE: answer_set(s, ""); break;
    default: break;
    }
}

static void on_command(session *s, const uint8_t *m, const hilp_header *ch) {
    char text[HILP_MAX_COMMAND + 1], reply[HILP_MAX_COMMAND + 1];
    size_t n = hilp_get16(m + 64);
    memcpy(text, m + 66, n);
    text[n] = '\0';
    s->commands++;
    unsigned v;
    if (strcmp(text, "status") == 0)
        snprintf(reply, sizeof reply, "ok frames=%lu estimates=%lu dark=%lu syncs=%lu bad=%lu dark_luma=%u "
                 "answers=%s last_camera=%u sets=%lu incomplete_sets=%lu late_frames=%lu", s->frames, s->estimates,
                 s->dark, s->syncs, s->bad, s->dark_luma, s->frame_sets ? "per-set" : "per-camera", s->last_camera,
                 s->sets, s->sets_incomplete, s->frames_late);
    else if (sscanf(text, "dark %u", &v) == 1 && v <= 255) {
        s->dark_luma = v;
        snprintf(reply, sizeof reply, "ok dark_luma=%u", v);
    } else
        snprintf(reply, sizeof reply, "error: unknown command (this target takes: status, dark N)");
    hilp_header h;
    header_init(&h, HILP_COMMAND, ch->vehicle_id);
    h.frame_id = ch->frame_id;
    h.ts[0] = now_ns(s);
    h.payload_len = (uint32_t)put_text(s->out + HILP_HEADER, 0, reply, HILP_MAX_COMMAND);
    send_msg(s, &h);
}

/* An AUTH challenge: prove the token (PROTOCOL.md 4.8); its vehicle is the one served. */
static void on_auth(session *s, const uint8_t *m, const hilp_header *ah) {
    if (m[64] != HILP_AUTH_CHALLENGE || !s->token) {
        send_error(s, HILP_E_UNEXPECTED, m[64] != HILP_AUTH_CHALLENGE ? "AUTH PROOF: a target never receives one"
                                                                     : "AUTH CHALLENGE: this target holds no token");
        return;
    }
    s->vehicle_id = ah->vehicle_id;
    hilp_header h;
    header_init(&h, HILP_AUTH, ah->vehicle_id);
    uint8_t *p = s->out + HILP_HEADER;
    memset(p, 0, 4);
    p[0] = HILP_AUTH_PROOF;
    hilp_auth_proof(s->token, s->token_len, m + 68, ah->vehicle_id, p + 4);
    h.payload_len = HILP_AUTH_LEN;
    send_msg(s, &h);
}

/* One whole message that passed the header checks: m holds 64 + payload_len bytes. */
static void on_message(session *s, const uint8_t *m, const hilp_header *h, int64_t t_rx) {
    hilp_err e;
    if (hilp_check_message(m, h, &e) != 0) {
        s->bad++;
        if (s->verbose) fprintf(stderr, "hil_target: bad message: %s\n", e.text);
        if (h->type != HILP_ERROR) send_error(s, e.code, e.text); /* never answer an ERROR with an ERROR */
        return;
    }
    switch (h->type) {
    case HILP_SYNC_REQUEST: {
        hilp_header r;
        header_init(&r, HILP_SYNC_RESPONSE, h->vehicle_id);
        s->vehicle_id = h->vehicle_id;
        r.frame_id = h->frame_id;
        r.ts[0] = h->ts[0]; /* t1, echoed */
        r.ts[1] = t_rx;     /* t2: when the request's last byte arrived */
        r.ts[2] = now_ns(s); /* t3: as late as possible, right before the send */
        if (send_msg(s, &r) == 0) s->syncs++;
        break;
    }
    case HILP_FRAME: on_frame(s, m, h, t_rx); break;
    case HILP_HEARTBEAT: s->heartbeats++; break;
    case HILP_ERROR:
        s->errors_received++;
        if (s->verbose) fprintf(stderr, "hil_target: harness error %u: %.*s\n", (unsigned)hilp_get16(m + 64),
                                (int)hilp_get16(m + 66), (const char *)(m + 68));
        break;
    case HILP_BYE: {
        size_t n = hilp_get16(m + 64);
        memcpy(s->bye_reason, m + 66, n);
        s->bye_reason[n] = '\0';
        s->harness_bye = 1;
        s->stop = 1;
        break;
    }
    case HILP_COMMAND: on_command(s, m, h); break;
    case HILP_AUTH: on_auth(s, m, h); break;
    default: { /* HELLO, ESTIMATE, SYNC_RESPONSE: well formed, but not for a target */
        char text[96];
        snprintf(text, sizeof text, "message type %u is not sent to a target (at byte offset 5)", (unsigned)h->type);
        s->bad++;
        send_error(s, HILP_E_UNEXPECTED, text);
    }
    }
}

static long find_magic(const uint8_t *p, size_t from, size_t len) {
    for (size_t i = from; i + 4 <= len; i++)
        if (p[i] == 'H' && p[i + 1] == 'I' && p[i + 2] == 'L' && p[i + 3] == 'P') return (long)i;
    return -1;
}

/* A bad header: report once, then resume at the next magic after its first byte. */
static size_t resync(session *s, size_t pos, const hilp_err *e) {
    s->bad++;
    if (s->verbose) fprintf(stderr, "hil_target: bad header: %s\n", e->text);
    send_error(s, e->code, e->text);
    s->skipping = 1;
    long found = find_magic(s->buf, pos + 1, s->len);
    if (found >= 0) return (size_t)found;
    return s->len >= 3 && s->len - 3 > pos + 1 ? s->len - 3 : pos + 1;
}

/* Decodes every whole message held (section 8's stream rules); keeps the rest. */
static void drain(session *s, int64_t t_rx) {
    size_t pos = 0;
    while (!s->stop) {
        size_t avail = s->len - pos;
        if (avail < 4) break;
        if (memcmp(s->buf + pos, "HILP", 4) != 0) {
            if (s->skipping) {
                long found = find_magic(s->buf, pos + 1, s->len);
                pos = found >= 0 ? (size_t)found : s->len - 3;
                continue;
            }
            hilp_err e;
            hilp_header h;
            hilp_decode_header(s->buf + pos, &h, &e); /* fails on the magic: fills e */
            pos = resync(s, pos, &e);
            continue;
        }
        if (avail < HILP_HEADER) break;
        hilp_header h;
        hilp_err e;
        if (hilp_decode_header(s->buf + pos, &h, &e) != 0) {
            pos = resync(s, pos, &e);
            continue;
        }
        s->skipping = 0;
        size_t total = HILP_HEADER + (size_t)h.payload_len;
        if (avail < total) {
            if (total > s->cap) { /* grow once to the announced size (at most 64 + 16 MiB) */
                memmove(s->buf, s->buf + pos, avail);
                s->len = avail;
                pos = 0;
                uint8_t *grown = realloc(s->buf, total);
                if (!grown) { fprintf(stderr, "hil_target: out of memory\n"); s->stop = 1; return; }
                s->buf = grown;
                s->cap = total;
            }
            break;
        }
        on_message(s, s->buf + pos, &h, t_rx);
        pos += total;
    }
    memmove(s->buf, s->buf + pos, s->len - pos);
    s->len -= pos;
}

#ifdef SCM_TIMESTAMPNS
#define MAX_BRACKET_NS 20000 /* a wider bracket (the reader was preempted) gives no mapping */

/* *offset: this clock minus CLOCK_REALTIME (ns), from a reading of the realtime clock
 * between two of this clock's, the tightest bracket of three, so that a reader
 * preempted between two reads (a loaded host) does not shift the mapping by half the
 * time it waited; *now: this clock's latest reading. 0 when no bracket was within
 * MAX_BRACKET_NS (then the caller keeps its own after-the-read stamp, never early). */
static int realtime_offset(const session *s, int64_t *offset, int64_t *now) {
    int64_t width = INT64_MAX;
    for (int i = 0; i < 3 && width > 2000; i++) {
        struct timespec r;
        int64_t a = now_ns(s);
        clock_gettime(CLOCK_REALTIME, &r);
        int64_t b = now_ns(s);
        *now = b;
        if (b - a < width) {
            width = b - a;
            *offset = a + (b - a) / 2 - ((int64_t)r.tv_sec * 1000000000LL + r.tv_nsec);
        }
    }
    return width <= MAX_BRACKET_NS;
}
#endif

/* Reads at most `want` bytes into the buffer; *t_rx is when the bytes arrived on this
 * target's clock: the kernel's receive time (SO_TIMESTAMPNS, CLOCK_REALTIME) mapped
 * with realtime_offset where the socket gives one, else the clock after the read. */
static ssize_t read_stamped(session *s, size_t want, int64_t *t_rx) {
    struct iovec iov = {s->buf + s->len, want < s->cap - s->len ? want : s->cap - s->len};
    union {
        char buf[CMSG_SPACE(sizeof(struct timespec))];
        struct cmsghdr align;
    } ctl;
    struct msghdr mh;
    memset(&mh, 0, sizeof mh);
    mh.msg_iov = &iov;
    mh.msg_iovlen = 1;
    mh.msg_control = ctl.buf;
    mh.msg_controllen = sizeof ctl.buf;
    ssize_t n = recvmsg(s->fd, &mh, 0);
    int64_t a = now_ns(s);
    *t_rx = a;
#ifdef SCM_TIMESTAMPNS
    for (struct cmsghdr *c = CMSG_FIRSTHDR(&mh); n > 0 && c; c = CMSG_NXTHDR(&mh, c)) {
        if (c->cmsg_level != SOL_SOCKET || c->cmsg_type != SCM_TIMESTAMPNS) continue;
        struct timespec k;
        memcpy(&k, CMSG_DATA(c), sizeof k);
        int64_t b = 0, offset = 0;
        int ok = realtime_offset(s, &offset, &b);
        int64_t kernel = (int64_t)k.tv_sec * 1000000000LL + k.tv_nsec;
        int64_t mapped = kernel + offset;
        if (ok && kernel > 0 && mapped <= b) {
            *t_rx = mapped;
            s->kernel_stamps++;
        }
    }
#endif
    return n;
}

/* Bytes to read next: up to the end of the current message (its header, then its
 * payload) and never into the next one, so the read that completes a message is
 * its own and its stamp is the arrival of its own last byte. drain() leaves fewer
 * than a whole message, starting at a magic (or up to 3 bytes that may begin one),
 * and grows the buffer to the size a header announces. */
static size_t wanted(const session *s) {
    if (s->len >= HILP_HEADER && memcmp(s->buf, "HILP", 4) == 0) {
        size_t total = HILP_HEADER + (size_t)hilp_get32(s->buf + 12);
        return total > s->len ? total - s->len : 1;
    }
    return s->len < HILP_HEADER ? HILP_HEADER - s->len : 1;
}

/* One session on s->fd until BYE, end of stream or SIGTERM; how it ended, in `ended`. */
static void serve(session *s, char *ended, size_t ended_size) {
    snprintf(ended, ended_size, "the harness closed the connection");
    send_hello(s);
    while (!s->stop) {
        if (g_term) {
            hilp_header h;
            header_init(&h, HILP_BYE, s->vehicle_id);
            h.payload_len = (uint32_t)put_text(s->out + HILP_HEADER, 0, "target stopping", HILP_MAX_REASON);
            send_msg(s, &h);
            snprintf(ended, ended_size, "stopped (SIGTERM)");
            return;
        }
        int wait_ms = 250;
        if (s->rig.open) { /* a frame set still incomplete: given up SET_TIMEOUT_NS after its first frame */
            int64_t left = s->rig.first_mono_ns + SET_TIMEOUT_NS - clock_ns(CLOCK_MONOTONIC);
            if (left <= 0) {
                answer_set(s, "timed out after 100 ms");
                continue;
            }
            if (left / 1000000 + 1 < wait_ms) wait_ms = (int)(left / 1000000 + 1);
        }
        struct pollfd pfd = {s->fd, POLLIN, 0};
        int r = poll(&pfd, 1, wait_ms);
        if (r < 0 && errno == EINTR) continue;
        if (r < 0) break;
        if (r == 0) {
            if (now_ns(s) - s->last_send_ns >= HEARTBEAT_IDLE_NS) {
                hilp_header h;
                header_init(&h, HILP_HEARTBEAT, s->vehicle_id);
                h.ts[0] = now_ns(s);
                send_msg(s, &h);
            }
            continue;
        }
        int64_t t_rx; /* the read that completes a message stamps it */
        ssize_t n = read_stamped(s, wanted(s), &t_rx);
        if (n < 0 && errno == EINTR) continue;
        if (n < 0) {
            snprintf(ended, ended_size, "the connection failed: %s", strerror(errno));
            break;
        }
        if (n == 0) break; /* end of stream: the harness has gone */
        s->len += (size_t)n;
        drain(s, t_rx);
    }
    if (s->harness_bye)
        snprintf(ended, ended_size, "the harness said BYE%s%s%s", s->bye_reason[0] ? " (" : "", s->bye_reason,
                 s->bye_reason[0] ? ")" : "");
}

static const char USAGE[] = "usage: hil_target [--transport local|tcp] [--listen HOST:PORT | --connect HOST:PORT] "
                            "[--name NAME] [--clock monotonic|realtime] [--dark LUMA] [--token-env NAME] "
                            "[--frame-sets] [--once | --keep-serving] [--verbose]\n";

/* One line naming the bad option, exit 2. */
static int usage(const char *why, const char *option) {
    fprintf(stderr, "hil_target: %s: %s (see --help)\n", option, why);
    return 2;
}

static int takes_value(const char *a) {
    static const char *const names[] = {"--transport", "--listen", "--connect", "--name", "--token-env", "--dark",
                                        "--clock"};
    for (size_t k = 0; k < sizeof names / sizeof names[0]; k++)
        if (strcmp(a, names[k]) == 0) return 1;
    return 0;
}

typedef struct {
    unsigned long frames, estimates, dark, syncs, heartbeats, bad, errors_sent, errors_received, commands, kernel_stamps;
} totals;

static void add_totals(totals *t, const session *s) {
    t->frames += s->frames;
    t->estimates += s->estimates;
    t->dark += s->dark;
    t->syncs += s->syncs;
    t->heartbeats += s->heartbeats;
    t->bad += s->bad;
    t->errors_sent += s->errors_sent;
    t->errors_received += s->errors_received;
    t->commands += s->commands;
    t->kernel_stamps += s->kernel_stamps;
}

/* Back to a fresh session on `fd` (same name, clock, AI setting, token, buffer). */
static void reset(session *s, int fd) {
    session keep = *s;
    memset(s, 0, sizeof *s);
    s->fd = fd;
    s->clock = keep.clock;
    s->clock_id = keep.clock_id;
    s->name = keep.name;
    s->dark_luma = keep.dark_luma;
    s->verbose = keep.verbose;
    s->frame_sets = keep.frame_sets;
    s->token = keep.token;
    s->token_len = keep.token_len;
    s->buf = keep.buf;
    s->cap = keep.cap;
    s->last_send_ns = now_ns(s);
}

int main(int argc, char **argv) {
    const char *transport = "local", *listen_at = "127.0.0.1:7600", *connect_to = NULL, *token_env = "HIL_SESSION_TOKEN";
    int keep = -1; /* -1: keep serving unless a harness started this target (it sets HIL_SESSION) */
    session s;
    memset(&s, 0, sizeof s);
    s.clock = CLOCK_MONOTONIC;
    s.clock_id = HILP_CLOCK_MONOTONIC;
    s.name = "c-reference";
    s.dark_luma = 40;
    for (int i = 1; i < argc; i++) {
        const char *a = argv[i], *v = i + 1 < argc ? argv[i + 1] : NULL;
        if (strcmp(a, "--verbose") == 0) { s.verbose = 1; continue; }
        if (strcmp(a, "--frame-sets") == 0) { s.frame_sets = 1; continue; }
        if (strcmp(a, "--once") == 0) { keep = 0; continue; }
        if (strcmp(a, "--keep-serving") == 0) { keep = 1; continue; }
        if (strcmp(a, "-h") == 0 || strcmp(a, "--help") == 0) { fputs(USAGE, stdout); return 0; }
        if (!takes_value(a)) return usage("unknown option", a);
        if (!v) return usage("missing its value", a);
        i++;
        if (strcmp(a, "--transport") == 0) transport = v;
        else if (strcmp(a, "--listen") == 0) listen_at = v;
        else if (strcmp(a, "--connect") == 0) connect_to = v;
        else if (strcmp(a, "--name") == 0) s.name = v;
        else if (strcmp(a, "--token-env") == 0) token_env = v;
        else if (strcmp(a, "--dark") == 0) s.dark_luma = (unsigned)strtoul(v, NULL, 10);
        else if (strcmp(a, "--clock") == 0) {
            if (strcmp(v, "monotonic") == 0) { s.clock = CLOCK_MONOTONIC; s.clock_id = HILP_CLOCK_MONOTONIC; }
            else if (strcmp(v, "realtime") == 0) { s.clock = CLOCK_REALTIME; s.clock_id = HILP_CLOCK_REALTIME; }
            else return usage("takes monotonic or realtime", "--clock");
        }
    }
    const char *token = getenv(token_env);
    if (token && *token) {
        s.token = (const uint8_t *)token;
        s.token_len = strlen(token);
        if (s.token_len < HILP_MIN_TOKEN) {
            fprintf(stderr, "hil_target: the token in $%s is %lu bytes; use at least %u (e.g. openssl rand -hex 32)\n",
                    token_env, (unsigned long)s.token_len, HILP_MIN_TOKEN);
            return 2;
        }
    }
    if (keep < 0) keep = getenv("HIL_SESSION") == NULL;
    signal(SIGPIPE, SIG_IGN);
    struct sigaction sa;
    memset(&sa, 0, sizeof sa);
    sa.sa_handler = on_term; /* no SA_RESTART: a blocked poll, accept or read returns EINTR */
    sigaction(SIGTERM, &sa, NULL);
    sigaction(SIGINT, &sa, NULL);
    int tcp = strcmp(transport, "tcp") == 0, ls = -1;
    char where[300];
    if (strcmp(transport, "local") == 0) {
        const char *fd_text = getenv("HIL_LOCAL_FD");
        if (!fd_text || !*fd_text) {
            fprintf(stderr, "hil_target: HIL_LOCAL_FD is not set: a local target is started by the harness (hil run); "
                            "to serve by hand, give --transport tcp\n");
            return 2;
        }
        s.fd = atoi(fd_text);
        keep = 0; /* the harness's socket carries one run */
        snprintf(where, sizeof where, "on the harness's socket (HIL_LOCAL_FD)");
    } else if (tcp) {
        if (!connect_to && (ls = net_listen(listen_at)) < 0) return 2;
        snprintf(where, sizeof where, connect_to ? "dialling the harness at %s" : "listening on %s",
                 connect_to ? connect_to : listen_at);
    } else
        return usage("takes local or tcp", "--transport");
    s.cap = BUF_START;
    s.buf = malloc(s.cap);
    if (!s.buf) return 1;
    struct timespec res;
    clock_getres(s.clock, &res);
    fprintf(stderr, "%s: %s target %s, clock %s (%ld ns), protocol v%d, capabilities: COMMANDS%s, CAMERAS%s, "
            "access: %s%s; %s\n",
            s.name, tcp ? "tcp" : "local", where, s.clock_id == HILP_CLOCK_MONOTONIC ? "MONOTONIC" : "REALTIME",
            (long)(res.tv_sec * 1000000000L + res.tv_nsec), HILP_VERSION, s.token ? ", AUTH" : "",
            s.frame_sets ? ", FRAME_SETS" : "",
            s.token ? "proves the token in $" : "no token: a harness that requires one refuses this target",
            s.token ? token_env : "", keep ? "serving run after run until Ctrl-C/SIGTERM" : "serving one run");
    totals t;
    memset(&t, 0, sizeof t);
    int rc = 0;
    for (unsigned long n = 1; !g_term; n++) {
        char peer[300] = "the harness", ended[HILP_MAX_REASON + 64];
        if (tcp) {
            int fd = connect_to ? net_dial(connect_to, keep, &g_term) : net_accept(ls, peer, sizeof peer, &g_term);
            if (fd < 0) {
                rc = g_term ? 0 : 2;
                break;
            }
            if (connect_to) snprintf(peer, sizeof peer, "%s", connect_to);
            reset(&s, fd);
        } else
            reset(&s, s.fd);
        serve(&s, ended, sizeof ended);
        add_totals(&t, &s);
        fprintf(stderr, "%s: session %lu with %s, vehicle %lu: %lu frames, %lu estimates, %lu clock syncs, "
                        "%lu bad messages; ended: %s\n",
                s.name, n, peer, (unsigned long)s.vehicle_id, s.frames, s.estimates, s.syncs, s.bad, ended);
        close(s.fd);
        if (!keep) break;
    }
    if (ls >= 0) close(ls);
    fprintf(stderr, "hil_target: frames=%lu estimates=%lu dark=%lu syncs=%lu heartbeats=%lu bad=%lu "
                    "errors_sent=%lu errors_received=%lu commands=%lu kernel_stamps=%lu\n",
            t.frames, t.estimates, t.dark, t.syncs, t.heartbeats, t.bad, t.errors_sent, t.errors_received,
            t.commands, t.kernel_stamps);
    free(s.buf);
    return rc;
}

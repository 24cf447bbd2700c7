/* HIL wire protocol v1: see hilp.h and PROTOCOL.md. */
#include "hilp.h"

#include <stdarg.h>
#include <stdio.h>
#include <string.h>

uint16_t hilp_get16(const uint8_t *p) { return (uint16_t)(p[0] | (p[1] << 8)); }
uint32_t hilp_get32(const uint8_t *p) {
    return (uint32_t)p[0] | ((uint32_t)p[1] << 8) | ((uint32_t)p[2] << 16) | ((uint32_t)p[3] << 24);
}
uint64_t hilp_get64(const uint8_t *p) { return (uint64_t)hilp_get32(p) | ((uint64_t)hilp_get32(p + 4) << 32); }
void hilp_put16(uint8_t *p, uint16_t v) { p[0] = (uint8_t)v; p[1] = (uint8_t)(v >> 8); }
void hilp_put32(uint8_t *p, uint32_t v) {
    for (int i = 0; i < 4; i++) p[i] = (uint8_t)(v >> (8 * i));
}
void hilp_put64(uint8_t *p, uint64_t v) {
    for (int i = 0; i < 8; i++) p[i] = (uint8_t)(v >> (8 * i));
}

static uint32_t crc_table[256];
static int crc_ready;

uint32_t hilp_crc32(const uint8_t *p, size_t n) {
    if (!crc_ready) { /* the bitwise form of PROTOCOL.md section 6, one byte at a time */
        for (uint32_t i = 0; i < 256; i++) {
            uint32_t c = i;
            for (int k = 0; k < 8; k++) c = (c >> 1) ^ (0xEDB88320u & (0u - (c & 1u)));
            crc_table[i] = c;
        }
        crc_ready = 1;
    }
    uint32_t c = 0xFFFFFFFFu;
    while (n--) c = crc_table[(c ^ *p++) & 0xFFu] ^ (c >> 8);
    return c ^ 0xFFFFFFFFu;
}

#if defined(__GNUC__)
__attribute__((format(printf, 4, 5)))
#endif
static int fail(hilp_err *e, uint16_t code, uint32_t offset, const char *fmt, ...) {
    char what[150];
    va_list ap;
    va_start(ap, fmt);
    vsnprintf(what, sizeof what, fmt, ap);
    va_end(ap);
    e->code = code;
    e->offset = offset;
    snprintf(e->text, sizeof e->text, "%s (at byte offset %lu)", what, (unsigned long)offset);
    return -1;
}

int hilp_decode_header(const uint8_t *p, hilp_header *h, hilp_err *e) {
    if (memcmp(p, "HILP", 4) != 0)
        return fail(e, HILP_E_MALFORMED, 0, "bad magic %02x %02x %02x %02x, expected HILP", p[0], p[1], p[2], p[3]);
    h->version = p[4];
    if (h->version != HILP_VERSION)
        return fail(e, HILP_E_UNSUPPORTED_VERSION, 4,
                    "unsupported protocol version %u; this target speaks version %u", (unsigned)h->version,
                    (unsigned)HILP_VERSION);
    h->type = p[5];
    if (h->type < HILP_HELLO || h->type > HILP_AUTH)
        return fail(e, HILP_E_MALFORMED, 5, "unknown message type %u", (unsigned)h->type);
    h->flags = hilp_get16(p + 6);
    if (h->flags & ~HILP_FLAG_PAYLOAD_CRC)
        return fail(e, HILP_E_MALFORMED, 6, "unknown flag bits 0x%04x (v1 knows 0x%04x)",
                    (unsigned)(h->flags & ~HILP_FLAG_PAYLOAD_CRC), (unsigned)HILP_FLAG_PAYLOAD_CRC);
    h->vehicle_id = hilp_get32(p + 8);
    h->payload_len = hilp_get32(p + 12);
    if (h->payload_len > HILP_MAX_PAYLOAD)
        return fail(e, HILP_E_MALFORMED, 12, "payload_len %lu exceeds MAX_PAYLOAD=%lu", (unsigned long)h->payload_len,
                    (unsigned long)HILP_MAX_PAYLOAD);
    if (hilp_crc32(p, 60) != hilp_get32(p + 60)) return fail(e, HILP_E_MALFORMED, 60, "header CRC mismatch");
    h->frame_id = hilp_get64(p + 16);
    for (int i = 0; i < 4; i++) h->ts[i] = (int64_t)hilp_get64(p + 24 + 8 * i);
    h->payload_crc = hilp_get32(p + 56);
    if (h->payload_crc && !(h->flags & HILP_FLAG_PAYLOAD_CRC))
        return fail(e, HILP_E_MALFORMED, 56, "payload_crc is set but FLAG_PAYLOAD_CRC is not");
    return 0;
}

int hilp_utf8_ok(const uint8_t *p, size_t n, size_t *bad) {
    size_t i = 0;
    while (i < n) {
        uint8_t c = p[i];
        size_t need;
        uint8_t lo = 0x80, hi = 0xBF; /* allowed range of the first continuation byte */
        if (c < 0x80) { i++; continue; }
        if (c >= 0xC2 && c <= 0xDF) need = 1;
        else if (c >= 0xE0 && c <= 0xEF) { need = 2; if (c == 0xE0) lo = 0xA0; if (c == 0xED) hi = 0x9F; }
        else if (c >= 0xF0 && c <= 0xF4) { need = 3; if (c == 0xF0) lo = 0x90; if (c == 0xF4) hi = 0x8F; }
        else { *bad = i; return 0; }
        for (size_t k = 1; k <= need; k++) {
            uint8_t lo_k = k == 1 ? lo : 0x80, hi_k = k == 1 ? hi : 0xBF;
            if (i + k >= n || p[i + k] < lo_k || p[i + k] > hi_k) { *bad = i; return 0; }
        }
        i += need + 1;
    }
    return 1;
}

static int f32_finite(const uint8_t *p) { return ((hilp_get32(p) >> 23) & 0xFFu) != 0xFFu; }
static float f32_at(const uint8_t *p) {
    uint32_t u = hilp_get32(p);
    float f;
    memcpy(&f, &u, sizeof f);
    return f;
}
static int check_finite(const uint8_t *m, uint32_t at, const char *name, int unit, hilp_err *e) {
    if (!f32_finite(m + at)) return fail(e, HILP_E_MALFORMED, at, "%s must be finite", name);
    if (unit) {
        float v = f32_at(m + at);
        if (!(v >= 0.0f && v <= 1.0f)) return fail(e, HILP_E_MALFORMED, at, "%s=%g is outside [0, 1]", name, (double)v);
    }
    return 0;
}
static int check_reserved(const uint8_t *m, uint32_t at, uint32_t n, hilp_err *e) {
    for (uint32_t i = 0; i < n; i++)
        if (m[at + i]) return fail(e, HILP_E_MALFORMED, at + i, "reserved byte is %u, must be 0", (unsigned)m[at + i]);
    return 0;
}
static int check_text(const uint8_t *m, uint32_t at, uint32_t n, const char *name, hilp_err *e) {
    size_t bad;
    if (!hilp_utf8_ok(m + at, n, &bad))
        return fail(e, HILP_E_MALFORMED, at + (uint32_t)bad, "%s is not valid UTF-8", name);
    return 0;
}
static int too_short(const hilp_header *h, uint32_t need, const char *type, hilp_err *e) {
    if (h->payload_len >= need) return 0;
    return fail(e, HILP_E_MALFORMED, 12, "payload_len %lu too short for %s (at least %lu)",
                (unsigned long)h->payload_len, type, (unsigned long)need);
}
/* A u16 length field at `at` of a payload that is `fixed` bytes plus the text. */
static int check_len(const hilp_header *h, const uint8_t *m, uint32_t at, uint32_t fixed, uint32_t limit,
                     const char *type, const char *name, hilp_err *e) {
    if (too_short(h, fixed, type, e)) return -1;
    uint32_t v = hilp_get16(m + at);
    if (v > limit) return fail(e, HILP_E_MALFORMED, at, "%s %u exceeds the limit %u", name, (unsigned)v, (unsigned)limit);
    if (fixed + v != h->payload_len)
        return fail(e, HILP_E_MALFORMED, at, "%s %u disagrees with payload_len %lu (expected %lu)", name, (unsigned)v,
                    (unsigned long)h->payload_len, (unsigned long)(h->payload_len - fixed));
    return check_text(m, HILP_HEADER + fixed, v, "text", e);
}

/* Per type: does it use frame_id, and how many leading ts slots (section 3). */
static const uint8_t uses_fid[11] = {0, 0, 1, 1, 1, 1, 0, 0, 0, 1, 0};
static const uint8_t n_ts[11] = {0, 0, 3, 4, 1, 3, 1, 0, 0, 1, 0};

static int check_frame(const uint8_t *m, const hilp_header *h, hilp_err *e) {
    static const char *const names[7] = {"fx", "fy", "cx", "cy", "mount_height_m", "pitch_rad", "ego_speed_mps"};
    if (too_short(h, 40, "FRAME", e)) return -1;
    unsigned w = hilp_get16(m + 64), ht = hilp_get16(m + 66);
    if (w < 1 || w > HILP_MAX_SIDE) return fail(e, HILP_E_MALFORMED, 64, "width %u px is outside 1..%u", w, HILP_MAX_SIDE);
    if (ht < 1 || ht > HILP_MAX_SIDE) return fail(e, HILP_E_MALFORMED, 66, "height %u px is outside 1..%u", ht, HILP_MAX_SIDE);
    if (m[68] > HILP_JPEG) return fail(e, HILP_E_MALFORMED, 68, "unknown image encoding %u", (unsigned)m[68]);
    unsigned ci = m[69], cc = m[70];
    if (cc == 1 || cc > HILP_MAX_CAMERAS)
        return fail(e, HILP_E_MALFORMED, 70, "camera_count=%u: 0 for a single camera, 2..%u for a frame set", cc,
                    HILP_MAX_CAMERAS);
    if (cc == 0 && ci)
        return fail(e, HILP_E_MALFORMED, 69, "camera_index=%u with camera_count 0: a single camera is camera 0", ci);
    if (cc && ci >= cc)
        return fail(e, HILP_E_MALFORMED, 69, "camera_index=%u is outside 0..%u (camera_count %u)", ci, cc - 1, cc);
    if (ci > h->frame_id)
        return fail(e, HILP_E_MALFORMED, 69, "camera_index=%u exceeds frame_id %llu: the set id would be negative", ci,
                    (unsigned long long)h->frame_id);
    if (check_reserved(m, 71, 1, e)) return -1;
    for (uint32_t i = 0; i < 7; i++)
        if (check_finite(m, 72 + 4 * i, names[i], 0, e)) return -1;
    uint32_t image_len = hilp_get32(m + 100);
    if (image_len != h->payload_len - 40)
        return fail(e, HILP_E_MALFORMED, 100, "image_len %lu disagrees with payload_len %lu (expected %lu)",
                    (unsigned long)image_len, (unsigned long)h->payload_len, (unsigned long)(h->payload_len - 40));
    if (m[68] != HILP_JPEG && (unsigned long)image_len != (unsigned long)w * ht * 3u)
        return fail(e, HILP_E_MALFORMED, 100, "%ux%u raw image needs %lu bytes, image_len is %lu", w, ht,
                    (unsigned long)w * ht * 3u, (unsigned long)image_len);
    return 0;
}

static int check_estimate(const uint8_t *m, const hilp_header *h, hilp_err *e) {
    if (too_short(h, 16, "ESTIMATE", e)) return -1;
    if (m[64] > HILP_STOP) return fail(e, HILP_E_MALFORMED, 64, "unknown driving state %u", (unsigned)m[64]);
    if (check_reserved(m, 65, 1, e)) return -1;
    uint32_t n = hilp_get16(m + 66);
    if (n > HILP_MAX_OBJECTS)
        return fail(e, HILP_E_MALFORMED, 66, "n_objects %u exceeds the limit %u", (unsigned)n, HILP_MAX_OBJECTS);
    if (16 + 36 * n != h->payload_len)
        return fail(e, HILP_E_MALFORMED, 66, "n_objects %u needs payload_len %lu, header says %lu", (unsigned)n,
                    (unsigned long)(16 + 36 * n), (unsigned long)h->payload_len);
    if (check_finite(m, 68, "steering_rad", 0, e) || check_finite(m, 72, "throttle", 1, e) ||
        check_finite(m, 76, "brake", 1, e))
        return -1;
    for (uint32_t i = 0; i < n; i++) {
        uint32_t at = 80 + 36 * i;
        if (m[at] > 3) return fail(e, HILP_E_MALFORMED, at, "unknown class %u of object %u", (unsigned)m[at], (unsigned)i);
        if (m[at + 1] >= HILP_MAX_CAMERAS)
            return fail(e, HILP_E_MALFORMED, at + 1, "object camera=%u is outside 0..%u", (unsigned)m[at + 1],
                        HILP_MAX_CAMERAS - 1);
        if (check_reserved(m, at + 2, 2, e) || check_finite(m, at + 4, "confidence", 1, e)) return -1;
        for (uint32_t k = 0; k < 7; k++)
            if (check_finite(m, at + 8 + 4 * k, "box/position", 0, e)) return -1;
    }
    return 0;
}

int hilp_check_message(const uint8_t *m, const hilp_header *h, hilp_err *e) {
    if ((h->flags & HILP_FLAG_PAYLOAD_CRC) && hilp_crc32(m + HILP_HEADER, h->payload_len) != h->payload_crc)
        return fail(e, HILP_E_MALFORMED, HILP_HEADER, "payload CRC mismatch");
    if (h->type == HILP_HELLO && h->vehicle_id)
        return fail(e, HILP_E_MALFORMED, 8, "HELLO carries vehicle_id 0, got %lu", (unsigned long)h->vehicle_id);
    if (!uses_fid[h->type] && h->frame_id)
        return fail(e, HILP_E_MALFORMED, 16, "type %u leaves frame_id 0, got %llu", (unsigned)h->type,
                    (unsigned long long)h->frame_id);
    for (int i = n_ts[h->type]; i < 4; i++)
        if (h->ts[i]) return fail(e, HILP_E_MALFORMED, 24 + 8 * (uint32_t)i, "type %u leaves ts%d 0", (unsigned)h->type, i);
    switch (h->type) {
    case HILP_HELLO: {
        if (too_short(h, 12, "HELLO", e)) return -1;
        if (m[64] > HILP_CLOCK_DEVICE) return fail(e, HILP_E_MALFORMED, 64, "unknown clock_id %u", (unsigned)m[64]);
        if (check_reserved(m, 65, 1, e)) return -1;
        uint32_t n = hilp_get16(m + 66);
        if (n > HILP_MAX_NAME) return fail(e, HILP_E_MALFORMED, 66, "name_len %u exceeds the limit %u", (unsigned)n, HILP_MAX_NAME);
        if (12 + n != h->payload_len)
            return fail(e, HILP_E_MALFORMED, 66, "name_len %u disagrees with payload_len %lu", (unsigned)n,
                        (unsigned long)h->payload_len);
        return check_text(m, 76, n, "target_name", e);
    }
    case HILP_FRAME: return check_frame(m, h, e);
    case HILP_ESTIMATE: return check_estimate(m, h, e);
    case HILP_SYNC_REQUEST:
    case HILP_SYNC_RESPONSE:
    case HILP_HEARTBEAT:
        if (h->payload_len)
            return fail(e, HILP_E_MALFORMED, 12, "type %u has no payload, payload_len is %lu", (unsigned)h->type,
                        (unsigned long)h->payload_len);
        return 0;
    case HILP_ERROR: return check_len(h, m, 66, 4, HILP_MAX_ERROR, "ERROR", "msg_len", e);
    case HILP_BYE: return check_len(h, m, 64, 2, HILP_MAX_REASON, "BYE", "reason_len", e);
    case HILP_COMMAND: return check_len(h, m, 64, 2, HILP_MAX_COMMAND, "COMMAND", "text_len", e);
    case HILP_AUTH:
        if (h->payload_len != HILP_AUTH_LEN)
            return fail(e, HILP_E_MALFORMED, 12, "AUTH payload_len must be %u, got %lu", HILP_AUTH_LEN,
                        (unsigned long)h->payload_len);
        if (m[64] != HILP_AUTH_CHALLENGE && m[64] != HILP_AUTH_PROOF)
            return fail(e, HILP_E_MALFORMED, 64, "unknown AUTH step %u", (unsigned)m[64]);
        return check_reserved(m, 65, 3, e);
    default: return fail(e, HILP_E_MALFORMED, 5, "unknown message type %u", (unsigned)h->type);
    }
}

void hilp_frame_view(const uint8_t *m, hilp_frame *f) {
    f->width = hilp_get16(m + 64);
    f->height = hilp_get16(m + 66);
    f->encoding = m[68];
    f->camera_index = m[69];
    f->camera_count = m[70];
    f->fx = f32_at(m + 72);
    f->fy = f32_at(m + 76);
    f->cx = f32_at(m + 80);
    f->cy = f32_at(m + 84);
    f->mount_height_m = f32_at(m + 88);
    f->pitch_rad = f32_at(m + 92);
    f->ego_speed_mps = f32_at(m + 96);
    f->image_len = hilp_get32(m + 100);
    f->image = m + 104;
}

size_t hilp_finish(uint8_t *out, const hilp_header *h) {
    memcpy(out, "HILP", 4);
    out[4] = HILP_VERSION;
    out[5] = h->type;
    hilp_put16(out + 6, h->flags);
    hilp_put32(out + 8, h->vehicle_id);
    hilp_put32(out + 12, h->payload_len);
    hilp_put64(out + 16, h->frame_id);
    for (int i = 0; i < 4; i++) hilp_put64(out + 24 + 8 * i, (uint64_t)h->ts[i]);
    uint32_t pcrc = (h->flags & HILP_FLAG_PAYLOAD_CRC) ? hilp_crc32(out + HILP_HEADER, h->payload_len) : 0;
    hilp_put32(out + 56, pcrc);
    hilp_put32(out + 60, hilp_crc32(out, 60));
    return HILP_HEADER + h->payload_len;
}

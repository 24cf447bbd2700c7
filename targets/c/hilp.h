/* HIL wire protocol v1 (PROTOCOL.md): CRC, header, message checks, encoding.
 * C99, libc only. All multi-byte fields are little-endian on the wire and are read
 * and written byte by byte, so the host's byte order does not matter. */
#ifndef HILP_H
#define HILP_H

#include <stddef.h>
#include <stdint.h>

#define HILP_VERSION 1
#define HILP_HEADER 64u
#define HILP_MAX_PAYLOAD 16777216u /* 16 MiB */
#define HILP_FLAG_PAYLOAD_CRC 0x0001u
#define HILP_CAP_SHM_FRAMES 0x00000001u
#define HILP_CAP_COMMANDS 0x00000002u
#define HILP_CAP_AUTH 0x00000004u
#define HILP_CAP_CAMERAS 0x00000008u    /* takes the FRAMEs of a frame set (PROTOCOL.md 4.2.1) */
#define HILP_CAP_FRAME_SETS 0x00000010u /* ... and answers one ESTIMATE per set */
#define HILP_MAX_CAMERAS 32u            /* cameras in one frame set */
#define HILP_AUTH_LEN 36u /* AUTH payload: step, 3 reserved bytes, 32 bytes of challenge or proof */
#define HILP_MIN_TOKEN 16u
#define HILP_MAX_NAME 64u
#define HILP_MAX_ERROR 1024u
#define HILP_MAX_REASON 256u
#define HILP_MAX_COMMAND 256u
#define HILP_MAX_OBJECTS 256u
#define HILP_MAX_SIDE 4096u

enum hilp_type {
    HILP_HELLO = 1, HILP_FRAME = 2, HILP_ESTIMATE = 3, HILP_SYNC_REQUEST = 4, HILP_SYNC_RESPONSE = 5,
    HILP_HEARTBEAT = 6, HILP_ERROR = 7, HILP_BYE = 8, HILP_COMMAND = 9, HILP_AUTH = 10
};
enum hilp_auth_step { HILP_AUTH_CHALLENGE = 1, HILP_AUTH_PROOF = 2 };
enum hilp_error_code {
    HILP_E_UNSPECIFIED = 0, HILP_E_MALFORMED = 1, HILP_E_UNSUPPORTED_VERSION = 2, HILP_E_UNEXPECTED = 3,
    HILP_E_TARGET_FAILURE = 4
};
enum hilp_encoding { HILP_RGB8 = 0, HILP_BGR8 = 1, HILP_JPEG = 2 };
enum hilp_clock { HILP_CLOCK_MONOTONIC = 0, HILP_CLOCK_REALTIME = 1, HILP_CLOCK_PTP = 2, HILP_CLOCK_DEVICE = 3 };
enum hilp_state { HILP_SAFE = 0, HILP_SLOW = 1, HILP_STOP = 2 };

typedef struct {
    uint8_t version;
    uint8_t type;
    uint16_t flags;
    uint32_t vehicle_id;
    uint32_t payload_len;
    uint64_t frame_id;
    int64_t ts[4];
    uint32_t payload_crc;
} hilp_header;

/* A decoding failure: the ErrorCode to reply with, the absolute byte offset of the
 * bad field within the message, and a line of text naming it. */
typedef struct {
    uint16_t code;
    uint32_t offset;
    char text[200];
} hilp_err;

/* A decoded FRAME (pointers into the message buffer). */
typedef struct {
    uint16_t width, height;
    uint8_t encoding;
    uint8_t camera_index; /* byte 69: the camera of the vehicle's rig */
    uint8_t camera_count; /* byte 70: cameras of its frame set; 0: a single camera */
    float fx, fy, cx, cy, mount_height_m, pitch_rad, ego_speed_mps;
    uint32_t image_len;
    const uint8_t *image;
} hilp_frame;

uint16_t hilp_get16(const uint8_t *p);
uint32_t hilp_get32(const uint8_t *p);
uint64_t hilp_get64(const uint8_t *p);
void hilp_put16(uint8_t *p, uint16_t v);
void hilp_put32(uint8_t *p, uint32_t v);
void hilp_put64(uint8_t *p, uint64_t v);

/* CRC-32 of IEEE 802.3 / zlib (PROTOCOL.md section 6). */
uint32_t hilp_crc32(const uint8_t *p, size_t n);

/* Validates the 64 header bytes at p in the order of PROTOCOL.md section 2 (magic,
 * version, type, flags, payload_len, header CRC, payload_crc without its flag).
 * Returns 0 and fills h, or -1 and fills e. */
int hilp_decode_header(const uint8_t *p, hilp_header *h, hilp_err *e);

/* Checks the rest of a message whose header h was decoded from p (p holds
 * 64 + h->payload_len bytes): payload CRC when flagged, unused header fields zero
 * (section 3), then every payload field (section 4). Returns 0 or -1 and fills e. */
int hilp_check_message(const uint8_t *p, const hilp_header *h, hilp_err *e);

/* The FRAME fields of a message that passed hilp_check_message. */
void hilp_frame_view(const uint8_t *p, hilp_frame *f);

/* Writes the header for h into out[0..63] over a payload already at out + 64 of
 * h->payload_len bytes (payload CRC filled when h->flags asks for it). Returns the
 * message length. */
size_t hilp_finish(uint8_t *out, const hilp_header *h);

/* HMAC-SHA256 (RFC 2104) of msg under key (hmac.c). */
void hilp_hmac_sha256(const uint8_t *key, size_t key_len, const uint8_t *msg, size_t msg_len, uint8_t out[32]);

/* The AUTH proof of PROTOCOL.md section 4.8: HMAC-SHA256(token, "HIL-AUTH-1" ||
 * challenge || vehicle_id as u32 little-endian). */
void hilp_auth_proof(const uint8_t *token, size_t token_len, const uint8_t challenge[32], uint32_t vehicle_id,
                     uint8_t out[32]);

/* 1 when the n bytes at p are well-formed UTF-8 (as Python decodes it); else 0 and
 * *bad is the index of the first bad byte. */
int hilp_utf8_ok(const uint8_t *p, size_t n, size_t *bad);

#endif

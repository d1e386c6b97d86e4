/* FlyTrack trigger serial link (protocol/SPEC.md section 3): CRC-16, COBS, frame encode/decode,
 * typed messages and a byte-at-a-time receiver.
 *
 * Header-only C99 for both the AVR firmware (ATmega328P: small code, no float, no big buffers) and
 * Linux. No allocation; no decoder reads past the length it is given.
 *
 * Choices the SPEC leaves open (see protocol/README.md):
 * - an empty frame (two delimiters in a row) is skipped by ft_tl_rx_push (senders may send a
 *   leading delimiter to resynchronise); ft_tl_decode on 0 bytes gives FT_E_TRUNCATED;
 * - TOO_LONG means more than FT_TL_MAX_FRAME = 65 bytes before the delimiter: the COBS size of the
 *   longest (64-byte) body;
 * - COBS encoding is canonical: a final full 254-byte block gets no trailing 0x01 code byte; the
 *   decoder accepts both forms.
 */
#ifndef FLYTRACK_TRIGGER_LINK_H
#define FLYTRACK_TRIGGER_LINK_H

#include "wire.h"

#define FT_TL_MAGIC 0x46
#define FT_TL_HEADER 4                                      /* magic, version, msg_id, seq */
#define FT_TL_OVERHEAD 6                                    /* header + CRC */
#define FT_TL_MAX_BODY 64                                   /* longest body (SPEC) */
#define FT_TL_MAX_PAYLOAD (FT_TL_MAX_BODY - FT_TL_OVERHEAD) /* 58 */
#define FT_TL_MAX_FRAME (FT_TL_MAX_BODY + 1)                /* COBS bytes of the longest body */
#define FT_TL_MAX_WIRE (FT_TL_MAX_FRAME + 1)                /* plus the 0x00 delimiter: 66 */

/* Message ids: requests (host -> device) */
#define FT_TL_GET_INFO 0x01
#define FT_TL_SET_RATE 0x02
#define FT_TL_START 0x03
#define FT_TL_STOP 0x04
#define FT_TL_STOP_RESET 0x05
#define FT_TL_CLOCK_QUERY 0x06
#define FT_TL_PULSE 0x07
#define FT_TL_SET_OUTPUT 0x08
#define FT_TL_SET_NAME 0x09
/* replies and events (device -> host) */
#define FT_TL_INFO 0x81
#define FT_TL_ACK 0x82
#define FT_TL_RATE 0x83
#define FT_TL_CLOCK 0x84
#define FT_TL_EVENT 0x85
#define FT_TL_ERROR 0x86

/* Codes carried in an ERROR reply */
#define FT_TL_ERR_BAD_CRC 1
#define FT_TL_ERR_BAD_COBS 2
#define FT_TL_ERR_UNKNOWN_TYPE 3
#define FT_TL_ERR_LENGTH_MISMATCH 4
#define FT_TL_ERR_BAD_ARG 5
#define FT_TL_ERR_BUSY 6
#define FT_TL_ERR_TOO_LONG 7
#define FT_TL_ERR_BAD_MAGIC 8
#define FT_TL_ERR_BAD_VERSION 9

/* Payload sizes fixed by msg_id */
#define FT_TL_SET_RATE_SIZE 3
#define FT_TL_PULSE_SIZE 7
#define FT_TL_SET_OUTPUT_SIZE 2
#define FT_TL_NAME_LEN 16
#define FT_TL_SET_NAME_SIZE 16
#define FT_TL_INFO_SIZE 28
#define FT_TL_ACK_SIZE 1
#define FT_TL_RATE_SIZE 7
#define FT_TL_CLOCK_SIZE 9
#define FT_TL_EVENT_SIZE 8
#define FT_TL_ERROR_SIZE 2

#define FT_TL_PULSE_NOW 0xFFFFFFFFu
#define FT_TL_MCU_ATMEGA328P 1
#define FT_TL_MCU_ATMEGA32U4 2

/* ---- CRC-16/CCITT-FALSE: poly 0x1021, init 0xFFFF, no reflection, no final xor ---- */

#define FT_CRC16_INIT 0xFFFFu

/* Byte-wise form of the polynomial division, no table (keeps AVR flash small). */
static inline uint16_t ft_crc16_update(uint16_t crc, uint8_t byte) {
    uint8_t x = (uint8_t)((crc >> 8) ^ byte);
    x ^= (uint8_t)(x >> 4);
    return (uint16_t)((uint16_t)(crc << 8) ^ (uint16_t)((uint16_t)x << 12) ^
                      (uint16_t)((uint16_t)x << 5) ^ (uint16_t)x);
}

static inline uint16_t ft_crc16(const uint8_t *p, size_t n) {
    uint16_t crc = FT_CRC16_INIT;
    size_t i;
    for (i = 0; i < n; i++)
        crc = ft_crc16_update(crc, p[i]);
    return crc;
}

/* ---- COBS ---- */

/* Encodes n bytes of src into dst (no delimiter). dst must not overlap src. Needs
 * n + n / 254 + 1 bytes at most; FT_E_NO_SPACE if cap is smaller than what this input needs. */
static inline ft_err ft_cobs_encode(const uint8_t *src, size_t n, uint8_t *dst, size_t cap,
                                    size_t *out_len) {
    size_t code_pos = 0, o = 1, i;
    uint8_t code = 1;
    if (cap < 1)
        return FT_E_NO_SPACE;
    for (i = 0; i < n; i++) {
        if (src[i] != 0) {
            if (o >= cap)
                return FT_E_NO_SPACE;
            dst[o++] = src[i];
            code++;
        }
        if (src[i] == 0 || code == 0xFF) {
            dst[code_pos] = code;
            code = 1;
            /* A full block that ends the input needs no new code byte (canonical form). */
            if (src[i] == 0 || i + 1 < n) {
                if (o >= cap)
                    return FT_E_NO_SPACE;
                code_pos = o++;
            } else {
                *out_len = o;
                return FT_OK;
            }
        }
    }
    dst[code_pos] = code;
    *out_len = o;
    return FT_OK;
}

/* Decodes n COBS bytes (no delimiter) into dst. FT_E_BAD_COBS if a zero byte appears or a code byte
 * points past the end; FT_E_NO_SPACE if the result does not fit in cap. dst may equal src (decoding
 * in place is safe: output never overtakes input). */
static inline ft_err ft_cobs_decode(const uint8_t *src, size_t n, uint8_t *dst, size_t cap,
                                    size_t *out_len) {
    size_t i = 0, o = 0;
    while (i < n) {
        uint8_t code = src[i++], k;
        if (code == 0 || (size_t)(code - 1) > n - i)
            return FT_E_BAD_COBS;
        for (k = 1; k < code; k++) {
            if (src[i] == 0)
                return FT_E_BAD_COBS;
            if (o >= cap)
                return FT_E_NO_SPACE;
            dst[o++] = src[i++];
        }
        if (code != 0xFF && i < n) {
            if (o >= cap)
                return FT_E_NO_SPACE;
            dst[o++] = 0;
        }
    }
    *out_len = o;
    return FT_OK;
}

/* ---- frames ---- */

/* Payload size fixed by msg_id, or -1 for an unknown id. */
static inline int ft_tl_payload_size(uint8_t msg_id) {
    switch (msg_id) {
    case FT_TL_GET_INFO:
    case FT_TL_START:
    case FT_TL_STOP:
    case FT_TL_STOP_RESET:
    case FT_TL_CLOCK_QUERY:
        return 0;
    case FT_TL_SET_RATE:
        return FT_TL_SET_RATE_SIZE;
    case FT_TL_PULSE:
        return FT_TL_PULSE_SIZE;
    case FT_TL_SET_OUTPUT:
        return FT_TL_SET_OUTPUT_SIZE;
    case FT_TL_SET_NAME:
        return FT_TL_SET_NAME_SIZE;
    case FT_TL_INFO:
        return FT_TL_INFO_SIZE;
    case FT_TL_ACK:
        return FT_TL_ACK_SIZE;
    case FT_TL_RATE:
        return FT_TL_RATE_SIZE;
    case FT_TL_CLOCK:
        return FT_TL_CLOCK_SIZE;
    case FT_TL_EVENT:
        return FT_TL_EVENT_SIZE;
    case FT_TL_ERROR:
        return FT_TL_ERROR_SIZE;
    default:
        return -1;
    }
}

/* Builds a whole wire frame: COBS(magic, version, msg_id, seq, payload, CRC) then 0x00.
 * Needs payload_len + 8 bytes of cap (at most FT_TL_MAX_WIRE). FT_E_LENGTH_MISMATCH if msg_id is
 * known and payload_len is not its size, or payload_len > FT_TL_MAX_PAYLOAD. Unknown ids are
 * allowed (tests send them on purpose). */
static inline ft_err ft_tl_encode(uint8_t *wire, size_t cap, uint8_t msg_id, uint8_t seq,
                                  const uint8_t *payload, uint8_t payload_len, size_t *wire_len) {
    int size = ft_tl_payload_size(msg_id);
    size_t n = (size_t)payload_len + FT_TL_OVERHEAD, i, code_pos = 0;
    uint16_t crc;
    if ((size >= 0 && size != (int)payload_len) || payload_len > FT_TL_MAX_PAYLOAD)
        return FT_E_LENGTH_MISMATCH;
    if (cap < n + 2)
        return FT_E_NO_SPACE;
    /* The body goes to wire[1..n]; COBS then runs in place: each zero becomes the code byte of the
     * block after it, wire[0] the first code. Blocks never reach 254 bytes since n <= 64. */
    wire[1] = FT_TL_MAGIC;
    wire[2] = FT_PROTOCOL_VERSION;
    wire[3] = msg_id;
    wire[4] = seq;
    for (i = 0; i < payload_len; i++)
        wire[5 + i] = payload[i];
    crc = ft_crc16(wire + 1, n - 2);
    ft_st_u16(wire + n - 1, crc);
    for (i = 1; i <= n; i++) {
        if (wire[i] == 0) {
            wire[code_pos] = (uint8_t)(i - code_pos);
            code_pos = i;
        }
    }
    wire[code_pos] = (uint8_t)(n + 1 - code_pos);
    wire[n + 1] = 0;
    *wire_len = n + 2;
    return FT_OK;
}

/* Decodes one frame (the COBS bytes before the delimiter) and checks, in SPEC order: COBS
 * (BAD_COBS), size >= 6 (TRUNCATED), CRC (BAD_CRC), magic (BAD_MAGIC), version (BAD_VERSION),
 * msg_id (UNKNOWN_TYPE), payload size (LENGTH_MISMATCH). Field values are checked by the
 * ft_tl_unpack_* functions. payload must hold FT_TL_MAX_PAYLOAD bytes (its content is undefined on
 * error). *msg_id and *seq are set whenever the body has 4 bytes, also on error, so that the device
 * can attribute an ERROR reply; 0 otherwise. Works as a stream: no copy of the body is kept. */
static inline ft_err ft_tl_decode(const uint8_t *frame, size_t len, uint8_t *msg_id, uint8_t *seq,
                                  uint8_t *payload, uint8_t *payload_len) {
    uint8_t hdr[FT_TL_HEADER] = {0, 0, 0, 0};
    uint8_t d0 = 0, d1 = 0; /* the last two decoded bytes: not yet in the CRC (they may be it) */
    uint16_t crc = FT_CRC16_INIT;
    size_t i = 0, n = 0;
    int size;
    *msg_id = 0;
    *seq = 0;
    *payload_len = 0;
    while (i < len) {
        uint8_t code = frame[i++];
        unsigned k;
        if (code == 0 || (size_t)(code - 1) > len - i)
            return FT_E_BAD_COBS;
        for (k = 1; k <= code; k++) {
            uint8_t b;
            if (k < code) {
                b = frame[i++];
                if (b == 0)
                    return FT_E_BAD_COBS;
            } else if (code == 0xFF || i == len) {
                break;
            } else {
                b = 0;
            }
            if (n >= 2)
                crc = ft_crc16_update(crc, d0);
            d0 = d1;
            d1 = b;
            if (n < FT_TL_HEADER)
                hdr[n] = b;
            else if (n - FT_TL_HEADER < FT_TL_MAX_PAYLOAD)
                payload[n - FT_TL_HEADER] = b;
            n++;
        }
    }
    if (n < FT_TL_HEADER + 2)
        return FT_E_TRUNCATED;
    *msg_id = hdr[2];
    *seq = hdr[3];
    if (crc != (uint16_t)((uint16_t)d0 | (uint16_t)((uint16_t)d1 << 8)))
        return FT_E_BAD_CRC;
    if (hdr[0] != FT_TL_MAGIC)
        return FT_E_BAD_MAGIC;
    if (hdr[1] != FT_PROTOCOL_VERSION)
        return FT_E_BAD_VERSION;
    size = ft_tl_payload_size(hdr[2]);
    if (size < 0)
        return FT_E_UNKNOWN_TYPE;
    if (n - FT_TL_OVERHEAD != (size_t)size)
        return FT_E_LENGTH_MISMATCH;
    *payload_len = (uint8_t)size;
    return FT_OK;
}

/* The ERROR-reply code for a decode error (TRUNCATED is reported as LENGTH_MISMATCH, BAD_FIELD as
 * BAD_ARG); 0 for FT_OK. */
static inline uint8_t ft_tl_err_code(ft_err e) {
    switch (e) {
    case FT_OK:
        return 0;
    case FT_E_BAD_CRC:
        return FT_TL_ERR_BAD_CRC;
    case FT_E_BAD_COBS:
        return FT_TL_ERR_BAD_COBS;
    case FT_E_UNKNOWN_TYPE:
        return FT_TL_ERR_UNKNOWN_TYPE;
    case FT_E_BAD_MAGIC:
        return FT_TL_ERR_BAD_MAGIC;
    case FT_E_BAD_VERSION:
        return FT_TL_ERR_BAD_VERSION;
    case FT_E_TRUNCATED:
    case FT_E_LENGTH_MISMATCH:
        return FT_TL_ERR_LENGTH_MISMATCH;
    default:
        return FT_TL_ERR_BAD_ARG;
    }
}

/* ---- byte-at-a-time receiver (firmware) ---- */

#define FT_TL_RX_NONE 0      /* need more bytes */
#define FT_TL_RX_FRAME 1     /* rx->buf[0 .. rx->len) holds a frame (delimiter excluded) */
#define FT_TL_RX_TOO_LONG -1 /* an over-long frame ended and was dropped: reply TOO_LONG */

typedef struct {
    uint8_t buf[FT_TL_MAX_WIRE];
    uint8_t len;      /* bytes in buf */
    uint8_t overflow; /* the frame under way is too long: dropping bytes up to its delimiter */
    uint8_t done;     /* the last push returned a frame: start afresh on the next byte */
} ft_tl_rx;

static inline void ft_tl_rx_init(ft_tl_rx *rx) {
    rx->len = 0;
    rx->overflow = 0;
    rx->done = 0;
}

/* Feeds one received byte. Returns FT_TL_RX_FRAME when a delimiter ends a non-empty frame (it stays
 * in rx->buf until the next push), FT_TL_RX_TOO_LONG when a delimiter ends a frame of more than
 * FT_TL_MAX_FRAME bytes (never stored past the buffer), else FT_TL_RX_NONE. */
static inline int ft_tl_rx_push(ft_tl_rx *rx, uint8_t byte) {
    if (rx->done) {
        rx->len = 0;
        rx->done = 0;
    }
    if (byte == 0) {
        if (rx->overflow) {
            rx->overflow = 0;
            rx->len = 0;
            return FT_TL_RX_TOO_LONG;
        }
        if (rx->len == 0)
            return FT_TL_RX_NONE;
        rx->done = 1;
        return FT_TL_RX_FRAME;
    }
    if (rx->overflow)
        return FT_TL_RX_NONE;
    if (rx->len >= FT_TL_MAX_FRAME) {
        rx->overflow = 1;
        return FT_TL_RX_NONE;
    }
    rx->buf[rx->len++] = byte;
    return FT_TL_RX_NONE;
}

/* ---- typed messages ----
 * ft_tl_pack_X writes the payload (FT_TL_X_SIZE bytes) and returns FT_OK, or FT_E_BAD_FIELD for a
 * value the SPEC does not allow. ft_tl_unpack_X checks the length (LENGTH_MISMATCH) then the fields
 * (BAD_FIELD). Messages without payload (GET_INFO, START, STOP, STOP_RESET, CLOCK_QUERY) have no
 * struct. */

typedef struct {
    uint8_t prescaler_code; /* 1 -> /1, 2 -> /8, 3 -> /64, 4 -> /256, 5 -> /1024 */
    uint16_t top;
} ft_tl_set_rate;

typedef struct {
    uint8_t channel;
    uint32_t frame; /* FT_TL_PULSE_NOW = now */
    uint16_t width_ticks;
} ft_tl_pulse;

typedef struct {
    uint8_t channel;
    uint8_t level; /* 0 or 1 */
} ft_tl_set_output;

typedef struct {
    char name[FT_TL_NAME_LEN + 1];
} ft_tl_set_name;

typedef struct {
    uint8_t protocol_version;
    uint8_t fw_major, fw_minor, fw_patch;
    uint8_t mcu; /* FT_TL_MCU_* */
    uint8_t n_outputs;
    uint32_t f_cpu;
    char name[FT_TL_NAME_LEN + 1];
} ft_tl_info;

typedef struct {
    uint8_t acked_id;
} ft_tl_ack;

typedef struct {
    uint32_t f_cpu;
    uint8_t prescaler_code;
    uint16_t top;
} ft_tl_rate;

typedef struct {
    uint32_t frame_count;
    uint16_t ticks, top;
    uint8_t running;
} ft_tl_clock;

typedef struct {
    uint8_t channel;
    uint8_t edge; /* 0 falling, 1 rising */
    uint32_t frame_count;
    uint16_t ticks;
} ft_tl_event;

typedef struct {
    uint8_t code;   /* FT_TL_ERR_* */
    uint8_t msg_id; /* the request's id, 0 if unknown */
} ft_tl_error;

static inline int ft_tl_prescaler_ok(uint8_t code) {
    return code >= 1 && code <= 5;
}

static inline ft_err ft_tl_pack_set_rate(uint8_t *p, const ft_tl_set_rate *m) {
    if (!ft_tl_prescaler_ok(m->prescaler_code))
        return FT_E_BAD_FIELD;
    p[0] = m->prescaler_code;
    ft_st_u16(p + 1, m->top);
    return FT_OK;
}
static inline ft_err ft_tl_unpack_set_rate(const uint8_t *p, uint8_t len, ft_tl_set_rate *m) {
    if (len != FT_TL_SET_RATE_SIZE)
        return FT_E_LENGTH_MISMATCH;
    m->prescaler_code = p[0];
    m->top = ft_ld_u16(p + 1);
    return ft_tl_prescaler_ok(m->prescaler_code) ? FT_OK : FT_E_BAD_FIELD;
}

static inline ft_err ft_tl_pack_pulse(uint8_t *p, const ft_tl_pulse *m) {
    p[0] = m->channel;
    ft_st_u32(p + 1, m->frame);
    ft_st_u16(p + 5, m->width_ticks);
    return FT_OK;
}
static inline ft_err ft_tl_unpack_pulse(const uint8_t *p, uint8_t len, ft_tl_pulse *m) {
    if (len != FT_TL_PULSE_SIZE)
        return FT_E_LENGTH_MISMATCH;
    m->channel = p[0];
    m->frame = ft_ld_u32(p + 1);
    m->width_ticks = ft_ld_u16(p + 5);
    return FT_OK;
}

static inline ft_err ft_tl_pack_set_output(uint8_t *p, const ft_tl_set_output *m) {
    if (m->level > 1)
        return FT_E_BAD_FIELD;
    p[0] = m->channel;
    p[1] = m->level;
    return FT_OK;
}
static inline ft_err ft_tl_unpack_set_output(const uint8_t *p, uint8_t len, ft_tl_set_output *m) {
    if (len != FT_TL_SET_OUTPUT_SIZE)
        return FT_E_LENGTH_MISMATCH;
    m->channel = p[0];
    m->level = p[1];
    return m->level > 1 ? FT_E_BAD_FIELD : FT_OK;
}

static inline ft_err ft_tl_pack_set_name(uint8_t *p, const ft_tl_set_name *m) {
    return ft_text_store(p, FT_TL_NAME_LEN, m->name);
}
static inline ft_err ft_tl_unpack_set_name(const uint8_t *p, uint8_t len, ft_tl_set_name *m) {
    if (len != FT_TL_SET_NAME_SIZE)
        return FT_E_LENGTH_MISMATCH;
    if (ft_text_check(p, FT_TL_NAME_LEN) != FT_OK)
        return FT_E_BAD_FIELD;
    ft_text_load(m->name, p, FT_TL_NAME_LEN);
    return FT_OK;
}

static inline ft_err ft_tl_pack_info(uint8_t *p, const ft_tl_info *m) {
    if (m->mcu < 1 || m->mcu > 2)
        return FT_E_BAD_FIELD;
    p[0] = m->protocol_version;
    p[1] = m->fw_major;
    p[2] = m->fw_minor;
    p[3] = m->fw_patch;
    p[4] = m->mcu;
    p[5] = m->n_outputs;
    ft_st_u16(p + 6, 0); /* reserved */
    ft_st_u32(p + 8, m->f_cpu);
    return ft_text_store(p + 12, FT_TL_NAME_LEN, m->name);
}
static inline ft_err ft_tl_unpack_info(const uint8_t *p, uint8_t len, ft_tl_info *m) {
    if (len != FT_TL_INFO_SIZE)
        return FT_E_LENGTH_MISMATCH;
    m->protocol_version = p[0];
    m->fw_major = p[1];
    m->fw_minor = p[2];
    m->fw_patch = p[3];
    m->mcu = p[4];
    m->n_outputs = p[5];
    m->f_cpu = ft_ld_u32(p + 8);
    if (m->mcu < 1 || m->mcu > 2 || ft_text_check(p + 12, FT_TL_NAME_LEN) != FT_OK)
        return FT_E_BAD_FIELD;
    ft_text_load(m->name, p + 12, FT_TL_NAME_LEN);
    return FT_OK;
}

static inline ft_err ft_tl_pack_ack(uint8_t *p, const ft_tl_ack *m) {
    p[0] = m->acked_id;
    return FT_OK;
}
static inline ft_err ft_tl_unpack_ack(const uint8_t *p, uint8_t len, ft_tl_ack *m) {
    if (len != FT_TL_ACK_SIZE)
        return FT_E_LENGTH_MISMATCH;
    m->acked_id = p[0];
    return FT_OK;
}

static inline ft_err ft_tl_pack_rate(uint8_t *p, const ft_tl_rate *m) {
    if (!ft_tl_prescaler_ok(m->prescaler_code))
        return FT_E_BAD_FIELD;
    ft_st_u32(p, m->f_cpu);
    p[4] = m->prescaler_code;
    ft_st_u16(p + 5, m->top);
    return FT_OK;
}
static inline ft_err ft_tl_unpack_rate(const uint8_t *p, uint8_t len, ft_tl_rate *m) {
    if (len != FT_TL_RATE_SIZE)
        return FT_E_LENGTH_MISMATCH;
    m->f_cpu = ft_ld_u32(p);
    m->prescaler_code = p[4];
    m->top = ft_ld_u16(p + 5);
    return ft_tl_prescaler_ok(m->prescaler_code) ? FT_OK : FT_E_BAD_FIELD;
}

static inline ft_err ft_tl_pack_clock(uint8_t *p, const ft_tl_clock *m) {
    ft_st_u32(p, m->frame_count);
    ft_st_u16(p + 4, m->ticks);
    ft_st_u16(p + 6, m->top);
    p[8] = m->running;
    return FT_OK;
}
static inline ft_err ft_tl_unpack_clock(const uint8_t *p, uint8_t len, ft_tl_clock *m) {
    if (len != FT_TL_CLOCK_SIZE)
        return FT_E_LENGTH_MISMATCH;
    m->frame_count = ft_ld_u32(p);
    m->ticks = ft_ld_u16(p + 4);
    m->top = ft_ld_u16(p + 6);
    m->running = p[8];
    return FT_OK;
}

static inline ft_err ft_tl_pack_event(uint8_t *p, const ft_tl_event *m) {
    if (m->edge > 1)
        return FT_E_BAD_FIELD;
    p[0] = m->channel;
    p[1] = m->edge;
    ft_st_u32(p + 2, m->frame_count);
    ft_st_u16(p + 6, m->ticks);
    return FT_OK;
}
static inline ft_err ft_tl_unpack_event(const uint8_t *p, uint8_t len, ft_tl_event *m) {
    if (len != FT_TL_EVENT_SIZE)
        return FT_E_LENGTH_MISMATCH;
    m->channel = p[0];
    m->edge = p[1];
    m->frame_count = ft_ld_u32(p + 2);
    m->ticks = ft_ld_u16(p + 6);
    return m->edge > 1 ? FT_E_BAD_FIELD : FT_OK;
}

static inline ft_err ft_tl_pack_error(uint8_t *p, const ft_tl_error *m) {
    p[0] = m->code;
    p[1] = m->msg_id;
    return FT_OK;
}
static inline ft_err ft_tl_unpack_error(const uint8_t *p, uint8_t len, ft_tl_error *m) {
    if (len != FT_TL_ERROR_SIZE)
        return FT_E_LENGTH_MISMATCH;
    m->code = p[0];
    m->msg_id = p[1];
    return FT_OK;
}

#endif /* FLYTRACK_TRIGGER_LINK_H */

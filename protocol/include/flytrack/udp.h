/* FlyTrack UDP messages (protocol/SPEC.md section 1): edge <-> host, host -> stimulus programs.
 *
 * Header-only C99, Linux side. For each message X: a struct, `ft_X_encode(buf, cap, ...,
 * &out_len)` and `ft_X_decode(buf, len, ...)`. Structs hold the header's `flags` masked to the bits
 * the type defines (others are written 0 and ignored on reading); reserved fields are not kept
 * (written 0, ignored on reading). Text fields of n bytes are char[n + 1], NUL-terminated (wire.h).
 *
 * Decoders check in SPEC order and return the first error:
 * 1. datagram < 8 bytes: TRUNCATED; magic: BAD_MAGIC; version: BAD_VERSION;
 * 2. type unknown, or not the decoder's: UNKNOWN_TYPE;
 * 3. datagram < 8 + the type's fixed part: TRUNCATED;
 * 4. header length != datagram - 8: LENGTH_MISMATCH;
 * 5. element count above the type's maximum, more elements than the payload holds, or (FEATURES
 *    without SPLIT) n_points > total_points: COUNT_OVERFLOW;
 * 6. bytes after the elements (or past a fixed-size type's size): LENGTH_MISMATCH;
 * 7. NaN/infinity checks, in field order: NOT_FINITE;
 * 8. every other field check (enums, text padding, parts, image geometry): BAD_FIELD.
 * Encoders run the same field checks (COUNT_OVERFLOW, NOT_FINITE, BAD_FIELD), so they never
 * produce a message a reader rejects, then give FT_E_NO_SPACE if cap is too small.
 * Floats travel as their IEEE-754 bits (memcpy), so NaN payloads survive a round trip.
 */
#ifndef FLYTRACK_UDP_H
#define FLYTRACK_UDP_H

#include <string.h>

#include "wire.h"

/* Floats travel as IEEE-754 binary32/binary64 bits: refuse to build where float/double differ
 * (e.g. avr-gcc, whose double is 32 bits; the AVR needs only trigger_link.h). */
typedef char
    ft_udp_needs_ieee754_float_and_double[(sizeof(float) == 4 && sizeof(double) == 8) ? 1 : -1];

#define FT_UDP_MAGIC0 0x46 /* 'F' */
#define FT_UDP_MAGIC1 0x54 /* 'T' */
#define FT_UDP_HEADER 8
#define FT_UDP_MAX_DATAGRAM 1472

#define FT_MSG_FEATURES 0x01
#define FT_MSG_STATUS 0x02
#define FT_MSG_CONTROL 0x03
#define FT_MSG_CONTROL_ACK 0x04
#define FT_MSG_IMAGE 0x05
#define FT_MSG_DVS_CLUSTERS 0x10
#define FT_MSG_DVS_WINGBEAT 0x11
#define FT_MSG_LIVE_ESTIMATES 0x20

/* Fixed part sizes and record sizes (payload bytes, after the 8-byte header) */
#define FT_FEATURES_FIXED 56
#define FT_POINT_SIZE 44
#define FT_FEATURES_MAX_POINTS 32
#define FT_STATUS_SIZE 144
#define FT_CONTROL_SIZE 40
#define FT_CONTROL_ACK_SIZE 56
#define FT_IMAGE_FIXED 36
#define FT_IMAGE_MAX_CHUNK 1428
#define FT_DVS_CLUSTERS_FIXED 48
#define FT_DVS_CLUSTER_SIZE 40
#define FT_DVS_MAX_CLUSTERS 35
#define FT_DVS_WINGBEAT_FIXED 24
#define FT_WING_EDGE_SIZE 20
#define FT_DVS_MAX_EDGES 8
#define FT_LIVE_FIXED 32
#define FT_LIVE_OBJECT_SIZE 52
#define FT_LIVE_MAX_OBJECTS 27

/* Flags */
#define FT_FEATURES_SPLIT 0x0001u
#define FT_FEATURES_TRUNCATED 0x0002u
#define FT_LIVE_SPLIT 0x0001u
#define FT_DVS_SYNCED 0x0001u /* DVS_CLUSTERS: trigger_frame and frame_period_us are valid */

/* Enumerations */
#define FT_PIXFMT_MONO8 0
#define FT_PIXFMT_MONO16 1
#define FT_PIXFMT_YUYV 2
#define FT_STATE_IDLE 0
#define FT_STATE_RUNNING 1
#define FT_STATE_ERROR 2
#define FT_STATE_STOPPED 3
#define FT_CMD_SET_PARAM 1
#define FT_CMD_TAKE_BACKGROUND 2
#define FT_CMD_SEND_FULL_IMAGE 3
#define FT_CMD_SEND_REGIONS 4
#define FT_CMD_START 5
#define FT_CMD_STOP 6
#define FT_ACK_OK 0
#define FT_ACK_UNKNOWN_COMMAND 1
#define FT_ACK_UNKNOWN_PARAM 2
#define FT_ACK_BAD_VALUE 3
#define FT_ACK_FAILED 4
#define FT_IMAGE_FULL_FRAME 0
#define FT_IMAGE_REGION 1
#define FT_CAMERA_ANY 0xFFFFu

#define FT_STATUS_NAME_LEN 32
#define FT_STATUS_ERROR_LEN 64
#define FT_CONTROL_PARAM_LEN 24
#define FT_CONTROL_ACK_MESSAGE_LEN 48

/* ---- floats as bits ---- */

static inline uint32_t ft_f32_bits(float f) {
    uint32_t u;
    memcpy(&u, &f, sizeof u);
    return u;
}
static inline uint64_t ft_f64_bits(double d) {
    uint64_t u;
    memcpy(&u, &d, sizeof u);
    return u;
}
static inline float ft_ld_f32(const uint8_t *p) {
    uint32_t u = ft_ld_u32(p);
    float f;
    memcpy(&f, &u, sizeof f);
    return f;
}
static inline double ft_ld_f64(const uint8_t *p) {
    uint64_t u = ft_ld_u64(p);
    double d;
    memcpy(&d, &u, sizeof d);
    return d;
}
static inline void ft_st_f32(uint8_t *p, float f) {
    ft_st_u32(p, ft_f32_bits(f));
}
static inline void ft_st_f64(uint8_t *p, double d) {
    ft_st_u64(p, ft_f64_bits(d));
}
/* Tests on the bits: no floating-point operation, so no FP exception or flag is involved. */
static inline int ft_f32_finite(float f) {
    return (ft_f32_bits(f) & 0x7F800000u) != 0x7F800000u;
}
static inline int ft_f32_inf(float f) {
    return (ft_f32_bits(f) & 0x7FFFFFFFu) == 0x7F800000u;
}
static inline int ft_f64_finite(double d) {
    return (ft_f64_bits(d) & 0x7FF0000000000000ull) != 0x7FF0000000000000ull;
}

/* ---- common header ---- */

static inline int ft_udp_fixed_size(uint8_t type) {
    switch (type) {
    case FT_MSG_FEATURES:
        return FT_FEATURES_FIXED;
    case FT_MSG_STATUS:
        return FT_STATUS_SIZE;
    case FT_MSG_CONTROL:
        return FT_CONTROL_SIZE;
    case FT_MSG_CONTROL_ACK:
        return FT_CONTROL_ACK_SIZE;
    case FT_MSG_IMAGE:
        return FT_IMAGE_FIXED;
    case FT_MSG_DVS_CLUSTERS:
        return FT_DVS_CLUSTERS_FIXED;
    case FT_MSG_DVS_WINGBEAT:
        return FT_DVS_WINGBEAT_FIXED;
    case FT_MSG_LIVE_ESTIMATES:
        return FT_LIVE_FIXED;
    default:
        return -1;
    }
}

/* The flag bits a type defines */
static inline uint16_t ft_udp_flag_mask(uint8_t type) {
    switch (type) {
    case FT_MSG_FEATURES:
        return FT_FEATURES_SPLIT | FT_FEATURES_TRUNCATED;
    case FT_MSG_LIVE_ESTIMATES:
        return FT_LIVE_SPLIT;
    case FT_MSG_DVS_CLUSTERS:
        return FT_DVS_SYNCED;
    default:
        return 0;
    }
}

/* Checks the common header of a datagram up to its length field: TRUNCATED, BAD_MAGIC,
 * BAD_VERSION, UNKNOWN_TYPE, TRUNCATED (shorter than the type's fixed part), LENGTH_MISMATCH
 * (length field != len - 8). On FT_OK *type is the message type (set also for later errors when
 * the type byte was read). */
static inline ft_err ft_peek_type(const uint8_t *buf, size_t len, uint8_t *type) {
    int fixed;
    *type = 0;
    if (len < FT_UDP_HEADER)
        return FT_E_TRUNCATED;
    if (buf[0] != FT_UDP_MAGIC0 || buf[1] != FT_UDP_MAGIC1)
        return FT_E_BAD_MAGIC;
    if (buf[2] != FT_PROTOCOL_VERSION)
        return FT_E_BAD_VERSION;
    *type = buf[3];
    fixed = ft_udp_fixed_size(buf[3]);
    if (fixed < 0)
        return FT_E_UNKNOWN_TYPE;
    if (len - FT_UDP_HEADER < (size_t)fixed)
        return FT_E_TRUNCATED;
    if ((size_t)ft_ld_u16(buf + 4) != len - FT_UDP_HEADER)
        return FT_E_LENGTH_MISMATCH;
    return FT_OK;
}

/* Header + element-count checks shared by the decoders. n_max = 0 and rec = 0 for fixed-size
 * types; count_ok = 0 adds a type-specific COUNT_OVERFLOW (checked after the generic ones). On
 * FT_OK *flags holds the header flags, masked to the type's bits. */
static inline ft_err ft_udp_check(const uint8_t *buf, size_t len, uint8_t want, uint32_t n,
                                  uint32_t n_max, uint32_t rec, int count_ok, uint16_t *flags) {
    uint8_t type;
    uint32_t payload, need;
    ft_err e = ft_peek_type(buf, len, &type);
    /* Another known type: this decoder does not know it (its size checks do not apply). */
    if ((e == FT_OK || e == FT_E_TRUNCATED || e == FT_E_LENGTH_MISMATCH) && type != 0 &&
        type != want)
        return FT_E_UNKNOWN_TYPE;
    if (e != FT_OK)
        return e;
    payload = (uint32_t)(len - FT_UDP_HEADER);
    need = (uint32_t)ft_udp_fixed_size(want) + n * rec;
    if (n > n_max || need > payload || !count_ok)
        return FT_E_COUNT_OVERFLOW;
    if (need != payload)
        return FT_E_LENGTH_MISMATCH;
    *flags = (uint16_t)(ft_ld_u16(buf + 6) & ft_udp_flag_mask(want));
    return FT_OK;
}

/* Writes the common header; the caller has checked cap. */
static inline void ft_udp_put_header(uint8_t *buf, uint8_t type, size_t payload, uint16_t flags) {
    buf[0] = FT_UDP_MAGIC0;
    buf[1] = FT_UDP_MAGIC1;
    buf[2] = FT_PROTOCOL_VERSION;
    buf[3] = type;
    ft_st_u16(buf + 4, (uint16_t)payload);
    ft_st_u16(buf + 6, (uint16_t)(flags & ft_udp_flag_mask(type)));
}

/* ---- FEATURES (0x01) ---- */

typedef struct {
    uint16_t flags; /* FT_FEATURES_SPLIT, FT_FEATURES_TRUNCATED */
    uint16_t camera_index;
    uint16_t n_points;
    uint32_t seq;
    uint64_t camera_frame;
    int64_t trigger_frame; /* -1: unknown */
    uint64_t device_timestamp_ns;
    uint64_t edge_recv_ns;
    uint64_t edge_done_ns;
    uint16_t total_points;
    uint8_t part_index;
    uint8_t part_count;
} ft_features_hdr;

typedef struct {
    float x_dist, y_dist;
    float x_undist, y_undist;
    float area;
    float peak_diff;
    float orientation;  /* NaN allowed */
    float eccentricity; /* NaN allowed */
    uint16_t cur_val;
    float mean_val;
    float sumsq_val;
} ft_point;

static inline ft_err ft_point_check(const ft_point *q) {
    if (!ft_f32_finite(q->x_dist) || !ft_f32_finite(q->y_dist) || !ft_f32_finite(q->x_undist) ||
        !ft_f32_finite(q->y_undist) || !ft_f32_finite(q->area) || !ft_f32_finite(q->peak_diff) ||
        ft_f32_inf(q->orientation) || ft_f32_inf(q->eccentricity) || !ft_f32_finite(q->mean_val) ||
        !ft_f32_finite(q->sumsq_val))
        return FT_E_NOT_FINITE;
    return FT_OK;
}

static inline ft_err ft_features_check(const ft_features_hdr *h, const ft_point *pts) {
    uint32_t i;
    if (h->n_points > FT_FEATURES_MAX_POINTS ||
        (!(h->flags & FT_FEATURES_SPLIT) && h->n_points > h->total_points))
        return FT_E_COUNT_OVERFLOW;
    for (i = 0; i < h->n_points; i++)
        if (ft_point_check(&pts[i]) != FT_OK)
            return FT_E_NOT_FINITE;
    if (h->part_count < 1 || h->part_index >= h->part_count)
        return FT_E_BAD_FIELD;
    return FT_OK;
}

/* pts: h->n_points points (may be NULL when n_points is 0). */
static inline ft_err ft_features_encode(uint8_t *buf, size_t cap, const ft_features_hdr *h,
                                        const ft_point *pts, size_t *out_len) {
    size_t payload, i;
    uint8_t *p;
    ft_err e = ft_features_check(h, pts);
    if (e != FT_OK)
        return e;
    payload = FT_FEATURES_FIXED + (size_t)h->n_points * FT_POINT_SIZE;
    if (cap < FT_UDP_HEADER + payload)
        return FT_E_NO_SPACE;
    ft_udp_put_header(buf, FT_MSG_FEATURES, payload, h->flags);
    p = buf + FT_UDP_HEADER;
    ft_st_u16(p + 0, h->camera_index);
    ft_st_u16(p + 2, h->n_points);
    ft_st_u32(p + 4, h->seq);
    ft_st_u64(p + 8, h->camera_frame);
    ft_st_i64(p + 16, h->trigger_frame);
    ft_st_u64(p + 24, h->device_timestamp_ns);
    ft_st_u64(p + 32, h->edge_recv_ns);
    ft_st_u64(p + 40, h->edge_done_ns);
    ft_st_u16(p + 48, h->total_points);
    p[50] = h->part_index;
    p[51] = h->part_count;
    ft_st_u32(p + 52, 0);
    for (i = 0; i < h->n_points; i++) {
        uint8_t *q = p + FT_FEATURES_FIXED + i * FT_POINT_SIZE;
        const ft_point *s = &pts[i];
        ft_st_f32(q + 0, s->x_dist);
        ft_st_f32(q + 4, s->y_dist);
        ft_st_f32(q + 8, s->x_undist);
        ft_st_f32(q + 12, s->y_undist);
        ft_st_f32(q + 16, s->area);
        ft_st_f32(q + 20, s->peak_diff);
        ft_st_f32(q + 24, s->orientation);
        ft_st_f32(q + 28, s->eccentricity);
        ft_st_u16(q + 32, s->cur_val);
        ft_st_u16(q + 34, 0);
        ft_st_f32(q + 36, s->mean_val);
        ft_st_f32(q + 40, s->sumsq_val);
    }
    *out_len = FT_UDP_HEADER + payload;
    return FT_OK;
}

/* pts: room for FT_FEATURES_MAX_POINTS points; h->n_points of them are written. */
static inline ft_err ft_features_decode(const uint8_t *buf, size_t len, ft_features_hdr *h,
                                        ft_point *pts) {
    const uint8_t *p = buf; /* + header once the length is checked */
    uint32_t n = 0, i;
    int count_ok = 1;
    ft_err e;
    if (len >= FT_UDP_HEADER + FT_FEATURES_FIXED) { /* else the header check fails first */
        n = ft_ld_u16(p + FT_UDP_HEADER + 2);
        count_ok =
            (ft_ld_u16(buf + 6) & FT_FEATURES_SPLIT) || n <= ft_ld_u16(p + FT_UDP_HEADER + 48);
    }
    e = ft_udp_check(buf, len, FT_MSG_FEATURES, n, FT_FEATURES_MAX_POINTS, FT_POINT_SIZE, count_ok,
                     &h->flags);
    if (e != FT_OK)
        return e;
    p += FT_UDP_HEADER;
    h->camera_index = ft_ld_u16(p + 0);
    h->n_points = (uint16_t)n;
    h->seq = ft_ld_u32(p + 4);
    h->camera_frame = ft_ld_u64(p + 8);
    h->trigger_frame = ft_ld_i64(p + 16);
    h->device_timestamp_ns = ft_ld_u64(p + 24);
    h->edge_recv_ns = ft_ld_u64(p + 32);
    h->edge_done_ns = ft_ld_u64(p + 40);
    h->total_points = ft_ld_u16(p + 48);
    h->part_index = p[50];
    h->part_count = p[51];
    for (i = 0; i < n; i++) {
        const uint8_t *q = p + FT_FEATURES_FIXED + i * FT_POINT_SIZE;
        ft_point *d = &pts[i];
        d->x_dist = ft_ld_f32(q + 0);
        d->y_dist = ft_ld_f32(q + 4);
        d->x_undist = ft_ld_f32(q + 8);
        d->y_undist = ft_ld_f32(q + 12);
        d->area = ft_ld_f32(q + 16);
        d->peak_diff = ft_ld_f32(q + 20);
        d->orientation = ft_ld_f32(q + 24);
        d->eccentricity = ft_ld_f32(q + 28);
        d->cur_val = ft_ld_u16(q + 32);
        d->mean_val = ft_ld_f32(q + 36);
        d->sumsq_val = ft_ld_f32(q + 40);
    }
    return ft_features_check(h, pts);
}

/* ---- STATUS (0x02) ---- */

typedef struct {
    uint16_t flags; /* 0 */
    uint16_t camera_index;
    uint16_t width, height;
    uint8_t pixel_format; /* FT_PIXFMT_* */
    uint8_t state;        /* FT_STATE_* */
    uint32_t seq;
    uint32_t last_error_code;
    uint64_t frames_seen;
    uint64_t frames_dropped;
    float fps, proc_us_mean, proc_us_max; /* finite */
    char camera_name[FT_STATUS_NAME_LEN + 1];
    char last_error[FT_STATUS_ERROR_LEN + 1];
} ft_status;

static inline ft_err ft_status_encode(uint8_t *buf, size_t cap, const ft_status *m,
                                      size_t *out_len) {
    uint8_t *p = buf; /* + header once cap is checked */
    if (!ft_f32_finite(m->fps) || !ft_f32_finite(m->proc_us_mean) || !ft_f32_finite(m->proc_us_max))
        return FT_E_NOT_FINITE;
    if (m->pixel_format > FT_PIXFMT_YUYV || m->state > FT_STATE_STOPPED ||
        !ft_text_fits(m->camera_name, FT_STATUS_NAME_LEN) ||
        !ft_text_fits(m->last_error, FT_STATUS_ERROR_LEN))
        return FT_E_BAD_FIELD;
    if (cap < FT_UDP_HEADER + FT_STATUS_SIZE)
        return FT_E_NO_SPACE;
    p += FT_UDP_HEADER;
    ft_text_store(p + 48, FT_STATUS_NAME_LEN, m->camera_name);
    ft_text_store(p + 80, FT_STATUS_ERROR_LEN, m->last_error);
    ft_udp_put_header(buf, FT_MSG_STATUS, FT_STATUS_SIZE, m->flags);
    ft_st_u16(p + 0, m->camera_index);
    ft_st_u16(p + 2, m->width);
    ft_st_u16(p + 4, m->height);
    p[6] = m->pixel_format;
    p[7] = m->state;
    ft_st_u32(p + 8, m->seq);
    ft_st_u32(p + 12, m->last_error_code);
    ft_st_u64(p + 16, m->frames_seen);
    ft_st_u64(p + 24, m->frames_dropped);
    ft_st_f32(p + 32, m->fps);
    ft_st_f32(p + 36, m->proc_us_mean);
    ft_st_f32(p + 40, m->proc_us_max);
    ft_st_u32(p + 44, 0);
    *out_len = FT_UDP_HEADER + FT_STATUS_SIZE;
    return FT_OK;
}

static inline ft_err ft_status_decode(const uint8_t *buf, size_t len, ft_status *m) {
    const uint8_t *p = buf; /* + header once the length is checked */
    ft_err e = ft_udp_check(buf, len, FT_MSG_STATUS, 0, 0, 0, 1, &m->flags);
    if (e != FT_OK)
        return e;
    p += FT_UDP_HEADER;
    m->camera_index = ft_ld_u16(p + 0);
    m->width = ft_ld_u16(p + 2);
    m->height = ft_ld_u16(p + 4);
    m->pixel_format = p[6];
    m->state = p[7];
    m->seq = ft_ld_u32(p + 8);
    m->last_error_code = ft_ld_u32(p + 12);
    m->frames_seen = ft_ld_u64(p + 16);
    m->frames_dropped = ft_ld_u64(p + 24);
    m->fps = ft_ld_f32(p + 32);
    m->proc_us_mean = ft_ld_f32(p + 36);
    m->proc_us_max = ft_ld_f32(p + 40);
    ft_text_load(m->camera_name, p + 48, FT_STATUS_NAME_LEN);
    ft_text_load(m->last_error, p + 80, FT_STATUS_ERROR_LEN);
    if (!ft_f32_finite(m->fps) || !ft_f32_finite(m->proc_us_mean) || !ft_f32_finite(m->proc_us_max))
        return FT_E_NOT_FINITE;
    if (m->pixel_format > FT_PIXFMT_YUYV || m->state > FT_STATE_STOPPED ||
        ft_text_check(p + 48, FT_STATUS_NAME_LEN) != FT_OK ||
        ft_text_check(p + 80, FT_STATUS_ERROR_LEN) != FT_OK)
        return FT_E_BAD_FIELD;
    return FT_OK;
}

/* ---- CONTROL (0x03) ---- */

typedef struct {
    uint16_t flags; /* 0 */
    uint32_t request_id;
    uint16_t camera_index; /* FT_CAMERA_ANY = whatever camera the edge serves */
    uint8_t command;       /* FT_CMD_* */
    char param[FT_CONTROL_PARAM_LEN + 1];
    double value; /* finite */
} ft_control;

static inline ft_err ft_control_encode(uint8_t *buf, size_t cap, const ft_control *m,
                                       size_t *out_len) {
    uint8_t *p = buf; /* + header once cap is checked */
    if (!ft_f64_finite(m->value))
        return FT_E_NOT_FINITE;
    if (m->command < FT_CMD_SET_PARAM || m->command > FT_CMD_STOP ||
        !ft_text_fits(m->param, FT_CONTROL_PARAM_LEN))
        return FT_E_BAD_FIELD;
    if (cap < FT_UDP_HEADER + FT_CONTROL_SIZE)
        return FT_E_NO_SPACE;
    p += FT_UDP_HEADER;
    ft_text_store(p + 8, FT_CONTROL_PARAM_LEN, m->param);
    ft_udp_put_header(buf, FT_MSG_CONTROL, FT_CONTROL_SIZE, m->flags);
    ft_st_u32(p + 0, m->request_id);
    ft_st_u16(p + 4, m->camera_index);
    p[6] = m->command;
    p[7] = 0;
    ft_st_f64(p + 32, m->value);
    *out_len = FT_UDP_HEADER + FT_CONTROL_SIZE;
    return FT_OK;
}

static inline ft_err ft_control_decode(const uint8_t *buf, size_t len, ft_control *m) {
    const uint8_t *p = buf; /* + header once the length is checked */
    ft_err e = ft_udp_check(buf, len, FT_MSG_CONTROL, 0, 0, 0, 1, &m->flags);
    if (e != FT_OK)
        return e;
    p += FT_UDP_HEADER;
    m->request_id = ft_ld_u32(p + 0);
    m->camera_index = ft_ld_u16(p + 4);
    m->command = p[6];
    ft_text_load(m->param, p + 8, FT_CONTROL_PARAM_LEN);
    m->value = ft_ld_f64(p + 32);
    if (!ft_f64_finite(m->value))
        return FT_E_NOT_FINITE;
    if (m->command < FT_CMD_SET_PARAM || m->command > FT_CMD_STOP ||
        ft_text_check(p + 8, FT_CONTROL_PARAM_LEN) != FT_OK)
        return FT_E_BAD_FIELD;
    return FT_OK;
}

/* ---- CONTROL_ACK (0x04) ---- */

typedef struct {
    uint16_t flags; /* 0 */
    uint32_t request_id;
    uint16_t camera_index;
    uint8_t command; /* echoed as received: not checked, an unknown one is acked UNKNOWN_COMMAND */
    uint8_t status;  /* FT_ACK_* */
    char message[FT_CONTROL_ACK_MESSAGE_LEN + 1];
} ft_control_ack;

static inline ft_err ft_control_ack_encode(uint8_t *buf, size_t cap, const ft_control_ack *m,
                                           size_t *out_len) {
    uint8_t *p = buf; /* + header once cap is checked */
    if (m->status > FT_ACK_FAILED || !ft_text_fits(m->message, FT_CONTROL_ACK_MESSAGE_LEN))
        return FT_E_BAD_FIELD;
    if (cap < FT_UDP_HEADER + FT_CONTROL_ACK_SIZE)
        return FT_E_NO_SPACE;
    p += FT_UDP_HEADER;
    ft_text_store(p + 8, FT_CONTROL_ACK_MESSAGE_LEN, m->message);
    ft_udp_put_header(buf, FT_MSG_CONTROL_ACK, FT_CONTROL_ACK_SIZE, m->flags);
    ft_st_u32(p + 0, m->request_id);
    ft_st_u16(p + 4, m->camera_index);
    p[6] = m->command;
    p[7] = m->status;
    *out_len = FT_UDP_HEADER + FT_CONTROL_ACK_SIZE;
    return FT_OK;
}

static inline ft_err ft_control_ack_decode(const uint8_t *buf, size_t len, ft_control_ack *m) {
    const uint8_t *p = buf; /* + header once the length is checked */
    ft_err e = ft_udp_check(buf, len, FT_MSG_CONTROL_ACK, 0, 0, 0, 1, &m->flags);
    if (e != FT_OK)
        return e;
    p += FT_UDP_HEADER;
    m->request_id = ft_ld_u32(p + 0);
    m->camera_index = ft_ld_u16(p + 4);
    m->command = p[6];
    m->status = p[7];
    ft_text_load(m->message, p + 8, FT_CONTROL_ACK_MESSAGE_LEN);
    if (m->status > FT_ACK_FAILED || ft_text_check(p + 8, FT_CONTROL_ACK_MESSAGE_LEN) != FT_OK)
        return FT_E_BAD_FIELD;
    return FT_OK;
}

/* ---- IMAGE (0x05) ---- */

typedef struct {
    uint16_t flags; /* 0 */
    uint16_t camera_index;
    uint8_t kind;            /* FT_IMAGE_FULL_FRAME, FT_IMAGE_REGION */
    uint8_t bytes_per_pixel; /* 1 or 2 */
    uint32_t image_id;
    uint64_t camera_frame;
    uint16_t x0, y0, width, height;
    uint32_t offset;      /* of this chunk in the image, bytes */
    uint32_t total_bytes; /* width * height * bytes_per_pixel */
    uint16_t chunk_len;   /* <= FT_IMAGE_MAX_CHUNK */
    const uint8_t *data;  /* chunk_len bytes; on decode it points into the datagram */
} ft_image;

static inline ft_err ft_image_check(const ft_image *m) {
    if (m->chunk_len > FT_IMAGE_MAX_CHUNK)
        return FT_E_COUNT_OVERFLOW;
    if (m->kind > FT_IMAGE_REGION || m->bytes_per_pixel < 1 || m->bytes_per_pixel > 2 ||
        (uint64_t)m->offset + m->chunk_len > m->total_bytes ||
        (uint64_t)m->width * m->height * m->bytes_per_pixel != m->total_bytes)
        return FT_E_BAD_FIELD;
    return FT_OK;
}

static inline ft_err ft_image_encode(uint8_t *buf, size_t cap, const ft_image *m, size_t *out_len) {
    uint8_t *p = buf; /* + header once cap is checked */
    size_t payload;
    ft_err e = ft_image_check(m);
    if (e != FT_OK)
        return e;
    payload = FT_IMAGE_FIXED + (size_t)m->chunk_len;
    if (cap < FT_UDP_HEADER + payload)
        return FT_E_NO_SPACE;
    p += FT_UDP_HEADER;
    ft_udp_put_header(buf, FT_MSG_IMAGE, payload, m->flags);
    ft_st_u16(p + 0, m->camera_index);
    p[2] = m->kind;
    p[3] = m->bytes_per_pixel;
    ft_st_u32(p + 4, m->image_id);
    ft_st_u64(p + 8, m->camera_frame);
    ft_st_u16(p + 16, m->x0);
    ft_st_u16(p + 18, m->y0);
    ft_st_u16(p + 20, m->width);
    ft_st_u16(p + 22, m->height);
    ft_st_u32(p + 24, m->offset);
    ft_st_u32(p + 28, m->total_bytes);
    ft_st_u16(p + 32, m->chunk_len);
    ft_st_u16(p + 34, 0);
    if (m->chunk_len)
        memmove(p + FT_IMAGE_FIXED, m->data, m->chunk_len);
    *out_len = FT_UDP_HEADER + payload;
    return FT_OK;
}

static inline ft_err ft_image_decode(const uint8_t *buf, size_t len, ft_image *m) {
    const uint8_t *p = buf; /* + header once the length is checked */
    uint32_t n = 0;
    ft_err e;
    if (len >= FT_UDP_HEADER + FT_IMAGE_FIXED)
        n = ft_ld_u16(p + FT_UDP_HEADER + 32);
    e = ft_udp_check(buf, len, FT_MSG_IMAGE, n, FT_IMAGE_MAX_CHUNK, 1, 1, &m->flags);
    if (e != FT_OK)
        return e;
    p += FT_UDP_HEADER;
    m->camera_index = ft_ld_u16(p + 0);
    m->kind = p[2];
    m->bytes_per_pixel = p[3];
    m->image_id = ft_ld_u32(p + 4);
    m->camera_frame = ft_ld_u64(p + 8);
    m->x0 = ft_ld_u16(p + 16);
    m->y0 = ft_ld_u16(p + 18);
    m->width = ft_ld_u16(p + 20);
    m->height = ft_ld_u16(p + 22);
    m->offset = ft_ld_u32(p + 24);
    m->total_bytes = ft_ld_u32(p + 28);
    m->chunk_len = (uint16_t)n;
    m->data = p + FT_IMAGE_FIXED;
    return ft_image_check(m);
}

/* ---- DVS_CLUSTERS (0x10) ---- */

typedef struct {
    uint16_t flags; /* FT_DVS_SYNCED */
    uint16_t camera_index;
    uint16_t n_clusters;
    uint32_t seq;
    uint64_t t_start_us;
    uint64_t t_end_us; /* the clusters are stated at this device time */
    uint64_t edge_done_ns;
    double trigger_frame;  /* trigger frame (with fraction) at t_end_us; 0 without FT_DVS_SYNCED */
    float frame_period_us; /* measured sync period; > 0 with FT_DVS_SYNCED, else 0 */
    uint32_t syncs;        /* sync events the edge has seen */
} ft_dvs_clusters_hdr;

typedef struct {
    uint32_t id;
    float x, y;                 /* px */
    float vx, vy;               /* px/s */
    float size;                 /* radius, px */
    float mass;                 /* decayed event count */
    float var_x, var_y, cov_xy; /* px^2: position covariance (the cluster's Kalman filter) */
} ft_dvs_cluster;

static inline ft_err ft_dvs_clusters_check(const ft_dvs_clusters_hdr *h, const ft_dvs_cluster *c) {
    uint32_t i;
    if (h->n_clusters > FT_DVS_MAX_CLUSTERS)
        return FT_E_COUNT_OVERFLOW;
    if (!ft_f64_finite(h->trigger_frame) || !ft_f32_finite(h->frame_period_us))
        return FT_E_NOT_FINITE;
    for (i = 0; i < h->n_clusters; i++)
        if (!ft_f32_finite(c[i].x) || !ft_f32_finite(c[i].y) || !ft_f32_finite(c[i].vx) ||
            !ft_f32_finite(c[i].vy) || !ft_f32_finite(c[i].size) || !ft_f32_finite(c[i].mass) ||
            !ft_f32_finite(c[i].var_x) || !ft_f32_finite(c[i].var_y) || !ft_f32_finite(c[i].cov_xy))
            return FT_E_NOT_FINITE;
    if (h->frame_period_us < 0.0f || ((h->flags & FT_DVS_SYNCED) && !(h->frame_period_us > 0.0f)))
        return FT_E_BAD_FIELD;
    for (i = 0; i < h->n_clusters; i++) {
        /* products of two floats are exact in double: the same test as the Python codec's */
        const double vx = c[i].var_x, vy = c[i].var_y, cxy = c[i].cov_xy;
        if (vx < 0.0 || vy < 0.0 || cxy * cxy > vx * vy)
            return FT_E_BAD_FIELD;
    }
    return FT_OK;
}

static inline ft_err ft_dvs_clusters_encode(uint8_t *buf, size_t cap, const ft_dvs_clusters_hdr *h,
                                            const ft_dvs_cluster *c, size_t *out_len) {
    uint8_t *p = buf; /* + header once cap is checked */
    size_t payload, i;
    ft_err e = ft_dvs_clusters_check(h, c);
    if (e != FT_OK)
        return e;
    payload = FT_DVS_CLUSTERS_FIXED + (size_t)h->n_clusters * FT_DVS_CLUSTER_SIZE;
    if (cap < FT_UDP_HEADER + payload)
        return FT_E_NO_SPACE;
    p += FT_UDP_HEADER;
    ft_udp_put_header(buf, FT_MSG_DVS_CLUSTERS, payload, h->flags);
    ft_st_u16(p + 0, h->camera_index);
    ft_st_u16(p + 2, h->n_clusters);
    ft_st_u32(p + 4, h->seq);
    ft_st_u64(p + 8, h->t_start_us);
    ft_st_u64(p + 16, h->t_end_us);
    ft_st_u64(p + 24, h->edge_done_ns);
    ft_st_f64(p + 32, h->trigger_frame);
    ft_st_f32(p + 40, h->frame_period_us);
    ft_st_u32(p + 44, h->syncs);
    for (i = 0; i < h->n_clusters; i++) {
        uint8_t *q = p + FT_DVS_CLUSTERS_FIXED + i * FT_DVS_CLUSTER_SIZE;
        ft_st_u32(q + 0, c[i].id);
        ft_st_f32(q + 4, c[i].x);
        ft_st_f32(q + 8, c[i].y);
        ft_st_f32(q + 12, c[i].vx);
        ft_st_f32(q + 16, c[i].vy);
        ft_st_f32(q + 20, c[i].size);
        ft_st_f32(q + 24, c[i].mass);
        ft_st_f32(q + 28, c[i].var_x);
        ft_st_f32(q + 32, c[i].var_y);
        ft_st_f32(q + 36, c[i].cov_xy);
    }
    *out_len = FT_UDP_HEADER + payload;
    return FT_OK;
}

/* c: room for FT_DVS_MAX_CLUSTERS records. */
static inline ft_err ft_dvs_clusters_decode(const uint8_t *buf, size_t len, ft_dvs_clusters_hdr *h,
                                            ft_dvs_cluster *c) {
    const uint8_t *p = buf; /* + header once the length is checked */
    uint32_t n = 0, i;
    ft_err e;
    if (len >= FT_UDP_HEADER + 4)
        n = ft_ld_u16(p + FT_UDP_HEADER + 2);
    e = ft_udp_check(buf, len, FT_MSG_DVS_CLUSTERS, n, FT_DVS_MAX_CLUSTERS, FT_DVS_CLUSTER_SIZE, 1,
                     &h->flags);
    if (e != FT_OK)
        return e;
    p += FT_UDP_HEADER;
    h->camera_index = ft_ld_u16(p + 0);
    h->n_clusters = (uint16_t)n;
    h->seq = ft_ld_u32(p + 4);
    h->t_start_us = ft_ld_u64(p + 8);
    h->t_end_us = ft_ld_u64(p + 16);
    h->edge_done_ns = ft_ld_u64(p + 24);
    h->trigger_frame = ft_ld_f64(p + 32);
    h->frame_period_us = ft_ld_f32(p + 40);
    h->syncs = ft_ld_u32(p + 44);
    for (i = 0; i < n; i++) {
        const uint8_t *q = p + FT_DVS_CLUSTERS_FIXED + i * FT_DVS_CLUSTER_SIZE;
        c[i].id = ft_ld_u32(q + 0);
        c[i].x = ft_ld_f32(q + 4);
        c[i].y = ft_ld_f32(q + 8);
        c[i].vx = ft_ld_f32(q + 12);
        c[i].vy = ft_ld_f32(q + 16);
        c[i].size = ft_ld_f32(q + 20);
        c[i].mass = ft_ld_f32(q + 24);
        c[i].var_x = ft_ld_f32(q + 28);
        c[i].var_y = ft_ld_f32(q + 32);
        c[i].cov_xy = ft_ld_f32(q + 36);
    }
    return ft_dvs_clusters_check(h, c);
}

/* ---- DVS_WINGBEAT (0x11) ---- */

typedef struct {
    uint16_t flags; /* 0 */
    uint16_t camera_index;
    uint16_t n_edges;
    uint32_t seq;
    uint64_t t_us;
    uint64_t edge_done_ns;
} ft_dvs_wingbeat_hdr;

typedef struct {
    uint8_t edge_id; /* 0 left, 1 right, ... */
    float angle;     /* rad */
    float amplitude; /* rad */
    float frequency; /* Hz */
    float phase;     /* rad */
} ft_wing_edge;

static inline ft_err ft_dvs_wingbeat_check(const ft_dvs_wingbeat_hdr *h, const ft_wing_edge *w) {
    uint32_t i;
    if (h->n_edges > FT_DVS_MAX_EDGES)
        return FT_E_COUNT_OVERFLOW;
    for (i = 0; i < h->n_edges; i++)
        if (!ft_f32_finite(w[i].angle) || !ft_f32_finite(w[i].amplitude) ||
            !ft_f32_finite(w[i].frequency) || !ft_f32_finite(w[i].phase))
            return FT_E_NOT_FINITE;
    return FT_OK;
}

static inline ft_err ft_dvs_wingbeat_encode(uint8_t *buf, size_t cap, const ft_dvs_wingbeat_hdr *h,
                                            const ft_wing_edge *w, size_t *out_len) {
    uint8_t *p = buf; /* + header once cap is checked */
    size_t payload, i;
    ft_err e = ft_dvs_wingbeat_check(h, w);
    if (e != FT_OK)
        return e;
    payload = FT_DVS_WINGBEAT_FIXED + (size_t)h->n_edges * FT_WING_EDGE_SIZE;
    if (cap < FT_UDP_HEADER + payload)
        return FT_E_NO_SPACE;
    p += FT_UDP_HEADER;
    ft_udp_put_header(buf, FT_MSG_DVS_WINGBEAT, payload, h->flags);
    ft_st_u16(p + 0, h->camera_index);
    ft_st_u16(p + 2, h->n_edges);
    ft_st_u32(p + 4, h->seq);
    ft_st_u64(p + 8, h->t_us);
    ft_st_u64(p + 16, h->edge_done_ns);
    for (i = 0; i < h->n_edges; i++) {
        uint8_t *q = p + FT_DVS_WINGBEAT_FIXED + i * FT_WING_EDGE_SIZE;
        q[0] = w[i].edge_id;
        q[1] = q[2] = q[3] = 0;
        ft_st_f32(q + 4, w[i].angle);
        ft_st_f32(q + 8, w[i].amplitude);
        ft_st_f32(q + 12, w[i].frequency);
        ft_st_f32(q + 16, w[i].phase);
    }
    *out_len = FT_UDP_HEADER + payload;
    return FT_OK;
}

/* w: room for FT_DVS_MAX_EDGES records. */
static inline ft_err ft_dvs_wingbeat_decode(const uint8_t *buf, size_t len, ft_dvs_wingbeat_hdr *h,
                                            ft_wing_edge *w) {
    const uint8_t *p = buf; /* + header once the length is checked */
    uint32_t n = 0, i;
    ft_err e;
    if (len >= FT_UDP_HEADER + 4)
        n = ft_ld_u16(p + FT_UDP_HEADER + 2);
    e = ft_udp_check(buf, len, FT_MSG_DVS_WINGBEAT, n, FT_DVS_MAX_EDGES, FT_WING_EDGE_SIZE, 1,
                     &h->flags);
    if (e != FT_OK)
        return e;
    p += FT_UDP_HEADER;
    h->camera_index = ft_ld_u16(p + 0);
    h->n_edges = (uint16_t)n;
    h->seq = ft_ld_u32(p + 4);
    h->t_us = ft_ld_u64(p + 8);
    h->edge_done_ns = ft_ld_u64(p + 16);
    for (i = 0; i < n; i++) {
        const uint8_t *q = p + FT_DVS_WINGBEAT_FIXED + i * FT_WING_EDGE_SIZE;
        w[i].edge_id = q[0];
        w[i].angle = ft_ld_f32(q + 4);
        w[i].amplitude = ft_ld_f32(q + 8);
        w[i].frequency = ft_ld_f32(q + 12);
        w[i].phase = ft_ld_f32(q + 16);
    }
    return ft_dvs_wingbeat_check(h, w);
}

/* ---- LIVE_ESTIMATES (0x20) ---- */

typedef struct {
    uint16_t flags; /* FT_LIVE_SPLIT */
    uint64_t trigger_frame;
    double trigger_time; /* host clock, s since the Unix epoch; finite */
    uint32_t seq;
    uint16_t n_objects;
    uint8_t part_index;
    uint8_t part_count; /* >= 1 */
    float latency_ms;   /* finite */
} ft_live_hdr;

typedef struct {
    uint32_t obj_id;
    float x, y, z;    /* m */
    float vx, vy, vz; /* m/s */
    float cov[6];     /* position covariance, m^2: xx, xy, xz, yy, yz, zz */
} ft_live_object;

static inline ft_err ft_live_check(const ft_live_hdr *h, const ft_live_object *o) {
    uint32_t i, k;
    if (h->n_objects > FT_LIVE_MAX_OBJECTS)
        return FT_E_COUNT_OVERFLOW;
    if (!ft_f64_finite(h->trigger_time) || !ft_f32_finite(h->latency_ms))
        return FT_E_NOT_FINITE;
    for (i = 0; i < h->n_objects; i++) {
        if (!ft_f32_finite(o[i].x) || !ft_f32_finite(o[i].y) || !ft_f32_finite(o[i].z) ||
            !ft_f32_finite(o[i].vx) || !ft_f32_finite(o[i].vy) || !ft_f32_finite(o[i].vz))
            return FT_E_NOT_FINITE;
        for (k = 0; k < 6; k++)
            if (!ft_f32_finite(o[i].cov[k]))
                return FT_E_NOT_FINITE;
    }
    if (h->part_count < 1 || h->part_index >= h->part_count)
        return FT_E_BAD_FIELD;
    return FT_OK;
}

static inline ft_err ft_live_estimates_encode(uint8_t *buf, size_t cap, const ft_live_hdr *h,
                                              const ft_live_object *o, size_t *out_len) {
    uint8_t *p = buf; /* + header once cap is checked */
    size_t payload, i, k;
    ft_err e = ft_live_check(h, o);
    if (e != FT_OK)
        return e;
    payload = FT_LIVE_FIXED + (size_t)h->n_objects * FT_LIVE_OBJECT_SIZE;
    if (cap < FT_UDP_HEADER + payload)
        return FT_E_NO_SPACE;
    p += FT_UDP_HEADER;
    ft_udp_put_header(buf, FT_MSG_LIVE_ESTIMATES, payload, h->flags);
    ft_st_u64(p + 0, h->trigger_frame);
    ft_st_f64(p + 8, h->trigger_time);
    ft_st_u32(p + 16, h->seq);
    ft_st_u16(p + 20, h->n_objects);
    p[22] = h->part_index;
    p[23] = h->part_count;
    ft_st_f32(p + 24, h->latency_ms);
    ft_st_u32(p + 28, 0);
    for (i = 0; i < h->n_objects; i++) {
        uint8_t *q = p + FT_LIVE_FIXED + i * FT_LIVE_OBJECT_SIZE;
        ft_st_u32(q + 0, o[i].obj_id);
        ft_st_f32(q + 4, o[i].x);
        ft_st_f32(q + 8, o[i].y);
        ft_st_f32(q + 12, o[i].z);
        ft_st_f32(q + 16, o[i].vx);
        ft_st_f32(q + 20, o[i].vy);
        ft_st_f32(q + 24, o[i].vz);
        for (k = 0; k < 6; k++)
            ft_st_f32(q + 28 + 4 * k, o[i].cov[k]);
    }
    *out_len = FT_UDP_HEADER + payload;
    return FT_OK;
}

/* o: room for FT_LIVE_MAX_OBJECTS records. */
static inline ft_err ft_live_estimates_decode(const uint8_t *buf, size_t len, ft_live_hdr *h,
                                              ft_live_object *o) {
    const uint8_t *p = buf; /* + header once the length is checked */
    uint32_t n = 0, i, k;
    ft_err e;
    if (len >= FT_UDP_HEADER + 22)
        n = ft_ld_u16(p + FT_UDP_HEADER + 20);
    e = ft_udp_check(buf, len, FT_MSG_LIVE_ESTIMATES, n, FT_LIVE_MAX_OBJECTS, FT_LIVE_OBJECT_SIZE,
                     1, &h->flags);
    if (e != FT_OK)
        return e;
    p += FT_UDP_HEADER;
    h->trigger_frame = ft_ld_u64(p + 0);
    h->trigger_time = ft_ld_f64(p + 8);
    h->seq = ft_ld_u32(p + 16);
    h->n_objects = (uint16_t)n;
    h->part_index = p[22];
    h->part_count = p[23];
    h->latency_ms = ft_ld_f32(p + 24);
    for (i = 0; i < n; i++) {
        const uint8_t *q = p + FT_LIVE_FIXED + i * FT_LIVE_OBJECT_SIZE;
        o[i].obj_id = ft_ld_u32(q + 0);
        o[i].x = ft_ld_f32(q + 4);
        o[i].y = ft_ld_f32(q + 8);
        o[i].z = ft_ld_f32(q + 12);
        o[i].vx = ft_ld_f32(q + 16);
        o[i].vy = ft_ld_f32(q + 20);
        o[i].vz = ft_ld_f32(q + 24);
        for (k = 0; k < 6; k++)
            o[i].cov[k] = ft_ld_f32(q + 28 + 4 * k);
    }
    return ft_live_check(h, o);
}

#endif /* FLYTRACK_UDP_H */

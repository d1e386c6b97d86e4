/* Golden-vector runner of the C codec (protocol/SPEC.md section 5), used by ft_vectors and by its
 * self-test. For every line of every <dir>/<family>.tsv: a valid vector must decode to exactly its
 * canonical field text and re-encode byte for byte; an invalid one must fail with exactly the named
 * error.
 *
 * Canonical text, as the Python codec prints it (host/flytrack_host/protocol/canonical.py):
 * `key=value` joined by one space. UDP: type, flags (masked to the type's bits), the fixed fields
 * in table order without reserved ones, then records as `points[i].field` (`objects[i].cov[k]`);
 * IMAGE ends with `data=<lowercase hex>`. Serial: msg_id, seq, payload fields. DVS packets:
 * n_words, then per word x, y, polarity, ts, reset, wrap, and t_us for event words (a decoder
 * starting at offset 0). f32 `%.9g`, f64 `%.17g`, `nan`, `inf`, `-inf`; text: bytes 0x21..0x7E
 * but backslash as is, every other byte `\xHH` (lowercase).
 */
#ifndef FT_VECTOR_RUNNER_H
#define FT_VECTOR_RUNNER_H

#include <dirent.h>
#include <inttypes.h>
#include <math.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "flytrack/protocol.h"

/* ---- canonical text builder ---- */

#define VR_TEXT_CAP (1 << 18)

typedef struct {
    char s[VR_TEXT_CAP];
    size_t len;
    int overflow;
} vr_text;

static inline void vr_reset(vr_text *t) {
    t->len = 0;
    t->s[0] = 0;
    t->overflow = 0;
}

/* Appends one `key=value` item (space-separated from the previous one). */
static inline void vr_add(vr_text *t, const char *fmt, ...) {
    va_list ap;
    int n;
    if (t->len > 0 && t->len + 1 < VR_TEXT_CAP)
        t->s[t->len++] = ' ';
    va_start(ap, fmt);
    n = vsnprintf(t->s + t->len, VR_TEXT_CAP - t->len, fmt, ap);
    va_end(ap);
    if (n < 0 || (size_t)n >= VR_TEXT_CAP - t->len) {
        t->overflow = 1;
        t->len = VR_TEXT_CAP - 1;
    } else {
        t->len += (size_t)n;
    }
}

static inline void vr_u(vr_text *t, const char *key, uint64_t v) {
    vr_add(t, "%s=%" PRIu64, key, v);
}
static inline void vr_i(vr_text *t, const char *key, int64_t v) {
    vr_add(t, "%s=%" PRId64, key, v);
}

static inline void vr_fmt_float(char *out, size_t cap, double v, int digits) {
    if (isnan(v))
        snprintf(out, cap, "nan");
    else if (isinf(v))
        snprintf(out, cap, v > 0 ? "inf" : "-inf");
    else
        snprintf(out, cap, "%.*g", digits, v);
}
static inline void vr_f32(vr_text *t, const char *key, float v) {
    char b[64];
    vr_fmt_float(b, sizeof b, (double)v, 9);
    vr_add(t, "%s=%s", key, b);
}
static inline void vr_f64(vr_text *t, const char *key, double v) {
    char b[64];
    vr_fmt_float(b, sizeof b, v, 17);
    vr_add(t, "%s=%s", key, b);
}
static inline void vr_str(vr_text *t, const char *key, const char *s) {
    char b[4 * 256 + 1];
    size_t o = 0;
    for (; *s && o + 5 < sizeof b; s++) {
        unsigned char c = (unsigned char)*s;
        if (c >= 0x21 && c <= 0x7E && c != '\\')
            b[o++] = (char)c;
        else
            o += (size_t)snprintf(b + o, sizeof b - o, "\\x%02x", c);
    }
    b[o] = 0;
    vr_add(t, "%s=%s", key, b);
}
static inline void vr_hex(vr_text *t, const char *key, const uint8_t *p, size_t n) {
    static char b[2 * FT_UDP_MAX_DATAGRAM + 1];
    size_t i;
    if (n > FT_UDP_MAX_DATAGRAM)
        n = FT_UDP_MAX_DATAGRAM;
    for (i = 0; i < n; i++)
        snprintf(b + 2 * i, 3, "%02x", p[i]);
    b[2 * n] = 0;
    vr_add(t, "%s=%s", key, b);
}

/* ---- per-family decode -> canonical text + re-encoded bytes ---- */

typedef struct {
    vr_text text;
    uint8_t again[4096]; /* re-encoded bytes */
    size_t again_len;
    char problem[512]; /* not a codec error, but a runner-level failure (e.g. wrong type) */
} vr_result;

static inline void vr_hdr(vr_text *t, uint8_t type, uint16_t flags) {
    vr_u(t, "type", type);
    vr_u(t, "flags", flags);
}

static inline ft_err vr_features(const uint8_t *b, size_t n, vr_result *r) {
    ft_features_hdr h;
    ft_point p[FT_FEATURES_MAX_POINTS];
    vr_text *t = &r->text;
    char k[64];
    unsigned i;
    ft_err e = ft_features_decode(b, n, &h, p);
    if (e != FT_OK)
        return e;
    vr_hdr(t, FT_MSG_FEATURES, h.flags);
    vr_u(t, "camera_index", h.camera_index);
    vr_u(t, "n_points", h.n_points);
    vr_u(t, "seq", h.seq);
    vr_u(t, "camera_frame", h.camera_frame);
    vr_i(t, "trigger_frame", h.trigger_frame);
    vr_u(t, "device_timestamp_ns", h.device_timestamp_ns);
    vr_u(t, "edge_recv_ns", h.edge_recv_ns);
    vr_u(t, "edge_done_ns", h.edge_done_ns);
    vr_u(t, "total_points", h.total_points);
    vr_u(t, "part_index", h.part_index);
    vr_u(t, "part_count", h.part_count);
    for (i = 0; i < h.n_points; i++) {
#define VR_PF(name) (snprintf(k, sizeof k, "points[%u]." #name, i), vr_f32(t, k, p[i].name))
        VR_PF(x_dist);
        VR_PF(y_dist);
        VR_PF(x_undist);
        VR_PF(y_undist);
        VR_PF(area);
        VR_PF(peak_diff);
        VR_PF(orientation);
        VR_PF(eccentricity);
        snprintf(k, sizeof k, "points[%u].cur_val", i);
        vr_u(t, k, p[i].cur_val);
        VR_PF(mean_val);
        VR_PF(sumsq_val);
#undef VR_PF
    }
    return ft_features_encode(r->again, sizeof r->again, &h, p, &r->again_len);
}

static inline ft_err vr_status(const uint8_t *b, size_t n, vr_result *r) {
    ft_status m;
    vr_text *t = &r->text;
    ft_err e = ft_status_decode(b, n, &m);
    if (e != FT_OK)
        return e;
    vr_hdr(t, FT_MSG_STATUS, m.flags);
    vr_u(t, "camera_index", m.camera_index);
    vr_u(t, "width", m.width);
    vr_u(t, "height", m.height);
    vr_u(t, "pixel_format", m.pixel_format);
    vr_u(t, "state", m.state);
    vr_u(t, "seq", m.seq);
    vr_u(t, "last_error_code", m.last_error_code);
    vr_u(t, "frames_seen", m.frames_seen);
    vr_u(t, "frames_dropped", m.frames_dropped);
    vr_f32(t, "fps", m.fps);
    vr_f32(t, "proc_us_mean", m.proc_us_mean);
    vr_f32(t, "proc_us_max", m.proc_us_max);
    vr_str(t, "camera_name", m.camera_name);
    vr_str(t, "last_error", m.last_error);
    return ft_status_encode(r->again, sizeof r->again, &m, &r->again_len);
}

static inline ft_err vr_control(const uint8_t *b, size_t n, vr_result *r) {
    ft_control m;
    vr_text *t = &r->text;
    ft_err e = ft_control_decode(b, n, &m);
    if (e != FT_OK)
        return e;
    vr_hdr(t, FT_MSG_CONTROL, m.flags);
    vr_u(t, "request_id", m.request_id);
    vr_u(t, "camera_index", m.camera_index);
    vr_u(t, "command", m.command);
    vr_str(t, "param", m.param);
    vr_f64(t, "value", m.value);
    return ft_control_encode(r->again, sizeof r->again, &m, &r->again_len);
}

static inline ft_err vr_control_ack(const uint8_t *b, size_t n, vr_result *r) {
    ft_control_ack m;
    vr_text *t = &r->text;
    ft_err e = ft_control_ack_decode(b, n, &m);
    if (e != FT_OK)
        return e;
    vr_hdr(t, FT_MSG_CONTROL_ACK, m.flags);
    vr_u(t, "request_id", m.request_id);
    vr_u(t, "camera_index", m.camera_index);
    vr_u(t, "command", m.command);
    vr_u(t, "status", m.status);
    vr_str(t, "message", m.message);
    return ft_control_ack_encode(r->again, sizeof r->again, &m, &r->again_len);
}

static inline ft_err vr_image(const uint8_t *b, size_t n, vr_result *r) {
    ft_image m;
    vr_text *t = &r->text;
    ft_err e = ft_image_decode(b, n, &m);
    if (e != FT_OK)
        return e;
    vr_hdr(t, FT_MSG_IMAGE, m.flags);
    vr_u(t, "camera_index", m.camera_index);
    vr_u(t, "kind", m.kind);
    vr_u(t, "bytes_per_pixel", m.bytes_per_pixel);
    vr_u(t, "image_id", m.image_id);
    vr_u(t, "camera_frame", m.camera_frame);
    vr_u(t, "x0", m.x0);
    vr_u(t, "y0", m.y0);
    vr_u(t, "width", m.width);
    vr_u(t, "height", m.height);
    vr_u(t, "offset", m.offset);
    vr_u(t, "total_bytes", m.total_bytes);
    vr_u(t, "chunk_len", m.chunk_len);
    vr_hex(t, "data", m.data, m.chunk_len);
    return ft_image_encode(r->again, sizeof r->again, &m, &r->again_len);
}

static inline ft_err vr_dvs_clusters(const uint8_t *b, size_t n, vr_result *r) {
    ft_dvs_clusters_hdr h;
    ft_dvs_cluster c[FT_DVS_MAX_CLUSTERS];
    vr_text *t = &r->text;
    char k[64];
    unsigned i;
    ft_err e = ft_dvs_clusters_decode(b, n, &h, c);
    if (e != FT_OK)
        return e;
    vr_hdr(t, FT_MSG_DVS_CLUSTERS, h.flags);
    vr_u(t, "camera_index", h.camera_index);
    vr_u(t, "n_clusters", h.n_clusters);
    vr_u(t, "seq", h.seq);
    vr_u(t, "t_start_us", h.t_start_us);
    vr_u(t, "t_end_us", h.t_end_us);
    vr_u(t, "edge_done_ns", h.edge_done_ns);
    vr_f64(t, "trigger_frame", h.trigger_frame);
    vr_f32(t, "frame_period_us", h.frame_period_us);
    vr_u(t, "syncs", h.syncs);
    for (i = 0; i < h.n_clusters; i++) {
        snprintf(k, sizeof k, "clusters[%u].id", i);
        vr_u(t, k, c[i].id);
#define VR_CF(name) (snprintf(k, sizeof k, "clusters[%u]." #name, i), vr_f32(t, k, c[i].name))
        VR_CF(x);
        VR_CF(y);
        VR_CF(vx);
        VR_CF(vy);
        VR_CF(size);
        VR_CF(mass);
        VR_CF(var_x);
        VR_CF(var_y);
        VR_CF(cov_xy);
#undef VR_CF
    }
    return ft_dvs_clusters_encode(r->again, sizeof r->again, &h, c, &r->again_len);
}

static inline ft_err vr_dvs_wingbeat(const uint8_t *b, size_t n, vr_result *r) {
    ft_dvs_wingbeat_hdr h;
    ft_wing_edge w[FT_DVS_MAX_EDGES];
    vr_text *t = &r->text;
    char k[64];
    unsigned i;
    ft_err e = ft_dvs_wingbeat_decode(b, n, &h, w);
    if (e != FT_OK)
        return e;
    vr_hdr(t, FT_MSG_DVS_WINGBEAT, h.flags);
    vr_u(t, "camera_index", h.camera_index);
    vr_u(t, "n_edges", h.n_edges);
    vr_u(t, "seq", h.seq);
    vr_u(t, "t_us", h.t_us);
    vr_u(t, "edge_done_ns", h.edge_done_ns);
    for (i = 0; i < h.n_edges; i++) {
        snprintf(k, sizeof k, "edges[%u].edge_id", i);
        vr_u(t, k, w[i].edge_id);
#define VR_WF(name) (snprintf(k, sizeof k, "edges[%u]." #name, i), vr_f32(t, k, w[i].name))
        VR_WF(angle);
        VR_WF(amplitude);
        VR_WF(frequency);
        VR_WF(phase);
#undef VR_WF
    }
    return ft_dvs_wingbeat_encode(r->again, sizeof r->again, &h, w, &r->again_len);
}

static inline ft_err vr_live(const uint8_t *b, size_t n, vr_result *r) {
    ft_live_hdr h;
    ft_live_object o[FT_LIVE_MAX_OBJECTS];
    vr_text *t = &r->text;
    char k[64];
    unsigned i, c;
    ft_err e = ft_live_estimates_decode(b, n, &h, o);
    if (e != FT_OK)
        return e;
    vr_hdr(t, FT_MSG_LIVE_ESTIMATES, h.flags);
    vr_u(t, "trigger_frame", h.trigger_frame);
    vr_f64(t, "trigger_time", h.trigger_time);
    vr_u(t, "seq", h.seq);
    vr_u(t, "n_objects", h.n_objects);
    vr_u(t, "part_index", h.part_index);
    vr_u(t, "part_count", h.part_count);
    vr_f32(t, "latency_ms", h.latency_ms);
    for (i = 0; i < h.n_objects; i++) {
        snprintf(k, sizeof k, "objects[%u].obj_id", i);
        vr_u(t, k, o[i].obj_id);
#define VR_OF(name) (snprintf(k, sizeof k, "objects[%u]." #name, i), vr_f32(t, k, o[i].name))
        VR_OF(x);
        VR_OF(y);
        VR_OF(z);
        VR_OF(vx);
        VR_OF(vy);
        VR_OF(vz);
#undef VR_OF
        for (c = 0; c < 6; c++) {
            snprintf(k, sizeof k, "objects[%u].cov[%u]", i, c);
            vr_f32(t, k, o[i].cov[c]);
        }
    }
    return ft_live_estimates_encode(r->again, sizeof r->again, &h, o, &r->again_len);
}

/* A serial vector is the whole wire frame, its 0x00 delimiter included. */
static inline ft_err vr_serial(const uint8_t *b, size_t n, vr_result *r) {
    uint8_t id, seq, pl[FT_TL_MAX_PAYLOAD], plen, out[FT_TL_MAX_PAYLOAD];
    vr_text *t = &r->text;
    ft_err e;
    if (n == 0 || b[n - 1] != 0) {
        snprintf(r->problem, sizeof r->problem, "a serial vector must end with its 0x00 delimiter");
        return FT_OK;
    }
    e = ft_tl_decode(b, n - 1, &id, &seq, pl, &plen);
    if (e != FT_OK)
        return e;
    vr_u(t, "msg_id", id);
    vr_u(t, "seq", seq);
    switch (id) {
    case FT_TL_SET_RATE: {
        ft_tl_set_rate m;
        if ((e = ft_tl_unpack_set_rate(pl, plen, &m)) != FT_OK)
            return e;
        vr_u(t, "prescaler_code", m.prescaler_code);
        vr_u(t, "top", m.top);
        e = ft_tl_pack_set_rate(out, &m);
        break;
    }
    case FT_TL_PULSE: {
        ft_tl_pulse m;
        if ((e = ft_tl_unpack_pulse(pl, plen, &m)) != FT_OK)
            return e;
        vr_u(t, "channel", m.channel);
        vr_u(t, "frame", m.frame);
        vr_u(t, "width_ticks", m.width_ticks);
        e = ft_tl_pack_pulse(out, &m);
        break;
    }
    case FT_TL_SET_OUTPUT: {
        ft_tl_set_output m;
        if ((e = ft_tl_unpack_set_output(pl, plen, &m)) != FT_OK)
            return e;
        vr_u(t, "channel", m.channel);
        vr_u(t, "level", m.level);
        e = ft_tl_pack_set_output(out, &m);
        break;
    }
    case FT_TL_SET_NAME: {
        ft_tl_set_name m;
        if ((e = ft_tl_unpack_set_name(pl, plen, &m)) != FT_OK)
            return e;
        vr_str(t, "name", m.name);
        e = ft_tl_pack_set_name(out, &m);
        break;
    }
    case FT_TL_INFO: {
        ft_tl_info m;
        if ((e = ft_tl_unpack_info(pl, plen, &m)) != FT_OK)
            return e;
        vr_u(t, "protocol_version", m.protocol_version);
        vr_u(t, "fw_major", m.fw_major);
        vr_u(t, "fw_minor", m.fw_minor);
        vr_u(t, "fw_patch", m.fw_patch);
        vr_u(t, "mcu", m.mcu);
        vr_u(t, "n_outputs", m.n_outputs);
        vr_u(t, "f_cpu", m.f_cpu);
        vr_str(t, "name", m.name);
        e = ft_tl_pack_info(out, &m);
        break;
    }
    case FT_TL_ACK: {
        ft_tl_ack m;
        if ((e = ft_tl_unpack_ack(pl, plen, &m)) != FT_OK)
            return e;
        vr_u(t, "acked_id", m.acked_id);
        e = ft_tl_pack_ack(out, &m);
        break;
    }
    case FT_TL_RATE: {
        ft_tl_rate m;
        if ((e = ft_tl_unpack_rate(pl, plen, &m)) != FT_OK)
            return e;
        vr_u(t, "f_cpu", m.f_cpu);
        vr_u(t, "prescaler_code", m.prescaler_code);
        vr_u(t, "top", m.top);
        e = ft_tl_pack_rate(out, &m);
        break;
    }
    case FT_TL_CLOCK: {
        ft_tl_clock m;
        if ((e = ft_tl_unpack_clock(pl, plen, &m)) != FT_OK)
            return e;
        vr_u(t, "frame_count", m.frame_count);
        vr_u(t, "ticks", m.ticks);
        vr_u(t, "top", m.top);
        vr_u(t, "running", m.running);
        e = ft_tl_pack_clock(out, &m);
        break;
    }
    case FT_TL_EVENT: {
        ft_tl_event m;
        if ((e = ft_tl_unpack_event(pl, plen, &m)) != FT_OK)
            return e;
        vr_u(t, "channel", m.channel);
        vr_u(t, "edge", m.edge);
        vr_u(t, "frame_count", m.frame_count);
        vr_u(t, "ticks", m.ticks);
        e = ft_tl_pack_event(out, &m);
        break;
    }
    case FT_TL_ERROR: {
        ft_tl_error m;
        if ((e = ft_tl_unpack_error(pl, plen, &m)) != FT_OK)
            return e;
        vr_u(t, "code", m.code);
        vr_u(t, "msg_id", m.msg_id);
        e = ft_tl_pack_error(out, &m);
        break;
    }
    default: /* the requests without payload */
        e = FT_OK;
        break;
    }
    if (e != FT_OK)
        return e;
    return ft_tl_encode(r->again, sizeof r->again, id, seq, out, plen, &r->again_len);
}

static inline ft_err vr_dvs_words(const uint8_t *b, size_t n, vr_result *r) {
    vr_text *t = &r->text;
    ft_dvs_decoder d;
    size_t i, n_events;
    char k[64];
    ft_err e = ft_dvs_packet_check(b, n, &n_events);
    if (e != FT_OK)
        return e;
    ft_dvs_decoder_init(&d);
    vr_u(t, "n_words", n / 4);
    for (i = 0; i < n / 4; i++) {
        ft_dvs_word w;
        ft_dvs_event ev;
        ft_dvs_word_decode(b + 4 * i, &w);
#define VR_DW(name, v) (snprintf(k, sizeof k, "words[%zu]." name, i), vr_u(t, k, v))
        VR_DW("x", w.x);
        VR_DW("y", w.y);
        VR_DW("polarity", w.polarity);
        VR_DW("ts", w.ts);
        VR_DW("reset", w.kind == FT_DVS_RESET);
        VR_DW("wrap", w.kind == FT_DVS_WRAP);
        VR_DW("sync", w.kind == FT_DVS_SYNC);
        if (ft_dvs_apply(&d, &w, &ev))
            VR_DW("t_us", ev.t_us);
        else if (w.kind == FT_DVS_SYNC)
            VR_DW("t_us", d.sync_t_us);
#undef VR_DW
        if ((e = ft_dvs_word_encode(r->again + 4 * i, &w)) != FT_OK)
            return e;
    }
    r->again_len = n;
    return FT_OK;
}

/* ---- families ---- */

typedef ft_err (*vr_decode_fn)(const uint8_t *b, size_t n, vr_result *r);

typedef struct {
    const char *name; /* file stem */
    int udp_type;     /* -1: not a UDP family */
    vr_decode_fn fn;
} vr_family;

static const vr_family vr_families[] = {
    {"features", FT_MSG_FEATURES, vr_features},
    {"status", FT_MSG_STATUS, vr_status},
    {"control", FT_MSG_CONTROL, vr_control},
    {"control_ack", FT_MSG_CONTROL_ACK, vr_control_ack},
    {"image", FT_MSG_IMAGE, vr_image},
    {"dvs_clusters", FT_MSG_DVS_CLUSTERS, vr_dvs_clusters},
    {"dvs_wingbeat", FT_MSG_DVS_WINGBEAT, vr_dvs_wingbeat},
    {"live_estimates", FT_MSG_LIVE_ESTIMATES, vr_live},
    {"trigger_link", -1, vr_serial},
    {"dvs_words", -1, vr_dvs_words},
};
#define VR_N_FAMILIES (sizeof vr_families / sizeof vr_families[0])

static inline const vr_family *vr_family_by_type(uint8_t type) {
    size_t i;
    for (i = 0; i < VR_N_FAMILIES; i++)
        if (vr_families[i].udp_type == (int)type)
            return &vr_families[i];
    return NULL;
}

/* Decodes one vector's bytes as its family does: UDP datagrams by the type in their header (as
 * the Python runner does; a type other than the file's family is a failure). */
static inline ft_err vr_decode(const vr_family *f, const uint8_t *b, size_t n, vr_result *r) {
    vr_reset(&r->text);
    r->again_len = 0;
    r->problem[0] = 0;
    if (f->udp_type >= 0) {
        uint8_t type;
        const vr_family *g;
        ft_err e = ft_peek_type(b, n, &type);
        if (e != FT_OK)
            return e;
        g = vr_family_by_type(type);
        e = g->fn(b, n, r);
        if (e == FT_OK && g != f)
            snprintf(r->problem, sizeof r->problem, "a %s vector decoded as %s", f->name, g->name);
        return e;
    }
    return f->fn(b, n, r);
}

/* ---- files ---- */

typedef struct {
    int passed, failed;
    FILE *log; /* failures are written here */
} vr_counts;

static inline int vr_hexval(int c) {
    if (c >= '0' && c <= '9')
        return c - '0';
    if (c >= 'a' && c <= 'f')
        return c - 'a' + 10;
    if (c >= 'A' && c <= 'F')
        return c - 'A' + 10;
    return -1;
}

/* Parses hex text into out (cap bytes); -1 on bad hex or too long. */
static inline long vr_unhex(const char *s, uint8_t *out, size_t cap) {
    size_t n = strlen(s), i;
    if (n % 2 || n / 2 > cap)
        return -1;
    for (i = 0; i < n / 2; i++) {
        int hi = vr_hexval(s[2 * i]), lo = vr_hexval(s[2 * i + 1]);
        if (hi < 0 || lo < 0)
            return -1;
        out[i] = (uint8_t)(hi << 4 | lo);
    }
    return (long)(n / 2);
}

static inline void vr_fail(vr_counts *c, const char *file, long line, const char *name,
                           const char *fmt, ...) {
    va_list ap;
    c->failed++;
    fprintf(c->log, "FAIL %s:%ld %s: ", file, line, name);
    va_start(ap, fmt);
    vfprintf(c->log, fmt, ap);
    va_end(ap);
    fputc('\n', c->log);
}

/* Checks one line (without its newline). Comments and empty lines are skipped. */
static inline void vr_line(vr_counts *c, const vr_family *f, const char *file, long lineno,
                           char *line, vr_result *r) {
    static uint8_t data[65536];
    char *col[4];
    char *p = line;
    int k, valid;
    long n;
    ft_err e;
    if (line[0] == 0 || line[0] == '#')
        return;
    for (k = 0; k < 4; k++) {
        col[k] = p;
        p = k < 3 ? strchr(p, '\t') : NULL;
        if (k < 3) {
            if (!p) {
                vr_fail(c, file, lineno, "?", "not 4 tab-separated columns");
                return;
            }
            *p++ = 0;
        }
    }
    if (strchr(col[3], '\t')) {
        vr_fail(c, file, lineno, col[1], "more than 4 columns");
        return;
    }
    if (strcmp(col[0], "valid") != 0 && strcmp(col[0], "invalid") != 0) {
        vr_fail(c, file, lineno, col[1], "first column is '%s', not valid/invalid", col[0]);
        return;
    }
    valid = col[0][0] == 'v';
    n = vr_unhex(col[2], data, sizeof data);
    if (n < 0) {
        vr_fail(c, file, lineno, col[1], "bad hex");
        return;
    }
    e = vr_decode(f, data, (size_t)n, r);
    if (r->problem[0]) {
        vr_fail(c, file, lineno, col[1], "%s", r->problem);
    } else if (!valid) {
        if (e == FT_OK)
            vr_fail(c, file, lineno, col[1], "expected %s, but it decoded: %s", col[3], r->text.s);
        else if (strcmp(ft_err_name(e), col[3]) != 0)
            vr_fail(c, file, lineno, col[1], "expected %s, got %s", col[3], ft_err_name(e));
        else
            c->passed++;
    } else if (e != FT_OK) {
        /* decode failed, or (after a full decode) the re-encoding was refused */
        vr_fail(c, file, lineno, col[1], "valid vector rejected: %s (after '%s')", ft_err_name(e),
                r->text.s);
    } else if (r->text.overflow || strcmp(r->text.s, col[3]) != 0) {
        vr_fail(c, file, lineno, col[1],
                "canonical fields differ:\n    got      %s\n    expected %s", r->text.s, col[3]);
    } else if (r->again_len != (size_t)n || memcmp(r->again, data, (size_t)n) != 0) {
        vr_fail(c, file, lineno, col[1], "re-encoding differs (%zu bytes, want %ld)", r->again_len,
                n);
    } else {
        c->passed++;
    }
}

/* Reads one .tsv file (path), family from its stem. */
static inline void vr_file(vr_counts *c, const char *path, const char *stem, vr_result *r) {
    const vr_family *f = NULL;
    size_t i, cap = 1 << 16, len;
    char *line;
    long lineno = 0;
    FILE *fp;
    for (i = 0; i < VR_N_FAMILIES; i++)
        if (strcmp(vr_families[i].name, stem) == 0)
            f = &vr_families[i];
    if (!f) {
        vr_fail(c, path, 0, stem, "no message family of this name");
        return;
    }
    fp = fopen(path, "rb");
    if (!fp) {
        vr_fail(c, path, 0, stem, "cannot open");
        return;
    }
    line = malloc(cap);
    if (!line) {
        fclose(fp);
        vr_fail(c, path, 0, stem, "out of memory");
        return;
    }
    for (;;) {
        int ch;
        len = 0;
        while ((ch = fgetc(fp)) != EOF && ch != '\n') {
            if (len + 1 >= cap) {
                char *bigger = realloc(line, cap * 2);
                if (!bigger) {
                    free(line);
                    fclose(fp);
                    vr_fail(c, path, lineno, stem, "out of memory");
                    return;
                }
                line = bigger;
                cap *= 2;
            }
            line[len++] = (char)ch;
        }
        if (ch == EOF && len == 0)
            break;
        if (len > 0 && line[len - 1] == '\r')
            len--;
        line[len] = 0;
        lineno++;
        vr_line(c, f, path, lineno, line, r);
        if (ch == EOF)
            break;
    }
    free(line);
    fclose(fp);
}

static inline int vr_cmp(const void *a, const void *b) {
    return strcmp(*(char *const *)a, *(char *const *)b);
}

/* Runs every <dir>/<family>.tsv (in name order). */
static inline void vr_run_dir(vr_counts *c, const char *dir) {
    static vr_result r; /* large: keep off the stack */
    char *names[256];
    size_t n = 0, i;
    struct dirent *de;
    DIR *d = opendir(dir);
    if (!d) {
        vr_fail(c, dir, 0, "-", "cannot open the vectors directory");
        return;
    }
    while ((de = readdir(d)) != NULL && n < 256) {
        size_t l = strlen(de->d_name);
        if (l > 4 && strcmp(de->d_name + l - 4, ".tsv") == 0) {
            names[n] = malloc(l + 1);
            if (names[n])
                memcpy(names[n++], de->d_name, l + 1);
        }
    }
    closedir(d);
    qsort(names, n, sizeof names[0], vr_cmp);
    for (i = 0; i < n; i++) {
        char path[4096], stem[256];
        size_t l = strlen(names[i]) - 4;
        if (l >= sizeof stem)
            l = sizeof stem - 1;
        memcpy(stem, names[i], l);
        stem[l] = 0;
        snprintf(path, sizeof path, "%s/%s", dir, names[i]);
        vr_file(c, path, stem, &r);
        free(names[i]);
    }
}

#endif

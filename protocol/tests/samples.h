/* Shared by the protocol tests: one valid sample of every message (built with the encoders) and a
 * table of every decoder behind one signature, for truncation and fuzz tests. */
#ifndef FT_TEST_SAMPLES_H
#define FT_TEST_SAMPLES_H

#include <math.h>
#include <string.h>

#include "flytrack/protocol.h"

typedef ft_err (*ft_any_decoder)(const uint8_t *buf, size_t len);

static ft_err dec_features(const uint8_t *b, size_t n) {
    ft_features_hdr h;
    ft_point pts[FT_FEATURES_MAX_POINTS];
    return ft_features_decode(b, n, &h, pts);
}
static ft_err dec_status(const uint8_t *b, size_t n) {
    ft_status m;
    return ft_status_decode(b, n, &m);
}
static ft_err dec_control(const uint8_t *b, size_t n) {
    ft_control m;
    return ft_control_decode(b, n, &m);
}
static ft_err dec_control_ack(const uint8_t *b, size_t n) {
    ft_control_ack m;
    return ft_control_ack_decode(b, n, &m);
}
static ft_err dec_image(const uint8_t *b, size_t n) {
    ft_image m;
    ft_err e = ft_image_decode(b, n, &m);
    if (e == FT_OK && m.chunk_len) { /* touch the chunk: must lie inside the datagram */
        volatile uint8_t s = 0;
        s = (uint8_t)(s + m.data[0] + m.data[m.chunk_len - 1]);
        (void)s;
    }
    return e;
}
static ft_err dec_dvs_clusters(const uint8_t *b, size_t n) {
    ft_dvs_clusters_hdr h;
    ft_dvs_cluster c[FT_DVS_MAX_CLUSTERS];
    return ft_dvs_clusters_decode(b, n, &h, c);
}
static ft_err dec_dvs_wingbeat(const uint8_t *b, size_t n) {
    ft_dvs_wingbeat_hdr h;
    ft_wing_edge w[FT_DVS_MAX_EDGES];
    return ft_dvs_wingbeat_decode(b, n, &h, w);
}
static ft_err dec_live(const uint8_t *b, size_t n) {
    ft_live_hdr h;
    ft_live_object o[FT_LIVE_MAX_OBJECTS];
    return ft_live_estimates_decode(b, n, &h, o);
}
static ft_err dec_peek(const uint8_t *b, size_t n) {
    uint8_t t;
    return ft_peek_type(b, n, &t);
}
/* Serial: the frame without its delimiter, then the typed unpack for its msg_id. */
static ft_err dec_serial(const uint8_t *b, size_t n) {
    uint8_t id, seq, pl[FT_TL_MAX_PAYLOAD], plen;
    ft_err e = ft_tl_decode(b, n, &id, &seq, pl, &plen);
    if (e != FT_OK)
        return e;
    switch (id) {
    case FT_TL_SET_RATE: {
        ft_tl_set_rate m;
        return ft_tl_unpack_set_rate(pl, plen, &m);
    }
    case FT_TL_PULSE: {
        ft_tl_pulse m;
        return ft_tl_unpack_pulse(pl, plen, &m);
    }
    case FT_TL_SET_OUTPUT: {
        ft_tl_set_output m;
        return ft_tl_unpack_set_output(pl, plen, &m);
    }
    case FT_TL_SET_NAME: {
        ft_tl_set_name m;
        return ft_tl_unpack_set_name(pl, plen, &m);
    }
    case FT_TL_INFO: {
        ft_tl_info m;
        return ft_tl_unpack_info(pl, plen, &m);
    }
    case FT_TL_ACK: {
        ft_tl_ack m;
        return ft_tl_unpack_ack(pl, plen, &m);
    }
    case FT_TL_RATE: {
        ft_tl_rate m;
        return ft_tl_unpack_rate(pl, plen, &m);
    }
    case FT_TL_CLOCK: {
        ft_tl_clock m;
        return ft_tl_unpack_clock(pl, plen, &m);
    }
    case FT_TL_EVENT: {
        ft_tl_event m;
        return ft_tl_unpack_event(pl, plen, &m);
    }
    case FT_TL_ERROR: {
        ft_tl_error m;
        return ft_tl_unpack_error(pl, plen, &m);
    }
    default:
        return plen == 0 ? FT_OK : FT_E_LENGTH_MISMATCH;
    }
}
static ft_err dec_cobs(const uint8_t *b, size_t n) {
    uint8_t out[2048];
    size_t ol;
    return ft_cobs_decode(b, n, out, sizeof out, &ol);
}
static ft_err dec_dvs(const uint8_t *b, size_t n) {
    ft_dvs_decoder d;
    static ft_dvs_event ev[1024];
    size_t ne;
    ft_dvs_decoder_init(&d);
    return ft_dvs_decode_packet(&d, b, n, ev, 1024, &ne);
}
static ft_err dec_rx(const uint8_t *b, size_t n) {
    /* Byte-at-a-time receiver, then decode of each frame it yields. */
    ft_tl_rx rx;
    size_t i;
    ft_err last = FT_OK;
    ft_tl_rx_init(&rx);
    for (i = 0; i < n; i++) {
        int r = ft_tl_rx_push(&rx, b[i]);
        if (r == FT_TL_RX_FRAME)
            last = dec_serial(rx.buf, rx.len);
        if (rx.len > FT_TL_MAX_FRAME)
            return FT_E_NO_SPACE; /* never happens: the fuzz test checks it */
    }
    return last;
}

typedef struct {
    const char *name;
    ft_any_decoder dec;
} ft_named_decoder;

static const ft_named_decoder ft_decoders[] = {
    {"features", dec_features},
    {"status", dec_status},
    {"control", dec_control},
    {"control_ack", dec_control_ack},
    {"image", dec_image},
    {"dvs_clusters", dec_dvs_clusters},
    {"dvs_wingbeat", dec_dvs_wingbeat},
    {"live_estimates", dec_live},
    {"peek", dec_peek},
    {"serial", dec_serial},
    {"cobs", dec_cobs},
    {"dvs", dec_dvs},
    {"rx", dec_rx},
};
#define FT_N_DECODERS (sizeof ft_decoders / sizeof ft_decoders[0])

/* ---- valid samples ---- */

typedef struct {
    const char *name;
    ft_any_decoder dec;
    uint8_t bytes[FT_UDP_MAX_DATAGRAM];
    size_t len;
} ft_sample;

static const uint8_t ft_image_pixels[64] = {1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15, 16};

/* Fills s[] with one valid message of each kind; returns how many (or 0 if an encoder failed). */
static size_t ft_make_samples(ft_sample *s) {
    size_t k = 0, i;
    {
        ft_features_hdr h = {FT_FEATURES_SPLIT, 3, 3, 1000, 123456, -1, 5000, 7000, 7100, 40, 1, 2};
        ft_point p[3];
        memset(p, 0, sizeof p);
        for (i = 0; i < 3; i++) {
            p[i].x_dist = 100.5f + (float)i;
            p[i].y_dist = 200.25f;
            p[i].x_undist = 101.0f;
            p[i].y_undist = 199.0f;
            p[i].area = 12.0f;
            p[i].peak_diff = 30.0f;
            p[i].orientation = i == 1 ? NAN : 0.5f;
            p[i].eccentricity = 1.5f;
            p[i].cur_val = 250;
            p[i].mean_val = 20.0f;
            p[i].sumsq_val = 410.0f;
        }
        s[k].name = "features";
        s[k].dec = dec_features;
        if (ft_features_encode(s[k].bytes, sizeof s[k].bytes, &h, p, &s[k].len) != FT_OK)
            return 0;
        k++;
    }
    {
        ft_status m = {0,    2, 1280,   1024,   FT_PIXFMT_MONO8, FT_STATE_RUNNING, 77,  0,
                       1000, 2, 100.0f, 850.5f, 1500.0f,         "cam-2",          "ok"};
        s[k].name = "status";
        s[k].dec = dec_status;
        if (ft_status_encode(s[k].bytes, sizeof s[k].bytes, &m, &s[k].len) != FT_OK)
            return 0;
        k++;
    }
    {
        ft_control m = {0, 42, FT_CAMERA_ANY, FT_CMD_SET_PARAM, "diff_threshold", 12.5};
        s[k].name = "control";
        s[k].dec = dec_control;
        if (ft_control_encode(s[k].bytes, sizeof s[k].bytes, &m, &s[k].len) != FT_OK)
            return 0;
        k++;
    }
    {
        ft_control_ack m = {0, 42, 1, FT_CMD_SET_PARAM, FT_ACK_OK, "diff_threshold = 12.5"};
        s[k].name = "control_ack";
        s[k].dec = dec_control_ack;
        if (ft_control_ack_encode(s[k].bytes, sizeof s[k].bytes, &m, &s[k].len) != FT_OK)
            return 0;
        k++;
    }
    {
        ft_image m = {0, 1, FT_IMAGE_REGION, 1, 9, 555, 10, 20, 8, 8, 48, 64, 16, ft_image_pixels};
        s[k].name = "image";
        s[k].dec = dec_image;
        if (ft_image_encode(s[k].bytes, sizeof s[k].bytes, &m, &s[k].len) != FT_OK)
            return 0;
        k++;
    }
    {
        ft_dvs_clusters_hdr h = {FT_DVS_SYNCED, 0, 2, 5, 1000, 2000, 99, 17.25, 10000.0f, 18};
        ft_dvs_cluster c[2] = {{1, 10, 20, 1, -1, 3, 40, 0.5f, 0.25f, -0.125f},
                               {2, 64, 64, 0, 0, 2.5f, 12, 4.0f, 4.0f, 0.0f}};
        s[k].name = "dvs_clusters";
        s[k].dec = dec_dvs_clusters;
        if (ft_dvs_clusters_encode(s[k].bytes, sizeof s[k].bytes, &h, c, &s[k].len) != FT_OK)
            return 0;
        k++;
    }
    {
        ft_dvs_wingbeat_hdr h = {0, 0, 2, 6, 3000, 100};
        ft_wing_edge w[2] = {{0, 0.5f, 1.2f, 210.0f, 0.1f}, {1, -0.5f, 1.1f, 211.0f, 3.0f}};
        s[k].name = "dvs_wingbeat";
        s[k].dec = dec_dvs_wingbeat;
        if (ft_dvs_wingbeat_encode(s[k].bytes, sizeof s[k].bytes, &h, w, &s[k].len) != FT_OK)
            return 0;
        k++;
    }
    {
        ft_live_hdr h = {0, 10000, 1700000000.25, 8, 2, 0, 1, 4.5f};
        ft_live_object o[2];
        memset(o, 0, sizeof o);
        for (i = 0; i < 2; i++) {
            o[i].obj_id = (uint32_t)(i + 7);
            o[i].x = 0.1f;
            o[i].z = 0.3f;
            o[i].vx = 1.0f;
            o[i].cov[0] = o[i].cov[3] = o[i].cov[5] = 1e-4f;
        }
        s[k].name = "live_estimates";
        s[k].dec = dec_live;
        if (ft_live_estimates_encode(s[k].bytes, sizeof s[k].bytes, &h, o, &s[k].len) != FT_OK)
            return 0;
        k++;
    }
    {
        ft_tl_info m = {1, 0, 2, 1, FT_TL_MCU_ATMEGA328P, 4, 16000000u, "box"};
        uint8_t p[FT_TL_INFO_SIZE];
        s[k].name = "serial_info";
        s[k].dec = dec_serial;
        if (ft_tl_pack_info(p, &m) != FT_OK ||
            ft_tl_encode(s[k].bytes, sizeof s[k].bytes, FT_TL_INFO, 3, p, sizeof p, &s[k].len) !=
                FT_OK)
            return 0;
        s[k].len--; /* without the delimiter */
        k++;
    }
    {
        ft_dvs_word w[4] = {{FT_DVS_EVENT, 5, 6, 1, 100},
                            {FT_DVS_WRAP, 0, 0, 0, 0},
                            {FT_DVS_EVENT, 127, 127, 0, 0x3FFF},
                            {FT_DVS_RESET, 0, 0, 0, 0}};
        s[k].name = "dvs";
        s[k].dec = dec_dvs;
        for (i = 0; i < 4; i++)
            if (ft_dvs_word_encode(s[k].bytes + 4 * i, &w[i]) != FT_OK)
                return 0;
        s[k].len = 16;
        k++;
    }
    return k;
}
#define FT_MAX_SAMPLES 16

#endif

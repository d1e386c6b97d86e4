/* Unit tests of udp.h and dvs.h: round trips, every truncation of every message, NO_SPACE at
 * every too-small capacity, and each decoder check with the error the SPEC names. */
#include <math.h>
#include <string.h>

#include "check.h"
#include "samples.h"

static ft_sample samples[FT_MAX_SAMPLES];
static size_t n_samples;

static const ft_sample *find(const char *name) {
    size_t i;
    for (i = 0; i < n_samples; i++)
        if (strcmp(samples[i].name, name) == 0)
            return &samples[i];
    return NULL;
}

static void test_truncations(void) {
    size_t i, cut;
    for (i = 0; i < n_samples; i++) {
        const ft_sample *s = &samples[i];
        int is_udp = s->dec != dec_serial && s->dec != dec_dvs;
        CHECK_ERR(s->dec(s->bytes, s->len), FT_OK);
        for (cut = 0; cut < s->len; cut++) {
            ft_err e = s->dec(s->bytes, cut);
            if (s->dec == dec_dvs) { /* a packet of whole words is a valid shorter packet */
                CHECK_ERR(e, cut % 4 ? FT_E_TRUNCATED : FT_OK);
                continue;
            }
            if (e == FT_OK)
                fprintf(stderr, "%s accepted at %zu of %zu bytes\n", s->name, cut, s->len);
            CHECK(e != FT_OK);
            if (is_udp) {
                /* header short: TRUNCATED; short of the fixed part: TRUNCATED; else the header's
                 * length disagrees with the datagram */
                int fixed = ft_udp_fixed_size(s->bytes[3]);
                CHECK_ERR(e, cut < FT_UDP_HEADER + (size_t)fixed ? FT_E_TRUNCATED
                                                                 : FT_E_LENGTH_MISMATCH);
            }
        }
        if (s->dec == dec_dvs)
            continue;
        /* A datagram (or frame) with one byte too many */
        {
            uint8_t big[FT_UDP_MAX_DATAGRAM + 1];
            memcpy(big, s->bytes, s->len);
            big[s->len] = 0x11;
            CHECK(s->dec(big, s->len + 1) != FT_OK);
        }
    }
}

static void test_roundtrips(void) {
    uint8_t out[FT_UDP_MAX_DATAGRAM];
    size_t ol = 0, cap;
    {
        const ft_sample *s = find("features");
        ft_features_hdr h;
        ft_point p[FT_FEATURES_MAX_POINTS];
        CHECK_ERR(ft_features_decode(s->bytes, s->len, &h, p), FT_OK);
        CHECK(h.n_points == 3 && h.trigger_frame == -1 && h.part_index == 1 && h.part_count == 2);
        CHECK(h.flags == FT_FEATURES_SPLIT && h.total_points == 40 && h.camera_frame == 123456);
        CHECK(p[0].x_dist == 100.5f && p[2].x_dist == 102.5f && isnan(p[1].orientation));
        CHECK(p[1].cur_val == 250 && p[2].sumsq_val == 410.0f);
        CHECK_ERR(ft_features_encode(out, sizeof out, &h, p, &ol), FT_OK);
        CHECK(ol == s->len && memcmp(out, s->bytes, ol) == 0);
        for (cap = 0; cap < s->len; cap++)
            CHECK_ERR(ft_features_encode(out, cap, &h, p, &ol), FT_E_NO_SPACE);
        /* encoder refuses what a decoder would refuse */
        h.n_points = 33;
        CHECK_ERR(ft_features_encode(out, sizeof out, &h, p, &ol), FT_E_COUNT_OVERFLOW);
        h.n_points = 3;
        p[0].orientation = INFINITY;
        CHECK_ERR(ft_features_encode(out, sizeof out, &h, p, &ol), FT_E_NOT_FINITE);
        p[0].orientation = 0;
        h.part_index = 2;
        CHECK_ERR(ft_features_encode(out, sizeof out, &h, p, &ol), FT_E_BAD_FIELD);
        /* 32 points fill a datagram exactly */
        {
            ft_point many[FT_FEATURES_MAX_POINTS];
            size_t i;
            for (i = 0; i < FT_FEATURES_MAX_POINTS; i++)
                many[i] = p[0];
            h.part_index = 0;
            h.part_count = 1;
            h.flags = FT_FEATURES_TRUNCATED;
            h.n_points = FT_FEATURES_MAX_POINTS;
            h.total_points = 100;
            CHECK_ERR(ft_features_encode(out, sizeof out, &h, many, &ol), FT_OK);
            CHECK(ol == FT_UDP_MAX_DATAGRAM);
            CHECK_ERR(ft_features_decode(out, ol, &h, p), FT_OK);
            CHECK(h.n_points == 32 && h.flags == FT_FEATURES_TRUNCATED);
        }
    }
    {
        const ft_sample *s = find("status");
        ft_status m;
        CHECK_ERR(ft_status_decode(s->bytes, s->len, &m), FT_OK);
        CHECK(m.width == 1280 && m.state == FT_STATE_RUNNING && m.fps == 100.0f);
        CHECK(strcmp(m.camera_name, "cam-2") == 0 && strcmp(m.last_error, "ok") == 0);
        CHECK_ERR(ft_status_encode(out, sizeof out, &m, &ol), FT_OK);
        CHECK(ol == s->len && memcmp(out, s->bytes, ol) == 0);
        for (cap = 0; cap < s->len; cap++)
            CHECK_ERR(ft_status_encode(out, cap, &m, &ol), FT_E_NO_SPACE);
        memset(m.camera_name, 'a', sizeof m.camera_name); /* no NUL: does not fit */
        CHECK_ERR(ft_status_encode(out, sizeof out, &m, &ol), FT_E_BAD_FIELD);
    }
    {
        const ft_sample *s = find("control");
        ft_control m;
        CHECK_ERR(ft_control_decode(s->bytes, s->len, &m), FT_OK);
        CHECK(m.value == 12.5 && strcmp(m.param, "diff_threshold") == 0 &&
              m.camera_index == 0xFFFF);
        CHECK_ERR(ft_control_encode(out, sizeof out, &m, &ol), FT_OK);
        CHECK(ol == s->len && memcmp(out, s->bytes, ol) == 0);
        for (cap = 0; cap < s->len; cap++)
            CHECK_ERR(ft_control_encode(out, cap, &m, &ol), FT_E_NO_SPACE);
        m.value = NAN;
        CHECK_ERR(ft_control_encode(out, sizeof out, &m, &ol), FT_E_NOT_FINITE);
    }
    {
        const ft_sample *s = find("control_ack");
        ft_control_ack m;
        CHECK_ERR(ft_control_ack_decode(s->bytes, s->len, &m), FT_OK);
        CHECK(m.request_id == 42 && strcmp(m.message, "diff_threshold = 12.5") == 0);
        CHECK_ERR(ft_control_ack_encode(out, sizeof out, &m, &ol), FT_OK);
        CHECK(ol == s->len && memcmp(out, s->bytes, ol) == 0);
        for (cap = 0; cap < s->len; cap++)
            CHECK_ERR(ft_control_ack_encode(out, cap, &m, &ol), FT_E_NO_SPACE);
    }
    {
        const ft_sample *s = find("image");
        ft_image m;
        CHECK_ERR(ft_image_decode(s->bytes, s->len, &m), FT_OK);
        CHECK(m.chunk_len == 16 && m.data == s->bytes + FT_UDP_HEADER + FT_IMAGE_FIXED);
        CHECK(memcmp(m.data, ft_image_pixels, 16) == 0 && m.offset == 48);
        CHECK_ERR(ft_image_encode(out, sizeof out, &m, &ol), FT_OK);
        CHECK(ol == s->len && memcmp(out, s->bytes, ol) == 0);
        for (cap = 0; cap < s->len; cap++)
            CHECK_ERR(ft_image_encode(out, cap, &m, &ol), FT_E_NO_SPACE);
        m.offset = 49; /* chunk past the image */
        CHECK_ERR(ft_image_encode(out, sizeof out, &m, &ol), FT_E_BAD_FIELD);
        m.offset = 0xFFFFFFF8u; /* offset + chunk_len overflows 32 bits */
        CHECK_ERR(ft_image_encode(out, sizeof out, &m, &ol), FT_E_BAD_FIELD);
        m.offset = 0;
        m.total_bytes = 65;
        CHECK_ERR(ft_image_encode(out, sizeof out, &m, &ol), FT_E_BAD_FIELD);
        m.chunk_len = FT_IMAGE_MAX_CHUNK + 1;
        CHECK_ERR(ft_image_encode(out, sizeof out, &m, &ol), FT_E_COUNT_OVERFLOW);
    }
    {
        const ft_sample *s = find("dvs_clusters");
        ft_dvs_clusters_hdr h;
        ft_dvs_cluster c[FT_DVS_MAX_CLUSTERS];
        CHECK_ERR(ft_dvs_clusters_decode(s->bytes, s->len, &h, c), FT_OK);
        CHECK(h.n_clusters == 2 && c[1].id == 2 && c[1].size == 2.5f && c[0].vy == -1.0f);
        CHECK(h.flags == FT_DVS_SYNCED && h.trigger_frame == 17.25 &&
              h.frame_period_us == 10000.0f && h.syncs == 18);
        CHECK(c[0].var_x == 0.5f && c[0].var_y == 0.25f && c[0].cov_xy == -0.125f);
        CHECK_ERR(ft_dvs_clusters_encode(out, sizeof out, &h, c, &ol), FT_OK);
        CHECK(ol == s->len && memcmp(out, s->bytes, ol) == 0);
        for (cap = 0; cap < s->len; cap++)
            CHECK_ERR(ft_dvs_clusters_encode(out, cap, &h, c, &ol), FT_E_NO_SPACE);
        /* not a covariance, a negative variance, SYNCED without a period: refused when sent */
        c[0].cov_xy = 0.5f;
        CHECK_ERR(ft_dvs_clusters_encode(out, sizeof out, &h, c, &ol), FT_E_BAD_FIELD);
        c[0].cov_xy = 0.0f;
        c[0].var_y = -1.0f;
        CHECK_ERR(ft_dvs_clusters_encode(out, sizeof out, &h, c, &ol), FT_E_BAD_FIELD);
        c[0].var_y = 0.25f;
        h.frame_period_us = 0.0f;
        CHECK_ERR(ft_dvs_clusters_encode(out, sizeof out, &h, c, &ol), FT_E_BAD_FIELD);
        h.flags = 0;
        CHECK_ERR(ft_dvs_clusters_encode(out, sizeof out, &h, c, &ol), FT_OK);
    }
    {
        const ft_sample *s = find("dvs_wingbeat");
        ft_dvs_wingbeat_hdr h;
        ft_wing_edge w[FT_DVS_MAX_EDGES];
        CHECK_ERR(ft_dvs_wingbeat_decode(s->bytes, s->len, &h, w), FT_OK);
        CHECK(h.n_edges == 2 && w[1].edge_id == 1 && w[1].frequency == 211.0f);
        CHECK_ERR(ft_dvs_wingbeat_encode(out, sizeof out, &h, w, &ol), FT_OK);
        CHECK(ol == s->len && memcmp(out, s->bytes, ol) == 0);
        for (cap = 0; cap < s->len; cap++)
            CHECK_ERR(ft_dvs_wingbeat_encode(out, cap, &h, w, &ol), FT_E_NO_SPACE);
    }
    {
        const ft_sample *s = find("live_estimates");
        ft_live_hdr h;
        ft_live_object o[FT_LIVE_MAX_OBJECTS];
        CHECK_ERR(ft_live_estimates_decode(s->bytes, s->len, &h, o), FT_OK);
        CHECK(h.trigger_time == 1700000000.25 && h.n_objects == 2 && o[1].obj_id == 8);
        CHECK(o[0].cov[5] == 1e-4f && h.latency_ms == 4.5f);
        CHECK_ERR(ft_live_estimates_encode(out, sizeof out, &h, o, &ol), FT_OK);
        CHECK(ol == s->len && memcmp(out, s->bytes, ol) == 0);
        for (cap = 0; cap < s->len; cap++)
            CHECK_ERR(ft_live_estimates_encode(out, cap, &h, o, &ol), FT_E_NO_SPACE);
        h.part_count = 0;
        CHECK_ERR(ft_live_estimates_encode(out, sizeof out, &h, o, &ol), FT_E_BAD_FIELD);
    }
}

/* Each header and field check, by mutating a valid sample. */
static void test_header_errors(void) {
    size_t i, j;
    uint8_t b[FT_UDP_MAX_DATAGRAM + 64];
    for (i = 0; i < n_samples; i++) {
        const ft_sample *s = &samples[i];
        uint8_t type;
        if (s->dec == dec_serial || s->dec == dec_dvs)
            continue;
        CHECK_ERR(ft_peek_type(s->bytes, s->len, &type), FT_OK);
        CHECK(type == s->bytes[3]);
        memcpy(b, s->bytes, s->len);
        b[0] = 'X';
        CHECK_ERR(s->dec(b, s->len), FT_E_BAD_MAGIC);
        CHECK_ERR(s->dec(b, 8), FT_E_BAD_MAGIC);
        b[0] = 'F';
        b[1] = 'F';
        CHECK_ERR(s->dec(b, s->len), FT_E_BAD_MAGIC);
        b[1] = 'T';
        b[2] = FT_PROTOCOL_VERSION + 1;
        CHECK_ERR(s->dec(b, s->len), FT_E_BAD_VERSION);
        b[2] = FT_PROTOCOL_VERSION - 1; /* the layout before: refused, not misread */
        CHECK_ERR(s->dec(b, s->len), FT_E_BAD_VERSION);
        b[2] = 0;
        CHECK_ERR(s->dec(b, s->len), FT_E_BAD_VERSION);
        b[2] = FT_PROTOCOL_VERSION;
        b[3] = 0x7F;
        CHECK_ERR(s->dec(b, s->len), FT_E_UNKNOWN_TYPE);
        CHECK_ERR(ft_peek_type(b, s->len, &type), FT_E_UNKNOWN_TYPE);
        b[3] = s->bytes[3];
        /* every other decoder calls this message type unknown */
        for (j = 0; j < n_samples; j++)
            if (samples[j].dec != s->dec && samples[j].dec != dec_serial &&
                samples[j].dec != dec_dvs)
                CHECK_ERR(samples[j].dec(b, s->len), FT_E_UNKNOWN_TYPE);
        ft_st_u16(b + 4, (uint16_t)(s->len - 8 + 1));
        CHECK_ERR(s->dec(b, s->len), FT_E_LENGTH_MISMATCH);
        CHECK_ERR(ft_peek_type(b, s->len, &type), FT_E_LENGTH_MISMATCH);
        ft_st_u16(b + 4, (uint16_t)(s->len - 8));
        /* undefined flag bits are ignored */
        ft_st_u16(b + 6, (uint16_t)(ft_ld_u16(b + 6) | 0xFFF0u));
        CHECK_ERR(s->dec(b, s->len), FT_OK);
        /* a longer datagram whose header agrees: extra bytes after the message */
        memcpy(b, s->bytes, s->len);
        memset(b + s->len, 0, 44);
        ft_st_u16(b + 4, (uint16_t)(s->len - 8 + 4));
        CHECK_ERR(s->dec(b, s->len + 4), FT_E_LENGTH_MISMATCH);
    }
}

/* Sets a u16 at payload offset off of a copy of sample s, fixes the header length to the datagram
 * size, and returns the decoder's verdict. */
static ft_err mutate16(const char *name, size_t off, uint16_t v, size_t extra) {
    const ft_sample *s = find(name);
    uint8_t b[4096];
    memset(b, 0, sizeof b);
    memcpy(b, s->bytes, s->len);
    ft_st_u16(b + 8 + off, v);
    ft_st_u16(b + 4, (uint16_t)(s->len + extra - 8));
    return s->dec(b, s->len + extra);
}
static ft_err mutate8(const char *name, size_t off, uint8_t v) {
    const ft_sample *s = find(name);
    uint8_t b[FT_UDP_MAX_DATAGRAM];
    memcpy(b, s->bytes, s->len);
    b[8 + off] = v;
    return s->dec(b, s->len);
}
static ft_err mutate32(const char *name, size_t off, uint32_t v) {
    const ft_sample *s = find(name);
    uint8_t b[FT_UDP_MAX_DATAGRAM];
    memcpy(b, s->bytes, s->len);
    ft_st_u32(b + 8 + off, v);
    return s->dec(b, s->len);
}

static void test_field_errors(void) {
    /* counts: more than the type allows, more than the payload holds, fewer than it holds */
    CHECK_ERR(mutate16("features", 2, 33, 0), FT_E_COUNT_OVERFLOW);
    CHECK_ERR(mutate16("features", 2, 33, 30 * 44), FT_E_COUNT_OVERFLOW);
    CHECK_ERR(mutate16("features", 2, 0xFFFF, 0), FT_E_COUNT_OVERFLOW);
    CHECK_ERR(mutate16("features", 2, 4, 0), FT_E_COUNT_OVERFLOW);
    CHECK_ERR(mutate16("features", 2, 2, 0), FT_E_LENGTH_MISMATCH);
    CHECK_ERR(mutate16("features", 2, 4, 44), FT_OK);
    CHECK_ERR(mutate16("dvs_clusters", 2, 52, 0), FT_E_COUNT_OVERFLOW);
    CHECK_ERR(mutate16("dvs_clusters", 2, 1, 0), FT_E_LENGTH_MISMATCH);
    CHECK_ERR(mutate16("dvs_wingbeat", 2, 9, 0), FT_E_COUNT_OVERFLOW);
    CHECK_ERR(mutate16("dvs_wingbeat", 2, 3, 0), FT_E_COUNT_OVERFLOW);
    CHECK_ERR(mutate16("live_estimates", 20, 28, 0), FT_E_COUNT_OVERFLOW);
    CHECK_ERR(mutate16("live_estimates", 20, 1, 0), FT_E_LENGTH_MISMATCH);
    CHECK_ERR(mutate16("image", 32, 17, 0), FT_E_COUNT_OVERFLOW);
    CHECK_ERR(mutate16("image", 32, 15, 0), FT_E_LENGTH_MISMATCH);
    CHECK_ERR(mutate16("image", 32, 1429, 1429 - 16), FT_E_COUNT_OVERFLOW);
    /* FEATURES fields */
    CHECK_ERR(mutate8("features", 51, 0), FT_E_BAD_FIELD); /* part_count 0 */
    CHECK_ERR(mutate8("features", 50, 2), FT_E_BAD_FIELD); /* part_index == part_count */
    CHECK_ERR(mutate16("features", 48, 2, 0), FT_OK);      /* total < n: fine when SPLIT */
    {
        /* not SPLIT: n_points must not exceed total_points */
        const ft_sample *s = find("features");
        uint8_t b[FT_UDP_MAX_DATAGRAM];
        memcpy(b, s->bytes, s->len);
        ft_st_u16(b + 6, 0);
        b[8 + 50] = 0;
        b[8 + 51] = 1;
        CHECK_ERR(s->dec(b, s->len), FT_OK);
        ft_st_u16(b + 8 + 48, 2);
        CHECK_ERR(s->dec(b, s->len), FT_E_COUNT_OVERFLOW);
        /* ... reported before bytes after the points */
        memset(b + s->len, 0, 4);
        ft_st_u16(b + 4, (uint16_t)(s->len - 8 + 4));
        CHECK_ERR(s->dec(b, s->len + 4), FT_E_COUNT_OVERFLOW);
    }
    CHECK_ERR(mutate32("features", 56, 0x7F800000u), FT_E_NOT_FINITE);      /* x_dist inf */
    CHECK_ERR(mutate32("features", 56, 0x7FC00000u), FT_E_NOT_FINITE);      /* x_dist NaN */
    CHECK_ERR(mutate32("features", 56 + 24, 0xFF800000u), FT_E_NOT_FINITE); /* orientation -inf */
    CHECK_ERR(mutate32("features", 56 + 24, 0x7FC00001u), FT_OK);           /* orientation NaN */
    CHECK_ERR(mutate32("features", 56 + 28, 0xFFC00000u), FT_OK);           /* eccentricity NaN */
    CHECK_ERR(mutate32("features", 56 + 40 + 88, 0x7F800001u), FT_E_NOT_FINITE); /* last point */
    /* NOT_FINITE is reported before BAD_FIELD */
    {
        const ft_sample *s = find("features");
        uint8_t b[FT_UDP_MAX_DATAGRAM];
        memcpy(b, s->bytes, s->len);
        b[8 + 51] = 0;
        ft_st_u32(b + 8 + 56, 0x7F800000u);
        CHECK_ERR(s->dec(b, s->len), FT_E_NOT_FINITE);
    }
    /* STATUS */
    CHECK_ERR(mutate8("status", 6, 3), FT_E_BAD_FIELD);
    CHECK_ERR(mutate8("status", 7, 4), FT_E_BAD_FIELD);
    CHECK_ERR(mutate32("status", 32, 0x7FC00000u), FT_E_NOT_FINITE);
    CHECK_ERR(mutate32("status", 40, 0xFF800000u), FT_E_NOT_FINITE);
    CHECK_ERR(mutate8("status", 48 + 31, 'x'), FT_E_BAD_FIELD); /* after the first NUL */
    CHECK_ERR(mutate8("status", 80 + 63, 'x'), FT_E_BAD_FIELD);
    CHECK_ERR(mutate32("status", 44, 0xFFFFFFFFu), FT_OK); /* reserved: ignored */
    {
        const ft_sample *s = find("status");
        uint8_t b[FT_UDP_MAX_DATAGRAM];
        ft_status m;
        memcpy(b, s->bytes, s->len);
        memset(b + 8 + 48, 'n', 32); /* a name that fills its field */
        CHECK_ERR(ft_status_decode(b, s->len, &m), FT_OK);
        CHECK(strlen(m.camera_name) == 32);
    }
    /* CONTROL, CONTROL_ACK */
    CHECK_ERR(mutate8("control", 6, 0), FT_E_BAD_FIELD);
    CHECK_ERR(mutate8("control", 6, 7), FT_E_BAD_FIELD);
    CHECK_ERR(mutate8("control", 6, 6), FT_OK);
    CHECK_ERR(mutate8("control", 7, 0xAA), FT_OK); /* reserved */
    CHECK_ERR(mutate32("control", 36, 0x7FF00000u), FT_E_NOT_FINITE);
    CHECK_ERR(mutate8("control", 8 + 23, 'x'), FT_E_BAD_FIELD);
    CHECK_ERR(mutate8("control_ack", 7, 5), FT_E_BAD_FIELD);
    CHECK_ERR(mutate8("control_ack", 6, 200), FT_OK); /* command echoed as is */
    CHECK_ERR(mutate8("control_ack", 8 + 47, 'x'), FT_E_BAD_FIELD);
    /* IMAGE */
    CHECK_ERR(mutate8("image", 2, 2), FT_E_BAD_FIELD);
    CHECK_ERR(mutate8("image", 3, 0), FT_E_BAD_FIELD);
    CHECK_ERR(mutate8("image", 3, 3), FT_E_BAD_FIELD);
    CHECK_ERR(mutate32("image", 24, 49), FT_E_BAD_FIELD);
    CHECK_ERR(mutate32("image", 24, 0xFFFFFFFFu), FT_E_BAD_FIELD);
    CHECK_ERR(mutate32("image", 28, 128), FT_E_BAD_FIELD);
    CHECK_ERR(mutate8("image", 34, 9), FT_OK); /* reserved */
    /* DVS_CLUSTERS, DVS_WINGBEAT, LIVE_ESTIMATES: all floats finite */
    CHECK_ERR(mutate32("dvs_clusters", 32 + 28 + 24, 0x7FC00000u), FT_E_NOT_FINITE);
    CHECK_ERR(mutate32("dvs_wingbeat", 24 + 4, 0x7F800000u), FT_E_NOT_FINITE);
    CHECK_ERR(mutate8("dvs_wingbeat", 24 + 1, 0xEE), FT_OK);                 /* reserved */
    CHECK_ERR(mutate32("live_estimates", 12, 0x7FF00000u), FT_E_NOT_FINITE); /* trigger_time */
    CHECK_ERR(mutate32("live_estimates", 24, 0x7FC00000u), FT_E_NOT_FINITE); /* latency */
    CHECK_ERR(mutate32("live_estimates", 32 + 52 + 48, 0x7FC00000u), FT_E_NOT_FINITE); /* cov zz */
    CHECK_ERR(mutate8("live_estimates", 23, 0), FT_E_BAD_FIELD);
    CHECK_ERR(mutate8("live_estimates", 22, 1), FT_E_BAD_FIELD);
}

static void test_dvs(void) {
    ft_dvs_word w;
    ft_dvs_decoder d;
    ft_dvs_event ev[8];
    size_t n;
    uint8_t b[32], o[4];
    const uint8_t ev_bytes[4] = {(uint8_t)((17 << 1) | 1), 99, 0x34, 0x12};
    CHECK_ERR(ft_dvs_word_decode(ev_bytes, &w), FT_OK);
    CHECK(w.kind == FT_DVS_EVENT && w.x == 17 && w.polarity == 1 && w.y == 99 && w.ts == 0x1234);
    CHECK_ERR(ft_dvs_word_encode(o, &w), FT_OK);
    CHECK(memcmp(o, ev_bytes, 4) == 0);
    {
        const uint8_t sync[4] = {0, 0x80, 0x10, 0}, sync_wrap[4] = {0, 0x80, 0, 0x80},
                      sync_reset[4] = {0, 0x80, 0, 0x40}, both[4] = {0, 0, 0, 0xC0};
        CHECK_ERR(ft_dvs_word_decode(sync, &w), FT_OK);
        CHECK(w.kind == FT_DVS_SYNC && w.ts == 0x10);
        CHECK_ERR(ft_dvs_word_encode(o, &w), FT_OK);
        CHECK(memcmp(o, sync, 4) == 0);
        ft_dvs_decoder_init(&d);
        CHECK(ft_dvs_apply(&d, &w, ev) == 0 && d.n_sync == 1 && d.sync_t_us == 0x10);
        CHECK_ERR(ft_dvs_word_decode(sync_wrap, &w), FT_E_BAD_FIELD);
        CHECK_ERR(ft_dvs_word_decode(sync_reset, &w), FT_E_BAD_FIELD);
        CHECK_ERR(ft_dvs_word_decode(both, &w), FT_E_BAD_FIELD);
    }
    w.x = 128;
    CHECK_ERR(ft_dvs_word_encode(o, &w), FT_E_BAD_FIELD);
    /* event 100, WRAP, event 5 (t = 0x4000 + 5), WRAP, WRAP, event 0, RESET, event 7 */
    {
        ft_dvs_word seq[8] = {{0, 1, 2, 1, 100},
                              {FT_DVS_WRAP, 0, 0, 0, 0},
                              {0, 3, 4, 0, 5},
                              {FT_DVS_WRAP, 0, 0, 0, 0},
                              {FT_DVS_WRAP, 0, 0, 0, 0},
                              {0, 5, 6, 1, 0},
                              {FT_DVS_RESET, 0, 0, 0, 0},
                              {0, 7, 8, 0, 7}};
        size_t i;
        for (i = 0; i < 8; i++)
            CHECK_ERR(ft_dvs_word_encode(b + 4 * i, &seq[i]), FT_OK);
        ft_dvs_decoder_init(&d);
        CHECK_ERR(ft_dvs_decode_packet(&d, b, 32, ev, 8, &n), FT_OK);
        CHECK(n == 4);
        CHECK(ev[0].t_us == 100 && ev[0].x == 1 && ev[0].y == 2 && ev[0].polarity == 1);
        CHECK(ev[1].t_us == 0x4000 + 5);
        CHECK(ev[2].t_us == 3 * 0x4000);
        CHECK(ev[3].t_us == 7 && ev[3].x == 7);
        /* not enough room: nothing applied */
        ft_dvs_decoder_init(&d);
        d.offset = 5;
        CHECK_ERR(ft_dvs_decode_packet(&d, b, 32, ev, 3, &n), FT_E_NO_SPACE);
        CHECK(d.offset == 5);
        /* a bad word in the middle: rejected whole, state kept */
        b[4 * 3 + 1] = 0x80;
        CHECK_ERR(ft_dvs_decode_packet(&d, b, 32, ev, 8, &n), FT_E_BAD_FIELD);
        CHECK(d.offset == 5);
        CHECK_ERR(ft_dvs_decode_packet(&d, b, 31, ev, 8, &n), FT_E_TRUNCATED);
        CHECK_ERR(ft_dvs_decode_packet(&d, b, 0, ev, 8, &n), FT_OK);
        CHECK(n == 0);
    }
    /* the running offset goes past 32 bits */
    {
        ft_dvs_word wr = {FT_DVS_WRAP, 0, 0, 0, 0}, e = {0, 1, 1, 1, 1};
        ft_dvs_event one;
        unsigned long k;
        ft_dvs_decoder_init(&d);
        for (k = 0; k < 300000ul; k++)
            ft_dvs_apply(&d, &wr, &one);
        CHECK(ft_dvs_apply(&d, &e, &one) == 1 && one.t_us == 300000ull * 0x4000 + 1);
    }
}

int main(void) {
    n_samples = ft_make_samples(samples);
    CHECK(n_samples == 10);
    if (n_samples == 0)
        return ft_test_report("test_udp");
    test_truncations();
    test_roundtrips();
    test_header_errors();
    test_field_errors();
    test_dvs();
    return ft_test_report("test_udp");
}

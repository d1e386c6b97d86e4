/* The background update spread over the frames after it (src/background.c):
 *  1. the block bounds predicted for after the next update (ft_fx_next_bounds8/16) hold: after
 *     updates with random frames (pixels at 0 and at the top of the range included), every
 *     pixel's new hi is at or above its block's predicted bound and every new lo at or below it;
 *     and they are tight (8-bit, alpha 0.01, diff_threshold 30: under 4 levels of slack on
 *     average);
 *  2. an extractor that spreads its updates gives the same results, bit for bit, as one that does
 *     each update whole in the frame that asks for it (ft_fx_debug_eager_update), frame after
 *     frame, with weak targets just past their thresholds right after the updates, every format,
 *     padded strides, masks, polarities, parameters changed and the background read midway.
 * Built with the library's native flags and under ASan + UBSan (CMake). */
#include "flytrack/features.h"
#include "fx_internal.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

static int failures;
#define CHECK(cond, ...)                                                                           \
    do {                                                                                           \
        if (!(cond)) {                                                                             \
            if (failures < 20) {                                                                   \
                fprintf(stderr, "%s:%d: CHECK failed: %s: ", __FILE__, __LINE__, #cond);           \
                fprintf(stderr, __VA_ARGS__);                                                      \
                fprintf(stderr, "\n");                                                             \
            }                                                                                      \
            failures++;                                                                            \
        }                                                                                          \
    } while (0)

static uint64_t rng_state = 0x2545f4914f6cdd1dull;
static uint32_t rnd(void) {
    rng_state ^= rng_state << 13;
    rng_state ^= rng_state >> 7;
    rng_state ^= rng_state << 17;
    return (uint32_t)(rng_state >> 32);
}
static double urand(void) {
    return rnd() / 4294967296.0;
}

/* A frame: a smooth background at level + drift, noise of +-noise, a few pixels at 0 or maxv, and
 * weak targets whose peak is thr + 1 .. thr + 3 above (or below) the background. */
static void make_frame(uint32_t *v, int w, int h, uint32_t maxv, double drift, double noise,
                       double thr, int extremes) {
    const double sc = maxv / 255.0;
    for (int y = 0; y < h; y++)
        for (int x = 0; x < w; x++) {
            double val =
                sc * (100 + 30 * sin(0.04 * x) * cos(0.05 * y)) + drift + noise * (2 * urand() - 1);
            v[y * w + x] = (uint32_t)(val < 0 ? 0 : val > maxv ? maxv : floor(val + 0.5));
        }
    for (int k = 0; k < 6; k++) { /* weak targets: one or a few pixels just past the threshold */
        int x = (int)(rnd() % (uint32_t)w), y = (int)(rnd() % (uint32_t)h);
        double d = (thr + 1 + rnd() % 3) * (rnd() & 1 ? 1 : -1);
        double val = v[y * w + x] + d;
        v[y * w + x] = (uint32_t)(val < 0 ? 0 : val > maxv ? maxv : val);
    }
    for (int k = 0; extremes && k < w * h / 50; k++)
        v[rnd() % (uint32_t)(w * h)] = rnd() & 1 ? maxv : 0;
}

static void *pack(const uint32_t *v, int w, int h, int fmt, int pad, size_t *bytes) {
    const size_t bpp = fmt == FT_FX_MONO8 ? 1 : 2, stride = (size_t)(w + pad) * bpp;
    *bytes = stride * (size_t)(h - 1) + (size_t)w * bpp;
    uint8_t *b = malloc(stride * (size_t)h);
    for (size_t i = 0; i < stride * (size_t)h; i++)
        b[i] = (uint8_t)rnd();
    for (int y = 0; y < h; y++)
        for (int x = 0; x < w; x++) {
            uint8_t *px = b + (size_t)y * stride + (size_t)x * bpp;
            if (fmt == FT_FX_MONO16)
                memcpy(px, &(uint16_t){(uint16_t)v[y * w + x]}, 2);
            else
                px[0] = (uint8_t)v[y * w + x];
        }
    return b;
}

/* 1. The predicted bounds hold after an update, and are tight in the common case. */
static void test_bounds_hold(void) {
    long blocks = 0, slack_hi = 0, slack_lo = 0, tight_blocks = 0;
    for (int c = 0; c < 60; c++) {
        /* every tenth case wider than 64 blocks (the bounds are computed 64 blocks at a time) */
        const int w = c % 10 == 3 ? 4100 + (int)(rnd() % 500) : 64 + (int)(rnd() % 200);
        const int h = c % 10 == 3 ? 3 : 3 + (int)(rnd() % 20);
        const int fmt = c % 3 == 2 ? FT_FX_MONO16 : FT_FX_MONO8;
        const uint32_t maxv = fmt == FT_FX_MONO16 ? 4095 : 255;
        const int tight = c % 4 == 0 && fmt == FT_FX_MONO8; /* alpha 0.01, T = diff_threshold */
        ft_fx_params p;
        ft_fx_params_default(&p, (uint32_t)w, (uint32_t)h, fmt);
        p.alpha = tight ? 0.01 : 0.002 + 0.5 * urand();
        p.n_sigma = tight ? 7.0 : 1.0 + 6 * urand();
        p.diff_threshold = (tight ? 30.0 : 5 + 40 * urand()) * maxv / 255.0;
        p.polarity = tight ? FT_FX_POLARITY_BOTH : (int32_t)(rnd() % 3);
        p.bg_update_interval = 0;
        ft_fx *fx = NULL;
        CHECK(ft_fx_create(&p, sizeof p, &fx) == FT_FX_OK, "create");
        ft_fx_debug_eager_update(fx, 1);
        uint32_t *v = malloc(sizeof(uint32_t) * (size_t)(w * h));
        size_t nb = fx->nblk * (size_t)h, bytes;
        void *pb = fx->hi16 ? (void *)fx->nbhi16 : (void *)fx->nbhi8;
        void *pl = fx->hi16 ? (void *)fx->nblo16 : (void *)fx->nblo8;
        size_t tb = fx->hi16 ? 2 : 1;
        uint8_t *pred_hi = malloc(nb * tb), *pred_lo = malloc(nb * tb);
        if (c % 5 == 1) { /* a mask: masked pixels never candidates */
            uint8_t *m = malloc((size_t)(w * h));
            for (int i = 0; i < w * h; i++)
                m[i] = rnd() % 5 != 0;
            ft_fx_set_mask(fx, m);
            free(m);
        }
        for (int f = 0; f < 6; f++) {
            make_frame(v, w, h, maxv, (tight ? 3 : 40) * (urand() - 0.5) * maxv / 255.0,
                       (tight ? 2 : 12) * maxv / 255.0, p.diff_threshold, !tight);
            void *buf = pack(v, w, h, fmt, 0, &bytes);
            ft_fx_result r;
            if (f == 0) {
                CHECK(ft_fx_process(fx, buf, bytes, &r) == FT_FX_OK, "take");
            } else {
                memcpy(pred_hi, pb, nb * tb); /* the bounds predicted before this update */
                memcpy(pred_lo, pl, nb * tb);
                ft_fx_set_param(fx, "bg_update_interval", 1);
                CHECK(ft_fx_process(fx, buf, bytes, &r) == FT_FX_OK, "update");
                CHECK(r.flags & FT_FX_RES_BG_UPDATED, "updated");
                ft_fx_set_param(fx, "bg_update_interval", 0);
                /* set_param refreshed the thresholds with the same parameters: unchanged */
                for (int y = 0; y < h; y++)
                    for (size_t b = 0; b < fx->nblk; b++) {
                        const size_t k = (size_t)y * fx->nblk + b;
                        uint32_t ph = tb == 2 ? ((uint16_t *)pred_hi)[k] : pred_hi[k];
                        uint32_t pl_ = tb == 2 ? ((uint16_t *)pred_lo)[k] : pred_lo[k];
                        uint32_t mh = maxv, ml = 0;
                        for (size_t x = b * FT_BLOCK; x < (b + 1) * FT_BLOCK && x < (size_t)w;
                             x++) {
                            size_t i = (size_t)y * (size_t)w + x;
                            uint32_t hi = tb == 2 ? fx->hi16[i] : fx->hi8[i];
                            uint32_t lo = tb == 2 ? fx->lo16[i] : fx->lo8[i];
                            mh = hi < mh ? hi : mh;
                            ml = lo > ml ? lo : ml;
                        }
                        CHECK(ph <= mh && pl_ >= ml,
                              "case %d frame %d row %d block %zu: predicted hi %u lo %u, new hi "
                              "%u lo %u",
                              c, f, y, b, ph, pl_, mh, ml);
                        blocks++;
                        if (tight) {
                            slack_hi += mh - ph;
                            slack_lo += pl_ - ml;
                            tight_blocks++;
                        }
                    }
            }
            free(buf);
        }
        free(pred_hi);
        free(pred_lo);
        free(v);
        ft_fx_destroy(fx);
    }
    printf(
        "test_lazy_update: predicted bounds held on %ld blocks; in the common case (8-bit, alpha "
        "0.01) mean slack %.2f levels (hi), %.2f (lo)\n",
        blocks, (double)slack_hi / (double)tight_blocks, (double)slack_lo / (double)tight_blocks);
}

static int same_result(const ft_fx_result *a, const ft_fx_result *b) {
    if (a->n_points != b->n_points || a->total_points != b->total_points ||
        a->n_candidates != b->n_candidates || a->flags != b->flags)
        return 0;
    return a->n_points == 0 || !memcmp(a->points, b->points, a->n_points * sizeof(ft_fx_point));
}

/* 2. Spread and whole updates give the same results. */
static void test_spread_equals_whole(void) {
    static const int geo[][2] = {{640, 48}, {130, 37}, {64, 20}, {13, 9}, {300, 5}, {200, 61}};
    static const unsigned ivs[] = {1, 2, 3, 5, 17};
    long frames = 0, points = 0, on_demand = 0, spread_frames = 0;
    const char *path = "none";
    for (int c = 0; c < 36; c++) {
        const int w0 = geo[c % 6][0], h = geo[c % 6][1], fmt = (c / 6) % 3,
                  pad = c % 4 == 3 ? 5 : 0;
        const int w = fmt == FT_FX_YUYV ? (w0 + 1) & ~1 : w0;
        const uint32_t maxv = fmt == FT_FX_MONO16 ? 4095 : 255;
        ft_fx_params p;
        ft_fx_params_default(&p, (uint32_t)w, (uint32_t)h, fmt);
        const size_t bpp = fmt == FT_FX_MONO8 ? 1 : 2;
        p.stride = pad ? (uint32_t)((size_t)(w + pad) * bpp) : 0;
        p.bg_update_interval = ivs[c % 5];
        p.alpha = c % 7 == 0 ? 0.3 : 0.01;
        p.diff_threshold = 30.0 * maxv / 255.0;
        p.despeckle_threshold = 0;
        p.polarity = c % 5 == 4 ? FT_FX_POLARITY_BRIGHT : FT_FX_POLARITY_BOTH;
        ft_fx *a = NULL, *b = NULL;
        CHECK(ft_fx_create(&p, sizeof p, &a) == FT_FX_OK && ft_fx_create(&p, sizeof p, &b) == 0,
              "create");
        ft_fx_debug_eager_update(b, 1);
        path = ft_fx_debug_scan_path(a);
        uint32_t *v = malloc(sizeof(uint32_t) * (size_t)(w * h));
        uint8_t *mask = malloc((size_t)(w * h));
        for (int f = 0; f < 60; f++) {
            make_frame(v, w, h, maxv, 6 * sin(0.2 * f) * maxv / 255.0, 2.0 * maxv / 255.0,
                       p.diff_threshold, 0);
            size_t bytes;
            void *buf = pack(v, w, h, fmt, pad, &bytes);
            if (f == 25 && c % 3 == 0) {
                for (int i = 0; i < w * h; i++)
                    mask[i] = rnd() % 9 != 0;
                ft_fx_set_mask(a, mask);
                ft_fx_set_mask(b, mask);
            }
            if (f == 40 && c % 3 == 1) {
                ft_fx_set_param(a, "alpha", 0.05);
                ft_fx_set_param(b, "alpha", 0.05);
            }
            const uint32_t before = ft_fx_debug_pending_rows(a);
            ft_fx_result ra, rb;
            CHECK(ft_fx_process(a, buf, bytes, &ra) == FT_FX_OK, "process");
            CHECK(ft_fx_process(b, buf, bytes, &rb) == FT_FX_OK, "process");
            CHECK(same_result(&ra, &rb),
                  "case %d (%dx%d fmt %d interval %u) frame %d: spread %u "
                  "points %u candidates, whole %u points %u candidates",
                  c, w, h, fmt, p.bg_update_interval, f, ra.n_points, ra.n_candidates, rb.n_points,
                  rb.n_candidates);
            CHECK(ft_fx_debug_pending_rows(b) == 0, "the whole update leaves no row behind");
            if (ra.flags & FT_FX_RES_BG_UPDATED)
                CHECK(ft_fx_debug_pending_rows(a) == (uint32_t)h, "rows pending after an update");
            /* rows brought up to date by the scan itself, beyond the scheduled ones */
            const uint32_t spread = p.bg_update_interval > 2 ? p.bg_update_interval - 1 : 1;
            const uint32_t sched = ((uint32_t)h + spread - 1) / spread;
            if (before && !(ra.flags & FT_FX_RES_BG_UPDATED)) {
                spread_frames++;
                const uint32_t after = ft_fx_debug_pending_rows(a);
                if (before - after > sched)
                    on_demand++;
            }
            if (f % 13 == 12) { /* reading the background finishes the update first */
                const float *ma = ft_fx_background_mean(a), *mb = ft_fx_background_mean(b);
                const float *sa = ft_fx_background_sumsq(a), *sb = ft_fx_background_sumsq(b);
                CHECK(!memcmp(ma, mb, sizeof(float) * (size_t)(w * h)) &&
                          !memcmp(sa, sb, sizeof(float) * (size_t)(w * h)),
                      "case %d frame %d: background differs", c, f);
                CHECK(ft_fx_debug_pending_rows(a) == 0, "read background is whole");
            }
            frames++;
            points += ra.n_points;
            free(buf);
        }
        free(v);
        free(mask);
        ft_fx_destroy(a);
        ft_fx_destroy(b);
    }
    CHECK(points > 2000, "too few points compared (%ld): the frames lost their targets", points);
    CHECK(on_demand > 50, "the scan brought rows up to date itself in only %ld frames", on_demand);
    printf("test_lazy_update: spread = whole on %ld frames, %ld points; %ld of %ld frames with "
           "rows pending brought some up to date from the scan (%s)\n",
           frames, points, on_demand, spread_frames, path);
}

int main(void) {
    test_bounds_hold();
    test_spread_equals_whole();
    if (failures) {
        fprintf(stderr, "test_lazy_update: %d checks failed\n", failures);
        return 1;
    }
    return 0;
}

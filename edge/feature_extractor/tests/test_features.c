/* Unit tests of libflytrack_features: API errors, detection of synthetic blobs in every pixel
 * format, masks, polarity, parameters, overflow. (The point-for-point comparison with a NumPy
 * reference is in host/tests/features/.) Built twice: plain and under ASan + UBSan. */
#include "flytrack/features.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

static int failures;
#define CHECK(cond)                                                                                \
    do {                                                                                           \
        if (!(cond)) {                                                                             \
            fprintf(stderr, "%s:%d: CHECK failed: %s\n", __FILE__, __LINE__, #cond);               \
            failures++;                                                                            \
        }                                                                                          \
    } while (0)

/* Adds a Gaussian blob (peak amp, std sigma) centred at (cx, cy) to a float image. */
static void blob(float *img, int w, int h, double cx, double cy, double sigma, double amp) {
    for (int y = 0; y < h; y++)
        for (int x = 0; x < w; x++) {
            double r2 = (x - cx) * (x - cx) + (y - cy) * (y - cy);
            img[y * w + x] += (float)(amp * exp(-r2 / (2 * sigma * sigma)));
        }
}

static void to8(const float *f, uint8_t *out, size_t n) {
    for (size_t i = 0; i < n; i++) {
        double v = floor(f[i] + 0.5);
        out[i] = (uint8_t)(v < 0 ? 0 : v > 255 ? 255 : v);
    }
}

static void test_errors(void) {
    ft_fx_params p;
    ft_fx *fx = NULL;
    ft_fx_params_default(&p, 64, 48, FT_FX_MONO8);
    CHECK(ft_fx_create(NULL, sizeof p, &fx) == FT_FX_E_ARG);
    CHECK(ft_fx_create(&p, sizeof p - 8, &fx) == FT_FX_E_ABI);
    p.pixel_format = 7;
    CHECK(ft_fx_create(&p, sizeof p, &fx) == FT_FX_E_FORMAT && fx == NULL);
    ft_fx_params_default(&p, 0, 48, FT_FX_MONO8);
    CHECK(ft_fx_create(&p, sizeof p, &fx) == FT_FX_E_SIZE);
    ft_fx_params_default(&p, 63, 48, FT_FX_YUYV);
    CHECK(ft_fx_create(&p, sizeof p, &fx) == FT_FX_E_SIZE);
    ft_fx_params_default(&p, 64, 48, FT_FX_MONO8);
    p.stride = 10;
    CHECK(ft_fx_create(&p, sizeof p, &fx) == FT_FX_E_SIZE);
    ft_fx_params_default(&p, 64, 48, FT_FX_MONO8);
    p.alpha = NAN;
    char msg[96];
    CHECK(ft_fx_params_check(&p, msg, sizeof msg) == FT_FX_E_BAD_VALUE && strstr(msg, "alpha"));
    ft_fx_params_default(&p, 64, 48, FT_FX_MONO8);
    p.max_points = FT_FX_MAX_POINTS + 1;
    CHECK(ft_fx_params_check(&p, msg, sizeof msg) == FT_FX_E_BAD_VALUE &&
          strstr(msg, "max_points"));
    CHECK(ft_fx_create(&p, sizeof p, &fx) == FT_FX_E_BAD_VALUE && fx == NULL);
    ft_fx_params_default(&p, 64, 48, FT_FX_MONO8);
    p.k1 = INFINITY;
    p.fx = p.fy = 100;
    CHECK(ft_fx_create(&p, sizeof p, &fx) == FT_FX_E_BAD_VALUE);

    ft_fx_params_default(&p, 64, 48, FT_FX_MONO8);
    CHECK(ft_fx_create(&p, sizeof p, &fx) == FT_FX_OK && fx);
    uint8_t frame[64 * 48];
    memset(frame, 10, sizeof frame);
    ft_fx_result r;
    CHECK(ft_fx_process(fx, frame, sizeof frame - 1, &r) == FT_FX_E_FRAME_SIZE);
    CHECK(ft_fx_process(fx, NULL, sizeof frame, &r) == FT_FX_E_ARG);
    double v = 0;
    CHECK(ft_fx_set_param(fx, "nope", 1) == FT_FX_E_UNKNOWN_PARAM);
    CHECK(ft_fx_set_param(fx, NULL, 1) == FT_FX_E_UNKNOWN_PARAM);
    CHECK(ft_fx_set_param(fx, "alpha", 0) == FT_FX_E_BAD_VALUE);
    CHECK(ft_fx_set_param(fx, "alpha", NAN) == FT_FX_E_BAD_VALUE);
    CHECK(ft_fx_set_param(fx, "max_points", 2.5) == FT_FX_E_BAD_VALUE);
    CHECK(ft_fx_set_param(fx, "max_points", -1) == FT_FX_E_BAD_VALUE);
    CHECK(ft_fx_set_param(fx, "polarity", 3) == FT_FX_E_BAD_VALUE);
    /* More than 255 parts x 32 points could not be sent: the cap holds for every caller. */
    CHECK(ft_fx_set_param(fx, "max_points", 100000) == FT_FX_E_BAD_VALUE);
    CHECK(ft_fx_set_param(fx, "max_points", FT_FX_MAX_POINTS + 1) == FT_FX_E_BAD_VALUE);
    CHECK(ft_fx_set_param(fx, "max_points", 4294967295.0) == FT_FX_E_BAD_VALUE);
    CHECK(ft_fx_get_param(fx, "max_points", &v) == FT_FX_OK && v == 100);
    CHECK(ft_fx_set_param(fx, "max_points", FT_FX_MAX_POINTS) == FT_FX_OK);
    CHECK(ft_fx_set_param(fx, "max_points", 100) == FT_FX_OK);
    CHECK(ft_fx_set_param(fx, "diff_threshold", 12) == FT_FX_OK);
    CHECK(ft_fx_get_param(fx, "diff_threshold", &v) == FT_FX_OK && v == 12);
    CHECK(ft_fx_get_param(fx, "max_points", &v) == FT_FX_OK && v == 100);
    CHECK(ft_fx_background_mean(fx) == NULL);
    ft_fx_destroy(fx);
    ft_fx_destroy(NULL);
    CHECK(strcmp(ft_fx_strerror(FT_FX_E_FRAME_SIZE), "unknown error") != 0);
}

/* One blob at a sub-pixel position in MONO8, MONO16 and YUYV gives the same point. */
static void test_formats(void) {
    enum { W = 96, H = 64 };
    static float f[W * H];
    static uint8_t bg8[W * H], fr8[W * H], yuyv0[W * H * 2], yuyv1[W * H * 2];
    static uint16_t bg16[W * H], fr16[W * H];
    for (int i = 0; i < W * H; i++)
        f[i] = 20.0f;
    to8(f, bg8, W * H);
    blob(f, W, H, 40.3, 21.7, 1.6, 180.0);
    to8(f, fr8, W * H);
    for (int i = 0; i < W * H; i++) {
        bg16[i] = bg8[i];
        fr16[i] = fr8[i];
        yuyv0[2 * i] = bg8[i];
        yuyv0[2 * i + 1] = 128;
        yuyv1[2 * i] = fr8[i];
        yuyv1[2 * i + 1] = (uint8_t)(i * 7); /* chroma must not matter */
    }
    const void *bgs[3] = {bg8, bg16, yuyv0}, *frs[3] = {fr8, fr16, yuyv1};
    size_t sizes[3] = {sizeof bg8, sizeof bg16, sizeof yuyv0};
    double xs[3], ys[3];
    for (int fmt = 0; fmt < 3; fmt++) {
        ft_fx_params p;
        ft_fx *fx;
        ft_fx_params_default(&p, W, H, fmt);
        CHECK(ft_fx_create(&p, sizeof p, &fx) == FT_FX_OK);
        ft_fx_result r;
        CHECK(ft_fx_process(fx, bgs[fmt], sizes[fmt], &r) == FT_FX_OK);
        CHECK(r.flags & FT_FX_RES_BACKGROUND_TAKEN);
        CHECK(r.n_points == 0);
        CHECK(ft_fx_process(fx, frs[fmt], sizes[fmt], &r) == FT_FX_OK);
        CHECK(r.n_points == 1 && r.total_points == 1);
        if (r.n_points == 1) {
            const ft_fx_point *pt = &r.points[0];
            xs[fmt] = pt->x_dist;
            ys[fmt] = pt->y_dist;
            CHECK(fabs(pt->x_dist - 40.3) < 0.06 && fabs(pt->y_dist - 21.7) < 0.06);
            CHECK(pt->x_undist == pt->x_dist && pt->y_undist == pt->y_dist);
            CHECK(pt->peak_x == 40 && pt->peak_y == 22);
            CHECK(pt->cur_val == fr8[22 * W + 40]);
            CHECK(pt->mean_val == 20.0 && pt->sumsq_val == 400.0);
            CHECK(pt->eccentricity >= 1.0 && pt->eccentricity < 1.3);
            CHECK(pt->area > 3 && pt->area < 40);
        }
        ft_fx_destroy(fx);
    }
    CHECK(xs[0] == xs[1] && xs[0] == xs[2] && ys[0] == ys[1] && ys[0] == ys[2]);
}

/* An elongated blob: orientation and eccentricity; polarity; mask; max_points; overflow. */
static void test_shape_polarity_mask(void) {
    enum { W = 80, H = 80 };
    static float f[W * H];
    static uint8_t bg[W * H], fr[W * H], mask[W * H];
    for (int i = 0; i < W * H; i++)
        f[i] = 100.0f;
    to8(f, bg, W * H);
    /* A bright blob elongated along 30 degrees, and a dark round blob. */
    double th = 30.0 * 3.14159265358979 / 180.0, c = cos(th), s = sin(th);
    for (int y = 0; y < H; y++)
        for (int x = 0; x < W; x++) {
            double dx = x - 20.5, dy = y - 30.25;
            double a = c * dx + s * dy, b = -s * dx + c * dy;
            f[y * W + x] += (float)(120.0 * exp(-(a * a / (2 * 9.0) + b * b / (2 * 1.0))));
        }
    blob(f, W, H, 60.0, 60.0, 1.5, -90.0);
    to8(f, fr, W * H);
    ft_fx_params p;
    ft_fx *fx;
    ft_fx_params_default(&p, W, H, FT_FX_MONO8);
    CHECK(ft_fx_create(&p, sizeof p, &fx) == FT_FX_OK);
    ft_fx_result r;
    ft_fx_process(fx, bg, sizeof bg, &r);
    CHECK(ft_fx_process(fx, fr, sizeof fr, &r) == FT_FX_OK);
    CHECK(r.n_points == 2);
    if (r.n_points == 2) {
        const ft_fx_point *a = &r.points[0], *b = &r.points[1];
        CHECK(a->peak_diff > b->peak_diff); /* strongest first */
        CHECK(fabs(a->orientation - th) < 0.05);
        CHECK(a->eccentricity > 2.0);
        CHECK(fabs(b->x_dist - 60.0) < 0.06 && fabs(b->y_dist - 60.0) < 0.06);
        CHECK(b->cur_val < 100);
    }
    CHECK(ft_fx_set_param(fx, "polarity", FT_FX_POLARITY_DARK) == FT_FX_OK);
    ft_fx_process(fx, fr, sizeof fr, &r);
    CHECK(r.n_points == 1 && r.points[0].cur_val < 100);
    CHECK(ft_fx_set_param(fx, "polarity", FT_FX_POLARITY_BRIGHT) == FT_FX_OK);
    ft_fx_process(fx, fr, sizeof fr, &r);
    CHECK(r.n_points == 1 && r.points[0].cur_val > 100);
    CHECK(ft_fx_set_param(fx, "polarity", FT_FX_POLARITY_BOTH) == FT_FX_OK);
    CHECK(ft_fx_set_param(fx, "max_points", 1) == FT_FX_OK);
    ft_fx_process(fx, fr, sizeof fr, &r);
    CHECK(r.n_points == 1 && r.total_points == 2 && (r.flags & FT_FX_RES_TRUNCATED));
    CHECK(ft_fx_set_param(fx, "max_points", 100) == FT_FX_OK);
    /* Mask out the left half: only the dark blob remains. */
    for (int y = 0; y < H; y++)
        for (int x = 0; x < W; x++)
            mask[y * W + x] = x >= 40;
    CHECK(ft_fx_set_mask(fx, mask) == FT_FX_OK);
    ft_fx_process(fx, fr, sizeof fr, &r);
    CHECK(r.n_points == 1 && r.points[0].peak_x >= 40);
    CHECK(ft_fx_set_mask(fx, NULL) == FT_FX_OK);
    ft_fx_process(fx, fr, sizeof fr, &r);
    CHECK(r.n_points == 2);
    /* New background: the current frame becomes the background, no points after. */
    ft_fx_take_background(fx);
    ft_fx_process(fx, fr, sizeof fr, &r);
    CHECK(r.flags & FT_FX_RES_BACKGROUND_TAKEN);
    ft_fx_process(fx, fr, sizeof fr, &r);
    CHECK(r.n_points == 0 && r.n_candidates == 0);
    ft_fx_destroy(fx);

    /* Candidate overflow: a frame entirely different from the background. */
    ft_fx_params_default(&p, W, H, FT_FX_MONO8);
    p.max_candidates = 100;
    CHECK(ft_fx_create(&p, sizeof p, &fx) == FT_FX_OK);
    ft_fx_process(fx, bg, sizeof bg, &r);
    memset(fr, 250, sizeof fr);
    CHECK(ft_fx_process(fx, fr, sizeof fr, &r) == FT_FX_OK);
    CHECK((r.flags & FT_FX_RES_CAND_OVERFLOW) && r.n_candidates == 100 && r.n_points >= 1);
    ft_fx_destroy(fx);
}

/* The background learns every bg_update_interval frames with weight alpha. */
static void test_background_update(void) {
    enum { W = 16, H = 8 };
    uint8_t a[W * H], b[W * H];
    memset(a, 50, sizeof a);
    memset(b, 150, sizeof b);
    ft_fx_params p;
    ft_fx *fx;
    ft_fx_params_default(&p, W, H, FT_FX_MONO8);
    p.bg_update_interval = 2;
    p.alpha = 0.5;
    CHECK(ft_fx_create(&p, sizeof p, &fx) == FT_FX_OK);
    ft_fx_result r;
    ft_fx_process(fx, a, sizeof a, &r);
    ft_fx_process(fx, b, sizeof b, &r);
    CHECK(!(r.flags & FT_FX_RES_BG_UPDATED) && r.n_points == 1);
    ft_fx_process(fx, b, sizeof b, &r);
    CHECK(r.flags & FT_FX_RES_BG_UPDATED);
    CHECK(ft_fx_background_mean(fx)[5] == 100.0f);
    CHECK(ft_fx_background_sumsq(fx)[5] == 0.5f * 2500.0f + 0.5f * 22500.0f);
    /* std = 50 now, so n_sigma 7 hides a difference of 50 */
    ft_fx_process(fx, b, sizeof b, &r);
    CHECK(r.n_points == 0);
    ft_fx_destroy(fx);
}

static void test_undistort(void) {
    ft_fx_params p;
    ft_fx_params_default(&p, 640, 480, FT_FX_MONO8);
    p.fx = 500;
    p.fy = 510;
    p.cx = 320;
    p.cy = 240;
    p.k1 = -0.2;
    p.k2 = 0.05;
    p.p1 = 0.001;
    p.p2 = -0.002;
    p.k3 = 0.01;
    /* Distort a known ideal point, then undistort it back. */
    double x = (100.0 - p.cx) / p.fx, y = (50.0 - p.cy) / p.fy;
    double r2 = x * x + y * y, rad = 1 + r2 * (p.k1 + r2 * (p.k2 + r2 * p.k3));
    double xd = x * rad + 2 * p.p1 * x * y + p.p2 * (r2 + 2 * x * x);
    double yd = y * rad + p.p1 * (r2 + 2 * y * y) + 2 * p.p2 * x * y;
    double u, v;
    ft_fx_undistort(&p, p.fx * xd + p.cx, p.fy * yd + p.cy, &u, &v);
    CHECK(fabs(u - 100.0) < 1e-6 && fabs(v - 50.0) < 1e-6);
}

int main(void) {
    test_errors();
    test_formats();
    test_shape_polarity_mask();
    test_background_update();
    test_undistort();
    if (failures) {
        fprintf(stderr, "%d check(s) failed\n", failures);
        return 1;
    }
    printf("test_features: all checks passed\n");
    return 0;
}

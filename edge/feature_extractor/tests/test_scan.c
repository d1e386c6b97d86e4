/* The candidate scan and the run labelling (src/scan.c, features.c) on random frames:
 *  1. the vector scan and the plain per-pixel scan give bit-identical results (every point field);
 *  2. both equal, bit for bit, a straightforward reference written here: the per-pixel rule against
 *     thresholds computed from the background, 8-connected regions by flood fill, the peak and the
 *     moments summed over each region's pixels in raster order.
 * Targets sit where the vector code has edges: across 64-pixel block borders, at the frame's edges,
 * touching each other diagonally, in rows shorter than a vector. Run once per vector path (CMake):
 * the one the library chooses on this CPU (AVX-512BW here), AVX2 (argument "avx2"), and the
 * portable GCC vector extensions under ASan + UBSan ("generic"); each run says which path it ran. A
 * path this build or CPU lacks exits 77 (skipped). */
#include "flytrack/features.h"
#include "fx_internal.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

static int failures;
static const char *force_path; /* argv[1]: the vector path to run, else the library's choice */
static const char *scan_path = "none"; /* the path the vector extractor ran */
static long points_checked, candidates_seen;
#define CHECK(cond, ...)                                                                           \
    do {                                                                                           \
        if (!(cond)) {                                                                             \
            fprintf(stderr, "%s:%d: CHECK failed: %s: ", __FILE__, __LINE__, #cond);               \
            fprintf(stderr, __VA_ARGS__);                                                          \
            fprintf(stderr, "\n");                                                                 \
            failures++;                                                                            \
        }                                                                                          \
    } while (0)

static uint64_t rng_state = 0x9e3779b97f4a7c15ull;
static uint32_t rnd(void) {
    rng_state ^= rng_state << 13;
    rng_state ^= rng_state >> 7;
    rng_state ^= rng_state << 17;
    return (uint32_t)(rng_state >> 32);
}
static double urand(void) {
    return rnd() / 4294967296.0;
}

/* ---- the reference ------------------------------------------------------------------------- */

typedef struct {
    double x, y, area, beta;
    uint32_t peak_x, peak_y, n_cand;
} ref_point;

/* Points of one frame (8-bit or 16-bit values in v[]) against the background bg[] taken from one
 * frame (so the variance is 0 and the threshold is diff_threshold), polarity both or bright,
 * subtract_cut 1, no mask. Returns the number of points (all regions with min_area kept pixels),
 * strongest first.
 */
static int reference(const uint32_t *v, const uint32_t *bg, int w, int h, uint32_t maxv,
                     const ft_fx_params *p, ref_point *out, int *label, int *stack) {
    const int n = w * h;
    for (int i = 0; i < n; i++) {
        float m = (float)bg[i];
        float var = m * m - m * m; /* sumsq - mean^2, as the library, = 0 */
        float t = (float)p->n_sigma * sqrtf(var > 0.0f ? var : 0.0f);
        t = t > (float)p->diff_threshold ? t : (float)p->diff_threshold;
        float up = m + t, dn = m - t;
        up = up < (float)maxv ? up : (float)maxv;
        dn = dn > 0.0f ? dn : 0.0f;
        uint32_t hi = (uint32_t)floorf(up), lo = (uint32_t)ceilf(dn);
        if (p->polarity == FT_FX_POLARITY_BRIGHT)
            lo = 0; /* never darker (candidates are brighter: |d| = d) */
        label[i] = (v[i] > hi || v[i] < lo) ? -1 : 0; /* -1: candidate, not yet labelled */
    }
    int np = 0;
    for (int i = 0; i < n; i++) {
        if (label[i] != -1)
            continue;
        /* Flood fill (8-connected) from the region's first pixel in raster order. */
        int top = 0, id = np + 1;
        stack[top++] = i;
        label[i] = id;
        while (top) {
            int k = stack[--top], x = k % w, y = k / w;
            for (int dy = -1; dy <= 1; dy++)
                for (int dx = -1; dx <= 1; dx++) {
                    int xx = x + dx, yy = y + dy;
                    if (xx < 0 || yy < 0 || xx >= w || yy >= h || label[yy * w + xx] != -1)
                        continue;
                    label[yy * w + xx] = id;
                    stack[top++] = yy * w + xx;
                }
        }
        /* Peak: the first largest |v - mean| in raster order. */
        float beta = -1.0f;
        int pk = i;
        uint32_t ncand = 0;
        for (int k = i; k < n; k++)
            if (label[k] == id) {
                float d = fabsf((float)v[k] - (float)bg[k]);
                ncand++;
                if (d > beta) {
                    beta = d;
                    pk = k;
                }
            }
        double cut = p->clear_fraction * (double)beta;
        if (cut < p->despeckle_threshold)
            cut = p->despeckle_threshold;
        if (cut < p->diff_threshold)
            cut = p->diff_threshold;
        double m0 = 0, mx = 0, my = 0;
        uint32_t kept = 0;
        for (int k = i; k < n; k++) {
            if (label[k] != id)
                continue;
            double d = fabsf((float)v[k] - (float)bg[k]);
            if (d < cut)
                continue;
            double wt = d - cut, ddx = (double)(k % w) - (double)(pk % w);
            double ddy = (double)(k / w) - (double)(pk / w);
            kept++;
            m0 += wt;
            mx += wt * ddx;
            my += wt * ddy;
        }
        if (kept < p->min_area)
            continue;
        ref_point *q = &out[np++];
        q->peak_x = (uint32_t)(pk % w);
        q->peak_y = (uint32_t)(pk / w);
        q->x = m0 > 0 ? q->peak_x + mx / m0 : q->peak_x;
        q->y = m0 > 0 ? q->peak_y + my / m0 : q->peak_y;
        q->area = kept;
        q->beta = beta;
        q->n_cand = ncand;
    }
    /* Strongest first; on a tie, the earlier peak. */
    for (int a = 1; a < np; a++)
        for (int b = a; b > 0; b--) {
            ref_point *x = &out[b - 1], *y = &out[b];
            int later = x->beta < y->beta ||
                        (x->beta == y->beta &&
                         x->peak_y * (uint32_t)w + x->peak_x > y->peak_y * (uint32_t)w + y->peak_x);
            if (!later)
                break;
            ref_point t = *x;
            *x = *y;
            *y = t;
        }
    return np;
}

/* ---- frames -------------------------------------------------------------------------------- */

/* A smooth background, or (striped) one whose level jumps from row to row, so that the bounds of
 * rows next to each other differ (a band or block test that took the wrong bound would then miss
 * the weak targets, which barely pass their thresholds). */
static int striped, bright_only;
static void make_background(int w, int h, uint32_t maxv, uint32_t *bg) {
    const double scale = maxv / 255.0, ph = urand() * 6.28;
    for (int y = 0; y < h; y++) {
        double level = striped ? 40 + 160 * urand() : 90 + 10 * cos(0.07 * y);
        for (int x = 0; x < w; x++)
            bg[y * w + x] = (uint32_t)(scale * (level + 25 * sin(0.05 * x + ph)));
    }
}

/* The background with noise, and targets where the scan has edges. */
static void make_frame(int w, int h, uint32_t maxv, const uint32_t *bg, uint32_t *fr) {
    const double scale = maxv / 255.0;
    double tx[16], ty[16], amp[16], sg[16];
    int nt = 0;
    const int nblk = (w + 63) / 64;
    for (int k = 0; k < 5 + (int)(rnd() % 6); k++) { /* on a block border, at any row */
        tx[nt] = 64.0 * (rnd() % (nblk + 1)) - 0.5 + (urand() - 0.5);
        ty[nt] = urand() * h;
        amp[nt] = (rnd() & 1 ? 1 : -1) * (60 + 80 * urand());
        sg[nt++] = 0.6 + 2.0 * urand();
    }
    tx[nt] = 0.2; /* frame corners and edges */
    ty[nt] = 0.3;
    amp[nt] = 120;
    sg[nt++] = 1.5;
    tx[nt] = w - 1.2;
    ty[nt] = h - 0.7;
    amp[nt] = -90;
    sg[nt++] = 1.2;
    tx[nt] = urand() * w; /* two touching targets (their regions may merge diagonally) */
    ty[nt] = urand() * h;
    amp[nt] = 110;
    sg[nt++] = 1.0;
    tx[nt] = tx[nt - 1] + 2.5;
    ty[nt] = ty[nt - 1] + 2.5;
    amp[nt] = 100;
    sg[nt++] = 1.0;
    for (int y = 0; y < h; y++)
        for (int x = 0; x < w; x++) {
            double val = bg[y * w + x] + scale * ((int)(rnd() % 5) - 2);
            for (int k = 0; k < nt; k++) {
                double r2 = (x - tx[k]) * (x - tx[k]) + (y - ty[k]) * (y - ty[k]);
                val += scale * amp[k] * exp(-r2 / (2 * sg[k] * sg[k]));
            }
            if (rnd() % 300 == 0) /* single-pixel speckle */
                val += scale * (rnd() & 1 ? 70 : -70);
            if (striped && rnd() % 97 == 0) /* weak: just past the threshold (30) or just short */
                val += scale * (rnd() & 1 ? 1 : -1) * (27 + (int)(rnd() % 8));
            val = floor(val + 0.5);
            fr[y * w + x] = (uint32_t)(val < 0 ? 0 : val > maxv ? maxv : val);
        }
}

/* Rows pad pixels apart beyond the width (stride = (w + pad) pixels); the padding holds garbage. */
static void *pack(const uint32_t *v, int w, int h, int fmt, int pad, size_t *bytes) {
    const size_t bpp = fmt == FT_FX_MONO8 ? 1 : 2, stride = (size_t)(w + pad) * bpp;
    *bytes = stride * (size_t)(h - 1) + (size_t)w * bpp;
    uint8_t *b = malloc(stride * (size_t)h);
    for (size_t i = 0; i < stride * (size_t)h; i++)
        b[i] = (uint8_t)rnd();
    for (int y = 0; y < h; y++)
        for (int x = 0; x < w; x++) {
            uint8_t *px = b + (size_t)y * stride + (size_t)x * bpp;
            uint32_t val = v[y * w + x];
            if (fmt == FT_FX_MONO16)
                memcpy(px, &(uint16_t){(uint16_t)val}, 2);
            else
                px[0] = (uint8_t)val; /* YUYV: the chroma byte after it stays garbage */
        }
    return b;
}

static int same_result(const ft_fx_result *a, const ft_fx_result *b) {
    if (a->n_points != b->n_points || a->total_points != b->total_points ||
        a->n_candidates != b->n_candidates || a->flags != b->flags)
        return 0;
    return a->n_points == 0 || !memcmp(a->points, b->points, a->n_points * sizeof(ft_fx_point));
}

/* One geometry and format: the vector scan, the plain scan and the reference on the same frames. */
static void run_case(int w, int h, int fmt, int pad, int frames, uint32_t max_candidates) {
    const uint32_t maxv = fmt == FT_FX_MONO16 ? 4095 : 255;
    size_t n = (size_t)w * h, bytes;
    uint32_t *bg = malloc(n * 4), *fr = malloc(n * 4);
    int *label = malloc(n * sizeof(int)), *stack = malloc(n * sizeof(int));
    ref_point *ref = malloc(n * sizeof(ref_point));
    ft_fx_params p;
    ft_fx_params_default(&p, (uint32_t)w, (uint32_t)h, fmt);
    p.stride = pad ? (uint32_t)((w + pad) * (fmt == FT_FX_MONO8 ? 1 : 2)) : 0;
    p.bg_update_interval = 0; /* the background stays the first frame: the reference's */
    p.polarity = bright_only ? FT_FX_POLARITY_BRIGHT : FT_FX_POLARITY_BOTH;
    p.diff_threshold = fmt == FT_FX_MONO16 ? 30.0 * 16 : 30.0;
    p.despeckle_threshold = 0;
    p.max_points = FT_FX_MAX_POINTS;
    p.max_candidates = max_candidates;
    ft_fx *vec, *plain;
    CHECK(ft_fx_create(&p, sizeof p, &vec) == FT_FX_OK && ft_fx_create(&p, sizeof p, &plain) == 0,
          "create %dx%d", w, h);
    ft_fx_debug_scalar_scan(plain, 1);
    if (force_path)
        CHECK(ft_fx_debug_scan_force(vec, force_path) == 0, "force %s", force_path);
    scan_path = ft_fx_debug_scan_path(vec);
    make_background(w, h, maxv, bg);
    void *b = pack(bg, w, h, fmt, pad, &bytes);
    ft_fx_result rv, rp;
    ft_fx_process(vec, b, bytes, &rv);
    ft_fx_process(plain, b, bytes, &rp);
    free(b);
    for (int f = 0; f < frames; f++) {
        make_frame(w, h, maxv, bg, fr); /* new targets on the same background */
        b = pack(fr, w, h, fmt, pad, &bytes);
        CHECK(ft_fx_process(vec, b, bytes, &rv) == FT_FX_OK, "process");
        CHECK(ft_fx_process(plain, b, bytes, &rp) == FT_FX_OK, "process");
        CHECK(same_result(&rv, &rp),
              "%dx%d fmt %d frame %d (%s): vector %u points %u cand, plain %u %u", w, h, fmt, f,
              scan_path, rv.n_points, rv.n_candidates, rp.n_points, rp.n_candidates);
        if (!max_candidates) {
            /* The reference sees the values the library saw (YUYV: the luma bytes). */
            int nr = reference(fr, bg, w, h, maxv, &p, ref, label, stack);
            int ok = nr == (int)rv.n_points;
            for (int k = 0; ok && k < nr; k++) {
                const ft_fx_point *q = &rv.points[k];
                ok = q->x_dist == ref[k].x && q->y_dist == ref[k].y && q->area == ref[k].area &&
                     q->peak_diff == ref[k].beta && q->peak_x == ref[k].peak_x &&
                     q->peak_y == ref[k].peak_y && q->n_candidates == ref[k].n_cand;
                if (!ok)
                    fprintf(stderr,
                            "point %d: lib (%.17g, %.17g) area %g peak %u,%u; ref (%.17g, %.17g) "
                            "area %g peak %u,%u\n",
                            k, q->x_dist, q->y_dist, q->area, q->peak_x, q->peak_y, ref[k].x,
                            ref[k].y, ref[k].area, ref[k].peak_x, ref[k].peak_y);
            }
            points_checked += nr;
            candidates_seen += rv.n_candidates;
            CHECK(ok, "%dx%d fmt %d frame %d: library %u points, reference %d", w, h, fmt, f,
                  rv.n_points, nr);
        } else {
            CHECK(rv.n_candidates <= max_candidates, "cap");
        }
        free(b);
    }
    ft_fx_destroy(vec);
    ft_fx_destroy(plain);
    free(bg);
    free(fr);
    free(label);
    free(stack);
    free(ref);
}

int main(int argc, char **argv) {
    if (argc > 1) {
        force_path = argv[1];
        ft_fx_params p;
        ft_fx_params_default(&p, 64, 4, FT_FX_MONO8);
        ft_fx *fx;
        if (ft_fx_create(&p, sizeof p, &fx) != FT_FX_OK)
            return 1;
        int ok = ft_fx_debug_scan_force(fx, force_path) == 0;
        ft_fx_destroy(fx);
        if (!ok) {
            printf("test_scan: path %s not in this build or not run by this CPU: skipped\n",
                   force_path);
            return 77;
        }
    }
    /* Widths: block multiples, one pixel past, shorter than a vector, a single column or row. */
    static const int sizes[][2] = {{640, 48}, {130, 37}, {64, 20}, {129, 33}, {13, 9},
                                   {1, 17},   {200, 1},  {250, 3}, {31, 40},  {2048, 6}};
    int cases = 0;
    for (size_t s = 0; s < sizeof sizes / sizeof sizes[0]; s++)
        for (int fmt = 0; fmt < 3; fmt++) {
            int w = sizes[s][0], h = sizes[s][1];
            if (fmt == FT_FX_YUYV && w % 2)
                w++;
            striped = 0;
            run_case(w, h, fmt, 0, 6, 0);
            striped = 1;
            run_case(w, h, fmt, 0, 4, 0);
            bright_only = 1; /* one bound only: a wrong band or block bound is not masked */
            run_case(w, h, fmt, 0, 4, 0);
            striped = bright_only = 0;
            run_case(w, h, fmt, 1 + (int)(rnd() % 40), 2, 0); /* rows with padding between them */
            run_case(w, h, fmt, 0, 2, 1 + rnd() % 200);       /* candidate cap reached mid-frame */
            cases++;
        }
    if (failures) {
        fprintf(stderr, "%d check(s) failed (%s path)\n", failures, scan_path);
        return 1;
    }
    printf("test_scan: %d geometries x formats, vector (%s) = plain = reference: %ld points, %ld "
           "candidates\n",
           cases, scan_path, points_checked, candidates_seen);
    if (points_checked < 1000) {
        fprintf(stderr, "too few points to compare: the frames lost their targets\n");
        return 1;
    }
    return 0;
}

/* libflytrack_features: see include/flytrack/features.h for the algorithm and the API.
 *
 * Speed plan: a pixel is a candidate against two precomputed per-pixel integer thresholds (hi:
 * brighter than the background by more than the allowed deviation; lo: darker). The hot loop reads
 * the frame alone, block by block, against each block's tightest bounds (max/min reductions the
 * compiler vectorises, -O3); only blocks it cannot rule out are compared pixel by pixel with hi and
 * lo. Only candidate pixels are labelled and measured. The float
 * background (mean, mean of squares) and the thresholds are recomputed only every
 * bg_update_interval frames.
 *
 * Float arithmetic is plain IEEE single precision in a fixed order (the library is built with
 * -ffp-contract=off), so a NumPy float32 reference reproduces the thresholds bit for bit.
 */
#include "flytrack/features.h"
#include "thresholds.h"

#include <math.h>
#if defined(__AVX2__) || defined(__AVX512BW__)
#include <immintrin.h>
#endif
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#define DEFAULT_MAX_CANDIDATES 65536u
#define FT_BLOCK 64u /* pixels per block of the scan's first, frame-only pass */
#define MAX_DIM 16384u
#define FT_PI 3.14159265358979323846

typedef struct {
    float beta;
    uint32_t peak_cand; /* candidate index of the peak */
    uint32_t n_cand, n_kept;
    double m0, mx, my, mxx, myy, mxy; /* moments about the peak pixel */
} region;

typedef struct {
    float beta;
    uint32_t peak_idx;
    uint32_t rid;
} rank;

struct ft_fx {
    ft_fx_params p;
    uint32_t w, h;
    size_t npix, stride, frame_bytes;
    uint32_t maxval;
    float *mean, *sumsq;
    uint8_t *hi8, *lo8;
    uint16_t *hi16, *lo16;
    /* Per block of FT_BLOCK pixels of a row: the lowest hi and the highest lo in it. A block whose
     * pixels all lie within [blo, bhi] holds no candidate, which the scan checks reading the frame
     * alone (see scan). */
    size_t nblk; /* blocks per row */
    uint8_t *bhi8, *blo8;
    uint16_t *bhi16, *blo16;
    /* The same bounds per whole row: the scan's very first check. */
    uint8_t *rhi8, *rlo8;
    uint16_t *rhi16, *rlo16;
    uint8_t *mask;   /* 1 = use, always allocated (all ones without a user mask) */
    uint8_t *luma;   /* YUYV: the luma plane of the current frame */
    uint32_t *label; /* per pixel: 0, or candidate index + 1 during a frame (reset after) */
    uint32_t cap;
    uint32_t *cand_idx;
    float *cand_d;
    uint32_t *parent, *cand_region;
    region *regions;
    rank *ranks;
    ft_fx_point *points;
    uint64_t frame_index;
    uint64_t since_update;
    int need_bg;
    int have_bg;
};

/* ---------------------------------------------------------------------------------------------- */
/* Parameters */

void ft_fx_params_default(ft_fx_params *p, uint32_t width, uint32_t height, int32_t pixel_format) {
    memset(p, 0, sizeof *p);
    p->width = width;
    p->height = height;
    p->stride = 0;
    p->pixel_format = pixel_format;
    p->polarity = FT_FX_POLARITY_BOTH;
    p->alpha = 0.01;
    p->n_sigma = 7.0;
    p->diff_threshold = 30.0;
    p->bg_update_interval = 200;
    p->clear_fraction = 0.3;
    p->despeckle_threshold = 5.0;
    p->min_area = 1;
    p->subtract_cut = 1;
    p->max_points = 100;
    p->max_candidates = DEFAULT_MAX_CANDIDATES;
}

static uint32_t bytes_per_pixel(int32_t fmt) {
    switch (fmt) {
    case FT_FX_MONO8:
        return 1;
    case FT_FX_MONO16:
    case FT_FX_YUYV:
        return 2;
    default:
        return 0;
    }
}

static int fail(char *msg, size_t len, int code, const char *text) {
    if (msg && len)
        snprintf(msg, len, "%s", text);
    return code;
}

static int finite_in(double v, double lo, double hi) {
    return isfinite(v) && v >= lo && v <= hi;
}

/* The runtime-tunable values: shared by ft_fx_params_check and ft_fx_set_param. */
static int check_tunables(const ft_fx_params *p, char *msg, size_t len) {
    if (!finite_in(p->alpha, 1e-9, 1.0))
        return fail(msg, len, FT_FX_E_BAD_VALUE, "alpha must be in (0, 1]");
    if (!finite_in(p->n_sigma, 0.0, 1e6))
        return fail(msg, len, FT_FX_E_BAD_VALUE, "n_sigma must be >= 0 and finite");
    if (!finite_in(p->diff_threshold, 0.0, 65535.0))
        return fail(msg, len, FT_FX_E_BAD_VALUE, "diff_threshold must be in [0, 65535]");
    if (p->polarity < FT_FX_POLARITY_BOTH || p->polarity > FT_FX_POLARITY_DARK)
        return fail(msg, len, FT_FX_E_BAD_VALUE, "polarity must be 0 (both), 1 (bright), 2 (dark)");
    if (!finite_in(p->clear_fraction, 0.0, 0.999999))
        return fail(msg, len, FT_FX_E_BAD_VALUE, "clear_fraction must be in [0, 1)");
    if (!finite_in(p->despeckle_threshold, 0.0, 65535.0))
        return fail(msg, len, FT_FX_E_BAD_VALUE, "despeckle_threshold must be in [0, 65535]");
    if (p->min_area < 1)
        return fail(msg, len, FT_FX_E_BAD_VALUE, "min_area must be >= 1");
    if (p->subtract_cut != 0 && p->subtract_cut != 1)
        return fail(msg, len, FT_FX_E_BAD_VALUE, "subtract_cut must be 0 or 1");
    if (p->max_points < 1 || p->max_points > FT_FX_MAX_POINTS)
        return fail(msg, len, FT_FX_E_BAD_VALUE, "max_points must be in 1..8160");
    return FT_FX_OK;
}

int ft_fx_params_check(const ft_fx_params *p, char *msg, size_t len) {
    if (!p)
        return fail(msg, len, FT_FX_E_ARG, "no parameters");
    uint32_t bpp = bytes_per_pixel(p->pixel_format);
    if (!bpp)
        return fail(msg, len, FT_FX_E_FORMAT, "unknown pixel format (0 MONO8, 1 MONO16, 2 YUYV)");
    if (p->width < 1 || p->height < 1 || p->width > MAX_DIM || p->height > MAX_DIM)
        return fail(msg, len, FT_FX_E_SIZE, "width and height must be in 1..16384");
    if (p->pixel_format == FT_FX_YUYV && (p->width % 2))
        return fail(msg, len, FT_FX_E_SIZE, "YUYV needs an even width");
    if (p->stride && p->stride < p->width * bpp)
        return fail(msg, len, FT_FX_E_SIZE, "stride is smaller than a row");
    int rc = check_tunables(p, msg, len);
    if (rc)
        return rc;
    if (p->max_candidates > (1u << 26))
        return fail(msg, len, FT_FX_E_BAD_VALUE, "max_candidates must be <= 67108864");
    const double cal[] = {p->fx, p->fy, p->cx, p->cy, p->skew, p->k1, p->k2, p->p1, p->p2, p->k3};
    for (size_t i = 0; i < sizeof cal / sizeof cal[0]; i++)
        if (!isfinite(cal[i]))
            return fail(msg, len, FT_FX_E_BAD_VALUE, "calibration contains NaN or infinity");
    if (p->fx != 0.0 && (p->fx <= 0.0 || p->fy <= 0.0))
        return fail(msg, len, FT_FX_E_BAD_VALUE, "calibration focal lengths must be > 0");
    return fail(msg, len, FT_FX_OK, "ok");
}

size_t ft_fx_frame_bytes(const ft_fx_params *p) {
    uint32_t bpp = bytes_per_pixel(p->pixel_format);
    size_t stride = p->stride ? p->stride : (size_t)p->width * bpp;
    if (!bpp || !p->height)
        return 0;
    return stride * (p->height - 1) + (size_t)p->width * bpp;
}

/* ---------------------------------------------------------------------------------------------- */
/* Create / destroy */

void ft_fx_destroy(ft_fx *fx) {
    if (!fx)
        return;
    free(fx->mean);
    free(fx->sumsq);
    free(fx->hi8);
    free(fx->lo8);
    free(fx->hi16);
    free(fx->lo16);
    free(fx->bhi8);
    free(fx->blo8);
    free(fx->bhi16);
    free(fx->blo16);
    free(fx->rhi8);
    free(fx->rlo8);
    free(fx->rhi16);
    free(fx->rlo16);
    free(fx->mask);
    free(fx->luma);
    free(fx->label);
    free(fx->cand_idx);
    free(fx->cand_d);
    free(fx->parent);
    free(fx->cand_region);
    free(fx->regions);
    free(fx->ranks);
    free(fx->points);
    free(fx);
}

int ft_fx_create(const ft_fx_params *p, size_t params_size, ft_fx **out) {
    if (!p || !out)
        return FT_FX_E_ARG;
    *out = NULL;
    if (params_size != sizeof(ft_fx_params))
        return FT_FX_E_ABI;
    int rc = ft_fx_params_check(p, NULL, 0);
    if (rc)
        return rc;
    ft_fx *fx = calloc(1, sizeof *fx);
    if (!fx)
        return FT_FX_E_NOMEM;
    fx->p = *p;
    if (!fx->p.max_candidates)
        fx->p.max_candidates = DEFAULT_MAX_CANDIDATES;
    fx->w = p->width;
    fx->h = p->height;
    fx->npix = (size_t)p->width * p->height;
    uint32_t bpp = bytes_per_pixel(p->pixel_format);
    fx->stride = p->stride ? p->stride : (size_t)p->width * bpp;
    fx->frame_bytes = ft_fx_frame_bytes(p);
    fx->maxval = p->pixel_format == FT_FX_MONO16 ? 65535u : 255u;
    fx->cap = fx->p.max_candidates;
    if (fx->cap > fx->npix)
        fx->cap = (uint32_t)fx->npix;
    fx->mean = malloc(fx->npix * sizeof(float));
    fx->sumsq = malloc(fx->npix * sizeof(float));
    fx->mask = malloc(fx->npix);
    fx->label = calloc(fx->npix, sizeof(uint32_t));
    fx->cand_idx = malloc(fx->cap * sizeof(uint32_t));
    fx->cand_d = malloc(fx->cap * sizeof(float));
    fx->parent = malloc(fx->cap * sizeof(uint32_t));
    fx->cand_region = malloc(fx->cap * sizeof(uint32_t));
    fx->regions = malloc(fx->cap * sizeof(region));
    fx->ranks = malloc(fx->cap * sizeof(rank));
    fx->points = malloc(fx->cap * sizeof(ft_fx_point));
    int ok = fx->mean && fx->sumsq && fx->mask && fx->label && fx->cand_idx && fx->cand_d &&
             fx->parent && fx->cand_region && fx->regions && fx->ranks && fx->points;
    fx->nblk = (fx->w + FT_BLOCK - 1) / FT_BLOCK;
    size_t nb = fx->nblk * fx->h;
    if (p->pixel_format == FT_FX_MONO16) {
        fx->hi16 = malloc(fx->npix * sizeof(uint16_t));
        fx->lo16 = malloc(fx->npix * sizeof(uint16_t));
        fx->bhi16 = malloc(nb * sizeof(uint16_t));
        fx->blo16 = malloc(nb * sizeof(uint16_t));
        fx->rhi16 = malloc(fx->h * sizeof(uint16_t));
        fx->rlo16 = malloc(fx->h * sizeof(uint16_t));
        ok = ok && fx->hi16 && fx->lo16 && fx->bhi16 && fx->blo16 && fx->rhi16 && fx->rlo16;
    } else {
        fx->hi8 = malloc(fx->npix);
        fx->lo8 = malloc(fx->npix);
        fx->bhi8 = malloc(nb);
        fx->blo8 = malloc(nb);
        fx->rhi8 = malloc(fx->h);
        fx->rlo8 = malloc(fx->h);
        ok = ok && fx->hi8 && fx->lo8 && fx->bhi8 && fx->blo8 && fx->rhi8 && fx->rlo8;
        if (p->pixel_format == FT_FX_YUYV) {
            fx->luma = malloc(fx->npix);
            ok = ok && fx->luma;
        }
    }
    if (!ok) {
        ft_fx_destroy(fx);
        return FT_FX_E_NOMEM;
    }
    memset(fx->mask, 1, fx->npix);
    fx->need_bg = 1;
    *out = fx;
    return FT_FX_OK;
}

/* ---------------------------------------------------------------------------------------------- */
/* Background model and per-pixel thresholds                                                      */

/* Per-pixel thresholds from the background. A pixel value x is a candidate when
 *   x > mean + T   <=>  x > floor(mean + T)      (x integer)  -> hi = floor(mean + T)
 *   x < mean - T   <=>  x < ceil(mean - T)                    -> lo = ceil(mean - T)
 * with T = max(diff_threshold, n_sigma * std). hi = maxval means "never brighter", lo = 0 "never
 * darker". Nonnegative float -> int conversion truncates, which is floor; it vectorises. */

static thr_cfg thr_config(const ft_fx *fx) {
    thr_cfg c;
    c.a = (float)fx->p.alpha;
    c.a1 = (float)(1.0 - fx->p.alpha);
    c.ns = (float)fx->p.n_sigma;
    c.dt = (float)fx->p.diff_threshold;
    c.maxv = (float)fx->maxval;
    c.bright = fx->p.polarity != FT_FX_POLARITY_DARK;
    c.dark = fx->p.polarity != FT_FX_POLARITY_BRIGHT;
    return c;
}

/* Running average: mean <- (1 - a) mean + a x, sumsq <- (1 - a) sumsq + a x^2; init: mean = x. */
#define DEFINE_UPDATE(NAME, T)                                                                     \
    static void NAME(size_t w, size_t h, const T *restrict img, size_t stride_px,                  \
                     float *restrict mean, float *restrict sumsq, int init, thr_cfg c) {           \
        for (size_t y = 0; y < h; y++) {                                                           \
            const T *restrict r = img + y * stride_px;                                             \
            float *restrict m = mean + y * w;                                                      \
            float *restrict s = sumsq + y * w;                                                     \
            if (init) {                                                                            \
                for (size_t x = 0; x < w; x++) {                                                   \
                    float v = (float)r[x];                                                         \
                    m[x] = v;                                                                      \
                    s[x] = v * v;                                                                  \
                }                                                                                  \
            } else {                                                                               \
                for (size_t x = 0; x < w; x++) {                                                   \
                    float v = (float)r[x];                                                         \
                    m[x] = c.a1 * m[x] + c.a * v;                                                  \
                    s[x] = c.a1 * s[x] + c.a * (v * v);                                            \
                }                                                                                  \
            }                                                                                      \
        }                                                                                          \
    }
DEFINE_UPDATE(update8, uint8_t)
DEFINE_UPDATE(update16, uint16_t)

/* bhi = min(hi), blo = max(lo) over each block of FT_BLOCK pixels of a row (the last one may be
 * short). */
#define DEFINE_BLOCK_BOUNDS(NAME, T)                                                               \
    static void NAME(size_t w, size_t h, size_t nblk, const T *restrict hi, const T *restrict lo,  \
                     T *restrict bhi, T *restrict blo, T *restrict rhi, T *restrict rlo) {         \
        for (size_t y = 0; y < h; y++) {                                                           \
            T rh = hi[y * w], rl = lo[y * w];                                                      \
            for (size_t b = 0; b < nblk; b++) {                                                    \
                size_t x0 = b * FT_BLOCK, x1 = x0 + FT_BLOCK < w ? x0 + FT_BLOCK : w;              \
                T mh = hi[y * w + x0], ml = lo[y * w + x0];                                        \
                for (size_t x = x0 + 1; x < x1; x++) {                                             \
                    T vh = hi[y * w + x], vl = lo[y * w + x];                                      \
                    mh = vh < mh ? vh : mh;                                                        \
                    ml = vl > ml ? vl : ml;                                                        \
                }                                                                                  \
                bhi[y * nblk + b] = mh;                                                            \
                blo[y * nblk + b] = ml;                                                            \
                rh = mh < rh ? mh : rh;                                                            \
                rl = ml > rl ? ml : rl;                                                            \
            }                                                                                      \
            rhi[y] = rh;                                                                           \
            rlo[y] = rl;                                                                           \
        }                                                                                          \
    }
DEFINE_BLOCK_BOUNDS(block_bounds8, uint8_t)
DEFINE_BLOCK_BOUNDS(block_bounds16, uint16_t)

static void refresh_thresholds(ft_fx *fx) {
    thr_cfg c = thr_config(fx);
    if (fx->hi16) {
        ft_fx_thresh16(fx->npix, fx->mean, fx->sumsq, fx->mask, fx->hi16, fx->lo16, c);
        block_bounds16(fx->w, fx->h, fx->nblk, fx->hi16, fx->lo16, fx->bhi16, fx->blo16, fx->rhi16,
                       fx->rlo16);
    } else {
        ft_fx_thresh8(fx->npix, fx->mean, fx->sumsq, fx->mask, fx->hi8, fx->lo8, c);
        block_bounds8(fx->w, fx->h, fx->nblk, fx->hi8, fx->lo8, fx->bhi8, fx->blo8, fx->rhi8,
                      fx->rlo8);
    }
}

static void update_background(ft_fx *fx, const void *img, size_t stride_bytes, int init) {
    thr_cfg c = thr_config(fx);
    if (fx->p.pixel_format == FT_FX_MONO16)
        update16(fx->w, fx->h, img, stride_bytes / 2, fx->mean, fx->sumsq, init, c);
    else
        update8(fx->w, fx->h, img, stride_bytes, fx->mean, fx->sumsq, init, c);
    refresh_thresholds(fx);
    fx->have_bg = 1;
}

/* ---------------------------------------------------------------------------------------------- */
/* Candidate scan: the hot loop */

/* The scan rules pixels out coarse to fine, reading the frame alone until it cannot:
 *  1. the whole row's brightest and darkest pixels against the row's bounds (the lowest hi and the
 *     highest lo over the row): a max/min reduction, about the cost of reading the row;
 *  2. if that fails (a candidate, or a background that varies a lot along the row), each full block
 *     of FT_BLOCK pixels against its own bounds, all blocks of the row in one pass;
 *  3. in a block that still cannot be ruled out, every pixel against its own hi and lo.
 * The thresholds sit at least diff_threshold from a background that is usually smooth, so most rows
 * end at step 1. Candidates are still found in raster order: the result is the plain per-pixel
 * rule's. */
#define DEFINE_BLOCK_OUT(NAME, T)                                                                  \
    static inline int NAME(const T *restrict r, T bh, T bl) {                                      \
        T out = 0; /* an OR of compare results: vector compares, one reduction at the end */       \
        for (size_t x = 0; x < FT_BLOCK; x++)                                                      \
            out |= (T)((r[x] > bh) | (r[x] < bl));                                                 \
        return out != 0;                                                                           \
    }                                                                                              \
    /* The whole row's full blocks at once: lane-wise ORs into acc, one reduction per row. */      \
    static inline int NAME##_row(const T *restrict r, const T *restrict bh, const T *restrict bl,  \
                                 size_t nfull) {                                                   \
        T acc[FT_BLOCK] = {0};                                                                     \
        for (size_t b = 0; b < nfull; b++) {                                                       \
            const T *restrict rb = r + b * FT_BLOCK;                                               \
            const T h = bh[b], l = bl[b];                                                          \
            for (size_t x = 0; x < FT_BLOCK; x++) { /* max(r, h) - h, max(r, l) - r: 0 = inside */ \
                T v = rb[x], a = v > h ? v : h, c = v > l ? v : l;                                 \
                acc[x] |= (T)((T)(a - h) | (T)(c - v));                                            \
            }                                                                                      \
        }                                                                                          \
        T out = 0;                                                                                 \
        for (size_t x = 0; x < FT_BLOCK; x++)                                                      \
            out |= acc[x];                                                                         \
        return out != 0;                                                                           \
    }                                                                                              \
    /* The whole row against its own bounds: a max/min reduction, about the cost of reading it. */ \
    static inline int NAME##_whole(const T *restrict r, size_t w, T rh, T rl) {                    \
        T mx = 0, mn = (T) ~(T)0;                                                                  \
        for (size_t x = 0; x < w; x++) {                                                           \
            mx = r[x] > mx ? r[x] : mx;                                                            \
            mn = r[x] < mn ? r[x] : mn;                                                            \
        }                                                                                          \
        return (mx > rh) | (mn < rl);                                                              \
    }
DEFINE_BLOCK_OUT(block_out8, uint8_t)
DEFINE_BLOCK_OUT(block_out16, uint16_t)

/* Bit x set: pixel x of the block is a candidate (r > hi or r < lo). The compiler does not turn the
 * plain loop into vector compares with a mask, so 8-bit frames use AVX-512BW or AVX2 when built
 * for them (-march=native); the loop is the portable fallback and the reference. */
#define DEFINE_BLOCK_MASK_SCALAR(NAME, T)                                                          \
    static inline uint64_t NAME(const T *restrict r, const T *restrict hr, const T *restrict lr) { \
        uint64_t m = 0;                                                                            \
        for (size_t x = 0; x < FT_BLOCK; x++)                                                      \
            m |= (uint64_t)((r[x] > hr[x]) | (r[x] < lr[x])) << x;                                 \
        return m;                                                                                  \
    }
DEFINE_BLOCK_MASK_SCALAR(block_out16_mask, uint16_t)
#if defined(__AVX512BW__)
static inline uint64_t block_out8_mask(const uint8_t *r, const uint8_t *hr, const uint8_t *lr) {
    __m512i v = _mm512_loadu_si512(r);
    return _mm512_cmpgt_epu8_mask(v, _mm512_loadu_si512(hr)) |
           _mm512_cmplt_epu8_mask(v, _mm512_loadu_si512(lr));
}
#elif defined(__AVX2__)
/* Unsigned r > h <=> max(r, h) != h; r < l <=> min(r, l) != l. */
static inline uint32_t out32_avx2(const uint8_t *r, const uint8_t *hr, const uint8_t *lr) {
    __m256i v = _mm256_loadu_si256((const __m256i *)r);
    __m256i h = _mm256_loadu_si256((const __m256i *)hr);
    __m256i l = _mm256_loadu_si256((const __m256i *)lr);
    __m256i in = _mm256_and_si256(_mm256_cmpeq_epi8(_mm256_max_epu8(v, h), h),
                                  _mm256_cmpeq_epi8(_mm256_min_epu8(v, l), l));
    return ~(uint32_t)_mm256_movemask_epi8(in);
}
static inline uint64_t block_out8_mask(const uint8_t *r, const uint8_t *hr, const uint8_t *lr) {
    return (uint64_t)out32_avx2(r, hr, lr) | (uint64_t)out32_avx2(r + 32, hr + 32, lr + 32) << 32;
}
#else
DEFINE_BLOCK_MASK_SCALAR(block_out8_mask, uint8_t)
#endif

#define DEFINE_SCAN(NAME, T, HI, LO, BHI, BLO, RHI, RLO, BLOCK_OUT)                                \
    static uint32_t NAME(ft_fx *fx, const T *restrict img, size_t stride_px, int *overflow) {      \
        const size_t w = fx->w, nblk = fx->nblk;                                                   \
        const T *restrict hi = fx->HI;                                                             \
        const T *restrict lo = fx->LO;                                                             \
        const float *restrict mean = fx->mean;                                                     \
        const int pol = fx->p.polarity;                                                            \
        uint32_t n = 0;                                                                            \
        for (size_t y = 0; y < fx->h; y++) {                                                       \
            const T *restrict r = img + y * stride_px;                                             \
            const T *restrict hr = hi + y * w;                                                     \
            const T *restrict lr = lo + y * w;                                                     \
            const T *restrict bh = fx->BHI + y * nblk;                                             \
            const T *restrict bl = fx->BLO + y * nblk;                                             \
            if (!BLOCK_OUT##_whole(r, w, fx->RHI[y], fx->RLO[y]))                                  \
                continue; /* the common case: a row smooth enough for one pair of bounds */        \
            const size_t nfull = w / FT_BLOCK;                                                     \
            /* Then its full blocks in one pass, reduced once; if they are clean, only a short     \
             * last block, if any, is left to look at. */                                          \
            size_t b0 = nfull && !BLOCK_OUT##_row(r, bh, bl, nfull) ? nfull : 0;                   \
            for (size_t b = b0; b < nblk; b++) {                                                   \
                size_t x0 = b * FT_BLOCK, x1 = x0 + FT_BLOCK;                                      \
                uint64_t m = 0; /* bit x - x0: pixel x is a candidate */                           \
                if (x1 <= w) {                                                                     \
                    if (!BLOCK_OUT(r + x0, bh[b], bl[b]))                                          \
                        continue;                                                                  \
                    m = BLOCK_OUT##_mask(r + x0, hr + x0, lr + x0);                                \
                } else {                                                                           \
                    for (size_t x = x0; x < w; x++) /* the short last block */                     \
                        m |= (uint64_t)((r[x] > hr[x]) | (r[x] < lr[x])) << (x - x0);              \
                }                                                                                  \
                for (; m; m &= m - 1) { /* candidates in raster order */                           \
                    size_t x = x0 + (size_t)__builtin_ctzll(m);                                    \
                    if (n == fx->cap) {                                                            \
                        *overflow = 1;                                                             \
                        return n;                                                                  \
                    }                                                                              \
                    size_t idx = y * w + x;                                                        \
                    float d = (float)r[x] - mean[idx];                                             \
                    if (pol == FT_FX_POLARITY_BOTH)                                                \
                        d = fabsf(d);                                                              \
                    else if (pol == FT_FX_POLARITY_DARK)                                           \
                        d = -d;                                                                    \
                    fx->cand_idx[n] = (uint32_t)idx;                                               \
                    fx->cand_d[n] = d;                                                             \
                    fx->label[idx] = n + 1;                                                        \
                    n++;                                                                           \
                }                                                                                  \
            }                                                                                      \
        }                                                                                          \
        return n;                                                                                  \
    }
DEFINE_SCAN(scan8, uint8_t, hi8, lo8, bhi8, blo8, rhi8, rlo8, block_out8)
DEFINE_SCAN(scan16, uint16_t, hi16, lo16, bhi16, blo16, rhi16, rlo16, block_out16)

static void luma_from_yuyv(size_t w, size_t h, const uint8_t *restrict img, size_t stride,
                           uint8_t *restrict out) {
    for (size_t y = 0; y < h; y++) {
        const uint8_t *restrict r = img + y * stride;
        uint8_t *restrict o = out + y * w;
        for (size_t x = 0; x < w; x++)
            o[x] = r[2 * x];
    }
}

/* ---------------------------------------------------------------------------------------------- */
/* Regions: union-find over candidates (8-connectivity), then moments */

static uint32_t uf_find(uint32_t *parent, uint32_t k) {
    while (parent[k] != k) {
        parent[k] = parent[parent[k]]; /* path halving */
        k = parent[k];
    }
    return k;
}

/* Links so that the root is the smallest index: a region's first candidate in raster order. */
static void uf_union(uint32_t *parent, uint32_t a, uint32_t b) {
    a = uf_find(parent, a);
    b = uf_find(parent, b);
    if (a < b)
        parent[b] = a;
    else if (b < a)
        parent[a] = b;
}

static int rank_cmp(const void *pa, const void *pb) {
    const rank *a = pa, *b = pb;
    if (a->beta != b->beta)
        return a->beta > b->beta ? -1 : 1;
    return a->peak_idx < b->peak_idx ? -1 : (a->peak_idx > b->peak_idx ? 1 : 0);
}

static void shape(const region *g, double *orientation, double *eccentricity) {
    double mx = g->mx / g->m0, my = g->my / g->m0;
    double u20 = g->mxx / g->m0 - mx * mx;
    double u02 = g->myy / g->m0 - my * my;
    double u11 = g->mxy / g->m0 - mx * my;
    double half_tr = 0.5 * (u20 + u02);
    double half_diff = 0.5 * (u20 - u02);
    double disc = sqrt(half_diff * half_diff + u11 * u11);
    double l1 = half_tr + disc, l2 = half_tr - disc;
    if (l1 <= 1e-12 || disc <= 1e-9 * half_tr) { /* a single pixel or a round blob */
        *orientation = NAN;
        *eccentricity = 1.0;
        return;
    }
    double th = 0.5 * atan2(2.0 * u11, u20 - u02);
    if (th <= -FT_PI / 2)
        th += FT_PI;
    *orientation = th;
    *eccentricity = l2 > 1e-12 * l1 ? sqrt(l1 / l2) : NAN; /* a line: the ratio is unbounded */
}

static uint32_t measure(ft_fx *fx, uint32_t n, uint32_t *total) {
    const uint32_t w = fx->w;
    uint32_t *parent = fx->parent;
    for (uint32_t k = 0; k < n; k++) {
        uint32_t idx = fx->cand_idx[k];
        uint32_t x = idx % w, y = idx / w;
        parent[k] = k;
        /* Earlier neighbours in raster order: W, NW, N, NE. */
        if (x > 0 && fx->label[idx - 1])
            uf_union(parent, k, fx->label[idx - 1] - 1);
        if (y > 0) {
            const uint32_t *up = fx->label + idx - w;
            if (x > 0 && up[-1])
                uf_union(parent, k, up[-1] - 1);
            if (up[0])
                uf_union(parent, k, up[0] - 1);
            if (x + 1 < w && up[1])
                uf_union(parent, k, up[1] - 1);
        }
    }
    uint32_t nreg = 0;
    for (uint32_t k = 0; k < n; k++) {
        uint32_t r = uf_find(parent, k);
        float d = fx->cand_d[k];
        if (r == k) { /* roots are visited first: the smallest index of each set */
            region *g = &fx->regions[nreg];
            memset(g, 0, sizeof *g);
            g->beta = d;
            g->peak_cand = k;
            fx->cand_region[k] = nreg++;
        } else {
            fx->cand_region[k] = fx->cand_region[r];
        }
        region *g = &fx->regions[fx->cand_region[k]];
        g->n_cand++;
        if (d > g->beta) { /* strict: on a tie the first in raster order is the peak */
            g->beta = d;
            g->peak_cand = k;
        }
    }
    const int sub = fx->p.subtract_cut;
    for (uint32_t k = 0; k < n; k++) {
        region *g = &fx->regions[fx->cand_region[k]];
        double cut = fx->p.clear_fraction * (double)g->beta;
        /* The cut never lies below the detection threshold either: with weights d - cut they then
         * fall continuously to zero at the region's edge, which keeps the centre unbiased. */
        if (cut < fx->p.despeckle_threshold)
            cut = fx->p.despeckle_threshold;
        if (cut < fx->p.diff_threshold)
            cut = fx->p.diff_threshold;
        double d = fx->cand_d[k];
        if (d < cut)
            continue;
        uint32_t idx = fx->cand_idx[k], pk = fx->cand_idx[g->peak_cand];
        double dx = (double)(idx % w) - (double)(pk % w);
        double dy = (double)(idx / w) - (double)(pk / w);
        double wt = sub ? d - cut : d;
        g->n_kept++;
        g->m0 += wt;
        g->mx += wt * dx;
        g->my += wt * dy;
        g->mxx += wt * dx * dx;
        g->myy += wt * dy * dy;
        g->mxy += wt * dx * dy;
    }
    uint32_t nr = 0;
    for (uint32_t r = 0; r < nreg; r++) {
        if (fx->regions[r].n_kept < fx->p.min_area)
            continue; /* speckle */
        fx->ranks[nr].beta = fx->regions[r].beta;
        fx->ranks[nr].peak_idx = fx->cand_idx[fx->regions[r].peak_cand];
        fx->ranks[nr].rid = r;
        nr++;
    }
    qsort(fx->ranks, nr, sizeof(rank), rank_cmp);
    *total = nr;
    uint32_t np = nr < fx->p.max_points ? nr : fx->p.max_points;
    for (uint32_t i = 0; i < np; i++) {
        const region *g = &fx->regions[fx->ranks[i].rid];
        ft_fx_point *pt = &fx->points[i];
        uint32_t pk = fx->cand_idx[g->peak_cand];
        pt->peak_x = pk % w;
        pt->peak_y = pk / w;
        if (g->m0 > 0.0) {
            pt->x_dist = pt->peak_x + g->mx / g->m0;
            pt->y_dist = pt->peak_y + g->my / g->m0;
            shape(g, &pt->orientation, &pt->eccentricity);
        } else { /* every kept pixel sits exactly at the cut: the peak is the centre */
            pt->x_dist = pt->peak_x;
            pt->y_dist = pt->peak_y;
            pt->orientation = NAN;
            pt->eccentricity = 1.0;
        }
        ft_fx_undistort(&fx->p, pt->x_dist, pt->y_dist, &pt->x_undist, &pt->y_undist);
        pt->area = g->n_kept;
        pt->peak_diff = g->beta;
        pt->mean_val = fx->mean[pk];
        pt->sumsq_val = fx->sumsq[pk];
        pt->n_candidates = g->n_cand;
    }
    return np;
}

/* ---------------------------------------------------------------------------------------------- */
/* Process */

int ft_fx_process(ft_fx *fx, const void *frame, size_t nbytes, ft_fx_result *res) {
    if (!fx || !frame || !res)
        return FT_FX_E_ARG;
    memset(res, 0, sizeof *res);
    res->points = fx->points;
    if (nbytes < fx->frame_bytes)
        return FT_FX_E_FRAME_SIZE;
    fx->frame_index++;
    res->frame_index = fx->frame_index;
    const void *img = frame;
    size_t stride = fx->stride;
    if (fx->p.pixel_format == FT_FX_YUYV) {
        luma_from_yuyv(fx->w, fx->h, frame, fx->stride, fx->luma);
        img = fx->luma;
        stride = fx->w;
    }
    if (fx->need_bg) {
        update_background(fx, img, stride, 1);
        fx->need_bg = 0;
        fx->since_update = 0;
        res->flags |= FT_FX_RES_BACKGROUND_TAKEN;
        return FT_FX_OK;
    }
    int overflow = 0;
    uint32_t n = fx->p.pixel_format == FT_FX_MONO16 ? scan16(fx, img, stride / 2, &overflow)
                                                    : scan8(fx, img, stride, &overflow);
    uint32_t total = 0, np = 0;
    if (n)
        np = measure(fx, n, &total);
    for (uint32_t k = 0; k < n; k++) /* leave the label image all zero for the next frame */
        fx->label[fx->cand_idx[k]] = 0;
    for (uint32_t i = 0; i < np; i++) {
        const ft_fx_point *pt = &fx->points[i];
        size_t off = (size_t)pt->peak_y * stride;
        fx->points[i].cur_val = fx->p.pixel_format == FT_FX_MONO16
                                    ? ((const uint16_t *)((const uint8_t *)img + off))[pt->peak_x]
                                    : ((const uint8_t *)img + off)[pt->peak_x];
    }
    res->n_points = np;
    res->total_points = total;
    res->n_candidates = n;
    if (overflow)
        res->flags |= FT_FX_RES_CAND_OVERFLOW;
    if (total > np)
        res->flags |= FT_FX_RES_TRUNCATED;
    /* The background learns from this frame after it was measured against the old one. */
    if (fx->p.bg_update_interval && ++fx->since_update >= fx->p.bg_update_interval) {
        fx->since_update = 0;
        update_background(fx, img, stride, 0);
        res->flags |= FT_FX_RES_BG_UPDATED;
    }
    return FT_FX_OK;
}

void ft_fx_take_background(ft_fx *fx) {
    if (fx)
        fx->need_bg = 1;
}

int ft_fx_set_mask(ft_fx *fx, const uint8_t *mask) {
    if (!fx)
        return FT_FX_E_ARG;
    if (mask)
        for (size_t i = 0; i < fx->npix; i++)
            fx->mask[i] = mask[i] != 0;
    else
        memset(fx->mask, 1, fx->npix);
    if (fx->have_bg)
        refresh_thresholds(fx);
    return FT_FX_OK;
}

/* ---------------------------------------------------------------------------------------------- */
/* Runtime parameters */

typedef enum { P_DOUBLE, P_U32, P_I32 } ptype;
typedef struct {
    const char *name;
    ptype type;
    size_t offset;
} pdesc;

#define PD(name, type)                                                                             \
    { #name, type, offsetof(ft_fx_params, name) }
static const pdesc tunables[] = {
    PD(alpha, P_DOUBLE),
    PD(n_sigma, P_DOUBLE),
    PD(diff_threshold, P_DOUBLE),
    PD(bg_update_interval, P_U32),
    PD(polarity, P_I32),
    PD(clear_fraction, P_DOUBLE),
    PD(despeckle_threshold, P_DOUBLE),
    PD(min_area, P_U32),
    PD(subtract_cut, P_I32),
    PD(max_points, P_U32),
};

static const pdesc *find_param(const char *name) {
    if (!name)
        return NULL;
    for (size_t i = 0; i < sizeof tunables / sizeof tunables[0]; i++)
        if (!strcmp(tunables[i].name, name))
            return &tunables[i];
    return NULL;
}

int ft_fx_set_param(ft_fx *fx, const char *name, double value) {
    if (!fx)
        return FT_FX_E_ARG;
    const pdesc *d = find_param(name);
    if (!d)
        return FT_FX_E_UNKNOWN_PARAM;
    if (!isfinite(value))
        return FT_FX_E_BAD_VALUE;
    ft_fx_params np = fx->p;
    char *field = (char *)&np + d->offset;
    if (d->type == P_DOUBLE) {
        memcpy(field, &value, sizeof value);
    } else {
        if (value != floor(value) || value < -2147483648.0 || value > 4294967295.0)
            return FT_FX_E_BAD_VALUE;
        if (d->type == P_U32) {
            if (value < 0)
                return FT_FX_E_BAD_VALUE;
            uint32_t u = (uint32_t)value;
            memcpy(field, &u, sizeof u);
        } else {
            if (value > 2147483647.0)
                return FT_FX_E_BAD_VALUE;
            int32_t s = (int32_t)value;
            memcpy(field, &s, sizeof s);
        }
    }
    if (check_tunables(&np, NULL, 0))
        return FT_FX_E_BAD_VALUE;
    fx->p = np;
    if (fx->have_bg)
        refresh_thresholds(fx);
    return FT_FX_OK;
}

int ft_fx_get_param(const ft_fx *fx, const char *name, double *value) {
    if (!fx || !value)
        return FT_FX_E_ARG;
    const pdesc *d = find_param(name);
    if (!d)
        return FT_FX_E_UNKNOWN_PARAM;
    const char *field = (const char *)&fx->p + d->offset;
    if (d->type == P_DOUBLE) {
        memcpy(value, field, sizeof *value);
    } else if (d->type == P_U32) {
        uint32_t u;
        memcpy(&u, field, sizeof u);
        *value = u;
    } else {
        int32_t s;
        memcpy(&s, field, sizeof s);
        *value = s;
    }
    return FT_FX_OK;
}

const ft_fx_params *ft_fx_get_params(const ft_fx *fx) {
    return fx ? &fx->p : NULL;
}
const float *ft_fx_background_mean(const ft_fx *fx) {
    return fx && fx->have_bg ? fx->mean : NULL;
}
const float *ft_fx_background_sumsq(const ft_fx *fx) {
    return fx && fx->have_bg ? fx->sumsq : NULL;
}

/* ---------------------------------------------------------------------------------------------- */
/* Lens distortion (OpenCV model, the same as host camera.py) */

static void distort_norm(const ft_fx_params *p, double x, double y, double *xd, double *yd) {
    double r2 = x * x + y * y;
    double radial = 1.0 + r2 * (p->k1 + r2 * (p->k2 + r2 * p->k3));
    *xd = x * radial + 2.0 * p->p1 * x * y + p->p2 * (r2 + 2.0 * x * x);
    *yd = y * radial + p->p1 * (r2 + 2.0 * y * y) + 2.0 * p->p2 * x * y;
}

void ft_fx_undistort(const ft_fx_params *p, double u, double v, double *u_out, double *v_out) {
    if (p->fx == 0.0 ||
        (p->k1 == 0.0 && p->k2 == 0.0 && p->p1 == 0.0 && p->p2 == 0.0 && p->k3 == 0.0)) {
        *u_out = u;
        *v_out = v;
        return;
    }
    double ydn = (v - p->cy) / p->fy;
    double xdn = (u - p->cx - p->skew * ydn) / p->fx;
    double x = xdn, y = ydn;
    /* Fixed-point iteration as OpenCV's undistortPoints, then Newton steps with the analytic
     * Jacobian to reach the exact inverse of the distortion (camera.py does the same). */
    for (int i = 0; i < 20; i++) {
        double r2 = x * x + y * y;
        double radial = 1.0 + r2 * (p->k1 + r2 * (p->k2 + r2 * p->k3));
        double dx = 2.0 * p->p1 * x * y + p->p2 * (r2 + 2.0 * x * x);
        double dy = p->p1 * (r2 + 2.0 * y * y) + 2.0 * p->p2 * x * y;
        x = (xdn - dx) / radial;
        y = (ydn - dy) / radial;
    }
    for (int i = 0; i < 3; i++) {
        double fx_, fy_;
        distort_norm(p, x, y, &fx_, &fy_);
        double ex = fx_ - xdn, ey = fy_ - ydn;
        double r2 = x * x + y * y;
        double radial = 1.0 + r2 * (p->k1 + r2 * (p->k2 + r2 * p->k3));
        double drad = p->k1 + r2 * (2.0 * p->k2 + 3.0 * p->k3 * r2);
        double a = radial + 2.0 * x * x * drad + 2.0 * p->p1 * y + 6.0 * p->p2 * x;
        double b = 2.0 * x * y * drad + 2.0 * p->p1 * x + 2.0 * p->p2 * y;
        double c = 2.0 * x * y * drad + 2.0 * p->p1 * x + 2.0 * p->p2 * y;
        double d = radial + 2.0 * y * y * drad + 6.0 * p->p1 * y + 2.0 * p->p2 * x;
        double det = a * d - b * c;
        if (!(fabs(det) > 1e-300))
            break;
        double nx = x - (d * ex - b * ey) / det;
        double ny = y - (-c * ex + a * ey) / det;
        if (!isfinite(nx) || !isfinite(ny))
            break;
        x = nx;
        y = ny;
    }
    *u_out = p->fx * x + p->skew * y + p->cx;
    *v_out = p->fy * y + p->cy;
}

/* ---------------------------------------------------------------------------------------------- */

const char *ft_fx_strerror(int code) {
    switch (code) {
    case FT_FX_OK:
        return "ok";
    case FT_FX_E_ARG:
        return "invalid argument";
    case FT_FX_E_SIZE:
        return "bad frame geometry (width, height or stride)";
    case FT_FX_E_FORMAT:
        return "unknown pixel format";
    case FT_FX_E_NOMEM:
        return "out of memory";
    case FT_FX_E_FRAME_SIZE:
        return "frame buffer smaller than the configured geometry";
    case FT_FX_E_UNKNOWN_PARAM:
        return "unknown parameter";
    case FT_FX_E_BAD_VALUE:
        return "parameter value out of range";
    case FT_FX_E_ABI:
        return "caller and library disagree on struct layout (rebuild)";
    }
    return "unknown error";
}

int ft_fx_abi_version(void) {
    return FT_FX_ABI_VERSION;
}
size_t ft_fx_sizeof_params(void) {
    return sizeof(ft_fx_params);
}
size_t ft_fx_sizeof_point(void) {
    return sizeof(ft_fx_point);
}

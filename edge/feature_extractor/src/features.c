/* libflytrack_features: see include/flytrack/features.h for the algorithm and the API.
 *
 * Speed plan: a pixel is a candidate against two precomputed per-pixel integer thresholds (hi:
 * brighter than the background by more than the allowed deviation; lo: darker). The hot loop
 * (scan.c) reads the frame alone against each row's and each block's tightest bounds (vector
 * max/min); only blocks it cannot rule out are compared pixel by pixel with hi and lo, and their
 * candidates are kept as runs (one row, consecutive x) with their differences. Regions are labelled
 * run by run and measured from those arrays (regions.c). The float background (mean, mean of
 * squares) and the thresholds are recomputed only every bg_update_interval frames.
 *
 * Float arithmetic is plain IEEE single precision in a fixed order (the library is built with
 * -ffp-contract=off), so a NumPy float32 reference reproduces the thresholds bit for bit.
 */
#include "flytrack/features.h"
#include "fx_internal.h"
#include "thresholds.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#define DEFAULT_MAX_CANDIDATES 65536u
#define MAX_DIM 16384u

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
    free(fx->ghi8);
    free(fx->glo8);
    free(fx->ghi16);
    free(fx->glo16);
    free(fx->nbhi8);
    free(fx->nblo8);
    free(fx->nbhi16);
    free(fx->nblo16);
    free(fx->saved);
    free(fx->pending);
    free(fx->whi8);
    free(fx->wlo8);
    free(fx->whi16);
    free(fx->wlo16);
    free(fx->mask);
    free(fx->luma);
    free(fx->cand_d);
    free(fx->runs);
    free(fx->queue);
    free(fx->qmask);
    free(fx->run_parent);
    free(fx->run_region);
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
    fx->scan = ft_fx_scan_select();
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
    fx->cand_d = malloc(fx->cap * sizeof(float));
    fx->runs = malloc(fx->cap * sizeof(ft_run)); /* a run holds at least one candidate */
    fx->run_parent = malloc(fx->cap * sizeof(uint32_t));
    fx->run_region = malloc(fx->cap * sizeof(uint32_t));
    fx->regions = malloc(fx->cap * sizeof(ft_region));
    fx->ranks = malloc(fx->cap * sizeof(ft_rank));
    fx->points = malloc(fx->cap * sizeof(ft_fx_point));
    int ok = fx->mean && fx->sumsq && fx->mask && fx->cand_d && fx->runs && fx->run_parent &&
             fx->run_region && fx->regions && fx->ranks && fx->points;
    fx->nblk = (fx->w + FT_BLOCK - 1) / FT_BLOCK;
    const size_t nb = fx->nblk * fx->h, nbands = (fx->h + FT_BAND - 1) / FT_BAND;
    const size_t ng = fx->nblk * nbands;
    fx->queue = malloc(nb * sizeof(uint32_t)); /* nblk <= 256: y << 8 | block */
    fx->qmask = malloc(nb * sizeof(uint64_t));
    fx->saved = malloc(fx->npix * bpp);
    fx->pending = calloc(fx->h, 1);
    ok = ok && fx->queue && fx->qmask && fx->saved && fx->pending;
    if (p->pixel_format == FT_FX_MONO16) {
        fx->hi16 = malloc(fx->npix * sizeof(uint16_t));
        fx->lo16 = malloc(fx->npix * sizeof(uint16_t));
        fx->bhi16 = malloc(nb * sizeof(uint16_t));
        fx->blo16 = malloc(nb * sizeof(uint16_t));
        fx->ghi16 = malloc(ng * sizeof(uint16_t));
        fx->glo16 = malloc(ng * sizeof(uint16_t));
        fx->nbhi16 = malloc(nb * sizeof(uint16_t));
        fx->nblo16 = malloc(nb * sizeof(uint16_t));
        ok = ok && fx->nbhi16 && fx->nblo16;
        fx->whi16 = malloc(nbands * sizeof(uint16_t));
        fx->wlo16 = malloc(nbands * sizeof(uint16_t));
        ok = ok && fx->hi16 && fx->lo16 && fx->bhi16 && fx->blo16 && fx->ghi16 && fx->glo16 &&
             fx->whi16 && fx->wlo16;
    } else {
        fx->hi8 = malloc(fx->npix);
        fx->lo8 = malloc(fx->npix);
        fx->bhi8 = malloc(nb);
        fx->blo8 = malloc(nb);
        fx->ghi8 = malloc(ng);
        fx->glo8 = malloc(ng);
        fx->nbhi8 = malloc(nb);
        fx->nblo8 = malloc(nb);
        ok = ok && fx->nbhi8 && fx->nblo8;
        fx->whi8 = malloc(nbands);
        fx->wlo8 = malloc(nbands);
        ok = ok && fx->hi8 && fx->lo8 && fx->bhi8 && fx->blo8 && fx->ghi8 && fx->glo8 && fx->whi8 &&
             fx->wlo8;
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
        ft_fx_bg_take(fx, img, stride);
        fx->need_bg = 0;
        fx->since_update = 0;
        res->flags |= FT_FX_RES_BACKGROUND_TAKEN;
        return FT_FX_OK;
    }
    if (fx->scalar_scan) /* the plain scan reads every row's thresholds */
        ft_fx_bg_finish(fx);
    int overflow = 0;
    uint32_t n = 0;
    uint32_t nr = fx->p.pixel_format == FT_FX_MONO16
                      ? fx->scan->scan16(fx, img, stride / 2, &n, &overflow)
                      : fx->scan->scan8(fx, img, stride, &n, &overflow);
    uint32_t total = 0, np = 0;
    if (nr)
        np = ft_fx_measure(fx, nr, &total);
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
        ft_fx_bg_update(fx, img, stride);
        res->flags |= FT_FX_RES_BG_UPDATED;
    } else {
        ft_fx_bg_step(fx);
    }
    return FT_FX_OK;
}

void ft_fx_take_background(ft_fx *fx) {
    if (fx) {
        ft_fx_bg_finish(fx); /* the model stays whole until the next frame replaces it */
        fx->need_bg = 1;
    }
}

int ft_fx_set_mask(ft_fx *fx, const uint8_t *mask) {
    if (!fx)
        return FT_FX_E_ARG;
    ft_fx_bg_finish(fx); /* the update in progress with the mask it began with */
    if (mask)
        for (size_t i = 0; i < fx->npix; i++)
            fx->mask[i] = mask[i] != 0;
    else
        memset(fx->mask, 1, fx->npix);
    fx->has_mask = mask != NULL;
    if (fx->have_bg)
        ft_fx_bg_refresh(fx);
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
    ft_fx_bg_finish(fx); /* the update in progress with the parameters it began with */
    fx->p = np;
    if (fx->have_bg)
        ft_fx_bg_refresh(fx);
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
/* The model is brought up to date first (a spread update may be in progress): the extractor was
 * created non-const by ft_fx_create, so finishing it through this pointer is allowed. */
const float *ft_fx_background_mean(const ft_fx *fx) {
    if (fx)
        ft_fx_bg_finish((ft_fx *)fx);
    return fx && fx->have_bg ? fx->mean : NULL;
}
const float *ft_fx_background_sumsq(const ft_fx *fx) {
    if (fx)
        ft_fx_bg_finish((ft_fx *)fx);
    return fx && fx->have_bg ? fx->sumsq : NULL;
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

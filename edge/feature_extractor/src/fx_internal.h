/* Internal to libflytrack_features: the extractor's state, shared by features.c (model, regions,
 * API) and scan.c (the per-frame candidate scan). */
#ifndef FLYTRACK_FX_INTERNAL_H
#define FLYTRACK_FX_INTERNAL_H

#include "flytrack/features.h"
#include "thresholds.h"

#include <stddef.h>
#include <stdint.h>

#define FT_BLOCK 64u /* pixels per block of the scan's bounds pass: one 64-bit candidate mask */
#define FT_BAND                                                                                    \
    4u /* rows the scan tests at once, block by block, before testing them one by one              \
        */

/* A run: candidates y, x0 .. x1 - 1 of one row, found in raster order; their differences are
 * cand_d[c0 .. c0 + x1 - x0 - 1]. Regions are unions of 8-connected runs. */
typedef struct {
    uint32_t y, x0, x1, c0;
} ft_run;

typedef struct {
    float beta;
    uint32_t peak_x, peak_y;
    uint32_t n_cand, n_kept;
    double cut;
    double m0, mx, my, mxx, myy, mxy; /* moments about the peak pixel */
} ft_region;

typedef struct {
    float beta;
    uint32_t peak_idx;
    uint32_t rid;
} ft_rank;

/* One vector path of the candidate scan (scan.c): see ft_fx_scan8 below. */
struct ft_fx;
typedef struct {
    const char *name; /* "avx512bw", "avx2" or "generic" */
    uint32_t (*scan8)(struct ft_fx *fx, const uint8_t *img, size_t stride, uint32_t *n_cand,
                      int *overflow);
    uint32_t (*scan16)(struct ft_fx *fx, const uint16_t *img, size_t stride_px, uint32_t *n_cand,
                       int *overflow);
} ft_fx_scan_impl;

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
     * alone (see scan.c). */
    size_t nblk; /* blocks per row */
    uint8_t *bhi8, *blo8;
    uint16_t *bhi16, *blo16;
    /* The same bounds per block of a band of FT_BAND rows (band y / FT_BAND, block b at
     * [band * nblk + b]): the scan's first check. */
    uint8_t *ghi8, *glo8;
    uint16_t *ghi16, *glo16;
    /* And per whole band (band y / FT_BAND): the very first check. */
    uint8_t *whi8, *wlo8;
    uint16_t *whi16, *wlo16;
    /* Per block, as bhi/blo: the bounds that hold after the next update (background.c). */
    uint8_t *nbhi8, *nblo8;
    uint16_t *nbhi16, *nblo16;
    /* The update spread over the following frames (background.c): rows not yet brought up to date
     * from the saved frame (packed), with the update's settings. */
    void *saved;
    uint8_t *pending;
    uint32_t n_pending, lazy_next;
    thr_cfg lazy_cfg;
    int eager_update; /* tests: 1 = the whole update in the frame that asks for it */
    uint8_t *mask;    /* 1 = use, always allocated (all ones without a user mask) */
    int has_mask;     /* a user mask is set (else the thresholds do not read mask) */
    uint8_t *luma;    /* YUYV: the luma plane of the current frame */
    uint32_t cap;     /* candidates (and so runs) per frame at most */
    uint32_t *queue;  /* the scan's blocks to look at pixel by pixel: y << 8 | block (h x nblk) */
    uint64_t *qmask;  /* the queued blocks' candidate masks */
    float *cand_d;    /* per candidate, raster order: its difference to the background */
    ft_run *runs;     /* per run, raster order */
    uint32_t *run_parent, *run_region;
    ft_region *regions;
    ft_rank *ranks;
    ft_fx_point *points;
    uint64_t frame_index;
    uint64_t since_update;
    int need_bg;
    int have_bg;
    int scalar_scan; /* 1: the plain per-pixel scan (the reference the vector scan is tested on) */
    const ft_fx_scan_impl *scan; /* the vector path, chosen at create (ft_fx_scan_select) */
};

/* The background model (background.c). take: the frame becomes the background; update: the
 * running average learns from the frame (rows brought up to date later, see bg_row); step: a few
 * more rows after a frame; finish: all of them; refresh: the thresholds again (parameters or mask
 * changed). ft_fx_bg_row must be called before a row's thresholds or model are read when
 * pending[y] is set. */
thr_cfg ft_fx_thr_config(const ft_fx *fx);
void ft_fx_bg_take(ft_fx *fx, const void *img, size_t stride_bytes);
void ft_fx_bg_update(ft_fx *fx, const void *img, size_t stride_bytes);
void ft_fx_bg_row(ft_fx *fx, uint32_t y);
void ft_fx_bg_step(ft_fx *fx);
void ft_fx_bg_finish(ft_fx *fx);
void ft_fx_bg_refresh(ft_fx *fx);

/* The candidate scan of one frame, fx->scan->scan8 or scan16: fills cand_d and runs, returns the
 * number of runs; *n_cand gets the candidates, *overflow 1 when cap was reached (the candidates
 * found so far are kept). One path per compile of scan.c; the portable x86 build (FT_FX_DISPATCH)
 * links all three and picks at create. */
extern const ft_fx_scan_impl ft_fx_scan_avx512bw, ft_fx_scan_avx2, ft_fx_scan_generic;
/* The widest path this CPU runs among those linked in. */
const ft_fx_scan_impl *ft_fx_scan_select(void);

/* The scan's nr runs united into regions and measured (regions.c): fills fx->points, strongest
 * first, and returns how many (at most max_points); *total gets the regions kept before the cap. */
uint32_t ft_fx_measure(ft_fx *fx, uint32_t nr, uint32_t *total);

/* Tests only: 1 makes ft_fx_process use the plain per-pixel scan, 0 the vector scan (default).
 * Both must give bit-identical results. */
void ft_fx_debug_scalar_scan(ft_fx *fx, int on);
/* Tests only: 1 makes each background update whole in the frame that asks for it (as before it
 * was spread); 0 spreads it (default). Both must give bit-identical results. */
void ft_fx_debug_eager_update(ft_fx *fx, int on);
/* Tests only: rows of the model not yet brought up to date. */
uint32_t ft_fx_debug_pending_rows(const ft_fx *fx);
/* Tests only: the vector path fx uses ("avx512bw", "avx2" or "generic"). */
const char *ft_fx_debug_scan_path(const ft_fx *fx);
/* Tests only: makes fx use the named path; -1 (fx unchanged) when it is not linked in or this CPU
 * cannot run it. */
int ft_fx_debug_scan_force(ft_fx *fx, const char *name);

#endif

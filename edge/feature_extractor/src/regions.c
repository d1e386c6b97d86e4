/* Regions of libflytrack_features: the scan's runs of candidates (scan.c) united into 8-connected
 * regions, and each region measured: peak, area, moments, shape, lens undistortion (undistort.c),
 * ranking. */
#include "fx_internal.h"

#include <math.h>
#include <stdlib.h>
#include <string.h>

#define FT_PI 3.14159265358979323846

/* ---------------------------------------------------------------------------------------------- */
/* Regions: union-find over runs of candidates (8-connectivity), then moments */

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
    const ft_rank *a = pa, *b = pb;
    if (a->beta != b->beta)
        return a->beta > b->beta ? -1 : 1;
    return a->peak_idx < b->peak_idx ? -1 : (a->peak_idx > b->peak_idx ? 1 : 0);
}

static void shape(const ft_region *g, double *orientation, double *eccentricity) {
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

/* Runs of consecutive rows are 8-connected when their x ranges overlap or touch diagonally. Both
 * rows' runs are in x order, so one sweep finds every pair. */
static void link_runs(ft_fx *fx, uint32_t nr) {
    const ft_run *runs = fx->runs;
    uint32_t *parent = fx->run_parent;
    /* The previous row's runs are [prev0, prev1); this row's start at cur0. */
    uint32_t prev0 = 0, prev1 = 0, cur0 = 0;
    for (uint32_t k = 0; k < nr; k++) {
        const ft_run *q = &runs[k];
        parent[k] = k;
        if (k == 0 || q->y != runs[k - 1].y) { /* a new row */
            int adjacent = k > 0 && q->y == runs[k - 1].y + 1;
            prev0 = adjacent ? cur0 : k; /* else no run above touches this row */
            prev1 = k;
            cur0 = k;
        }
        while (prev0 < prev1 && runs[prev0].x1 < q->x0) /* ends left of q: touches no later run */
            prev0++;
        for (uint32_t j = prev0; j < prev1 && runs[j].x0 <= q->x1; j++)
            uf_union(parent, k, j);
    }
}

/* Regions from the runs, measured as the per-pixel algorithm does: candidates in raster order, the
 * peak the first largest difference, moments summed in raster order (so the sums are the same,
 * bit for bit, as one pass over the region's pixels). */
uint32_t ft_fx_measure(ft_fx *fx, uint32_t nr, uint32_t *total) {
    const uint32_t w = fx->w;
    const ft_run *runs = fx->runs;
    const float *cd = fx->cand_d;
    link_runs(fx, nr);
    uint32_t nreg = 0;
    for (uint32_t k = 0; k < nr; k++) {
        uint32_t root = uf_find(fx->run_parent, k);
        const ft_run *q = &runs[k];
        ft_region *g;
        if (root == k) { /* roots are visited first: the smallest index of each set */
            g = &fx->regions[nreg];
            memset(g, 0, sizeof *g);
            g->beta = cd[q->c0];
            g->peak_x = q->x0;
            g->peak_y = q->y;
            fx->run_region[k] = nreg++;
        } else {
            fx->run_region[k] = fx->run_region[root];
            g = &fx->regions[fx->run_region[k]];
        }
        const uint32_t len = q->x1 - q->x0;
        g->n_cand += len;
        /* The run's first largest difference without a branch per pixel (rising and falling
         * differences would mispredict it), then one strict compare with the region's: on a tie
         * the first in raster order, as pixel by pixel. */
        float best = cd[q->c0];
        uint32_t bj = 0;
        for (uint32_t j = 1; j < len; j++) {
            const float v = cd[q->c0 + j];
            const int better = v > best;
            best = better ? v : best;
            bj = better ? j : bj;
        }
        if (best > g->beta) {
            g->beta = best;
            g->peak_x = q->x0 + bj;
            g->peak_y = q->y;
        }
    }
    for (uint32_t r = 0; r < nreg; r++) {
        ft_region *g = &fx->regions[r];
        double cut = fx->p.clear_fraction * (double)g->beta;
        /* The cut never lies below the detection threshold either: with weights d - cut they then
         * fall continuously to zero at the region's edge, which keeps the centre unbiased. */
        if (cut < fx->p.despeckle_threshold)
            cut = fx->p.despeckle_threshold;
        if (cut < fx->p.diff_threshold)
            cut = fx->p.diff_threshold;
        g->cut = cut;
    }
    const int sub = fx->p.subtract_cut;
    for (uint32_t k = 0; k < nr; k++) {
        const ft_run *q = &runs[k];
        ft_region *g = &fx->regions[fx->run_region[k]];
        const double cut = g->cut;
        const double dy = (double)q->y - (double)g->peak_y;
        const uint32_t len = q->x1 - q->x0;
        /* Without a branch (whether a pixel is kept is a coin toss at a region's edge): a pixel
         * below the cut adds zero weight, which leaves every sum as it was, bit for bit (the sums
         * start at +0 and never become -0). */
        double m0 = g->m0, mx = g->mx, my = g->my, mxx = g->mxx, myy = g->myy, mxy = g->mxy;
        uint32_t kept = 0;
        for (uint32_t j = 0; j < len; j++) {
            double d = cd[q->c0 + j];
            int keep = d >= cut;
            double dx = (double)(q->x0 + j) - (double)g->peak_x;
            double wt = keep ? (sub ? d - cut : d) : 0.0;
            kept += (uint32_t)keep;
            m0 += wt;
            mx += wt * dx;
            my += wt * dy;
            mxx += wt * dx * dx;
            myy += wt * dy * dy;
            mxy += wt * dx * dy;
        }
        g->n_kept += kept;
        g->m0 = m0;
        g->mx = mx;
        g->my = my;
        g->mxx = mxx;
        g->myy = myy;
        g->mxy = mxy;
    }
    uint32_t nk = 0;
    for (uint32_t r = 0; r < nreg; r++) {
        const ft_region *g = &fx->regions[r];
        if (g->n_kept < fx->p.min_area)
            continue; /* speckle */
        fx->ranks[nk].beta = g->beta;
        fx->ranks[nk].peak_idx = g->peak_y * w + g->peak_x;
        fx->ranks[nk].rid = r;
        nk++;
    }
    if (nk <= 32) { /* a few regions, the usual case: insertion sort, no calls through a pointer */
        for (uint32_t i = 1; i < nk; i++) {
            ft_rank t = fx->ranks[i];
            uint32_t j = i;
            for (; j > 0 && rank_cmp(&t, &fx->ranks[j - 1]) < 0; j--)
                fx->ranks[j] = fx->ranks[j - 1];
            fx->ranks[j] = t;
        }
    } else {
        qsort(fx->ranks, nk, sizeof(ft_rank), rank_cmp); /* a total order: the same result */
    }
    *total = nk;
    uint32_t np = nk < fx->p.max_points ? nk : fx->p.max_points;
    for (uint32_t i = 0; i < np; i++) {
        const ft_region *g = &fx->regions[fx->ranks[i].rid];
        ft_fx_point *pt = &fx->points[i];
        uint32_t pk = g->peak_y * w + g->peak_x;
        pt->peak_x = g->peak_x;
        pt->peak_y = g->peak_y;
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

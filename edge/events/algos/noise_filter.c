/* Noise filters for event streams (see flytrack/event_algos.h). O(1) work per event: each filter
 * reads and writes a fixed number of per-pixel timestamps. The maps have a one-pixel border so that
 * the 8-neighbourhood of an edge pixel needs no bounds checks. */
#include "flytrack/event_algos.h"

#include <stdlib.h>
#include <string.h>

struct ft_noise_filter {
    ft_nf_params p;
    uint32_t stride;   /* width + 2 */
    uint32_t *support; /* BA: last time a neighbour of this pixel fired */
    uint32_t *last;    /* STC: last time this pixel fired (any event) */
    uint32_t *passed;  /* refractory: last time an event of this pixel survived */
    uint32_t *count;   /* hot pixel: events in the current learning window */
    uint8_t *hot;
    int64_t window_start;
    int started;
    ft_nf_stats st;
};

void ft_nf_defaults(ft_nf_params *p, uint32_t width, uint32_t height) {
    memset(p, 0, sizeof *p);
    p->width = width;
    p->height = height;
    p->ba_window_us = 2000;
    p->stc_min_neighbours = 0;
    p->refractory_us = 100;
    p->hot_pixel_count = 10000;
    p->hot_pixel_window_us = 1000000;
}

ft_noise_filter *ft_nf_create(const ft_nf_params *p) {
    if (!p || p->width == 0 || p->height == 0 || p->width > 8192 || p->height > 8192 ||
        p->stc_min_neighbours > 8 || (p->hot_pixel_count && p->hot_pixel_window_us == 0))
        return NULL;
    ft_noise_filter *f = calloc(1, sizeof *f);
    if (!f)
        return NULL;
    f->p = *p;
    f->stride = p->width + 2;
    size_t n = (size_t)f->stride * (p->height + 2);
    f->support = malloc(n * sizeof *f->support);
    f->last = malloc(n * sizeof *f->last);
    f->passed = malloc(n * sizeof *f->passed);
    f->count = calloc(n, sizeof *f->count);
    f->hot = calloc(n, 1);
    if (!f->support || !f->last || !f->passed || !f->count || !f->hot) {
        ft_nf_destroy(f);
        return NULL;
    }
    return f;
}

void ft_nf_destroy(ft_noise_filter *f) {
    if (!f)
        return;
    free(f->support);
    free(f->last);
    free(f->passed);
    free(f->count);
    free(f->hot);
    free(f);
}

void ft_nf_get_stats(const ft_noise_filter *f, ft_nf_stats *s) {
    *s = f->st;
}

/* "Long ago" for every pixel at the first event: half the 32-bit range before it. */
static void start(ft_noise_filter *f, int64_t t0) {
    size_t n = (size_t)f->stride * (f->p.height + 2);
    uint32_t never = (uint32_t)t0 - 0x80000000u;
    for (size_t i = 0; i < n; i++)
        f->support[i] = f->last[i] = f->passed[i] = never;
    f->window_start = t0;
    f->started = 1;
}

/* End of a hot-pixel learning window: pixels that fired too often in it are hot from now on. */
static void learn_hot(ft_noise_filter *f, int64_t t) {
    size_t n = (size_t)f->stride * (f->p.height + 2);
    for (size_t i = 0; i < n; i++) {
        if (f->count[i] >= f->p.hot_pixel_count && !f->hot[i]) {
            f->hot[i] = 1;
            f->st.hot_pixels++;
        }
        f->count[i] = 0;
    }
    f->window_start = t;
}

size_t ft_nf_apply(ft_noise_filter *f, ft_event *ev, size_t n) {
    const uint32_t W = f->p.width, H = f->p.height, S = f->stride;
    const uint32_t ba = f->p.ba_window_us, refr = f->p.refractory_us;
    const uint32_t k = f->p.stc_min_neighbours, hot_n = f->p.hot_pixel_count;
    const long off[8] = {-(long)S - 1, -(long)S, -(long)S + 1, -1, 1,
                         (long)S - 1,  (long)S,  (long)S + 1};
    size_t out = 0;
    if (n && !f->started)
        start(f, ev[0].t);
    f->st.in += n;
    for (size_t i = 0; i < n; i++) {
        const ft_event e = ev[i];
        if (e.x >= W || e.y >= H) {
            f->st.ba_removed++;
            continue;
        }
        const uint32_t t = (uint32_t)e.t;
        const size_t c = (size_t)(e.y + 1) * S + (e.x + 1);
        int keep = 1;
        if (hot_n) {
            if (e.t - f->window_start >= (int64_t)f->p.hot_pixel_window_us)
                learn_hot(f, e.t);
            f->count[c]++;
            if (f->hot[c]) {
                f->st.hot_removed++;
                keep = 0;
            }
        }
        if (ba) {
            /* libcaer's way: this pixel's map holds the last time a neighbour fired; then this
             * event is the newest neighbour of the 8 around it, kept or not. */
            if (keep && t - f->support[c] > ba) {
                f->st.ba_removed++;
                keep = 0;
            }
            for (int j = 0; j < 8; j++)
                f->support[c + off[j]] = t;
        }
        if (k) {
            uint32_t near = 0;
            for (int j = 0; j < 8; j++)
                near += (t - f->last[c + off[j]]) <= (ba ? ba : 2000u);
            f->last[c] = t;
            if (keep && near < k) {
                f->st.stc_removed++;
                keep = 0;
            }
        }
        if (keep && refr) {
            if (t - f->passed[c] < refr) {
                f->st.refractory_removed++;
                keep = 0;
            } else {
                f->passed[c] = t;
            }
        }
        if (keep)
            ev[out++] = e;
    }
    f->st.out += out;
    return out;
}

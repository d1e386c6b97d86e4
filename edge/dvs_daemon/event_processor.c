/* flytrack-edge's event processor (event_pipeline.h): each slice's events go through the noise
 * filters, then the cluster tracker with its Kalman filters (edge/events/algos, defaults of
 * flytrack/event_algos.h); the live clusters at the slice's end go out as DVS_CLUSTERS records. */
#include <math.h>
#include <stdlib.h>
#include <string.h>

#include "event_pipeline.h"
#include "flytrack/event_algos.h"

typedef struct {
    ft_noise_filter *nf;
    ft_cluster_tracker *ct;
    ft_event *buf; /* the slice's events, filtered in place (the caller's are const) */
    size_t cap;
} processor;

static size_t slice(void *ctx, const ft_event *ev, size_t n, int64_t t_start, int64_t t_end,
                    ft_dvs_cluster *out, size_t cap) {
    processor *p = ctx;
    (void)t_start;
    if (n > p->cap) {
        ft_event *b = realloc(p->buf, n * sizeof *b);
        if (!b)
            return 0; /* no memory this slice: no clusters, the next slice tries again */
        p->buf = b;
        p->cap = n;
    }
    memcpy(p->buf, ev, n * sizeof *ev);
    size_t kept = ft_nf_apply(p->nf, p->buf, n);
    ft_ct_feed(p->ct, p->buf, kept);
    ft_ct_cluster cl[FT_CT_MAX_CLUSTERS];
    size_t k =
        ft_ct_clusters(p->ct, t_end, cl, cap < FT_CT_MAX_CLUSTERS ? cap : FT_CT_MAX_CLUSTERS);
    for (size_t i = 0; i < k; i++) {
        out[i].id = cl[i].id;
        out[i].x = cl[i].x;
        out[i].y = cl[i].y;
        out[i].vx = cl[i].vx;
        out[i].vy = cl[i].vy;
        out[i].size = cl[i].size;
        out[i].mass = cl[i].mass;
        /* a covariance on the wire (SPEC 1.6): variances >= 0, |cov| <= sqrt(var_x var_y) */
        const float vx = cl[i].var_x > 0 ? cl[i].var_x : 0, vy = cl[i].var_y > 0 ? cl[i].var_y : 0;
        const float lim = 0.999f * sqrtf(vx * vy);
        out[i].var_x = vx;
        out[i].var_y = vy;
        out[i].cov_xy = cl[i].cov_xy > lim ? lim : cl[i].cov_xy < -lim ? -lim : cl[i].cov_xy;
    }
    return k;
}

static void destroy(void *ctx) {
    processor *p = ctx;
    ft_nf_destroy(p->nf);
    ft_ct_destroy(p->ct);
    free(p->buf);
    free(p);
}

int ft_event_processor_create(ft_event_processor *proc, uint32_t width, uint32_t height,
                              uint32_t ba_window_us, float min_mass) {
    ft_nf_params np;
    ft_ct_params cp;
    ft_nf_defaults(&np, width, height);
    ft_ct_defaults(&cp, width, height);
    if (ba_window_us > 0)
        np.ba_window_us = ba_window_us;
    if (min_mass > 0)
        cp.min_mass = min_mass;
    processor *p = calloc(1, sizeof *p);
    if (!p)
        return -1;
    p->nf = ft_nf_create(&np);
    p->ct = ft_ct_create(&cp);
    if (!p->nf || !p->ct) {
        destroy(p);
        return -1;
    }
    proc->ctx = p;
    proc->slice = slice;
    proc->destroy = destroy;
    return 0;
}

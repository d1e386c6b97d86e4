/* flytrack-edge's wing-beat mode (see edge_wingbeat.h). */
#include "edge_wingbeat.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#include "flytrack/udp.h"
#include "flytrack/wingbeat.h"
#include "util.h"

struct edge_wingbeat {
    ft_wb_tracker *t;
    uint16_t camera_index;
    int64_t report_us;
    int64_t next; /* event time of the next report */
    int have_next;
    int64_t last_t, last_report_t;
    int have_last;
    uint64_t failures_seen;
    int was_tracking;
    uint64_t reports;
    const uint32_t *seq;
    edge_wb_send_fn send;
    void *ctx;
    char msg[200];
};

edge_wingbeat *edge_wb_create(const edge_config *cfg, uint32_t width, uint32_t height,
                              const uint32_t *seq, edge_wb_send_fn send, void *ctx) {
    ft_wb_params p;
    ft_wb_defaults(&p, width, height);
    p.harmonics = (uint32_t)cfg->wingbeat_harmonics;
    p.events_per_update = (uint32_t)cfg->wingbeat_events_per_update;
    p.start_freq_hz = cfg->wingbeat_start_freq;
    p.init_us = (uint32_t)cfg->wingbeat_init_us;
    edge_wingbeat *w = calloc(1, sizeof *w);
    if (!w)
        return NULL;
    w->t = ft_wb_create(&p);
    if (!w->t) {
        edge_log("wing-beat tracker: bad parameters or no memory");
        free(w);
        return NULL;
    }
    w->camera_index = (uint16_t)cfg->camera_index;
    w->report_us = cfg->wingbeat_report_us;
    w->seq = seq;
    w->send = send;
    w->ctx = ctx;
    edge_log(
        "wing-beat mode: %ux%u sensor, fly found in the first %u us, EKF with %u harmonics, %u "
        "events per update; a DVS_WINGBEAT every %lld us of event time",
        width, height, p.init_us, p.harmonics, p.events_per_update, (long long)w->report_us);
    return w;
}

static void report(edge_wingbeat *w, int64_t t_us) {
    ft_dvs_wingbeat_hdr h;
    ft_wing_edge rec[6];
    memset(&h, 0, sizeof h);
    memset(rec, 0, sizeof rec);
    h.camera_index = w->camera_index;
    h.seq = *w->seq;
    h.t_us = (uint64_t)(t_us < 0 ? 0 : t_us);
    if (ft_wb_state(w->t) == FT_WB_TRACKING) {
        ft_wb_estimate wings[2], edges[4];
        ft_wb_wings(w->t, wings);
        ft_wb_edges(w->t, edges);
        for (int i = 0; i < 6; i++) {
            const ft_wb_estimate *s = i < 2 ? &wings[i] : &edges[i - 2];
            rec[i].edge_id = (uint8_t)i;
            rec[i].angle = s->angle;
            rec[i].amplitude = s->amplitude;
            rec[i].frequency = s->freq_hz;
            rec[i].phase = s->phase;
        }
        h.n_edges = 6;
    }
    struct timespec rt;
    clock_gettime(CLOCK_REALTIME, &rt);
    h.edge_done_ns = (uint64_t)rt.tv_sec * 1000000000ull + (uint64_t)rt.tv_nsec;
    uint8_t buf[FT_UDP_MAX_DATAGRAM];
    size_t len;
    if (ft_dvs_wingbeat_encode(buf, sizeof buf, &h, rec, &len) != FT_OK) {
        /* a diverged filter (non-finite state): say so and send the datagram without records */
        edge_log("wing-beat estimate not finite at t=%lld us: sent without records",
                 (long long)t_us);
        h.n_edges = 0;
        if (ft_dvs_wingbeat_encode(buf, sizeof buf, &h, rec, &len) != FT_OK)
            return;
    }
    w->send(w->ctx, buf, len);
    w->reports++;
    w->last_report_t = t_us;
}

/* After feeding: a new initialisation failure, or the fly just found. */
static const char *news(edge_wingbeat *w) {
    uint64_t fails;
    const char *err = ft_wb_last_error(w->t, &fails);
    int tracking = ft_wb_state(w->t) == FT_WB_TRACKING;
    if (tracking && !w->was_tracking) {
        w->was_tracking = 1;
        ft_wb_geometry g;
        ft_wb_get_geometry(w->t, &g);
        edge_log("wing-beat: fly found: body (%.1f, %.1f) px, heading %.1f deg, size %.1f px, "
                 "start frequency %.1f / %.1f Hz",
                 g.body_x, g.body_y, g.heading * 180.0 / M_PI, g.size_px, g.start_freq_hz[0],
                 g.start_freq_hz[1]);
        w->failures_seen = fails;
        return "";
    }
    if (fails != w->failures_seen) {
        /* every window's failure is news, but a log line per 0.1 s would drown the rest */
        if (w->failures_seen < 3 || fails / 50 != w->failures_seen / 50)
            edge_log("wing-beat: no fly in the initialisation window (%llu so far): %s; trying "
                     "the next window",
                     (unsigned long long)fails, err);
        w->failures_seen = fails;
        snprintf(w->msg, sizeof w->msg, "%s", err);
        return w->msg;
    }
    return NULL;
}

const char *edge_wb_take(edge_wingbeat *w, const ft_event *ev, size_t n) {
    const char *out = NULL, *m;
    size_t i = 0;
    while (i < n) {
        if (!w->have_next) {
            w->next = ev[i].t + w->report_us;
            w->have_next = 1;
        }
        size_t j = i;
        while (j < n && ev[j].t < w->next)
            j++;
        if (j > i) {
            ft_wb_feed(w->t, ev + i, j - i, NULL, 0);
            w->last_t = ev[j - 1].t;
            w->have_last = 1;
            if ((m = news(w)) != NULL)
                out = m;
        }
        if (j < n) {
            report(w, w->next);
            w->next += w->report_us;
            if (ev[j].t >= w->next) /* a gap in the events: the grid restarts after it */
                w->next = ev[j].t + w->report_us;
        }
        i = j;
    }
    return out;
}

void edge_wb_flush(edge_wingbeat *w) {
    uint64_t fails;
    ft_wb_last_error(w->t, &fails);
    if (w->have_last && ft_wb_state(w->t) != FT_WB_TRACKING && !fails)
        edge_log(
            "wing-beat: the events ended inside the first initialisation window: no fly found");
    if (w->have_last && (!w->reports || w->last_t > w->last_report_t))
        report(w, w->last_t);
}

void edge_wb_log_summary(const edge_wingbeat *w) {
    ft_wb_stats s;
    ft_wb_get_stats(w->t, &s);
    edge_log("wing-beat: %llu reports; %llu events, %llu near the fly, %llu filter updates, %llu "
             "gated, %llu beats; %llu of %llu initialisation windows found no fly",
             (unsigned long long)w->reports, (unsigned long long)s.events,
             (unsigned long long)s.in_roi, (unsigned long long)s.updates,
             (unsigned long long)s.gated, (unsigned long long)s.beats,
             (unsigned long long)s.init_failures, (unsigned long long)s.init_attempts);
}

void edge_wb_destroy(edge_wingbeat *w) {
    if (!w)
        return;
    ft_wb_destroy(w->t);
    free(w);
}

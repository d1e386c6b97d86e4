/* Wing-beat tracker of a tethered fly (see flytrack/wingbeat.h): the initialisation phase once per
 * window, then per event an angle, a running mean of events_per_update events, and one EKF update
 * of a fixed small size (at most 10 states). Mirrors flytrack_host.dvs.wingbeat step for step, so
 * the two can be checked against each other on the same events. */
#include "flytrack/wingbeat.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#define TWO_PI 6.283185307179586
#define NMAX (2 * FT_WB_MAX_HARMONICS + 2)
#define MIN_EVENTS 200 /* a window with fewer cannot hold two beating wings */
#define FIRES 4        /* a wing's pixel fires at every stroke; noise once or twice a window */
#define BIN_US 100.0   /* frequency search: mean angle per 0.1 ms */
#define LO_HZ 50.0
#define HI_HZ 1000.0
#define AMP_SAMPLES 96 /* h sampled over a beat for its amplitude */

typedef struct {
    int started;
    double x[NMAX];
    double P[NMAX][NMAX];
    double t_last; /* s */
    double cycle;
    int64_t sum_t; /* the events gathered for the next update */
    double sum_z;
    uint32_t count;
    uint64_t updates;
} edge_filter;

struct ft_wb_tracker {
    ft_wb_params p;
    int state;
    int n, ns; /* state size, shape part */
    double r, q[NMAX];
    /* initialisation window */
    ft_event *buf;
    size_t nbuf;
    int64_t win_start;
    int have_win;
    uint32_t *counts;
    double *xy;     /* kept events' positions */
    uint8_t *label; /* their 2-means cluster */
    double *ang;    /* their angles, per wing, for the percentiles */
    /* the fly */
    ft_wb_geometry g;
    double hx, hy;
    double size2_lo, size2_hi, inner2_lo, inner2_hi; /* squared radii with a margin either side */
    edge_filter e[4];
    /* beats of the current ft_wb_feed call */
    ft_wb_beat *out;
    size_t out_cap, out_n;
    char err[160];
    uint64_t failures;
    ft_wb_stats st;
};

void ft_wb_defaults(ft_wb_params *p, uint32_t width, uint32_t height) {
    memset(p, 0, sizeof *p);
    p->width = width;
    p->height = height;
    p->init_us = 100000;
    p->init_max_events = 131072;
    p->harmonics = 2;
    p->events_per_update = 4;
    p->measurement_std_rad = 0.06;
    p->q_centre = 0.05;
    p->q_shape = 1.0;
    p->q_phase = 2.0;
    p->q_omega = 4e3;
    p->gate_sigma = 4.0;
    p->initial_phase_std = M_PI;
    p->initial_freq_std_hz = 5.0;
    p->start_freq_hz = 0.0;
}

ft_wb_tracker *ft_wb_create(const ft_wb_params *p) {
    if (!p || p->width == 0 || p->height == 0 || p->width > 65536 || p->height > 65536 ||
        p->init_us == 0 || p->init_max_events < MIN_EVENTS || p->harmonics < 1 ||
        p->harmonics > FT_WB_MAX_HARMONICS || p->events_per_update < 1 ||
        !(p->measurement_std_rad > 0) || !(p->q_centre >= 0) || !(p->q_shape >= 0) ||
        !(p->q_phase >= 0) || !(p->q_omega >= 0) || !(p->gate_sigma > 0) ||
        !(p->initial_phase_std > 0) || !(p->initial_freq_std_hz > 0) || !(p->start_freq_hz >= 0) ||
        !isfinite(p->start_freq_hz))
        return NULL;
    ft_wb_tracker *t = calloc(1, sizeof *t);
    if (!t)
        return NULL;
    t->p = *p;
    size_t cap = p->init_max_events;
    t->buf = malloc(cap * sizeof *t->buf);
    t->counts = malloc((size_t)p->width * p->height * sizeof *t->counts);
    t->xy = malloc(2 * cap * sizeof *t->xy);
    t->label = malloc(cap);
    t->ang = malloc(cap * sizeof *t->ang);
    if (!t->buf || !t->counts || !t->xy || !t->label || !t->ang) {
        ft_wb_destroy(t);
        return NULL;
    }
    t->ns = 2 * (int)p->harmonics;
    t->n = t->ns + 2;
    t->r = p->measurement_std_rad * p->measurement_std_rad / p->events_per_update;
    t->q[0] = p->q_centre;
    for (int i = 1; i < t->ns; i++)
        t->q[i] = p->q_shape;
    t->q[t->ns] = p->q_phase;
    t->q[t->ns + 1] = p->q_omega;
    return t;
}

void ft_wb_destroy(ft_wb_tracker *t) {
    if (!t)
        return;
    free(t->buf);
    free(t->counts);
    free(t->xy);
    free(t->label);
    free(t->ang);
    free(t);
}

/* ---- initialisation ----------------------------------------------------------------------------
 */

static int fail(ft_wb_tracker *t, const char *msg) {
    snprintf(t->err, sizeof t->err, "%s", msg);
    t->failures++;
    t->st.init_failures++;
    return -1;
}

/* Eq. 8: angle from the heading about the body, folded to its side; -1 outside the region. */
static int event_angle(const ft_wb_tracker *t, double x, double y, double *ang) {
    double dx = x - t->g.body_x, dy = y - t->g.body_y;
    /* most events far outside (or inside) the region are told by r^2 alone; near its borders
     * hypot decides, exactly as the host's NumPy does */
    double r2 = dx * dx + dy * dy;
    if (r2 > t->size2_hi || r2 < t->inner2_lo)
        return -1;
    if (r2 > t->size2_lo || r2 < t->inner2_hi) {
        double r = hypot(dx, dy);
        if (r > t->g.size_px || r < t->g.inner_px)
            return -1;
    }
    double a = atan2(-dx * t->hy + dy * t->hx, dx * t->hx + dy * t->hy);
    *ang = fabs(a);
    return a >= 0.0 ? 0 : 1;
}

static int cmp_double(const void *a, const void *b) {
    double x = *(const double *)a, y = *(const double *)b;
    return (x > y) - (x < y);
}

/* NumPy's default (linear) percentile of sorted a[0..n). */
static double percentile(const double *a, size_t n, double q) {
    double v = (double)n * q + (1.0 - q) - 1.0;
    if (v <= 0)
        return a[0];
    if (v >= (double)(n - 1))
        return a[n - 1];
    size_t lo = (size_t)floor(v);
    double f = v - (double)lo, d = a[lo + 1] - a[lo];
    return f >= 0.5 ? a[lo + 1] - d * (1.0 - f) : a[lo] + d * f;
}

/* The beat frequency of one wing's window events: autocorrelation of the mean angle per bin. */
static int find_frequency(ft_wb_tracker *t, int wing, double *freq) {
    int64_t t0 = 0, t1 = 0;
    size_t cnt = 0;
    double a;
    for (size_t i = 0; i < t->nbuf; i++) {
        if (event_angle(t, t->buf[i].x, t->buf[i].y, &a) != wing)
            continue;
        if (!cnt)
            t0 = t->buf[i].t;
        t1 = t->buf[i].t;
        cnt++;
    }
    if (cnt < 50 || (double)(t1 - t0) < 3e6 / LO_HZ)
        return fail(
            t, "too short a window to estimate the wing-beat frequency (need 3 slowest beats)");
    size_t nb = (size_t)((double)(t1 - t0) / BIN_US) + 1;
    double *s = calloc(nb, sizeof *s), *c = calloc(nb, sizeof *c), *m = calloc(nb, sizeof *m);
    double *ac = malloc(nb * sizeof *ac);
    int rc = -1;
    if (!s || !c || !m || !ac) {
        fail(t, "no memory for the frequency search");
        goto out;
    }
    for (size_t i = 0; i < t->nbuf; i++) {
        if (event_angle(t, t->buf[i].x, t->buf[i].y, &a) != wing)
            continue;
        size_t k = (size_t)((double)(t->buf[i].t - t0) / BIN_US);
        s[k] += a;
        c[k] += 1.0;
    }
    double sum = 0;
    size_t used = 0;
    for (size_t k = 0; k < nb; k++)
        if (c[k] > 0) {
            m[k] = s[k] / c[k];
            sum += m[k];
            used++;
        }
    double mean = sum / (double)used;
    for (size_t k = 0; k < nb; k++)
        m[k] = c[k] > 0 ? m[k] - mean : 0.0;
    for (size_t k = 0; k < nb; k++) { /* the lags the search and the climb may look at */
        double v = 0;
        for (size_t i = 0; i + k < nb; i++)
            v += m[i] * m[i + k];
        ac[k] = v;
        if ((double)k * BIN_US * 1e-6 > 2.0 / LO_HZ)
            break; /* nothing past twice the slowest period is needed */
    }
    size_t kmax = 0, have = 0;
    double best = -INFINITY;
    for (size_t k = 0; k < nb; k++) {
        double lag = (double)k * BIN_US * 1e-6;
        if (lag >= 1.0 / HI_HZ && lag <= 1.0 / LO_HZ && ac[k] > best) {
            best = ac[k];
            have = 1;
        }
        if (lag > 1.0 / LO_HZ)
            break;
    }
    if (!have) {
        fail(t, "window too short for the frequency search");
        goto out;
    }
    for (size_t k = 0; k < nb; k++) { /* the first lag near the best: the period, not a multiple */
        double lag = (double)k * BIN_US * 1e-6;
        if (lag >= 1.0 / HI_HZ && lag <= 1.0 / LO_HZ && ac[k] >= 0.85 * best) {
            kmax = k;
            break;
        }
    }
    size_t limit = nb;
    for (size_t k = 0; k < nb; k++)
        if ((double)k * BIN_US * 1e-6 > 2.0 / LO_HZ) {
            limit = k + 1; /* ac computed up to here */
            break;
        }
    while (kmax + 1 < limit && ac[kmax + 1] > ac[kmax])
        kmax++;
    double kf = (double)kmax;
    if (kmax > 0 && kmax + 1 < limit) { /* parabolic refinement */
        double y0 = ac[kmax - 1], y1 = ac[kmax], y2 = ac[kmax + 1];
        double den = y0 - 2 * y1 + y2;
        kf += den != 0 ? 0.5 * (y0 - y2) / den : 0.0;
    }
    *freq = 1.0 / (kf * BIN_US * 1e-6);
    rc = isfinite(*freq) && *freq > 0 ? 0 : fail(t, "no wing-beat frequency found in the window");
out:
    free(s);
    free(c);
    free(m);
    free(ac);
    return rc;
}

static int initialise(ft_wb_tracker *t) {
    const uint32_t W = t->p.width, H = t->p.height;
    size_t n = t->nbuf;
    char msg[160];
    t->st.init_attempts++;
    if (n < MIN_EVENTS) {
        snprintf(msg, sizeof msg, "%zu events are too few to find the fly (need at least %d)", n,
                 MIN_EVENTS);
        return fail(t, msg);
    }
    memset(t->counts, 0, (size_t)W * H * sizeof *t->counts);
    for (size_t i = 0; i < n; i++)
        t->counts[(size_t)t->buf[i].y * W + t->buf[i].x]++;
    size_t nk = 0;
    for (size_t i = 0; i < n; i++)
        if (t->counts[(size_t)t->buf[i].y * W + t->buf[i].x] >= FIRES) {
            t->xy[2 * nk] = t->buf[i].x;
            t->xy[2 * nk + 1] = t->buf[i].y;
            nk++;
        }
    if (nk < 100 || (double)nk / (double)n < 0.2)
        return fail(t, "no pixel fires repeatedly in the window: no beating wing in view");
    /* 2-means, prototypes at the upper-right and lower-left corners */
    double proto[2][2] = {{W - 1.0, 0.0}, {0.0, H - 1.0}};
    for (int it = 0; it < 50; it++) {
        int changed = 0;
        double sx[2] = {0, 0}, sy[2] = {0, 0};
        size_t cnt[2] = {0, 0};
        for (size_t i = 0; i < nk; i++) {
            double x = t->xy[2 * i], y = t->xy[2 * i + 1];
            double d0 =
                (x - proto[0][0]) * (x - proto[0][0]) + (y - proto[0][1]) * (y - proto[0][1]);
            double d1 =
                (x - proto[1][0]) * (x - proto[1][0]) + (y - proto[1][1]) * (y - proto[1][1]);
            uint8_t l = d1 < d0;
            if (it == 0 || l != t->label[i])
                changed = 1;
            t->label[i] = l;
            sx[l] += x;
            sy[l] += y;
            cnt[l]++;
        }
        if (it && !changed)
            break;
        for (int k = 0; k < 2; k++)
            if (cnt[k]) {
                proto[k][0] = sx[k] / (double)cnt[k];
                proto[k][1] = sy[k] / (double)cnt[k];
            }
    }
    size_t n1 = 0;
    for (size_t i = 0; i < nk; i++)
        n1 += t->label[i];
    size_t n0 = nk - n1;
    if ((double)(n0 < n1 ? n0 : n1) < 0.1 * (double)nk) {
        snprintf(msg, sizeof msg,
                 "the events form one cluster (%zu / %zu): two beating wings are not in view", n0,
                 n1);
        return fail(t, msg);
    }
    double bx = 0.5 * (proto[0][0] + proto[1][0]), by = 0.5 * (proto[0][1] + proto[1][1]);
    double half = hypot(proto[0][0] - bx, proto[0][1] - by);
    if (half < 2.0)
        return fail(t, "the two wing clusters coincide: two beating wings are not in view");
    double ax = (proto[0][0] - proto[1][0]) / (2.0 * half);
    double ay = (proto[0][1] - proto[1][1]) / (2.0 * half);
    double px = -ay, py = ax;
    size_t pos = 0, neg = 0;
    for (size_t i = 0; i < nk; i++) {
        double dx = t->xy[2 * i] - bx, dy = t->xy[2 * i + 1] - by;
        if (hypot(dx, dy) > 2.0 * half)
            continue;
        double side = dx * px + dy * py;
        pos += side > 0;
        neg += side < 0;
    }
    if (pos > neg) { /* the tail is where more wing events fall */
        px = -px;
        py = -py;
    }
    t->g.body_x = bx;
    t->g.body_y = by;
    t->g.heading = atan2(py, px);
    t->g.size_px = 2.0 * half;
    t->g.inner_px = 0.15 * half;
    t->hx = cos(t->g.heading);
    t->hy = sin(t->g.heading);
    t->size2_lo = t->g.size_px * t->g.size_px * (1 - 1e-9);
    t->size2_hi = t->g.size_px * t->g.size_px * (1 + 1e-9);
    t->inner2_lo = t->g.inner_px * t->g.inner_px * (1 - 1e-9);
    t->inner2_hi = t->g.inner_px * t->g.inner_px * (1 + 1e-9);
    for (int w = 0; w < 2; w++) {
        size_t na = 0;
        double sum = 0, a;
        for (size_t i = 0; i < nk; i++)
            if (event_angle(t, t->xy[2 * i], t->xy[2 * i + 1], &a) == w) {
                t->ang[na++] = a;
                sum += a;
            }
        if (na < 20) {
            snprintf(msg, sizeof msg, "too few events on wing %d after initialisation (%zu)", w,
                     na);
            return fail(t, msg);
        }
        qsort(t->ang, na, sizeof *t->ang, cmp_double);
        t->g.mean_stroke[w] = sum / (double)na;
        t->g.spread[w] = 0.5 * (percentile(t->ang, na, 0.95) - percentile(t->ang, na, 0.05));
    }
    for (int w = 0; w < 2; w++) {
        if (t->p.start_freq_hz > 0)
            t->g.start_freq_hz[w] = t->p.start_freq_hz;
        else if (find_frequency(t, w, &t->g.start_freq_hz[w]))
            return -1;
    }
    return 0;
}

/* ---- the EKF of one edge ------------------------------------------------------------------------
 */

static double shape_at(const ft_wb_tracker *t, const double *x, double xi) {
    double s1 = sin(xi), c1 = cos(xi), s = s1, c = c1;
    double h = x[0] + x[1] * s1;
    for (int j = 2; j <= (int)t->p.harmonics; j++) {
        double sn = s * c1 + c * s1, cn = c * c1 - s * s1;
        s = sn;
        c = cn;
        h += x[2 * j - 2] * s + x[2 * j - 1] * c;
    }
    return h;
}

static double shape_amplitude(const ft_wb_tracker *t, const double *x) {
    if (t->p.harmonics == 1)
        return fabs(x[1]);
    double lo = INFINITY, hi = -INFINITY;
    for (int i = 0; i < AMP_SAMPLES; i++) {
        double h = shape_at(t, x, (double)i * (TWO_PI / AMP_SAMPLES));
        lo = h < lo ? h : lo;
        hi = h > hi ? h : hi;
    }
    return 0.5 * (hi - lo);
}

static void emit_beat(ft_wb_tracker *t, int k, double t_s) {
    const edge_filter *f = &t->e[k];
    t->st.beats++;
    if (!t->out || t->out_n >= t->out_cap) {
        t->st.beats_dropped++;
        return;
    }
    ft_wb_beat *b = &t->out[t->out_n++];
    memset(b, 0, sizeof *b);
    b->t_us = (int64_t)llround(t_s * 1e6);
    b->wing = (uint8_t)(k / 2);
    b->edge = (uint8_t)(k % 2);
    b->freq_hz = (float)(f->x[t->ns + 1] / TWO_PI);
    b->amplitude = (float)shape_amplitude(t, f->x);
}

static void ekf_update(ft_wb_tracker *t, int k, double ts, double z) {
    edge_filter *f = &t->e[k];
    const int n = t->n, ixi = t->ns, iom = t->ns + 1;
    double *x = f->x;
    double(*P)[NMAX] = f->P;
    if (!f->started) {
        int w = k / 2;
        double centre = t->g.mean_stroke[w], amp = t->g.spread[w];
        memset(x, 0, sizeof f->x);
        memset(P, 0, sizeof f->P);
        x[0] = centre;
        x[1] = amp;
        x[iom] = TWO_PI * t->g.start_freq_hz[w];
        double u = (z - centre) / (amp > 1e-6 ? amp : 1e-6);
        x[ixi] = asin(u < -1 ? -1 : u > 1 ? 1 : u);
        P[0][0] = 0.1 * 0.1;
        for (int i = 1; i < t->ns; i++)
            P[i][i] = 0.3 * 0.3;
        P[ixi][ixi] = t->p.initial_phase_std * t->p.initial_phase_std;
        P[iom][iom] = (TWO_PI * t->p.initial_freq_std_hz) * (TWO_PI * t->p.initial_freq_std_hz);
        f->t_last = ts;
        f->cycle = floor(x[ixi] / TWO_PI);
        f->started = 1;
    }
    double dt = ts - f->t_last;
    if (dt > 0.0) { /* eq. 10: only the phase moves; F P F^T + Q dt */
        x[ixi] += x[iom] * dt;
        for (int j = 0; j < n; j++)
            P[ixi][j] += dt * P[iom][j];
        for (int j = 0; j < n; j++)
            P[j][ixi] += dt * P[j][iom];
        for (int j = 0; j < n; j++)
            P[j][j] += t->q[j] * dt;
        f->t_last = ts;
        double c = floor(x[ixi] / TWO_PI);
        if (c != f->cycle) {
            f->cycle = c;
            emit_beat(t, k, ts);
        }
    }
    double H[NMAX] = {0}, PH[NMAX];
    double xi = x[ixi], s1 = sin(xi), c1 = cos(xi), s = s1, c = c1;
    H[0] = 1.0;
    H[1] = s1;
    double h = x[0] + x[1] * s1, dxi = x[1] * c1;
    for (int j = 2; j <= (int)t->p.harmonics; j++) {
        double sn = s * c1 + c * s1, cn = c * c1 - s * s1;
        s = sn;
        c = cn;
        H[2 * j - 2] = s;
        H[2 * j - 1] = c;
        double bj = x[2 * j - 2], cj = x[2 * j - 1];
        h += bj * s + cj * c;
        dxi += j * (bj * c - cj * s);
    }
    H[ixi] = dxi;
    double y = z - h, sv = t->r;
    for (int i = 0; i < n; i++) {
        double v = 0;
        for (int j = 0; j < n; j++)
            v += P[i][j] * H[j];
        PH[i] = v;
        sv += H[i] * v;
    }
    if (y * y > t->p.gate_sigma * t->p.gate_sigma * sv) {
        t->st.gated++;
        return;
    }
    for (int i = 0; i < n; i++) {
        double g = PH[i] / sv;
        x[i] += g * y;
        for (int j = 0; j < n; j++)
            P[i][j] -= g * PH[j];
    }
    for (int i = 0; i < n; i++) /* kept symmetric */
        for (int j = i + 1; j < n; j++) {
            double v = 0.5 * (P[i][j] + P[j][i]);
            P[i][j] = P[j][i] = v;
        }
    f->updates++;
    t->st.updates++;
}

static void track(ft_wb_tracker *t, const ft_event *ev) {
    double z;
    int w = event_angle(t, ev->x, ev->y, &z);
    if (w < 0)
        return;
    t->st.in_roi++;
    int k = 2 * w + (ev->p ? 1 : 0);
    edge_filter *f = &t->e[k];
    f->sum_t += ev->t;
    f->sum_z += z;
    if (++f->count == t->p.events_per_update) {
        double m = (double)t->p.events_per_update;
        double ts = (double)f->sum_t / m * 1e-6, zz = f->sum_z / m;
        f->sum_t = 0;
        f->sum_z = 0;
        f->count = 0;
        ekf_update(t, k, ts, zz);
    }
}

size_t ft_wb_feed(ft_wb_tracker *t, const ft_event *ev, size_t n, ft_wb_beat *beats, size_t cap) {
    t->out = beats;
    t->out_cap = beats ? cap : 0;
    t->out_n = 0;
    for (size_t i = 0; i < n; i++) {
        t->st.events++;
        if (ev[i].x >= t->p.width || ev[i].y >= t->p.height) {
            t->st.bad_events++;
            continue;
        }
        if (t->state == FT_WB_INITIALISING) {
            if (!t->have_win) {
                t->win_start = ev[i].t;
                t->have_win = 1;
            }
            if (ev[i].t >= t->win_start + (int64_t)t->p.init_us ||
                t->nbuf == t->p.init_max_events) {
                if (initialise(t) == 0) {
                    t->state = FT_WB_TRACKING;
                    for (size_t j = 0; j < t->nbuf; j++) /* the window's events are not lost */
                        track(t, &t->buf[j]);
                    t->nbuf = 0;
                } else {
                    t->nbuf = 0;
                    t->win_start = ev[i].t;
                }
            }
            if (t->state == FT_WB_INITIALISING) {
                t->buf[t->nbuf++] = ev[i];
                continue;
            }
        }
        track(t, &ev[i]);
    }
    t->out = NULL;
    return t->out_n;
}

int ft_wb_state(const ft_wb_tracker *t) {
    return t->state;
}

const char *ft_wb_last_error(const ft_wb_tracker *t, uint64_t *failures) {
    if (failures)
        *failures = t->failures;
    return t->err;
}

int ft_wb_get_geometry(const ft_wb_tracker *t, ft_wb_geometry *g) {
    if (t->state != FT_WB_TRACKING)
        return -1;
    *g = t->g;
    return 0;
}

void ft_wb_edges(const ft_wb_tracker *t, ft_wb_estimate out[4]) {
    for (int k = 0; k < 4; k++) {
        const edge_filter *f = &t->e[k];
        memset(&out[k], 0, sizeof out[k]);
        if (!f->started)
            continue;
        double xi = f->x[t->ns];
        out[k].angle = (float)shape_at(t, f->x, xi);
        out[k].amplitude = (float)shape_amplitude(t, f->x);
        out[k].freq_hz = (float)(f->x[t->ns + 1] / TWO_PI);
        out[k].phase = (float)(xi - TWO_PI * floor(xi / TWO_PI));
        out[k].updates = f->updates;
    }
}

void ft_wb_wings(const ft_wb_tracker *t, ft_wb_estimate out[2]) {
    ft_wb_estimate e[4];
    ft_wb_edges(t, e);
    for (int w = 0; w < 2; w++) {
        const ft_wb_estimate *a = &e[2 * w], *b = &e[2 * w + 1];
        memset(&out[w], 0, sizeof out[w]);
        int na = a->updates > 0, nb = b->updates > 0;
        if (!na && !nb)
            continue;
        float k = (float)(na + nb);
        out[w].angle = ((na ? a->angle : 0) + (nb ? b->angle : 0)) / k;
        out[w].amplitude = ((na ? a->amplitude : 0) + (nb ? b->amplitude : 0)) / k;
        out[w].freq_hz = ((na ? a->freq_hz : 0) + (nb ? b->freq_hz : 0)) / k;
        out[w].phase = na ? a->phase : b->phase;
        out[w].updates = a->updates + b->updates;
    }
}

void ft_wb_get_stats(const ft_wb_tracker *t, ft_wb_stats *s) {
    *s = t->st;
}

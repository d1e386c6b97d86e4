/* Cluster tracker with a Kalman filter per cluster (see flytrack/event_algos.h).
 *
 * Per event: the nearest cluster containing it moves by eq. 1 and gains mass, or a new cluster
 * starts. Everything else (mass decay to the tick, death, merging, velocities, the Kalman filter)
 * runs once per kf_interval_us of event time over at most max_clusters clusters, so the per-event
 * work is a scan of a few centres. */
#include "flytrack/event_algos.h"

#include <math.h>
#include <stdlib.h>
#include <string.h>

/* A cluster whose decayed mass falls under this has had no event lately: it dies. */
#define DEATH_MASS 0.5f

typedef struct {
    int alive;
    uint32_t id;
    float x, y, vx, vy, mass;
    int64_t t_mass; /* time the mass was last brought up to date */
    float px, py;   /* centre at the last tick, for the velocity */
    uint32_t events;
    /* the events taken since the last tick: count and sums (kf_centroid's measurement) */
    uint32_t nk, nall; /* gated for the centroid, all */
    uint32_t misses;   /* ticks in a row with events but none in the centroid's gate */
    double sx, sy, sxx, syy;
    /* Kalman filter, state (y, y', x, x') as the seed writes it */
    int tracking;
    float s[4];
    float P[4][4];
    uint32_t updates;
} cluster;

struct ft_cluster_tracker {
    ft_ct_params p;
    cluster c[FT_CT_MAX_CLUSTERS];
    uint32_t next_id;
    int64_t next_tick, last_tick;
    int started;
    ft_ct_stats st;
};

void ft_ct_defaults(ft_ct_params *p, uint32_t width, uint32_t height) {
    memset(p, 0, sizeof *p);
    p->width = width;
    p->height = height;
    p->max_clusters = 10;
    p->radius_px = 0.1f * (float)(width > height ? width : height);
    p->mixing = 0.05f;
    p->mass_decay_us = 10000;
    p->min_mass = 5.0f;
    p->merge_max_dv = 200.0f;
    p->velocity_tau_us = 5000.0f;
    p->kalman = 1;
    p->kf_interval_us = 1000;
    p->feedback = 0;
    p->dynamic_variances = 1;
    p->kf_ramp = 50;
    p->events_until_track = 0;
    p->max_meas_var = 1.0f;
    p->min_proc_var = 2500.0f;
    p->kf_centroid = 1;
    p->centroid_var = 0.5f;
    p->centroid_gate_px = 4.0f;
}

ft_cluster_tracker *ft_ct_create(const ft_ct_params *p) {
    if (!p || p->max_clusters == 0 || p->max_clusters > FT_CT_MAX_CLUSTERS || !(p->radius_px > 0) ||
        !(p->mixing > 0 && p->mixing <= 1) || p->mass_decay_us == 0 || p->kf_interval_us == 0 ||
        !(p->max_meas_var > 0) || !(p->min_proc_var > 0) || !(p->velocity_tau_us > 0) ||
        !(p->centroid_var >= 0))
        return NULL;
    ft_cluster_tracker *t = calloc(1, sizeof *t);
    if (!t)
        return NULL;
    t->p = *p;
    t->next_id = 1;
    return t;
}

void ft_ct_destroy(ft_cluster_tracker *t) {
    free(t);
}

void ft_ct_get_stats(const ft_cluster_tracker *t, ft_ct_stats *s) {
    *s = t->st;
}

/* exp(-dt / tau), cheap for the usual small steps. */
static float decay(int64_t dt, uint32_t tau) {
    float u = (float)dt / (float)tau;
    if (u <= 0.0f)
        return 1.0f;
    if (u < 0.05f)
        return 1.0f - u + 0.5f * u * u;
    return expf(-u);
}

static void kf_start(ft_cluster_tracker *t, cluster *c) {
    const float r = t->p.max_meas_var;
    memset(c->P, 0, sizeof c->P);
    c->s[0] = c->y;
    c->s[1] = 0.0f; /* velocity unknown: 0 with a large variance (the seed's start) */
    c->s[2] = c->x;
    c->s[3] = 0.0f;
    c->P[0][0] = c->P[2][2] = r;
    c->P[1][1] = c->P[3][3] = 1e4f;
    c->updates = 0;
    c->tracking = 1;
}

/* The filter's measurement at a tick: the cluster's centre with the seed's measurement variance
 * (kf_centroid 0), or the centroid of the events the cluster took since the last tick, whose
 * variance per axis is the events' spread over their number, plus a pixel's quantisation (1/12
 * px^2). The centre follows events by the mixing factor, so it trails a moving animal by about
 * (1 - m) / m events (a few px at a few hundred events/s); the centroid does not trail. Returns 0
 * when there is nothing to measure (no event since the last tick). */
static int kf_measure(const ft_cluster_tracker *t, const cluster *c, float *zy, float *zx,
                      float *ry, float *rx) {
    float ramp =
        t->p.dynamic_variances && t->p.kf_ramp ? (float)c->updates / (float)t->p.kf_ramp : 1.0f;
    if (ramp > 1.0f)
        ramp = 1.0f;
    if (!t->p.kf_centroid) {
        *zy = c->y;
        *zx = c->x;
        *ry = *rx =
            t->p.dynamic_variances ? t->p.max_meas_var * (0.1f + 0.9f * ramp) : t->p.max_meas_var;
        return 1;
    }
    if (c->nk == 0)
        return 0;
    const double n = (double)c->nk, my = c->sy / n, mx = c->sx / n;
    double vy = c->syy / n - my * my, vx = c->sxx / n - mx * mx;
    /* one or two events say little about the spread: at least half a pixel squared */
    vy = vy > 0.5 ? vy : 0.5;
    vx = vx > 0.5 ? vx : 0.5;
    *zy = (float)my;
    *zx = (float)mx;
    *ry = (float)(vy / n + 1.0 / 12.0);
    *rx = (float)(vx / n + 1.0 / 12.0);
    return 1;
}

/* Predict by dt (s) and update with the measurement (eqs 2-6). The seed's eq. 2 prints the
 * velocity entries as dt; the constant-velocity transition is y += dt y', x += dt x'. */
static void kf_step(ft_cluster_tracker *t, cluster *c, float dt) {
    float ramp =
        t->p.dynamic_variances && t->p.kf_ramp ? (float)c->updates / (float)t->p.kf_ramp : 1.0f;
    if (ramp > 1.0f)
        ramp = 1.0f;
    const float q =
        t->p.dynamic_variances ? t->p.min_proc_var * (10.0f - 9.0f * ramp) : t->p.min_proc_var;
    float(*P)[4] = c->P;
    /* x' = F x */
    c->s[0] += dt * c->s[1];
    c->s[2] += dt * c->s[3];
    /* P = F P F^T + Q: the two 2x2 blocks (y, y') and (x, x') and their cross terms */
    for (int i = 0; i < 4; i += 2) {
        for (int j = 0; j < 4; j++) /* rows: P[i] += dt P[i+1] */
            P[i][j] += dt * P[i + 1][j];
        for (int j = 0; j < 4; j++) /* columns */
            P[j][i] += dt * P[j][i + 1];
    }
    P[1][1] += q * dt;
    P[3][3] += q * dt;
    P[0][0] += 0.01f * q * dt * dt; /* a little on the positions keeps P well conditioned */
    P[2][2] += 0.01f * q * dt * dt;
    float zy, zx, ry, rx;
    if (!kf_measure(t, c, &zy, &zx, &ry, &rx))
        return; /* no event since the last tick: the prediction only */
    /* S = H P H^T + R, H picks y (0) and x (2) */
    const float s00 = P[0][0] + ry, s01 = P[0][2], s11 = P[2][2] + rx;
    const float det = s00 * s11 - s01 * s01;
    if (!(det > 0.0f))
        return;
    const float i00 = s11 / det, i01 = -s01 / det, i11 = s00 / det;
    float K[4][2];
    for (int i = 0; i < 4; i++) {
        K[i][0] = P[i][0] * i00 + P[i][2] * i01;
        K[i][1] = P[i][0] * i01 + P[i][2] * i11;
    }
    const float ey = zy - c->s[0], ex = zx - c->s[2];
    for (int i = 0; i < 4; i++)
        c->s[i] += K[i][0] * ey + K[i][1] * ex;
    /* P = (I - K H) P, then symmetrised */
    float N[4][4];
    for (int i = 0; i < 4; i++)
        for (int j = 0; j < 4; j++)
            N[i][j] = P[i][j] - (K[i][0] * P[0][j] + K[i][1] * P[2][j]);
    for (int i = 0; i < 4; i++)
        for (int j = 0; j < 4; j++)
            P[i][j] = 0.5f * (N[i][j] + N[j][i]);
    c->updates++;
    t->st.kf_updates++;
    if (t->p.feedback) {
        c->y = c->s[0];
        c->x = c->s[2];
    }
}

/* The periodic work at event time `now`. */
static void tick(ft_cluster_tracker *t, int64_t now) {
    const float dt = (float)(now - t->last_tick) * 1e-6f;
    const float a =
        dt > 0 ? 1.0f - decay(now - t->last_tick, (uint32_t)t->p.velocity_tau_us) : 0.0f;
    const uint32_t n = t->p.max_clusters;
    for (uint32_t i = 0; i < n; i++) {
        cluster *c = &t->c[i];
        if (!c->alive)
            continue;
        c->mass *= decay(now - c->t_mass, t->p.mass_decay_us);
        c->t_mass = now;
        if (c->mass < DEATH_MASS) {
            c->alive = 0;
            t->st.died++;
            continue;
        }
        if (dt > 0) {
            c->vx += a * ((c->x - c->px) / dt - c->vx);
            c->vy += a * ((c->y - c->py) / dt - c->vy);
        }
        c->px = c->x;
        c->py = c->y;
    }
    /* Merge near clusters that move alike into the heavier one. */
    for (uint32_t i = 0; i < n; i++) {
        cluster *ci = &t->c[i];
        if (!ci->alive)
            continue;
        for (uint32_t j = i + 1; j < n; j++) {
            cluster *cj = &t->c[j];
            if (!cj->alive)
                continue;
            const float dx = ci->x - cj->x, dy = ci->y - cj->y, lim = t->p.radius_px;
            if (dx * dx + dy * dy >= lim * lim)
                continue;
            const float dvx = ci->vx - cj->vx, dvy = ci->vy - cj->vy;
            if (dvx * dvx + dvy * dvy > t->p.merge_max_dv * t->p.merge_max_dv)
                continue;
            cluster *keep = ci->mass >= cj->mass ? ci : cj, *gone = keep == ci ? cj : ci;
            const float w = keep->mass + gone->mass;
            keep->x = (keep->x * keep->mass + gone->x * gone->mass) / w;
            keep->y = (keep->y * keep->mass + gone->y * gone->mass) / w;
            keep->px = keep->x;
            keep->py = keep->y;
            keep->mass = w;
            keep->events += gone->events;
            gone->alive = 0;
            t->st.merged++;
            if (gone == ci)
                break;
        }
    }
    if (t->p.kalman && t->st.events >= t->p.events_until_track) {
        for (uint32_t i = 0; i < n; i++) {
            cluster *c = &t->c[i];
            if (!c->alive || c->mass < t->p.min_mass)
                continue;
            /* the filter lost its animal (events keep coming, none near it): start again at the
             * cluster's centre */
            c->misses = c->nall && !c->nk ? c->misses + 1 : 0;
            if (!c->tracking || (t->p.kf_centroid && c->misses >= 3)) {
                kf_start(t, c);
                c->misses = 0;
            } else {
                kf_step(t, c, dt);
            }
        }
    }
    for (uint32_t i = 0; i < n; i++) {
        t->c[i].nk = t->c[i].nall = 0;
        t->c[i].sx = t->c[i].sy = t->c[i].sxx = t->c[i].syy = 0.0;
    }
    t->last_tick = now;
}

/* kf_centroid's measurement gate: once a cluster's filter runs, only the events near where the
 * filter puts the animal at the event's time count towards the centroid (3 sigma of its position,
 * at least centroid_gate_px). The a priori radius is many animals wide: without the gate a second
 * animal inside it pulls the centroid between the two. The events outside still move the cluster
 * (eq. 1) and feed its mass. */
static int centroid_gate(const ft_cluster_tracker *t, const cluster *c, float ex, float ey,
                         int64_t t_us) {
    if (!c->tracking || !(t->p.centroid_gate_px > 0))
        return 1;
    const float dt = t_us > t->last_tick ? (float)(t_us - t->last_tick) * 1e-6f : 0.0f;
    const float dy = ey - (c->s[0] + dt * c->s[1]), dx = ex - (c->s[2] + dt * c->s[3]);
    const float g0 = t->p.centroid_gate_px * t->p.centroid_gate_px;
    const float g = 4.5f * (c->P[0][0] + c->P[2][2]); /* 3 sigma, both axes' mean variance */
    return dx * dx + dy * dy <= (g > g0 ? g : g0);
}

void ft_ct_feed(ft_cluster_tracker *t, const ft_event *ev, size_t n) {
    const uint32_t nc = t->p.max_clusters;
    const float r2 = t->p.radius_px * t->p.radius_px, m = t->p.mixing;
    if (n && !t->started) {
        t->started = 1;
        t->last_tick = ev[0].t;
        t->next_tick = ev[0].t + t->p.kf_interval_us;
    }
    for (size_t i = 0; i < n; i++) {
        const ft_event e = ev[i];
        while (e.t >= t->next_tick) {
            tick(t, t->next_tick);
            t->next_tick += t->p.kf_interval_us;
            if (e.t - t->next_tick > (int64_t)t->p.mass_decay_us * 20) /* a long gap: skip ahead */
                t->next_tick = e.t - (e.t - t->next_tick) % t->p.kf_interval_us;
        }
        const float ex = (float)e.x, ey = (float)e.y;
        cluster *best = NULL;
        float bd = r2;
        int free_slot = -1;
        for (uint32_t j = 0; j < nc; j++) {
            cluster *c = &t->c[j];
            if (!c->alive) {
                if (free_slot < 0)
                    free_slot = (int)j;
                continue;
            }
            const float dx = ex - c->x, dy = ey - c->y, d = dx * dx + dy * dy;
            if (d < bd) {
                bd = d;
                best = c;
            }
        }
        t->st.events++;
        if (best) {
            best->x += m * (ex - best->x);
            best->y += m * (ey - best->y);
            best->mass = best->mass * decay(e.t - best->t_mass, t->p.mass_decay_us) + 1.0f;
            best->t_mass = e.t;
            best->events++;
            best->nall++;
            if (centroid_gate(t, best, ex, ey, e.t)) {
                best->nk++;
                best->sx += ex;
                best->sy += ey;
                best->sxx += (double)ex * ex;
                best->syy += (double)ey * ey;
            }
        } else if (free_slot >= 0) {
            cluster *c = &t->c[free_slot];
            memset(c, 0, sizeof *c);
            c->alive = 1;
            c->id = t->next_id++;
            c->x = c->px = ex;
            c->y = c->py = ey;
            c->mass = 1.0f;
            c->t_mass = e.t;
            c->events = 1;
            c->nk = 1;
            c->sx = ex;
            c->sy = ey;
            c->sxx = (double)ex * ex;
            c->syy = (double)ey * ey;
            t->st.created++;
        } else {
            t->st.unassigned++;
        }
    }
}

size_t ft_ct_clusters(ft_cluster_tracker *t, int64_t t_us, ft_ct_cluster *out, size_t cap) {
    size_t k = 0;
    for (uint32_t i = 0; i < t->p.max_clusters && k < cap; i++) {
        cluster *c = &t->c[i];
        if (!c->alive)
            continue;
        const float mass = c->mass * decay(t_us - c->t_mass, t->p.mass_decay_us);
        if (mass < t->p.min_mass)
            continue;
        ft_ct_cluster *o = &out[k++];
        o->id = c->id;
        o->size = t->p.radius_px;
        o->mass = mass;
        o->events = c->events;
        o->tracking = c->tracking;
        if (c->tracking) {
            /* the filter predicted from its last tick to t_us (state and covariance) */
            const float dt = t_us > t->last_tick ? (float)(t_us - t->last_tick) * 1e-6f : 0.0f;
            const float(*P)[4] = (const float(*)[4])c->P;
            o->y = c->s[0] + dt * c->s[1];
            o->vy = c->s[1];
            o->x = c->s[2] + dt * c->s[3];
            o->vx = c->s[3];
            o->var_y = P[0][0] + 2.0f * dt * P[0][1] + dt * dt * P[1][1];
            o->var_x = P[2][2] + 2.0f * dt * P[2][3] + dt * dt * P[3][3];
            o->cov_xy = P[0][2] + dt * (P[0][3] + P[1][2]) + dt * dt * P[1][3];
            if (t->p.kf_centroid) {
                o->var_x += t->p.centroid_var;
                o->var_y += t->p.centroid_var;
            }
        } else {
            o->x = c->x;
            o->y = c->y;
            o->vx = c->vx;
            o->vy = c->vy;
            /* No filter yet: the centre is known to about a quarter of the radius squared (a
             * uniform disc's variance per axis). */
            o->var_x = o->var_y = 0.25f * t->p.radius_px * t->p.radius_px;
            o->cov_xy = 0.0f;
        }
    }
    return k;
}

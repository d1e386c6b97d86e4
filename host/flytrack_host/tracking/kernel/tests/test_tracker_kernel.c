/* The tracker kernel on random frames under ASan + UBSan: plausible and absurd cameras, states and
 * points (NaN, inf, huge, denormal), every buffer sized exactly to its capacity so that any overrun
 * is caught. Checks the invariants the Python side relies on and the argument checks. */
#include "tracker_kernel.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

static uint64_t rng_state = 0x9e3779b97f4a7c15ull;
static uint64_t next_u64(void) {
    rng_state ^= rng_state << 13;
    rng_state ^= rng_state >> 7;
    rng_state ^= rng_state << 17;
    return rng_state;
}
static double unif(double lo, double hi) {
    return lo + (hi - lo) * (double)(next_u64() >> 11) / 9007199254740992.0;
}
static double wild(double lo, double hi) {
    switch (next_u64() % 24) {
    case 0:
        return NAN;
    case 1:
        return INFINITY;
    case 2:
        return -INFINITY;
    case 3:
        return 1e300;
    case 4:
        return 4.9e-324;
    case 5:
        return 0.0;
    default:
        return unif(lo, hi);
    }
}

/* Doubles out of float range become +-inf (a cast would be undefined behaviour). */
static float tof(double d) {
    if (d > 3.4e38)
        return INFINITY;
    if (d < -3.4e38)
        return -INFINITY;
    return (float)d;
}

static int failures = 0;
#define CHECK(cond)                                                                                \
    do {                                                                                           \
        if (!(cond)) {                                                                             \
            fprintf(stderr, "%s:%d: check failed: %s\n", __FILE__, __LINE__, #cond);               \
            failures++;                                                                            \
        }                                                                                          \
    } while (0)

static void *xcalloc(size_t n, size_t size) {
    void *p = calloc(n ? n : 1, size);
    if (!p) {
        perror("calloc");
        exit(2);
    }
    return p;
}

typedef struct {
    ftk_buffers b;
    double *cams;
} rig;

static void make_rig(rig *r, int64_t C, int64_t tcap, int64_t ncap, int absurd) {
    ftk_buffers *b = &r->b;
    memset(b, 0, sizeof *b);
    b->n_cameras = C;
    b->t_cap = tcap;
    b->n_cap = ncap;
    b->scratch_len = ftk_scratch_len(C, tcap);
    b->x = xcalloc((size_t)(6 * tcap), sizeof(double));
    b->P = xcalloc((size_t)(36 * tcap), sizeof(double));
    b->area = xcalloc((size_t)tcap, sizeof(double));
    b->n_obs = xcalloc((size_t)tcap, sizeof(int64_t));
    b->axis = xcalloc((size_t)(3 * tcap), sizeof(double));
    b->slot = xcalloc((size_t)ncap, sizeof(int64_t));
    b->index = xcalloc((size_t)ncap, sizeof(int64_t));
    b->rank = xcalloc((size_t)ncap, sizeof(int64_t));
    b->starts = xcalloc((size_t)(C + 1), sizeof(int64_t));
    b->uv = xcalloc((size_t)(2 * ncap), sizeof(double));
    b->uvi = xcalloc((size_t)(2 * ncap), sizeof(double));
    b->parea = xcalloc((size_t)ncap, sizeof(double));
    b->ori = xcalloc((size_t)ncap, sizeof(double));
    b->ecc = xcalloc((size_t)ncap, sizeof(double));
    b->rays = xcalloc((size_t)(3 * ncap), sizeof(double));
    b->ori_ok = xcalloc((size_t)ncap, 1);
    b->claimed = xcalloc((size_t)ncap, 1);
    b->cost = xcalloc((size_t)(ncap * tcap), sizeof(double));
    b->d2 = xcalloc((size_t)(ncap * tcap), sizeof(double));
    b->puv = xcalloc((size_t)(2 * C * tcap), sizeof(double));
    b->J = xcalloc((size_t)(6 * C * tcap), sizeof(double));
    b->front = xcalloc((size_t)(C * tcap), 1);
    b->assign = xcalloc((size_t)(C * tcap), sizeof(int64_t));
    b->n_cams = xcalloc((size_t)tcap, sizeof(int64_t));
    b->dead = xcalloc((size_t)tcap, 1);
    b->scratch = xcalloc((size_t)b->scratch_len, sizeof(double));
    r->cams = xcalloc((size_t)(FTK_CAM_STRIDE * C), sizeof(double));
    for (int64_t c = 0; c < C; c++) {
        double *cm = r->cams + c * FTK_CAM_STRIDE;
        /* A camera looking along +z from z = -2 (rotated about z), or garbage. */
        double a = unif(0, 6.283), ca = cos(a), sa = sin(a);
        double R[9] = {ca, -sa, 0, sa, ca, 0, 0, 0, 1};
        memcpy(cm + FTK_CAM_R, R, sizeof R);
        cm[FTK_CAM_T + 2] = 2.0;
        double f = unif(300, 900);
        double K[5] = {f, 0.0, 320.0, f, 240.0};
        memcpy(cm + FTK_CAM_K, K, sizeof K);
        double D[5] = {unif(-0.2, 0), unif(0, 0.05), unif(-1e-3, 1e-3), unif(-1e-3, 1e-3), 0.0};
        memcpy(cm + FTK_CAM_DIST, D, sizeof D);
        /* Distortion frame (flydra's intrinsic_linear): near identity, principal point shifted. */
        double DF[6] = {unif(0.98, 1.02), 0.0, 0.0, unif(0.98, 1.02), unif(-0.05, 0.05),
                        unif(-0.05, 0.05)};
        memcpy(cm + FTK_CAM_DFA, DF, sizeof DF);
        cm[FTK_CAM_CENTER + 2] = -2.0;
        for (int i = 0; i < 3; i++) { /* R^T K^-1 for zero skew */
            cm[FTK_CAM_RAYB + 3 * i] = R[i] / f;
            cm[FTK_CAM_RAYB + 3 * i + 1] = R[3 + i] / f;
            cm[FTK_CAM_RAYB + 3 * i + 2] = R[6 + i] - (R[i] * 320.0 + R[3 + i] * 240.0) / f;
        }
        for (int i = 0; i < 3; i++) {
            for (int j = 0; j < 3; j++)
                cm[FTK_CAM_P + 4 * i + j] =
                    (i < 2 ? f : 1.0) * R[3 * i + j] + (i < 2 ? K[2 + i] : 0.0) * R[6 + j];
            cm[FTK_CAM_P + 4 * i + 3] = (i == 2 ? 2.0 : (i == 0 ? 320.0 : 240.0) * 2.0);
        }
        if (absurd)
            for (int k = 0; k < FTK_CAM_STRIDE; k++)
                if (next_u64() % 8 == 0)
                    cm[k] = wild(-1e3, 1e3);
    }
}

static void free_rig(rig *r) {
    ftk_buffers *b = &r->b;
    void *ptrs[] = {b->x,     b->P,      b->area,    b->n_obs, b->axis,    b->slot, b->index,
                    b->rank,  b->starts, b->uv,      b->uvi,   b->parea,   b->ori,  b->ecc,
                    b->rays,  b->ori_ok, b->claimed, b->cost,  b->d2,      b->puv,  b->J,
                    b->front, b->assign, b->n_cams,  b->dead,  b->scratch, r->cams};
    for (size_t i = 0; i < sizeof ptrs / sizeof ptrs[0]; i++)
        free(ptrs[i]);
}

static void random_state(rig *r, int64_t T, int absurd) {
    for (int64_t t = 0; t < T; t++) {
        double *x = r->b.x + 6 * t, *P = r->b.P + 36 * t;
        for (int i = 0; i < 6; i++)
            x[i] = absurd ? wild(-1, 1) : unif(-0.3, 0.3);
        memset(P, 0, 36 * sizeof(double));
        for (int i = 0; i < 6; i++)
            P[7 * i] = absurd ? wild(1e-9, 1e-2) : unif(1e-6, 1e-3);
        if (absurd && next_u64() % 4 == 0)
            P[1] = P[6] = wild(-1, 1);
        r->b.area[t] = absurd ? wild(-10, 100) : unif(10, 60);
        r->b.n_obs[t] = 0;
        for (int k = 0; k < 3; k++)
            r->b.axis[3 * t + k] = next_u64() % 2 ? NAN : unif(-1, 1);
    }
}

/* Settle clashes the simplest way (the Python side uses scipy): the first target keeps the point.
 */
static void settle(rig *r, int64_t T) {
    int64_t C = r->b.n_cameras;
    for (int64_t c = 0; c < C; c++)
        for (int64_t t = 0; t < T; t++)
            for (int64_t s = 0; s < t; s++)
                if (r->b.assign[c * T + t] >= 0 && r->b.assign[c * T + t] == r->b.assign[c * T + s])
                    r->b.assign[c * T + t] = -1;
}

static void one_frame(rig *r, ftk_params *p, int64_t T, int absurd) {
    int64_t C = r->b.n_cameras, counts[16], total = 0, stats[FTK_ST_COUNT];
    for (int64_t c = 0; c < C; c++) {
        counts[c] = (int64_t)(next_u64() % 5);
        if (total + counts[c] > r->b.n_cap)
            counts[c] = r->b.n_cap - total;
        total += counts[c];
    }
    float *raw = xcalloc((size_t)(total * FTK_POINT_WORDS), sizeof(float));
    for (int64_t i = 0; i < total; i++) {
        float *w = raw + i * FTK_POINT_WORDS;
        w[0] = tof(absurd ? wild(-100, 740) : unif(200, 440));
        w[1] = tof(absurd ? wild(-100, 580) : unif(150, 330));
        w[2] = tof(absurd ? wild(-100, 740) : w[0]);
        w[3] = tof(absurd ? wild(-100, 580) : w[1]);
        w[4] = tof(wild(1, 80));
        w[6] = tof(wild(-2, 2));
        w[7] = tof(wild(1, 3));
    }
    double dt = absurd && next_u64() % 3 == 0 ? wild(1e-6, 10) : 0.01;
    int rc = ftk_frame(p, r->cams, &r->b, raw, counts, T, dt, stats);
    if (T > 0 && !(isfinite(dt) && dt > 0)) {
        CHECK(rc == FTK_EINVAL);
        free(raw);
        return;
    }
    CHECK(rc == FTK_OK);
    CHECK(stats[FTK_ST_POINTS] + stats[FTK_ST_NONFINITE] == total);
    if (stats[FTK_ST_RESOLVE]) {
        settle(r, T);
        CHECK(ftk_update(p, r->cams, &r->b, T, stats) == FTK_OK);
    }
    int64_t N = r->b.starts[C];
    CHECK(N == stats[FTK_ST_POINTS]);
    for (int64_t n = 0; n < N; n++)
        CHECK(r->b.slot[n] >= 0 && r->b.slot[n] < C && r->b.index[n] < counts[r->b.slot[n]]);
    for (int64_t t = 0; t < T; t++) {
        CHECK(r->b.n_cams[t] >= 0 && r->b.n_cams[t] <= C);
        const double *P = r->b.P + 36 * t;
        if (r->b.n_cams[t] > 0)
            for (int i = 0; i < 6; i++)
                for (int j = 0; j < 6; j++)
                    CHECK(P[6 * i + j] == P[6 * j + i] && isfinite(P[6 * i + j]));
    }
    for (int64_t k = 0; k < C * T; k++)
        CHECK(r->b.assign[k] >= -1 && r->b.assign[k] < N);
    CHECK(stats[FTK_ST_UNCLAIMED] >= 0 && stats[FTK_ST_UNCLAIMED] <= N);
    free(raw);
}

int main(void) {
    ftk_params p = {20.0, 10.0, 0.0,    20.0, 1.0, 0.1, 0.01212 * 0.01212,
                    0.1,  1.4,  0.0875, 20.0, 1,   2};
    CHECK(ftk_abi_version() == FTK_ABI_VERSION);
    int64_t frames = 0;
    for (int trial = 0; trial < 400; trial++) {
        int64_t C = 1 + (int64_t)(next_u64() % 11), tcap = 1 + (int64_t)(next_u64() % 12);
        int64_t ncap = (int64_t)(next_u64() % 40);
        int absurd = trial % 2;
        rig r;
        make_rig(&r, C, tcap, ncap, absurd);
        p.exclusive_points = trial % 3 != 0;
        p.min_area_px = trial % 5 == 0 ? 5.0 : 0.0;
        int64_t T = (int64_t)(next_u64() % (uint64_t)(tcap + 1));
        random_state(&r, T, absurd);
        for (int f = 0; f < 20; f++, frames++)
            one_frame(&r, &p, T, absurd);
        /* Argument checks: more targets than room, more points than room, negative counts, NULLs.
         */
        int64_t stats[FTK_ST_COUNT], counts[16] = {0};
        CHECK(ftk_frame(&p, r.cams, &r.b, NULL, counts, tcap + 1, 0.01, stats) == FTK_EINVAL);
        counts[0] = ncap + 1;
        float *raw = xcalloc((size_t)((ncap + 1) * FTK_POINT_WORDS), sizeof(float));
        CHECK(ftk_frame(&p, r.cams, &r.b, raw, counts, T, 0.01, stats) == FTK_ECAPACITY);
        counts[0] = -1;
        CHECK(ftk_frame(&p, r.cams, &r.b, raw, counts, T, 0.01, stats) == FTK_EINVAL);
        counts[0] = 0;
        CHECK(ftk_frame(&p, NULL, &r.b, raw, counts, T, 0.01, stats) == FTK_EINVAL);
        CHECK(ftk_frame(&p, r.cams, NULL, raw, counts, T, 0.01, stats) == FTK_EINVAL);
        free(raw);
        free_rig(&r);
    }
    printf("tracker kernel: %lld random frames, %d failures\n", (long long)frames, failures);
    return failures ? 1 : 0;
}

/* The tracker's per-frame hot path; see tracker_kernel.h. Each step mirrors the NumPy code named in
 * its comment (same formulas in the same order), so both paths agree to rounding. */
#include "tracker_kernel.h"

#include <math.h>
#include <string.h>

int ftk_abi_version(void) {
    return FTK_ABI_VERSION;
}
size_t ftk_sizeof_params(void) {
    return sizeof(ftk_params);
}
size_t ftk_sizeof_buffers(void) {
    return sizeof(ftk_buffers);
}

int64_t ftk_scratch_len(int64_t n_cameras, int64_t t_cap) {
    int64_t m = 2 * n_cameras;
    /* inverse position covariances (9 per target); Joseph update: H (m x 3), y, S (m x m), P H^T
     * and the solution (6 x m each), K (6 x m) */
    return 9 * t_cap + 3 * m + m + m * m + 3 * 6 * m + 64;
}

static int valid_buffers(const ftk_buffers *b, int64_t n_targets) {
    if (!b || b->n_cameras < 1 || n_targets < 0 || n_targets > b->t_cap || b->n_cap < 0)
        return 0;
    if (b->scratch_len < ftk_scratch_len(b->n_cameras, b->t_cap))
        return 0;
    return b->x && b->P && b->area && b->n_obs && b->axis && b->slot && b->index && b->rank &&
           b->starts && b->uv && b->uvi && b->parea && b->ori && b->ecc && b->rays && b->ori_ok &&
           b->claimed && b->cost && b->d2 && b->puv && b->J && b->front && b->assign && b->n_cams &&
           b->dead && b->scratch;
}

/* tracker._gather: finite points in slot order, rays (CameraArray.ray_directions). */
static int gather(const ftk_params *p, const double *cams, const ftk_buffers *b,
                  const unsigned char *raw, const int64_t *counts, int64_t *stats) {
    int64_t C = b->n_cameras, total = 0;
    for (int64_t c = 0; c < C; c++) {
        if (counts[c] < 0)
            return FTK_EINVAL;
        total += counts[c];
    }
    if (total > b->n_cap)
        return FTK_ECAPACITY;
    if (total > 0 && !raw)
        return FTK_EINVAL;
    int64_t n = 0, row = 0, maxpc = 0;
    for (int64_t c = 0; c < C; c++) {
        const double *B = cams + c * FTK_CAM_STRIDE + FTK_CAM_RAYB;
        int64_t r = 0;
        b->starts[c] = n;
        for (int64_t i = 0; i < counts[c]; i++, row++) {
            float w[FTK_POINT_WORDS];
            memcpy(w, raw + (size_t)row * sizeof w, sizeof w); /* bytes may be unaligned */
            double u = w[0], v = w[1], ui = w[2], vi = w[3], a = w[4], o = w[6], e = w[7];
            if (!(isfinite(u) && isfinite(v) && isfinite(ui) && isfinite(vi) && isfinite(a))) {
                stats[FTK_ST_NONFINITE]++;
                continue;
            }
            if (isinf(o) || isinf(e)) {
                stats[FTK_ST_NONFINITE_ORI]++;
                o = NAN;
            }
            b->slot[n] = c;
            b->index[n] = i;
            b->rank[n] = r++;
            b->uv[2 * n] = u;
            b->uv[2 * n + 1] = v;
            b->uvi[2 * n] = ui;
            b->uvi[2 * n + 1] = vi;
            b->parea[n] = a;
            b->ori[n] = o;
            b->ecc[n] = e;
            b->ori_ok[n] = (uint8_t)(isfinite(o) && e >= p->min_eccentricity);
            for (int k = 0; k < 3; k++)
                b->rays[3 * n + k] = B[3 * k] * ui + B[3 * k + 1] * vi + B[3 * k + 2];
            n++;
        }
        if (r > maxpc)
            maxpc = r;
    }
    b->starts[C] = n;
    stats[FTK_ST_POINTS] = n;
    stats[FTK_ST_MAX_PER_CAMERA] = maxpc;
    return FTK_OK;
}

/* ekf.predict with ekf.cv_transition / cv_process_noise: x = F x, P = F P F^T + Q. */
static void predict(const ftk_params *p, const ftk_buffers *b, int64_t T, double dt) {
    double F[36] = {0}, Q[36] = {0};
    double q = p->motion_noise_scale;
    double q3 = q * pow(dt, 3.0) / 3.0, q2 = q * pow(dt, 2.0) / 2.0, q1 = q * dt;
    for (int i = 0; i < 6; i++)
        F[7 * i] = 1.0;
    for (int i = 0; i < 3; i++) {
        F[6 * i + i + 3] = dt;
        Q[6 * i + i] = q3;
        Q[6 * i + i + 3] = Q[6 * (i + 3) + i] = q2;
        Q[6 * (i + 3) + i + 3] = q1;
    }
    for (int64_t t = 0; t < T; t++) {
        double *x = b->x + 6 * t, *P = b->P + 36 * t, xn[6], FP[36];
        for (int i = 0; i < 6; i++) {
            double s = 0.0;
            for (int j = 0; j < 6; j++)
                s += x[j] * F[6 * i + j];
            xn[i] = s;
        }
        memcpy(x, xn, sizeof xn);
        for (int i = 0; i < 6; i++)
            for (int j = 0; j < 6; j++) {
                double s = 0.0;
                for (int k = 0; k < 6; k++)
                    s += F[6 * i + k] * P[6 * k + j];
                FP[6 * i + j] = s;
            }
        for (int i = 0; i < 6; i++)
            for (int j = 0; j < 6; j++) {
                double s = 0.0;
                for (int k = 0; k < 6; k++)
                    s += FP[6 * i + k] * F[6 * j + k];
                P[6 * i + j] = s + Q[6 * i + j];
            }
    }
}

/* CameraArray.project_jacobian for every (camera, target). */
static void project(const double *cams, const ftk_buffers *b, int64_t T) {
    for (int64_t c = 0; c < b->n_cameras; c++) {
        const double *cm = cams + c * FTK_CAM_STRIDE;
        const double *R = cm + FTK_CAM_R, *tv = cm + FTK_CAM_T;
        double fx = cm[FTK_CAM_K], skew = cm[FTK_CAM_K + 1], cx = cm[FTK_CAM_K + 2];
        double fy = cm[FTK_CAM_K + 3], cy = cm[FTK_CAM_K + 4];
        double k1 = cm[FTK_CAM_DIST], k2 = cm[FTK_CAM_DIST + 1], p1 = cm[FTK_CAM_DIST + 2];
        double p2 = cm[FTK_CAM_DIST + 3], k3 = cm[FTK_CAM_DIST + 4];
        double pv[2] = {p1, p2}, ps[2] = {p2, p1};
        /* flydra's model: the distortion acts on q = A q0 + b (K_dist^-1 K), not on q0 itself. */
        const double *A = cm + FTK_CAM_DFA;
        for (int64_t t = 0; t < T; t++) {
            const double *X = b->x + 6 * t;
            int64_t ct = c * T + t;
            double Xc[3];
            for (int j = 0; j < 3; j++)
                Xc[j] = X[0] * R[3 * j] + X[1] * R[3 * j + 1] + X[2] * R[3 * j + 2] + tv[j];
            double z = Xc[2];
            int front = z > 1e-9;
            double zi = 1.0 / (front ? z : 1.0);
            double q0[2] = {Xc[0] * zi, Xc[1] * zi};
            double q[2] = {A[0] * q0[0] + A[1] * q0[1] + A[4], A[2] * q0[0] + A[3] * q0[1] + A[5]};
            double qq[2] = {q[0] * q[0], q[1] * q[1]};
            double r2 = qq[0] + qq[1];
            double radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3));
            double dradial = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2);
            double xy = q[0] * q[1];
            double qs[2] = {q[1], q[0]};
            double qd[2];
            for (int i = 0; i < 2; i++)
                qd[i] = q[i] * radial + 2.0 * pv[i] * xy + ps[i] * (r2 + 2.0 * qq[i]);
            b->puv[2 * ct] = qd[0] * fx + qd[1] * skew + cx;
            b->puv[2 * ct + 1] = qd[0] * 0.0 + qd[1] * fy + cy;
            double Dd[2][2], KD[2][2], KDA[2][2], G[2][3];
            for (int i = 0; i < 2; i++)
                for (int j = 0; j < 2; j++) {
                    Dd[i][j] = 2.0 * dradial * (q[i] * q[j]);
                    Dd[i][j] += 2.0 * pv[i] * qs[j];
                    Dd[i][j] += 2.0 * ps[i] * q[j];
                }
            for (int i = 0; i < 2; i++)
                Dd[i][i] += radial + 4.0 * ps[i] * q[i];
            for (int j = 0; j < 2; j++) {
                KD[0][j] = fx * Dd[0][j] + skew * Dd[1][j];
                KD[1][j] = 0.0 * Dd[0][j] + fy * Dd[1][j];
            }
            for (int i = 0; i < 2; i++)
                for (int j = 0; j < 2; j++)
                    KDA[i][j] = KD[i][0] * A[j] + KD[i][1] * A[2 + j];
            for (int i = 0; i < 2; i++)
                for (int k = 0; k < 3; k++)
                    G[i][k] = R[3 * i + k] - q0[i] * R[6 + k];
            double *J = b->J + 6 * ct;
            for (int i = 0; i < 2; i++)
                for (int k = 0; k < 3; k++)
                    J[3 * i + k] = (KDA[i][0] * G[0][k] + KDA[i][1] * G[1][k]) * zi;
            b->front[ct] = (uint8_t)front;
        }
    }
}

/* Inverse of a 3x3 matrix by the adjugate (association.inv3); singular gives inf/NaN, refused
 * later. */
static void inv3(const double *M, double *out) {
    double a = M[0], bb = M[1], c = M[2], d = M[3], e = M[4], f = M[5], g = M[6], h = M[7],
           i = M[8];
    double co_a = e * i - f * h, co_b = f * g - d * i, co_c = d * h - e * g;
    double det = a * co_a + bb * co_b + c * co_c;
    double adj[9] = {co_a,          c * h - bb * i, bb * f - c * e, co_b,          a * i - c * g,
                     c * d - a * f, co_c,           bb * g - a * h, a * e - bb * d};
    for (int k = 0; k < 9; k++)
        out[k] = adj[k] / det;
}

/* association.associate up to the clash test: gates, ray Mahalanobis distance, nearest neighbour.
 */
static void associate(const ftk_params *p, const double *cams, const ftk_buffers *b, int64_t T,
                      int64_t *stats) {
    int64_t C = b->n_cameras, N = b->starts[C];
    for (int64_t k = 0; k < C * T; k++)
        b->assign[k] = -1;
    if (T == 0 || N == 0)
        return;
    double *Ainv = b->scratch;
    for (int64_t t = 0; t < T; t++) {
        const double *P = b->P + 36 * t;
        double cov[9] = {P[0], P[1], P[2], P[6], P[7], P[8], P[12], P[13], P[14]};
        inv3(cov, Ainv + 9 * t);
    }
    double gate2 = p->gate_px * p->gate_px, r = p->area_gate_ratio, rinv = 1.0 / r;
    for (int64_t n = 0; n < N; n++) {
        int64_t c = b->slot[n];
        const double *o = cams + c * FTK_CAM_STRIDE + FTK_CAM_CENTER, *d = b->rays + 3 * n;
        for (int64_t t = 0; t < T; t++) {
            int64_t ct = c * T + t;
            double dx = b->uv[2 * n] - b->puv[2 * ct], dy = b->uv[2 * n + 1] - b->puv[2 * ct + 1];
            double d2 = dx * dx + dy * dy;
            double ratio = b->parea[n] / b->area[t];
            double cost = INFINITY;
            b->d2[n * T + t] = d2;
            int ok = b->front[ct] && d2 < gate2 && ratio < r && ratio > rinv;
            if (ok && p->min_area_px > 0)
                ok = b->parea[n] > p->min_area_px;
            if (ok) {
                const double *A = Ainv + 9 * t, *m = b->x + 6 * t;
                double w[3] = {m[0] - o[0], m[1] - o[1], m[2] - o[2]}, Aw[3], Ad[3];
                for (int i = 0; i < 3; i++) {
                    Aw[i] = A[3 * i] * w[0] + A[3 * i + 1] * w[1] + A[3 * i + 2] * w[2];
                    Ad[i] = A[3 * i] * d[0] + A[3 * i + 1] * d[1] + A[3 * i + 2] * d[2];
                }
                double wAw = w[0] * Aw[0] + w[1] * Aw[1] + w[2] * Aw[2];
                double dAw = d[0] * Aw[0] + d[1] * Aw[1] + d[2] * Aw[2];
                double dAd = d[0] * Ad[0] + d[1] * Ad[1] + d[2] * Ad[2];
                double dist2 = wAw - dAw * dAw / dAd;
                double dm = dist2 < 0.0 ? 0.0 : sqrt(dist2); /* NaN stays NaN: refused below */
                if (dm < p->max_mahalanobis)
                    cost = dm;
            }
            b->cost[n * T + t] = cost;
        }
    }
    /* Each camera's nearest point per target (the first of equal ones, as np.argmin). */
    for (int64_t c = 0; c < C; c++)
        for (int64_t t = 0; t < T; t++) {
            double best = INFINITY;
            int64_t j = -1;
            for (int64_t n = b->starts[c]; n < b->starts[c + 1]; n++)
                if (b->cost[n * T + t] < best) {
                    best = b->cost[n * T + t];
                    j = n;
                }
            b->assign[c * T + t] = j;
        }
    /* Cameras where two targets chose the same point. claimed[] is a scratch mark here. */
    int64_t conflicts = 0;
    memset(b->claimed, 0, (size_t)N);
    for (int64_t c = 0; c < C; c++) {
        int clash = 0;
        for (int64_t t = 0; t < T; t++) {
            int64_t j = b->assign[c * T + t];
            if (j < 0)
                continue;
            if (b->claimed[j])
                clash = 1;
            b->claimed[j] = 1;
        }
        conflicts += clash;
    }
    stats[FTK_ST_CONFLICTS] = p->exclusive_points ? conflicts : 0;
    stats[FTK_ST_RESOLVE] = p->exclusive_points ? conflicts > 0 : 1;
}

/* Solve S X = B for X (m x 6), S (m x m) overwritten, by LU with partial pivoting (LAPACK gesv's
 * method, as np.linalg.solve). A zero pivot leaves NaNs, which the acceptance test refuses. */
static void lu_solve(double *S, double *B, int m) {
    for (int k = 0; k < m; k++) {
        int piv = k;
        double big = fabs(S[k * m + k]);
        for (int i = k + 1; i < m; i++)
            if (fabs(S[i * m + k]) > big) {
                big = fabs(S[i * m + k]);
                piv = i;
            }
        if (piv != k) {
            for (int j = 0; j < m; j++) {
                double tmp = S[k * m + j];
                S[k * m + j] = S[piv * m + j];
                S[piv * m + j] = tmp;
            }
            for (int j = 0; j < 6; j++) {
                double tmp = B[k * 6 + j];
                B[k * 6 + j] = B[piv * 6 + j];
                B[piv * 6 + j] = tmp;
            }
        }
        double pk = S[k * m + k];
        if (pk == 0.0)
            pk = NAN;
        for (int i = k + 1; i < m; i++) {
            double f = S[i * m + k] / pk;
            if (f == 0.0)
                continue;
            for (int j = k + 1; j < m; j++)
                S[i * m + j] -= f * S[k * m + j];
            for (int j = 0; j < 6; j++)
                B[i * 6 + j] -= f * B[k * 6 + j];
        }
    }
    for (int k = m - 1; k >= 0; k--) {
        double pk = S[k * m + k];
        if (pk == 0.0)
            pk = NAN;
        for (int j = 0; j < 6; j++) {
            double s = B[k * 6 + j];
            for (int i = k + 1; i < m; i++)
                s -= S[k * m + i] * B[i * 6 + j];
            B[k * 6 + j] = s / pk;
        }
    }
}

/* ekf._usable: finite with a Cholesky factor. */
static int usable(const double *x, const double *P) {
    for (int i = 0; i < 6; i++)
        if (!isfinite(x[i]))
            return 0;
    for (int i = 0; i < 36; i++)
        if (!isfinite(P[i]))
            return 0;
    double L[36] = {0};
    for (int j = 0; j < 6; j++) {
        double s = P[7 * j];
        for (int k = 0; k < j; k++)
            s -= L[6 * j + k] * L[6 * j + k];
        if (!(s > 0.0))
            return 0;
        L[7 * j] = sqrt(s);
        for (int i = j + 1; i < 6; i++) {
            double v = P[6 * i + j];
            for (int k = 0; k < j; k++)
                v -= L[6 * i + k] * L[6 * j + k];
            L[6 * i + j] = v / L[7 * j];
        }
    }
    return 1;
}

/* tracker._ekf + ekf.joseph_update for one target with its m = 2 k observations. */
static int joseph(const ftk_params *p, const ftk_buffers *b, int64_t T, int64_t t, double *scr) {
    int64_t C = b->n_cameras;
    int m = 0;
    double *H = scr, *y = H + 3 * 2 * C, *S = y + 2 * C, *PHt = S + 4 * C * C, *X = PHt + 12 * C,
           *K = X + 12 * C;
    for (int64_t c = 0; c < C; c++) {
        int64_t j = b->assign[c * T + t], ct = c * T + t;
        if (j < 0)
            continue;
        for (int r = 0; r < 2; r++) {
            for (int k = 0; k < 3; k++)
                H[3 * (m + r) + k] = b->J[6 * ct + 3 * r + k];
            y[m + r] = b->uv[2 * j + r] - b->puv[2 * ct + r];
        }
        m += 2;
    }
    const double *P = b->P + 36 * t, *x = b->x + 6 * t;
    for (int r = 0; r < 6; r++)
        for (int i = 0; i < m; i++)
            PHt[r * m + i] =
                P[6 * r] * H[3 * i] + P[6 * r + 1] * H[3 * i + 1] + P[6 * r + 2] * H[3 * i + 2];
    for (int i = 0; i < m; i++)
        for (int j = 0; j < m; j++)
            S[i * m + j] = H[3 * i] * PHt[j] + H[3 * i + 1] * PHt[m + j] +
                           H[3 * i + 2] * PHt[2 * m + j] + (i == j ? p->r2 : 0.0);
    for (int i = 0; i < m; i++)
        for (int r = 0; r < 6; r++)
            X[6 * i + r] = PHt[r * m + i];
    lu_solve(S, X, m);
    for (int r = 0; r < 6; r++)
        for (int i = 0; i < m; i++)
            K[r * m + i] = X[6 * i + r];
    double xp[6], IKH[36], A[36], Pp[36];
    for (int r = 0; r < 6; r++) {
        double s = 0.0;
        for (int i = 0; i < m; i++)
            s += K[r * m + i] * y[i];
        xp[r] = x[r] + s;
    }
    for (int r = 0; r < 6; r++)
        for (int c = 0; c < 6; c++) {
            double s = 0.0;
            if (c < 3)
                for (int i = 0; i < m; i++)
                    s += K[r * m + i] * H[3 * i + c];
            IKH[6 * r + c] = (r == c ? 1.0 : 0.0) - s;
        }
    for (int r = 0; r < 6; r++)
        for (int c = 0; c < 6; c++) {
            double s = 0.0;
            for (int k = 0; k < 6; k++)
                s += IKH[6 * r + k] * P[6 * k + c];
            A[6 * r + c] = s;
        }
    for (int r = 0; r < 6; r++)
        for (int c = 0; c < 6; c++) {
            double s = 0.0, kk = 0.0;
            for (int k = 0; k < 6; k++)
                s += A[6 * r + k] * IKH[6 * c + k];
            for (int i = 0; i < m; i++)
                kk += (K[r * m + i] * p->r2) * K[c * m + i];
            Pp[6 * r + c] = s + kk;
        }
    double Ps[36];
    for (int r = 0; r < 6; r++)
        for (int c = 0; c < 6; c++)
            Ps[6 * r + c] = (Pp[6 * r + c] + Pp[6 * c + r]) * 0.5;
    if (!usable(xp, Ps))
        return 0;
    memcpy(b->x + 6 * t, xp, sizeof xp);
    memcpy(b->P + 36 * t, Ps, sizeof Ps);
    return 1;
}

/* Eigen-decomposition of a symmetric 3x3 matrix by cyclic Jacobi rotations: eigenvalues ascending
 * in w, eigenvectors in the columns of V (as np.linalg.eigh). */
static void eig3(const double *M, double *w, double *V) {
    double a[9];
    memcpy(a, M, sizeof a);
    for (int i = 0; i < 9; i++)
        V[i] = (i % 4 == 0) ? 1.0 : 0.0;
    for (int sweep = 0; sweep < 60; sweep++) {
        double off = a[1] * a[1] + a[2] * a[2] + a[5] * a[5];
        double diag = a[0] * a[0] + a[4] * a[4] + a[8] * a[8];
        if (!(off > 1e-40 * diag) || off == 0.0)
            break;
        static const int PQ[3][2] = {{0, 1}, {0, 2}, {1, 2}};
        for (int k = 0; k < 3; k++) {
            int pp = PQ[k][0], qq = PQ[k][1];
            double apq = a[3 * pp + qq];
            if (apq == 0.0)
                continue;
            double theta = (a[3 * qq + qq] - a[3 * pp + pp]) / (2.0 * apq);
            double tt = fabs(theta) > 1e150
                            ? 0.5 / theta
                            : (theta >= 0 ? 1.0 : -1.0) / (fabs(theta) + sqrt(theta * theta + 1.0));
            double cs = 1.0 / sqrt(tt * tt + 1.0), sn = tt * cs;
            for (int r = 0; r < 3; r++) { /* a = a G */
                double arp = a[3 * r + pp], arq = a[3 * r + qq];
                a[3 * r + pp] = cs * arp - sn * arq;
                a[3 * r + qq] = sn * arp + cs * arq;
            }
            for (int r = 0; r < 3; r++) { /* a = G^T a */
                double apr = a[3 * pp + r], aqr = a[3 * qq + r];
                a[3 * pp + r] = cs * apr - sn * aqr;
                a[3 * qq + r] = sn * apr + cs * aqr;
            }
            a[3 * pp + qq] = a[3 * qq + pp] = 0.0;
            for (int r = 0; r < 3; r++) {
                double vrp = V[3 * r + pp], vrq = V[3 * r + qq];
                V[3 * r + pp] = cs * vrp - sn * vrq;
                V[3 * r + qq] = sn * vrp + cs * vrq;
            }
        }
    }
    int order[3] = {0, 1, 2};
    double d[3] = {a[0], a[4], a[8]};
    for (int i = 0; i < 3; i++)
        for (int j = i + 1; j < 3; j++)
            if (d[order[j]] < d[order[i]]) {
                int tmp = order[i];
                order[i] = order[j];
                order[j] = tmp;
            }
    double Vs[9];
    for (int i = 0; i < 3; i++) {
        w[i] = d[order[i]];
        for (int r = 0; r < 3; r++)
            Vs[3 * r + i] = V[3 * r + order[i]];
    }
    memcpy(V, Vs, sizeof Vs);
}

/* tracker._orient for one target just updated (J at the prior, velocity of the posterior). */
static void orient(const ftk_params *p, const ftk_buffers *b, int64_t T, int64_t t) {
    int64_t C = b->n_cameras;
    double M[9] = {0};
    int used = 0;
    double *ax = b->axis + 3 * t;
    for (int64_t c = 0; c < C; c++) {
        int64_t j = b->assign[c * T + t];
        if (j < 0 || !b->ori_ok[j])
            continue;
        const double *J = b->J + 6 * (c * T + t);
        double th = b->ori[j], a0 = -sin(th), a1 = cos(th), n[3];
        for (int k = 0; k < 3; k++)
            n[k] = a0 * J[k] + a1 * J[3 + k];
        double norm = sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2]);
        double sc = 1.0 / (norm > 0 ? norm : 1.0);
        for (int k = 0; k < 3; k++)
            n[k] *= sc;
        for (int i = 0; i < 3; i++)
            for (int k = 0; k < 3; k++)
                M[3 * i + k] += n[i] * n[k];
        used++;
    }
    if (used < 2) {
        ax[0] = ax[1] = ax[2] = NAN;
        return;
    }
    for (int i = 0; i < 9; i++)
        if (!isfinite(M[i])) {
            ax[0] = ax[1] = ax[2] = NAN;
            return;
        }
    double lam[3], V[9];
    eig3(M, lam, V);
    double s1 = sqrt(lam[1] > 0 ? lam[1] : 0.0), s2 = sqrt(lam[2] > 0 ? lam[2] : 0.0);
    int ok = s1 / (s2 > 1e-300 ? s2 : 1e-300) >= p->min_plane_tan_half;
    double e[3] = {V[0], V[3], V[6]}, dot = 0.0;
    const double *vel = b->x + 6 * t + 3;
    for (int k = 0; k < 3; k++)
        dot += e[k] * (isfinite(ax[k]) ? ax[k] : vel[k]);
    for (int k = 0; k < 3; k++)
        ax[k] = !ok ? NAN : (dot < 0 ? -e[k] : e[k]);
}

/* birth.sampson2 for one pair of points from two cameras, compared with the seed gate, and
 * birth.in_front (birth.seed_pairs): find_births can only start a target from such a pair. The
 * fundamental matrix F = B_b^T [c_a - c_b]_x B_a is applied through the rays d = B x, which the
 * gather computed. */
static int pair_may_give_birth(const ftk_params *p, const double *cams, const ftk_buffers *b,
                               int64_t ia, int64_t ib) {
    const double *ca = cams + b->slot[ia] * FTK_CAM_STRIDE,
                 *cb = cams + b->slot[ib] * FTK_CAM_STRIDE;
    const double *oa = ca + FTK_CAM_CENTER, *ob = cb + FTK_CAM_CENTER;
    const double *Ba = ca + FTK_CAM_RAYB, *Bb = cb + FTK_CAM_RAYB;
    const double *da = b->rays + 3 * ia, *db = b->rays + 3 * ib;
    double t[3] = {oa[0] - ob[0], oa[1] - ob[1], oa[2] - ob[2]};
    double ta[3] = {t[1] * da[2] - t[2] * da[1], t[2] * da[0] - t[0] * da[2],
                    t[0] * da[1] - t[1] * da[0]}; /* t x d_a */
    double tb[3] = {t[1] * db[2] - t[2] * db[1], t[2] * db[0] - t[0] * db[2],
                    t[0] * db[1] - t[1] * db[0]}; /* t x d_b */
    /* F x_a = B_b^T (t x d_a): the epipolar line in b; F^T x_b = -B_a^T (t x d_b), in a. */
    double la0 = Bb[0] * ta[0] + Bb[3] * ta[1] + Bb[6] * ta[2];
    double la1 = Bb[1] * ta[0] + Bb[4] * ta[1] + Bb[7] * ta[2];
    double lb0 = Ba[0] * tb[0] + Ba[3] * tb[1] + Ba[6] * tb[2];
    double lb1 = Ba[1] * tb[0] + Ba[4] * tb[1] + Ba[7] * tb[2];
    double num = db[0] * ta[0] + db[1] * ta[1] + db[2] * ta[2];
    double den = la0 * la0 + la1 * la1 + lb0 * lb0 + lb1 * lb1;
    double g = p->birth_seed_gate_px;
    if (!(num * num <= g * g * den && den > 0.0))
        return 0;
    /* birth.in_front: the rays come closest in front of both cameras (a hair of slack, so that
     * rounding never hides a pair the NumPy gate keeps). */
    double aa = 0, ab = 0, bb = 0, aw = 0, bw = 0;
    for (int k = 0; k < 3; k++) {
        aa += da[k] * da[k];
        ab += da[k] * db[k];
        bb += db[k] * db[k];
        aw += da[k] * t[k];
        bw += db[k] * t[k];
    }
    double tol = 1e-12 * (fabs(ab * bw) + fabs(bb * aw) + fabs(aa * bw) + fabs(ab * aw));
    return ab * bw - bb * aw > -tol && aa * bw - ab * aw > -tol;
}

int ftk_update(const ftk_params *p, const double *cams, const ftk_buffers *b, int64_t T,
               int64_t *stats) {
    if (!p || !cams || !stats || !valid_buffers(b, T))
        return FTK_EINVAL;
    int64_t C = b->n_cameras, N = b->starts[C];
    if (N < 0 || N > b->n_cap)
        return FTK_EINVAL;
    double *scr = b->scratch + 9 * b->t_cap;
    int64_t updated = 0, rejected = 0, dead = 0, claimed = 0;
    memset(b->claimed, 0, (size_t)N);
    for (int64_t t = 0; t < T; t++) {
        int64_t k = 0;
        for (int64_t c = 0; c < C; c++) {
            int64_t j = b->assign[c * T + t];
            if (j < -1 || j >= N || (j >= 0 && b->slot[j] != c))
                return FTK_EINVAL;
            if (j >= 0) {
                k++;
                /* Claimed before the update is accepted, as tracker.process does. */
                if (!b->claimed[j])
                    claimed++;
                b->claimed[j] = 1;
            }
        }
        b->n_cams[t] = 0;
        if (k == 0)
            continue;
        if (!joseph(p, b, T, t, scr)) {
            rejected++;
            for (int64_t c = 0; c < C; c++)
                b->assign[c * T + t] = -1;
            continue;
        }
        updated++;
        b->n_cams[t] = k;
        double sum = 0.0, a = p->area_smoothing;
        for (int64_t c = 0; c < C; c++) {
            int64_t j = b->assign[c * T + t];
            sum += j >= 0 ? b->parea[j] : 0.0;
        }
        b->area[t] = (1 - a) * b->area[t] + a * sum / (double)k;
        b->n_obs[t]++;
        orient(p, b, T, t);
    }
    for (int64_t t = 0; t < T; t++) {
        const double *P = b->P + 36 * t;
        int alive = P[0] <= p->death_var && P[7] <= p->death_var && P[14] <= p->death_var;
        b->dead[t] = (uint8_t)!alive;
        dead += !alive;
    }
    int64_t pairs = 0;
    if (N - claimed >= p->birth_min_cameras)
        for (int64_t i = 0; i < N && !pairs; i++) {
            if (b->claimed[i])
                continue;
            for (int64_t j = i + 1; j < N; j++)
                if (!b->claimed[j] && b->slot[j] != b->slot[i] &&
                    pair_may_give_birth(p, cams, b, i, j)) {
                    pairs = 1;
                    break;
                }
        }
    stats[FTK_ST_UPDATED] = updated;
    stats[FTK_ST_REJECTED] = rejected;
    stats[FTK_ST_DEAD] = dead;
    stats[FTK_ST_UNCLAIMED] = N - claimed;
    stats[FTK_ST_BIRTH_PAIRS] = pairs;
    return FTK_OK;
}

int ftk_associate(const ftk_params *p, const double *cams, const ftk_buffers *b, const void *raw,
                  const int64_t *counts, int64_t T, double dt, int64_t *stats) {
    if (!p || !cams || !counts || !stats || !valid_buffers(b, T))
        return FTK_EINVAL;
    if (T > 0 && !(isfinite(dt) && dt > 0))
        return FTK_EINVAL;
    for (int k = 0; k < FTK_ST_COUNT; k++)
        stats[k] = 0;
    int rc = gather(p, cams, b, (const unsigned char *)raw, counts, stats);
    if (rc != FTK_OK)
        return rc;
    if (T > 0) {
        predict(p, b, T, dt);
        project(cams, b, T);
    }
    associate(p, cams, b, T, stats);
    return FTK_OK;
}

int ftk_frame(const ftk_params *p, const double *cams, const ftk_buffers *b, const void *raw,
              const int64_t *counts, int64_t T, double dt, int64_t *stats) {
    int rc = ftk_associate(p, cams, b, raw, counts, T, dt, stats);
    if (rc != FTK_OK || stats[FTK_ST_RESOLVE])
        return rc;
    return ftk_update(p, cams, b, T, stats);
}

#include "fish_kernel.h"

#include <math.h>
#include <stdlib.h>

int ffk_abi_version(void) {
    return FFK_ABI_VERSION;
}

/* Parabolic refinement of a minimum at y0 with neighbours ym, yp (the same rule as fit.py). */
static double parabola(double ym, double y0, double yp) {
    double den = ym + yp - 2.0 * y0;
    double dif = ym - yp;
    if (den > fabs(dif) + 1e-12) {
        return y0 - dif * dif / (8.0 * den);
    }
    return y0;
}

/* Squared distance of line (p, v) to the points of one ring, refined around the ring. */
static double ring_min(const double *ring, int64_t Nu, const double *p, const double *v) {
    double best = INFINITY;
    int64_t kbest = -1;
    double d2s[256];
    for (int64_t k = 0; k < Nu; k++) {
        const double *s = ring + 3 * k;
        double dx = s[0] - p[0], dy = s[1] - p[1], dz = s[2] - p[2];
        double t = dx * v[0] + dy * v[1] + dz * v[2];
        double d2 = dx * dx + dy * dy + dz * dz - t * t;
        d2s[k] = d2;
        if (d2 < best) {
            best = d2;
            kbest = k;
        }
    }
    if (kbest < 0) {
        return NAN;
    }
    double r = parabola(d2s[(kbest + Nu - 1) % Nu], best, d2s[(kbest + 1) % Nu]);
    return r > 0.0 ? r : 0.0;
}

int ffk_line_distances(const double *S, int64_t B, int64_t Ns, int64_t Nu, const double *p,
                       const double *v, int64_t N, double *D) {
    if (B < 0 || Ns < 1 || Nu < 3 || Nu > 256 || N < 0 || (!S && B > 0) || (!D && B * N > 0)) {
        return -1;
    }
    double *centre = malloc(sizeof(double) * (size_t)(4 * Ns));
    double *e = malloc(sizeof(double) * (size_t)Ns);
    if (!centre || !e) {
        free(centre);
        free(e);
        return -1;
    }
    for (int64_t b = 0; b < B; b++) {
        const double *Sb = S + b * Ns * Nu * 3;
        /* bounding sphere of each ring: its centroid and largest radius */
        for (int64_t i = 0; i < Ns; i++) {
            const double *ring = Sb + i * Nu * 3;
            double c[3] = {0.0, 0.0, 0.0};
            for (int64_t k = 0; k < Nu; k++) {
                c[0] += ring[3 * k];
                c[1] += ring[3 * k + 1];
                c[2] += ring[3 * k + 2];
            }
            c[0] /= (double)Nu;
            c[1] /= (double)Nu;
            c[2] /= (double)Nu;
            double R2 = 0.0;
            for (int64_t k = 0; k < Nu; k++) {
                double dx = ring[3 * k] - c[0], dy = ring[3 * k + 1] - c[1],
                       dz = ring[3 * k + 2] - c[2];
                double r2 = dx * dx + dy * dy + dz * dz;
                R2 = r2 > R2 ? r2 : R2;
            }
            centre[4 * i] = c[0];
            centre[4 * i + 1] = c[1];
            centre[4 * i + 2] = c[2];
            centre[4 * i + 3] = sqrt(R2);
        }
        for (int64_t n = 0; n < N; n++) {
            const double *pn = p + 3 * n, *vn = v + 3 * n;
            /* first pass: the station whose centre is nearest the line seeds the bound */
            int64_t i0 = 0;
            double lb0 = INFINITY;
            for (int64_t i = 0; i < Ns; i++) {
                const double *c = centre + 4 * i;
                double dx = c[0] - pn[0], dy = c[1] - pn[1], dz = c[2] - pn[2];
                double t = dx * vn[0] + dy * vn[1] + dz * vn[2];
                double d2 = dx * dx + dy * dy + dz * dz - t * t;
                double lb = sqrt(d2 > 0.0 ? d2 : 0.0) - c[3];
                e[i] = lb; /* lower bound on the distance to ring i, for now */
                if (lb < lb0) {
                    lb0 = lb;
                    i0 = i;
                }
            }
            double best = ring_min(Sb + i0 * Nu * 3, Nu, pn, vn);
            int64_t ibest = i0;
            e[i0] = best;
            for (int64_t i = 0; i < Ns; i++) {
                if (i == i0) {
                    continue;
                }
                double lb = e[i];
                if (lb > 0.0 && lb * lb > best) {
                    e[i] = INFINITY; /* cannot be the least; filled in below if it is a neighbour */
                    continue;
                }
                e[i] = ring_min(Sb + i * Nu * 3, Nu, pn, vn);
                if (e[i] < best) {
                    best = e[i];
                    ibest = i;
                }
            }
            double out = best;
            if (ibest > 0 && ibest < Ns - 1) {
                double em = e[ibest - 1], ep = e[ibest + 1];
                if (isinf(em)) {
                    em = ring_min(Sb + (ibest - 1) * Nu * 3, Nu, pn, vn);
                }
                if (isinf(ep)) {
                    ep = ring_min(Sb + (ibest + 1) * Nu * 3, Nu, pn, vn);
                }
                out = parabola(em, best, ep);
            }
            D[b * N + n] = sqrt(out > 0.0 ? out : 0.0);
        }
    }
    free(centre);
    free(e);
    return 0;
}

/* Lens distortion of libflytrack_features (OpenCV model, the same as host camera.py):
 * ft_fx_undistort, public, used by regions.c for each point. A file of its own because it needs
 * nothing of the extractor but its parameters: regions.c calls it, and it calls nothing back. */
#include "flytrack/features.h"

#include <math.h>

static void distort_norm(const ft_fx_params *p, double x, double y, double *xd, double *yd) {
    double r2 = x * x + y * y;
    double radial = 1.0 + r2 * (p->k1 + r2 * (p->k2 + r2 * p->k3));
    *xd = x * radial + 2.0 * p->p1 * x * y + p->p2 * (r2 + 2.0 * x * x);
    *yd = y * radial + p->p1 * (r2 + 2.0 * y * y) + 2.0 * p->p2 * x * y;
}

void ft_fx_undistort(const ft_fx_params *p, double u, double v, double *u_out, double *v_out) {
    if (p->fx == 0.0 ||
        (p->k1 == 0.0 && p->k2 == 0.0 && p->p1 == 0.0 && p->p2 == 0.0 && p->k3 == 0.0)) {
        *u_out = u;
        *v_out = v;
        return;
    }
    double ydn = (v - p->cy) / p->fy;
    double xdn = (u - p->cx - p->skew * ydn) / p->fx;
    double x = xdn, y = ydn;
    /* Fixed-point iteration as OpenCV's undistortPoints, then Newton steps with the analytic
     * Jacobian to reach the exact inverse of the distortion (camera.py does the same). */
    for (int i = 0; i < 20; i++) {
        double r2 = x * x + y * y;
        double radial = 1.0 + r2 * (p->k1 + r2 * (p->k2 + r2 * p->k3));
        double dx = 2.0 * p->p1 * x * y + p->p2 * (r2 + 2.0 * x * x);
        double dy = p->p1 * (r2 + 2.0 * y * y) + 2.0 * p->p2 * x * y;
        x = (xdn - dx) / radial;
        y = (ydn - dy) / radial;
    }
    for (int i = 0; i < 3; i++) {
        double fx_, fy_;
        distort_norm(p, x, y, &fx_, &fy_);
        double ex = fx_ - xdn, ey = fy_ - ydn;
        double r2 = x * x + y * y;
        double radial = 1.0 + r2 * (p->k1 + r2 * (p->k2 + r2 * p->k3));
        double drad = p->k1 + r2 * (2.0 * p->k2 + 3.0 * p->k3 * r2);
        double a = radial + 2.0 * x * x * drad + 2.0 * p->p1 * y + 6.0 * p->p2 * x;
        double b = 2.0 * x * y * drad + 2.0 * p->p1 * x + 2.0 * p->p2 * y;
        double c = 2.0 * x * y * drad + 2.0 * p->p1 * x + 2.0 * p->p2 * y;
        double d = radial + 2.0 * y * y * drad + 6.0 * p->p1 * y + 2.0 * p->p2 * x;
        double det = a * d - b * c;
        if (!(fabs(det) > 1e-300))
            break;
        double nx = x - (d * ex - b * ey) / det;
        double ny = y - (-c * ex + a * ey) / det;
        if (!isfinite(nx) || !isfinite(ny))
            break;
        x = nx;
        y = ny;
    }
    *u_out = p->fx * x + p->skew * y + p->cx;
    *v_out = p->fy * y + p->cy;
}

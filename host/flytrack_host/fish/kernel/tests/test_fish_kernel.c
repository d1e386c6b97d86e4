/* The fish kernel under ASan + UBSan: random surfaces and lines, NaN and infinite inputs, bad
 * sizes. */
#include <math.h>
#include <stdio.h>
#include <stdlib.h>

#include "fish_kernel.h"

static double urand(void) {
    return (double)rand() / (double)RAND_MAX * 2.0 - 1.0;
}

int main(void) {
    srand(7);
    int fails = 0;
    for (int trial = 0; trial < 200; trial++) {
        int64_t B = 1 + rand() % 4, Ns = 1 + rand() % 20, Nu = 3 + rand() % 12, N = rand() % 30;
        double *S = malloc(sizeof(double) * (size_t)(B * Ns * Nu * 3));
        double *p = malloc(sizeof(double) * (size_t)(N * 3 + 1));
        double *v = malloc(sizeof(double) * (size_t)(N * 3 + 1));
        double *D = malloc(sizeof(double) * (size_t)(B * N + 1));
        for (int64_t i = 0; i < B * Ns * Nu * 3; i++) {
            S[i] = trial % 17 == 0 && i % 5 == 0
                       ? NAN
                       : (trial % 23 == 0 && i % 7 == 0 ? INFINITY : 10.0 * urand());
        }
        for (int64_t n = 0; n < N; n++) {
            double a = urand(), b = urand(), c = urand(), l = sqrt(a * a + b * b + c * c) + 1e-9;
            v[3 * n] = a / l;
            v[3 * n + 1] = b / l;
            v[3 * n + 2] = c / l;
            p[3 * n] = 10.0 * urand();
            p[3 * n + 1] = 10.0 * urand();
            p[3 * n + 2] = 10.0 * urand();
        }
        if (ffk_line_distances(S, B, Ns, Nu, p, v, N, D) != 0) {
            fails++;
        }
        /* a clean trial's distances are finite and at most the distance to any sample point */
        if (trial % 17 != 0 && trial % 23 != 0) {
            for (int64_t b = 0; b < B; b++) {
                for (int64_t n = 0; n < N; n++) {
                    const double *s = S + b * Ns * Nu * 3;
                    double dx = s[0] - p[3 * n], dy = s[1] - p[3 * n + 1], dz = s[2] - p[3 * n + 2];
                    double t = dx * v[3 * n] + dy * v[3 * n + 1] + dz * v[3 * n + 2];
                    double d = sqrt(fmax(dx * dx + dy * dy + dz * dz - t * t, 0.0));
                    if (!isfinite(D[b * N + n]) || D[b * N + n] > d + 1e-9) {
                        fails++;
                    }
                }
            }
        }
        free(S);
        free(p);
        free(v);
        free(D);
    }
    double x = 0.0;
    if (ffk_line_distances(&x, 1, 1, 2, &x, &x, 1, &x) != -1 ||
        ffk_line_distances(NULL, 1, 1, 8, &x, &x, 1, &x) != -1) {
        fails++;
    }
    printf("fish kernel: %d failures\n", fails);
    return fails ? 1 : 0;
}

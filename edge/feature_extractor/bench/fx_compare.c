/* Two builds of libflytrack_features, loaded with dlopen, on the same random frames: every result
 * field, every point and (on a quarter of the frames and the last) the background model must be
 * bit-identical. For changes that must not change results (`make compare-edge OLD=...`).
 * 160 cases: 8 geometries (rows shorter than a vector, a few rows, padded strides), MONO8, MONO16
 * (12- and 16-bit) and YUYV, random alpha, n_sigma, diff_threshold, polarity, cut, max_points, a
 * small candidate cap; backgrounds smooth, striped by noise level, or rough; frames drifting, with
 * 0-11 targets, speckle; masks set and removed, parameters changed, background retaken midway.
 * Usage: fx_compare OLD.so NEW.so [frames per case, default 40]. Exit 0: identical, 1: differ. */
#include "flytrack/features.h"
#include <dlfcn.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
typedef struct {
    void (*pdef)(ft_fx_params *, uint32_t, uint32_t, int32_t);
    int (*create)(const ft_fx_params *, size_t, ft_fx **);
    void (*destroy)(ft_fx *);
    int (*proc)(ft_fx *, const void *, size_t, ft_fx_result *);
    int (*setp)(ft_fx *, const char *, double);
    int (*setm)(ft_fx *, const uint8_t *);
    void (*take)(ft_fx *);
    const float *(*bm)(const ft_fx *);
    const float *(*bs)(const ft_fx *);
} lib;
static lib L(const char *path) {
    void *h = dlopen(path, RTLD_NOW | RTLD_LOCAL);
    if (!h) {
        fprintf(stderr, "fx_compare: %s\n", dlerror());
        exit(2);
    }
    lib l;
    *(void **)&l.pdef = dlsym(h, "ft_fx_params_default");
    *(void **)&l.create = dlsym(h, "ft_fx_create");
    *(void **)&l.destroy = dlsym(h, "ft_fx_destroy");
    *(void **)&l.proc = dlsym(h, "ft_fx_process");
    *(void **)&l.setp = dlsym(h, "ft_fx_set_param");
    *(void **)&l.setm = dlsym(h, "ft_fx_set_mask");
    *(void **)&l.take = dlsym(h, "ft_fx_take_background");
    *(void **)&l.bm = dlsym(h, "ft_fx_background_mean");
    *(void **)&l.bs = dlsym(h, "ft_fx_background_sumsq");
    return l;
}
static uint64_t st = 0x243f6a8885a308d3ull;
static uint32_t rnd(void) {
    st ^= st << 13;
    st ^= st >> 7;
    st ^= st << 17;
    return (uint32_t)(st >> 32);
}
static double ur(void) {
    return rnd() / 4294967296.0;
}
static long frames_cmp, points_cmp, fails;
int main(int argc, char **argv) {
    if (argc < 3 || (argc > 3 && atoi(argv[3]) < 1)) {
        fprintf(stderr, "usage: fx_compare OLD.so NEW.so [frames per case >= 1]\n");
        return 2;
    }
    lib A = L(argv[1]), B = L(argv[2]);
    int nfr = argc > 3 ? atoi(argv[3]) : 40;
    static const int geo[][2] = {{640, 48}, {130, 37},  {64, 20}, {13, 9},
                                 {1000, 3}, {200, 130}, {128, 4}, {70, 5}};
    for (int c = 0; c < 160; c++) {
        int w = geo[c % 8][0], h = geo[c % 8][1], fmt = (c / 8) % 3, pad = (c / 24) % 2 ? 7 : 0;
        if (fmt == FT_FX_YUYV && (w & 1))
            w++;
        uint32_t maxv = fmt == FT_FX_MONO16 ? (c & 1 ? 65535 : 4095) : 255;
        double sc = maxv / 255.0;
        ft_fx_params p;
        A.pdef(&p, w, h, fmt);
        size_t bpp = fmt == FT_FX_MONO8 ? 1 : 2;
        p.stride = pad ? (uint32_t)((w + pad) * bpp) : 0;
        static const unsigned ivs[] = {0, 1, 2, 3, 7, 20, 200};
        static const double als[] = {0.01, 0.05, 0.3, 1.0};
        p.bg_update_interval = ivs[rnd() % 7];
        p.alpha = als[rnd() % 4];
        p.n_sigma = rnd() % 3 ? 7.0 : 2.0;
        p.diff_threshold = (rnd() % 2 ? 30.0 : 12.0) * sc;
        p.polarity = rnd() % 3;
        p.despeckle_threshold = rnd() % 2 ? 5.0 : 0.0;
        p.subtract_cut = rnd() % 2;
        p.max_points = 1 + rnd() % 100;
        p.max_candidates = rnd() % 4 ? 0 : 200;
        ft_fx *fa, *fb;
        if (A.create(&p, sizeof p, &fa) || B.create(&p, sizeof p, &fb)) {
            fprintf(stderr, "fx_compare: ft_fx_create failed\n");
            return 2;
        }
        size_t stride = p.stride ? p.stride : w * bpp, bytes = stride * (h - 1) + w * bpp;
        uint8_t *buf = malloc(stride * h), *mask = malloc((size_t)w * h);
        double *bg = malloc(sizeof(double) * w * h), *ns = malloc(sizeof(double) * w * h);
        double ph = ur() * 6.3;
        for (int y = 0; y < h; y++)
            for (int x = 0; x < w; x++) {
                bg[y * w + x] = sc * (90 + 40 * sin(0.05 * x + ph) * cos(0.09 * y) +
                                      (c % 5 == 0 ? 60 * ur() : 0));
                ns[y * w + x] = sc * (x % 37 < 5 ? 9.0 : 1.5);
            }
        for (int f = 0; f < nfr; f++) {
            double drift = sc * 25 * sin(0.3 * f + ph);
            int nt = rnd() % 12;
            double tx[12], ty[12], am[12], sg[12];
            for (int k = 0; k < nt; k++) {
                tx[k] = ur() * w;
                ty[k] = ur() * h;
                am[k] = sc * (rnd() & 1 ? 1 : -1) * (40 + 100 * ur());
                sg[k] = 0.5 + 2.5 * ur();
            }
            for (size_t i = 0; i < stride * h; i++)
                buf[i] = (uint8_t)rnd();
            for (int y = 0; y < h; y++)
                for (int x = 0; x < w; x++) {
                    double v =
                        bg[y * w + x] + drift + ns[y * w + x] * (ur() + ur() + ur() - 1.5) * 2;
                    for (int k = 0; k < nt; k++) {
                        double dx = x - tx[k], dy = y - ty[k];
                        if (dx * dx + dy * dy < 100)
                            v += am[k] * exp(-(dx * dx + dy * dy) / (2 * sg[k] * sg[k]));
                    }
                    if (rnd() % 500 == 0)
                        v += sc * (rnd() & 1 ? 80 : -80);
                    v = floor(v + 0.5);
                    uint32_t u = v < 0 ? 0 : v > maxv ? maxv : (uint32_t)v;
                    uint8_t *px = buf + y * stride + x * bpp;
                    if (fmt == FT_FX_MONO16) {
                        uint16_t s = (uint16_t)u;
                        memcpy(px, &s, 2);
                    } else
                        px[0] = (uint8_t)u;
                }
            int op = rnd() % 40;
            if (op == 0) {
                for (int i = 0; i < w * h; i++)
                    mask[i] = rnd() % 7 != 0;
                A.setm(fa, mask);
                B.setm(fb, mask);
            } else if (op == 1) {
                A.setm(fa, NULL);
                B.setm(fb, NULL);
            } else if (op == 2) {
                double a = als[rnd() % 4];
                A.setp(fa, "alpha", a);
                B.setp(fb, "alpha", a);
            } else if (op == 3) {
                double v = ivs[rnd() % 7];
                A.setp(fa, "bg_update_interval", v);
                B.setp(fb, "bg_update_interval", v);
            } else if (op == 4) {
                A.take(fa);
                B.take(fb);
            } else if (op == 5) {
                double v = 2 + rnd() % 8;
                A.setp(fa, "n_sigma", v);
                B.setp(fb, "n_sigma", v);
            }
            ft_fx_result ra, rb;
            int ca = A.proc(fa, buf, bytes, &ra), cb = B.proc(fb, buf, bytes, &rb);
            frames_cmp++;
            int same = ca == cb && ra.frame_index == rb.frame_index && ra.n_points == rb.n_points &&
                       ra.total_points == rb.total_points && ra.n_candidates == rb.n_candidates &&
                       ra.flags == rb.flags &&
                       (ra.n_points == 0 ||
                        !memcmp(ra.points, rb.points, ra.n_points * sizeof(ft_fx_point)));
            points_cmp += ra.n_points;
            if (rnd() % 4 == 0 || f == nfr - 1) {
                const float *ma = A.bm(fa), *mb = B.bm(fb), *sa = A.bs(fa), *sb = B.bs(fb);
                if ((ma == NULL) != (mb == NULL))
                    same = 0;
                else if (ma && (memcmp(ma, mb, sizeof(float) * w * h) ||
                                memcmp(sa, sb, sizeof(float) * w * h)))
                    same = 0;
            }
            if (!same) {
                if (fails < 10)
                    fprintf(stderr,
                            "case %d (%dx%d fmt %d pad %d iv %u alpha %g) frame %d differs: pts "
                            "%u/%u cand %u/%u flags %x/%x\n",
                            c, w, h, fmt, pad, p.bg_update_interval, p.alpha, f, ra.n_points,
                            rb.n_points, ra.n_candidates, rb.n_candidates, ra.flags, rb.flags);
                fails++;
            }
        }
        A.destroy(fa);
        B.destroy(fb);
        free(buf);
        free(mask);
        free(bg);
        free(ns);
    }
    printf("fx_compare: %ld frames, %ld points compared: %ld differ\n", frames_cmp, points_cmp,
           fails);
    return fails != 0;
}

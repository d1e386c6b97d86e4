/* `make bench-edge`, second part: the extractor built for this CPU alone (-march=native, as
 * FLYTRACK_EDGE_NATIVE=ON builds it) against the portable build (x86-64-v2, wider paths chosen at
 * run time), side by side on the same frames, with their ratio. Both are timed by the bench's own
 * helper (fx_bench.c: the monotonic clock around each ft_fx_process call, the frame read just
 * before so that it is in cache: the code's speed, not memory's). Frames as the Python bench makes
 * them: 640x480 and 2048x2048 8-bit, a smooth textured background with noise (sd 2), 0, 1 or 10
 * moving Gaussian targets; the background update every 200 frames is included (whole intervals
 * timed). The two libraries take turns, one interval at a time, for five rounds over the same
 * frames; each frame position counts with its best round (a frame preempted by another job in one
 * round is not in all five). Both must find the same points. Usage: fx_bench_paths NATIVE.so
 * PORTABLE.so [--quick] */
#include "flytrack/features.h"

#include <dlfcn.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

int ft_bench_time_process(void *process, void *fx, void *result, const void *const *frames,
                          size_t nframes, size_t start, size_t count, size_t nbytes, int warm,
                          uint64_t *ns);

typedef struct {
    const char *path;
    void (*pdef)(ft_fx_params *, uint32_t, uint32_t, int32_t);
    int (*create)(const ft_fx_params *, size_t, ft_fx **);
    void (*destroy)(ft_fx *);
    int (*proc)(ft_fx *, const void *, size_t, ft_fx_result *);
    const char *(*scan_path)(const ft_fx *);
} lib;

static lib load(const char *path) {
    void *h = dlopen(path, RTLD_NOW | RTLD_LOCAL);
    if (!h) {
        fprintf(stderr, "fx_bench_paths: %s\n", dlerror());
        exit(2);
    }
    lib l = {path, 0, 0, 0, 0, 0};
    *(void **)&l.pdef = dlsym(h, "ft_fx_params_default");
    *(void **)&l.create = dlsym(h, "ft_fx_create");
    *(void **)&l.destroy = dlsym(h, "ft_fx_destroy");
    *(void **)&l.proc = dlsym(h, "ft_fx_process");
    *(void **)&l.scan_path = dlsym(h, "ft_fx_debug_scan_path");
    if (!l.pdef || !l.create || !l.destroy || !l.proc || !l.scan_path) {
        fprintf(stderr, "fx_bench_paths: %s lacks an extractor symbol\n", path);
        exit(2);
    }
    return l;
}

static uint64_t st = 0x9e3779b97f4a7c15ull;
static double ur(void) {
    st ^= st << 13;
    st ^= st >> 7;
    st ^= st << 17;
    return (double)(st >> 11) / 9007199254740992.0;
}

/* The background: uniform 30..140 blurred by a Gaussian of sd 3 (as the Python bench), then
 * nframes frames with n targets moving across it. */
static uint8_t **make_frames(int w, int h, int nt, int nframes, uint8_t **bg_out) {
    const size_t npix = (size_t)w * h;
    float *bg = malloc(sizeof(float) * npix), *tmp = malloc(sizeof(float) * npix);
    for (size_t i = 0; i < npix; i++)
        tmp[i] = (float)(30 + 110 * ur());
    float g[19], gs = 0; /* the kernel, radius 3 sd, edges clamped */
    for (int k = -9; k <= 9; k++)
        gs += g[k + 9] = (float)exp(-k * k / 18.0);
    for (int pass = 0; pass < 2; pass++) { /* rows then columns */
        const float *in = pass ? bg : tmp;
        float *out = pass ? tmp : bg;
        for (int y = 0; y < h; y++)
            for (int x = 0; x < w; x++) {
                float s = 0;
                for (int k = -9; k <= 9; k++) {
                    int xx = pass ? x : x + k, yy = pass ? y + k : y;
                    xx = xx < 0 ? 0 : xx >= w ? w - 1 : xx;
                    yy = yy < 0 ? 0 : yy >= h ? h - 1 : yy;
                    s += g[k + 9] * in[(size_t)yy * w + xx];
                }
                out[(size_t)y * w + x] = s / gs;
            }
    }
    memcpy(bg, tmp, sizeof(float) * npix);
    free(tmp);
    double px[10], py[10], vx[10], vy[10];
    for (int k = 0; k < nt; k++) {
        px[k] = 20 + ur() * (w - 40);
        py[k] = 20 + ur() * (h - 40);
        vx[k] = 6 * ur() - 3;
        vy[k] = 6 * ur() - 3;
    }
    uint8_t **fr = malloc(sizeof(uint8_t *) * (size_t)nframes);
    for (int f = 0; f < nframes; f++) {
        uint8_t *o = malloc((size_t)w * h);
        for (size_t i = 0; i < (size_t)w * h; i++) { /* noise of sd 2: four uniforms summed */
            double v = bg[i] + 2.0 * 1.732 * (ur() + ur() + ur() + ur() - 2.0);
            o[i] = (uint8_t)(v < 0 ? 0 : v > 255 ? 255 : lrint(v));
        }
        for (int k = 0; k < nt; k++) {
            for (int y = (int)py[k] - 8; y <= (int)py[k] + 8; y++)
                for (int x = (int)px[k] - 8; x <= (int)px[k] + 8; x++) {
                    double dx = x - px[k], dy = y - py[k];
                    double v = o[(size_t)y * w + x] + 120 * exp(-(dx * dx + dy * dy) / 8.0);
                    o[(size_t)y * w + x] = (uint8_t)(v > 255 ? 255 : lrint(v));
                }
            px[k] += vx[k];
            py[k] += vy[k];
            if (px[k] < 20 || px[k] > w - 21)
                vx[k] = -vx[k], px[k] = px[k] < 20 ? 20 : w - 21;
            if (py[k] < 20 || py[k] > h - 21)
                vy[k] = -vy[k], py[k] = py[k] < 20 ? 20 : h - 21;
        }
        fr[f] = o;
    }
    uint8_t *b = malloc((size_t)w * h);
    for (size_t i = 0; i < (size_t)w * h; i++)
        b[i] = (uint8_t)lrint(bg[i]);
    free(bg);
    *bg_out = b;
    return fr;
}

int main(int argc, char **argv) {
    if (argc < 3) {
        fprintf(stderr, "usage: fx_bench_paths NATIVE.so PORTABLE.so [--quick]\n");
        return 2;
    }
    const int quick = argc > 3 && !strcmp(argv[3], "--quick");
    lib libs[2] = {load(argv[1]), load(argv[2])};
    static const int cases[][3] = {{640, 480, 0},   {640, 480, 1},   {640, 480, 10},
                                   {2048, 2048, 0}, {2048, 2048, 1}, {2048, 2048, 10}};
    const int rounds = quick ? 2 : 5, interval = 200;
    int status = 0;
    for (int c = 0; c < 6; c++) {
        const int w = cases[c][0], h = cases[c][1], nt = cases[c][2];
        const int count = w * h > 1000000 ? interval : 2 * interval; /* whole update intervals */
        const int nframes = w * h > 1000000 ? 20 : 100;
        uint8_t *bg, **fr = make_frames(w, h, nt, nframes, &bg);
        ft_fx *fx[2];
        ft_fx_result res;
        uint64_t *ns = malloc(sizeof(uint64_t) * (size_t)count);
        uint64_t *best[2];
        long points[2] = {0, 0};
        for (int k = 0; k < 2; k++) {
            ft_fx_params p;
            libs[k].pdef(&p, (uint32_t)w, (uint32_t)h, FT_FX_MONO8);
            p.bg_update_interval = interval;
            if (libs[k].create(&p, sizeof p, &fx[k]) ||
                libs[k].proc(fx[k], bg, (size_t)w * h, &res)) {
                fprintf(stderr, "fx_bench_paths: %s: create or first frame failed\n", libs[k].path);
                return 2;
            }
            best[k] = malloc(sizeof(uint64_t) * (size_t)count);
            for (int i = 0; i < count; i++)
                best[k][i] = UINT64_MAX;
        }
        for (int r = 0; r < rounds; r++)
            for (int i0 = 0; i0 < count; i0 += interval) /* take turns, an interval at a time */
                for (int j = 0; j < 2; j++) {
                    const int k = (r + j) % 2; /* each goes first in every other round */
                    if (ft_bench_time_process(*(void **)&libs[k].proc, fx[k], &res,
                                              (const void *const *)fr, (size_t)nframes, (size_t)i0,
                                              (size_t)interval, (size_t)w * h, 1, ns)) {
                        fprintf(stderr, "fx_bench_paths: %s: ft_fx_process failed\n", libs[k].path);
                        return 2;
                    }
                    points[k] += res.n_points; /* the last frame of each interval */
                    for (int i = 0; i < interval; i++)
                        if (ns[i] < best[k][i0 + i])
                            best[k][i0 + i] = ns[i];
                }
        double mean[2];
        for (int k = 0; k < 2; k++) {
            double s = 0;
            for (int i = 0; i < count; i++)
                s += (double)best[k][i];
            mean[k] = s / count / 1000.0;
        }
        if (c == 0) {
            printf("native vs portable edge extractor: us per frame, hot cache, whole background-"
                   "update intervals, each frame position's best of %d rounds\n",
                   rounds);
            printf("  native:   %s (scan path %s)\n  portable: %s (scan path %s)\n", libs[0].path,
                   libs[0].scan_path(fx[0]), libs[1].path, libs[1].scan_path(fx[1]));
            printf("      frame tgt |   native  portable  portable/native\n");
        }
        printf("  %9s %3d | %8.1f  %8.1f  %.2fx\n", w == 640 ? "640x480" : "2048x2048", nt, mean[0],
               mean[1], mean[1] / mean[0]);
        if (points[0] != points[1]) {
            fprintf(stderr, "fx_bench_paths: %dx%d %d targets: the two found different points\n", w,
                    h, nt);
            status = 1;
        }
        for (int k = 0; k < 2; k++) {
            libs[k].destroy(fx[k]);
            free(best[k]);
        }
        for (int f = 0; f < nframes; f++)
            free(fr[f]);
        free(fr);
        free(bg);
        free(ns);
    }
    return status;
}

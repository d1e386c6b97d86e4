/* Unit test of the wing-beat tracker under ASan + UBSan: a synthetic tethered fly (two wings as
 * edges sweeping about a body, 20 % noise) gives its body, heading, frequency and amplitude back;
 * a window without a beating wing is a clear error and the next window is tried; bad parameters,
 * events off the sensor, a full beat array, events all at one time. */
#include "flytrack/wingbeat.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "check.h" /* CHECK(), ft_test_report: protocol/tests/check.h */

static uint64_t rng = 88172645463325252ull;
static double uni(void) { /* xorshift64: the same stream on every platform */
    rng ^= rng << 13;
    rng ^= rng >> 7;
    rng ^= rng << 17;
    return (double)(rng >> 11) / 9007199254740992.0;
}

#define BX 60.0
#define BY 66.0
#define HEADING 0.6
#define F0 200.0
#define MEAN 1.75
#define AMP 1.0
#define WIDTH_RAD 0.22

/* Events of a fly beating from t0 to t1 (us) every 2 us: each wing's leading edge (OFF) and
 * trailing edge (ON) at a random radius, plus a share of uniform noise. noise_only: no wings. */
static size_t fly(ft_event *ev, size_t cap, int64_t t0, int64_t t1, double noise, int noise_only) {
    size_t n = 0;
    for (int64_t t = t0; t < t1 && n + 4 < cap; t += 2) {
        double s = (double)t * 1e-6, th = 2 * M_PI * F0 * s;
        double phi = MEAN + AMP * sin(th), dir = cos(th) >= 0 ? 1.0 : -1.0;
        if (!noise_only && uni() < 0.6) {
            int wing = uni() < 0.5, lead = uni() < 0.5;
            double edge = phi + (lead ? dir : -dir) * WIDTH_RAD / 2;
            double side = wing ? -1.0 : 1.0, r = 8 + 17 * uni();
            double a = HEADING + side * edge; /* image angle: heading +- stroke */
            ft_event e = {t,
                          (uint16_t)lround(BX + r * cos(a)),
                          (uint16_t)lround(BY + r * sin(a)),
                          (uint8_t)(lead ? 0 : 1),
                          {0, 0, 0}};
            ev[n++] = e;
        }
        if (uni() < (noise_only ? 0.2 : 0.6 * noise / (1 - noise))) {
            ft_event e = {t,
                          (uint16_t)(uni() * 128),
                          (uint16_t)(uni() * 128),
                          (uint8_t)(uni() < 0.5),
                          {0, 0, 0}};
            ev[n++] = e;
        }
    }
    return n;
}

static double wrap(double a) {
    return atan2(sin(a), cos(a));
}

static void test_fly(void) {
    ft_wb_params p;
    ft_wb_defaults(&p, 128, 128);
    ft_wb_tracker *t = ft_wb_create(&p);
    CHECK(t);
    size_t cap = 800000;
    ft_event *ev = malloc(cap * sizeof *ev);
    size_t n = fly(ev, cap, 1000, 1001000, 0.2, 0);
    ft_wb_beat *beats = malloc(4000 * sizeof *beats);
    size_t nb = 0;
    for (size_t i = 0; i < n; i += 3000) /* in chunks, as a daemon gets them */
        nb += ft_wb_feed(t, ev + i, n - i < 3000 ? n - i : 3000, beats + nb, 4000 - nb);
    CHECK(ft_wb_state(t) == FT_WB_TRACKING);
    ft_wb_geometry g;
    CHECK(ft_wb_get_geometry(t, &g) == 0);
    CHECK(fabs(g.body_x - BX) < 2 && fabs(g.body_y - BY) < 2);
    CHECK(fabs(wrap(g.heading - HEADING)) < 0.15);
    CHECK(fabs(g.start_freq_hz[0] / F0 - 1) < 0.05 && fabs(g.start_freq_hz[1] / F0 - 1) < 0.05);
    /* wing 0 is on the +90 degree side of the heading: the one drawn with side = +1 */
    ft_wb_estimate w[2];
    ft_wb_wings(t, w);
    for (int k = 0; k < 2; k++) {
        CHECK(fabs(w[k].freq_hz / F0 - 1) < 0.01);
        CHECK(fabs(w[k].amplitude / AMP - 1) < 0.08);
        CHECK(w[k].updates > 1000);
    }
    /* about one beat per edge per period over the second (the first few are convergence) */
    CHECK(nb > 4 * 180 && nb < 4 * 215);
    int late = 0, good = 0;
    for (size_t i = 0; i < nb; i++)
        if (beats[i].t_us > 300000) {
            late++;
            good +=
                fabs(beats[i].freq_hz / F0 - 1) < 0.02 && fabs(beats[i].amplitude / AMP - 1) < 0.1;
        }
    CHECK(late > 400 && good > 0.95 * late);
    ft_wb_stats st;
    ft_wb_get_stats(t, &st);
    CHECK(st.events == n && st.init_failures == 0 && st.beats == nb && st.beats_dropped == 0);
    CHECK(st.gated > 0 && st.in_roi > n / 2); /* noise inside the region was gated */
    const char *msg = ft_wb_last_error(t, NULL);
    CHECK(msg[0] == 0);

    /* a beat array too small: counted, never overrun */
    ft_wb_tracker *t2 = ft_wb_create(&p);
    size_t got = ft_wb_feed(t2, ev, n, beats, 5);
    ft_wb_get_stats(t2, &st);
    CHECK(got == 5 && st.beats_dropped == st.beats - 5);
    ft_wb_destroy(t2);
    free(beats);
    free(ev);
    ft_wb_destroy(t);
}

static void test_no_fly(void) {
    ft_wb_params p;
    ft_wb_defaults(&p, 128, 128);
    ft_wb_tracker *t = ft_wb_create(&p);
    size_t cap = 600000;
    ft_event *ev = malloc(cap * sizeof *ev);
    /* 0.35 s of noise alone: three windows fail, each saying why */
    size_t n = fly(ev, cap, 0, 350000, 1, 1);
    ft_wb_feed(t, ev, n, NULL, 0);
    uint64_t fails;
    const char *msg = ft_wb_last_error(t, &fails);
    CHECK(ft_wb_state(t) == FT_WB_INITIALISING && fails == 3);
    CHECK(strstr(msg, "no beating wing in view") != NULL);
    ft_wb_geometry g;
    CHECK(ft_wb_get_geometry(t, &g) == -1);
    ft_wb_estimate w[2];
    ft_wb_wings(t, w);
    CHECK(w[0].updates == 0 && w[1].freq_hz == 0);
    /* then the fly starts beating: found in the next window */
    n = fly(ev, cap, 350000, 700000, 0.2, 0);
    ft_wb_feed(t, ev, n, NULL, 0);
    CHECK(ft_wb_state(t) == FT_WB_TRACKING);
    ft_wb_wings(t, w);
    CHECK(fabs(w[0].freq_hz / F0 - 1) < 0.02 && fabs(w[1].freq_hz / F0 - 1) < 0.02);
    ft_wb_destroy(t);

    /* a sparse window: too few events */
    t = ft_wb_create(&p);
    for (int i = 0; i < 150; i++) {
        ft_event e = {i * 700, 5, 5, 1, {0, 0, 0}};
        ev[i] = e;
    }
    ft_wb_feed(t, ev, 150, NULL, 0);
    msg = ft_wb_last_error(t, &fails);
    CHECK(fails == 1 && strstr(msg, "too few") != NULL);
    ft_wb_destroy(t);

    /* one wing only: one cluster, or too few on a wing; never tracking */
    t = ft_wb_create(&p);
    n = 0;
    for (int64_t tt = 0; tt < 250000 && n < cap; tt += 3) {
        double phi = MEAN + AMP * sin(2 * M_PI * F0 * tt * 1e-6), r = 8 + 17 * uni();
        ft_event e = {tt,
                      (uint16_t)lround(BX + r * cos(HEADING + phi)),
                      (uint16_t)lround(BY + r * sin(HEADING + phi)),
                      0,
                      {0, 0, 0}};
        ev[n++] = e;
    }
    ft_wb_feed(t, ev, n, NULL, 0);
    msg = ft_wb_last_error(t, &fails);
    CHECK(ft_wb_state(t) == FT_WB_INITIALISING && fails >= 1 && msg[0] != 0);
    ft_wb_destroy(t);
    free(ev);
}

static void test_bad_input(void) {
    ft_wb_params p;
    ft_wb_defaults(&p, 128, 128);
    p.harmonics = 0;
    CHECK(ft_wb_create(&p) == NULL);
    p.harmonics = FT_WB_MAX_HARMONICS + 1;
    CHECK(ft_wb_create(&p) == NULL);
    ft_wb_defaults(&p, 128, 128);
    p.measurement_std_rad = NAN;
    CHECK(ft_wb_create(&p) == NULL);
    ft_wb_defaults(&p, 0, 128);
    CHECK(ft_wb_create(&p) == NULL);
    CHECK(ft_wb_create(NULL) == NULL);

    /* off-sensor events are counted and skipped; events all at one time do not divide by zero */
    ft_wb_defaults(&p, 128, 128);
    p.start_freq_hz = 200;
    p.harmonics = 4;
    p.events_per_update = 1;
    ft_wb_tracker *t = ft_wb_create(&p);
    size_t cap = 400000;
    ft_event *ev = malloc(cap * sizeof *ev);
    size_t n = fly(ev, cap, 0, 300000, 0.2, 0);
    ev[10].x = 500;
    ev[11].y = 128;
    ft_wb_feed(t, ev, n, NULL, 0);
    for (size_t i = 0; i < 5000; i++) {
        ev[i].t = 300000;
        ev[i].x = (uint16_t)(40 + i % 40);
        ev[i].y = 60;
    }
    ft_wb_feed(t, ev, 5000, NULL, 0);
    ft_wb_stats st;
    ft_wb_get_stats(t, &st);
    CHECK(st.bad_events == 2);
    CHECK(ft_wb_state(t) == FT_WB_TRACKING);
    if (ft_wb_state(t) != FT_WB_TRACKING)
        fprintf(stderr, "%s\n", ft_wb_last_error(t, NULL));
    ft_wb_estimate e[4];
    ft_wb_edges(t, e);
    for (int k = 0; k < 4; k++)
        CHECK(isfinite(e[k].angle) && isfinite(e[k].freq_hz) && e[k].phase >= 0 &&
              e[k].phase < 2 * M_PI + 1e-6);
    ft_wb_geometry g;
    CHECK(ft_wb_get_geometry(t, &g) == 0 && g.start_freq_hz[0] == 200);
    free(ev);
    ft_wb_destroy(t);
}

int main(void) {
    test_fly();
    test_no_fly();
    test_bad_input();
    return ft_test_report("wingbeat");
}

/* Unit test of the noise filters and the cluster tracker, under ASan + UBSan: each filter on events
 * built by hand, the tracker on a blob moving at a known velocity, bad parameters, random input. */
#include "flytrack/event_algos.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>

#include "check.h" /* CHECK(), ft_test_failures: protocol/tests/check.h */

static ft_event E(int64_t t, int x, int y) {
    ft_event e = {t, (uint16_t)x, (uint16_t)y, 1, {0, 0, 0}};
    return e;
}

static void test_filters(void) {
    ft_nf_params p;
    ft_nf_defaults(&p, 32, 32);
    ft_noise_filter *f = ft_nf_create(&p);
    /* t=10000: a lone event (no neighbour ever) goes; its neighbour 1 ms later stays; the same
     * pixel 50 us later is refractory; an event off the sensor goes; a neighbour 3 ms later goes.
     */
    ft_event ev[] = {E(10000, 5, 5), E(11000, 6, 5), E(11050, 6, 5), E(11100, 40, 3),
                     E(14100, 7, 7)};
    size_t n = ft_nf_apply(f, ev, 5);
    CHECK(n == 1 && ev[0].x == 6 && ev[0].t == 11000);
    ft_nf_stats st;
    ft_nf_get_stats(f, &st);
    CHECK(st.in == 5 && st.out == 1 && st.ba_removed == 3 && st.refractory_removed == 1);
    ft_nf_destroy(f);

    /* Hot pixel: 12,000 events of one pixel (with a busy neighbour) in the first second; after the
     * window the pixel is hot, its neighbour is not. */
    p.refractory_us = 0;
    f = ft_nf_create(&p);
    enum { N = 24000 };
    ft_event *hot = malloc(N * sizeof *hot);
    for (int i = 0; i < N; i++)
        hot[i] = E(i * 40, i % 2 ? 10 : 11, 10); /* 12,000 each over 0.96 s */
    n = ft_nf_apply(f, hot, N);
    CHECK(n == N - 1); /* only the very first event had no neighbour */
    for (int i = 0; i < 100; i++)
        hot[i] = E(1000000 + i * 80, i % 2 ? 10 : 11, 10);
    ft_nf_get_stats(f, &st);
    n = ft_nf_apply(f, hot, 100);
    ft_nf_get_stats(f, &st);
    CHECK(st.hot_pixels == 2 && n == 0); /* both fired 12,000 > 10,000 times */
    free(hot);
    ft_nf_destroy(f);

    /* Correlation filter: needs k distinct neighbours. */
    ft_nf_defaults(&p, 32, 32);
    p.ba_window_us = 0;
    p.refractory_us = 0;
    p.stc_min_neighbours = 2;
    f = ft_nf_create(&p);
    /* (6,5) and (7,5) have one recent neighbour each; (6,6) has three; (20,20) none. */
    ft_event c[] = {E(100, 5, 5), E(200, 6, 5), E(300, 7, 5), E(350, 6, 6), E(400, 20, 20)};
    n = ft_nf_apply(f, c, 5);
    CHECK(n == 1 && c[0].x == 6 && c[0].y == 6);
    ft_nf_destroy(f);

    p.stc_min_neighbours = 9;
    CHECK(ft_nf_create(&p) == NULL);
    p.stc_min_neighbours = 0;
    p.width = 0;
    CHECK(ft_nf_create(&p) == NULL);
}

static void test_tracker(void) {
    ft_ct_params p;
    ft_ct_defaults(&p, 128, 128);
    ft_cluster_tracker *t = ft_ct_create(&p);
    /* A blob of radius 3 px moving at (+400, -200) px/s for 0.2 s, 200 events per ms. */
    enum { N = 40000 };
    ft_event *ev = malloc(N * sizeof *ev);
    unsigned s = 1;
    for (int i = 0; i < N; i++) {
        double tt = i * 5e-6; /* s */
        double cx = 30 + 400 * tt, cy = 90 - 200 * tt;
        s = s * 1103515245u + 12345u;
        double a = (s >> 8) % 6283 / 1000.0;
        s = s * 1103515245u + 12345u;
        double r = 3.0 * ((s >> 8) % 1000) / 1000.0;
        ev[i] = E((int64_t)(tt * 1e6), (int)lround(cx + r * cos(a)), (int)lround(cy + r * sin(a)));
    }
    ft_ct_feed(t, ev, N);
    ft_ct_cluster out[8];
    size_t k = ft_ct_clusters(t, ev[N - 1].t, out, 8);
    CHECK(k == 1);
    if (k == 1) {
        const double tt = (N - 1) * 5e-6, cx = 30 + 400 * tt, cy = 90 - 200 * tt;
        CHECK(out[0].tracking);
        CHECK(fabs(out[0].x - cx) < 1.5 && fabs(out[0].y - cy) < 1.5);
        CHECK(fabs(out[0].vx - 400) < 40 && fabs(out[0].vy + 200) < 40);
        CHECK(out[0].var_x > 0 && out[0].var_y > 0 && out[0].var_x < 4);
    }
    /* 150 ms later, with no events: the cluster has died (its mass ~2000 decays by e^-15). */
    ft_event late = E(ev[N - 1].t + 150000, 1, 1);
    ft_ct_feed(t, &late, 1);
    ft_ct_stats st;
    ft_ct_get_stats(t, &st);
    CHECK(st.died == 1 && st.created == 2);
    if (st.died != 1 || st.created != 2)
        fprintf(stderr, "died %llu created %llu merged %llu\n", (unsigned long long)st.died,
                (unsigned long long)st.created, (unsigned long long)st.merged);
    free(ev);
    ft_ct_destroy(t);

    p.max_clusters = 0;
    CHECK(ft_ct_create(&p) == NULL);
    p.max_clusters = FT_CT_MAX_CLUSTERS + 1;
    CHECK(ft_ct_create(&p) == NULL);
}

/* Random events (any coordinates, times going back and jumping) must not break either stage. */
static void test_random(void) {
    ft_nf_params np;
    ft_nf_defaults(&np, 64, 48);
    np.stc_min_neighbours = 1;
    ft_ct_params cp;
    ft_ct_defaults(&cp, 64, 48);
    ft_noise_filter *f = ft_nf_create(&np);
    ft_cluster_tracker *t = ft_ct_create(&cp);
    ft_event ev[512];
    unsigned s = 7;
    int64_t now = 0;
    for (int round = 0; round < 200; round++) {
        for (int i = 0; i < 512; i++) {
            s = s * 1664525u + 1013904223u;
            now += (int64_t)(s >> 20) - 200;
            if (round == 100 && i == 0)
                now += 4000000000LL; /* a gap of more than an hour */
            ev[i] = E(now, (int)((s >> 4) % 80), (int)((s >> 12) % 60));
        }
        size_t n = ft_nf_apply(f, ev, 512);
        ft_ct_feed(t, ev, n);
        ft_ct_cluster out[FT_CT_MAX_CLUSTERS];
        size_t k = ft_ct_clusters(t, now, out, FT_CT_MAX_CLUSTERS);
        for (size_t j = 0; j < k; j++)
            CHECK(isfinite(out[j].x) && isfinite(out[j].vx) && isfinite(out[j].var_x));
    }
    ft_nf_destroy(f);
    ft_ct_destroy(t);
}

int main(void) {
    test_filters();
    test_tracker();
    test_random();
    if (ft_test_failures) {
        fprintf(stderr, "test_event_algos: %d checks failed\n", ft_test_failures);
        return 1;
    }
    printf("test_event_algos: all checks passed\n");
    return 0;
}

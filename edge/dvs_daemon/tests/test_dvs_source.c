/* The DVS128 source of flytrack-edge through its USB seam, under ASan + UBSan. No DVS128 exists on
 * the build machine: a fake device stands in for libusb (ft_usb_ops). It delivers a DVS word stream
 * in bulk transfers of random sizes (words split across transfers), with WRAP and RESET words and
 * garbage words, is unplugged in the middle of a word and plugged back in after a few failed
 * reopen attempts. Checked: every event decoded with the right time (computed here from the SPEC,
 * independently of the codec), garbage counted, the vendor requests (biases, timestamp master,
 * reset timestamps, start) sent on open and again after the replug, stop on close. */
#define _POSIX_C_SOURCE 200809L
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "dvs_stream.h"
#include "source_events.h"

#include "check.h" /* CHECK(), ft_test_failures: protocol/tests/check.h */

static uint64_t rng = 88172645463325252ull;
static uint32_t rnd(uint32_t n) {
    rng ^= rng << 13;
    rng ^= rng >> 7;
    rng ^= rng << 17;
    return (uint32_t)(rng % n);
}

/* ---- a word stream and the events it must give ---------------------------------------------- */

#define MAXW 20000
typedef struct {
    uint8_t b[4 * MAXW];
    size_t n;
    ft_event expect[MAXW];
    size_t n_expect, n_garbage, n_sync;
    int64_t sync_t[MAXW];
} stream;

static void put_word(stream *s, uint8_t b0, uint8_t b1, uint16_t t) {
    s->b[s->n++] = b0;
    s->b[s->n++] = b1;
    s->b[s->n++] = (uint8_t)t;
    s->b[s->n++] = (uint8_t)(t >> 8);
}

/* Events with a rising 14-bit time, a WRAP word when it passes 0x3FFF, one RESET, garbage. */
static void make_stream(stream *s, size_t words) {
    memset(s, 0, sizeof *s);
    uint64_t offset = 0;
    uint32_t ts = 0;
    for (size_t i = 0; i < words; i++) {
        uint32_t kind = rnd(100);
        if (kind == 0) { /* garbage: RESET and WRAP both set (BAD_FIELD in the SPEC) */
            put_word(s, (uint8_t)rnd(256), (uint8_t)rnd(128), (uint16_t)(0xC000u | rnd(0x4000)));
            s->n_garbage++;
            continue;
        }
#ifdef FT_DVS_SYNC
        if (kind == 2) { /* a sync pulse (protocol versions with the SYNC word) */
            put_word(s, 0, 0x80, (uint16_t)ts);
            s->sync_t[s->n_sync++] = (int64_t)(offset + ts);
            continue;
        }
#endif
        if (kind == 1 && i > words / 2 && offset) { /* the device zeroed its counter */
            put_word(s, 0, 0, 0x4000);
            offset = 0;
            ts = 0;
            continue;
        }
        ts += rnd(40);
        if (ts > 0x3FFF) {
            put_word(s, 0, 0, 0x8000);
            offset += 0x4000;
            ts -= 0x4000;
        }
        uint8_t x = (uint8_t)rnd(128), y = (uint8_t)rnd(128), p = (uint8_t)rnd(2);
        put_word(s, (uint8_t)(x << 1 | p), y, (uint16_t)ts);
        ft_event *e = &s->expect[s->n_expect++];
        e->t = (int64_t)(offset + ts);
        e->x = x;
        e->y = y;
        e->p = p;
    }
}

static int same_event(const ft_event *a, const ft_event *b) {
    return a->t == b->t && a->x == b->x && a->y == b->y && a->p == b->p;
}

/* The parser alone, fed in random pieces (1 byte up to 300), small output room. */
static void test_stream_pieces(void) {
    static stream s;
    make_stream(&s, 5000);
    for (int round = 0; round < 20; round++) {
        ft_dvs_stream st;
        ft_dvs_stream_init(&st);
        static ft_event out[MAXW];
        size_t n = 0, i = 0;
        while (i < s.n) {
            size_t piece = 1 + rnd(round < 5 ? 7 : 300), used;
            if (piece > s.n - i)
                piece = s.n - i;
            size_t off = 0;
            while (off < piece) {
                size_t cap = 1 + rnd(50);
                n += ft_dvs_stream_feed(&st, s.b + i + off, piece - off, out + n, cap, &used);
                off += used;
            }
            i += piece;
        }
        CHECK(n == s.n_expect && st.bad_words == s.n_garbage && st.n_carry == 0);
        size_t bad = 0;
        for (size_t k = 0; k < n && k < s.n_expect; k++)
            bad += !same_event(&out[k], &s.expect[k]);
        CHECK(bad == 0);
        CHECK(st.resets >= 1 && st.wraps >= 1 && st.syncs == s.n_sync && s.n_sync > 10);
        /* each SYNC word's time is kept (the latest FT_DVS_STREAM_SYNCS): the trigger-frame stamp
         */
        size_t wrong = 0;
        for (size_t k = s.n_sync > FT_DVS_STREAM_SYNCS ? s.n_sync - FT_DVS_STREAM_SYNCS : 0;
             k < s.n_sync; k++)
            wrong += st.sync_t[k % FT_DVS_STREAM_SYNCS] != s.sync_t[k];
        CHECK(wrong == 0);
    }
}

/* ---- the fake device behind ft_usb_ops --------------------------------------------------------
 */

typedef struct {
    stream *s;
    size_t pos, unplug_at;
    int present, unplugged_once, failed_opens, opens_to_fail;
    uint8_t requests[64];
    uint16_t values[64];
    int n_requests, closes, biases_ok;
} fake_dev;
static fake_dev dev;

static int f_init(void **ctx) {
    *ctx = &dev;
    return 0;
}
static void *f_open(void *ctx, uint16_t vid, uint16_t pid) {
    fake_dev *d = ctx;
    if (vid != FT_DVS128_VID || pid != FT_DVS128_PID)
        return NULL;
    if (!d->present) {
        if (++d->failed_opens >= d->opens_to_fail)
            d->present = 1; /* plugged back in: the next open finds it */
        return NULL;
    }
    return d;
}
static int f_control(void *h, uint8_t req, uint16_t value, const uint8_t *data, uint16_t len,
                     unsigned timeout_ms) {
    fake_dev *d = h;
    (void)timeout_ms;
    if (d->n_requests < 64) {
        d->values[d->n_requests] = value;
        d->requests[d->n_requests++] = req;
    }
    if (req == FT_DVS128_REQ_BIASES)
        d->biases_ok = len == FT_DVS128_BIAS_BYTES && data && data[0] == 0xAB && data[35] == 0xCD;
    return FT_USB_OK;
}
static int f_bulk(void *h, uint8_t ep, uint8_t *buf, int len, int *got, unsigned timeout_ms) {
    fake_dev *d = h;
    (void)timeout_ms;
    *got = 0;
    if (ep != FT_DVS128_EP_IN)
        return FT_USB_ERROR;
    if (!d->present)
        return FT_USB_NO_DEVICE;
    size_t n = 1 + rnd(333); /* not a multiple of 4: words split across transfers */
    if (n > (size_t)len)
        n = (size_t)len;
    if (!d->unplugged_once && d->pos + n > d->unplug_at) { /* pulled out inside a word */
        n = d->unplug_at - d->pos;
        memcpy(buf, d->s->b + d->pos, n);
        d->pos += n;
        d->present = 0;
        d->unplugged_once = 1;
        *got = (int)n;
        return FT_USB_NO_DEVICE;
    }
    if (d->pos + n > d->s->n)
        n = d->s->n - d->pos;
    if (n == 0)
        return FT_USB_TIMEOUT;
    memcpy(buf, d->s->b + d->pos, n);
    d->pos += n;
    *got = (int)n;
    return FT_USB_OK;
}
static void f_close(void *h) {
    ((fake_dev *)h)->closes++;
}
static const ft_usb_ops fake_ops = {f_init, NULL, f_open, f_control, f_bulk, f_close};

static void test_unplug_replug(void) {
    static stream s1, s2;
    make_stream(&s1, 6000);
    make_stream(&s2, 3000);
    /* after the replug the device restarts its clock: stream 2 follows the cut point */
    static stream all;
    memset(&all, 0, sizeof all);
    size_t cut_word = 2500, unplug_at = 4 * cut_word + 2; /* half a word */
    memcpy(all.b, s1.b, unplug_at);
    memcpy(all.b + unplug_at, s2.b, s2.n);
    all.n = unplug_at + s2.n;
    /* events expected: those of s1's first cut_word words, then all of s2's */
    size_t before = 0;
    {
        ft_dvs_stream st;
        ft_dvs_stream_init(&st);
        static ft_event tmp[MAXW];
        size_t used;
        before = ft_dvs_stream_feed(&st, s1.b, 4 * cut_word, tmp, MAXW, &used);
    }
    memset(&dev, 0, sizeof dev);
    dev.s = &all;
    dev.present = 1;
    dev.unplug_at = unplug_at;
    dev.opens_to_fail = 3;
    uint8_t biases[36] = {0xAB};
    biases[35] = 0xCD;
    ft_ev_source src;
    CHECK(ft_ev_source_open_dvs128(&src, &fake_ops, biases, 10) == 0);
    CHECK(src.width == 128 && src.height == 128 && src.connected);
    CHECK(dev.n_requests == 4 && dev.requests[0] == FT_DVS128_REQ_BIASES && dev.biases_ok);
    CHECK(dev.requests[1] == FT_DVS128_REQ_TS_MASTER && dev.values[1] == 1);
    CHECK(dev.requests[2] == FT_DVS128_REQ_RESET_TS && dev.requests[3] == FT_DVS128_REQ_START);
    static ft_event got[2 * MAXW];
    size_t n = 0;
    int saw_unplug = 0, calls = 0;
    while (calls++ < 100000) {
        long k = src.next(&src, got + n, 16 + rnd(100), 5);
        CHECK(k >= 0);
        if (k < 0)
            break;
        n += (size_t)k;
        if (src.state_changed) {
            src.state_changed = 0;
            saw_unplug += !src.connected;
        }
        if (dev.pos == all.n && src.connected && k == 0)
            break;
    }
    CHECK(saw_unplug == 1 && src.reconnects == 1 && src.connected);
    CHECK(dev.failed_opens == 3);
    /* requests again after the replug: biases, master, reset, start */
    CHECK(dev.n_requests == 8 && dev.requests[7] == FT_DVS128_REQ_START);
    CHECK(n == before + s2.n_expect);
    size_t bad = 0;
    for (size_t k = 0; k < before && k < n; k++)
        bad += !same_event(&got[k], &s1.expect[k]);
    for (size_t k = 0; k < s2.n_expect && before + k < n; k++)
        bad += !same_event(&got[before + k], &s2.expect[k]);
    CHECK(bad == 0);
    CHECK(src.lost >= s2.n_garbage);
    src.close(&src);
    CHECK(dev.requests[dev.n_requests - 1] == FT_DVS128_REQ_STOP);
    CHECK(dev.closes == 2);

    /* an original DVS128 (raw bit 0 = 1 is OFF): polarities inverted on request */
    memset(&dev, 0, sizeof dev);
    dev.s = &s2;
    dev.present = 1;
    dev.unplug_at = (size_t)-1;
    dev.unplugged_once = 1;
    CHECK(ft_ev_source_open_dvs128(&src, &fake_ops, NULL, 10) == 0);
    src.invert_polarity = 1;
    n = 0;
    for (calls = 0; calls < 10000; calls++) {
        long k = src.next(&src, got + n, 64, 5);
        if (k > 0)
            n += (size_t)k;
        else if (dev.pos == s2.n)
            break; /* all delivered and drained */
    }
    CHECK(n == s2.n_expect);
    size_t flipped = 0;
    for (size_t k = 0; k < n && k < s2.n_expect; k++)
        flipped += got[k].p == (s2.expect[k].p ^ 1u) && got[k].x == s2.expect[k].x;
    CHECK(flipped == s2.n_expect);
    src.close(&src);

    /* no device at the start: a clear error, nothing leaked */
    memset(&dev, 0, sizeof dev);
    dev.opens_to_fail = 1000;
    CHECK(ft_ev_source_open_dvs128(&src, &fake_ops, NULL, 10) != 0);
    CHECK(strstr(src.error, "no DVS128 (USB 152a:8400) found") != NULL);
}

int main(void) {
    test_stream_pieces();
    test_unplug_replug();
    if (ft_test_failures) {
        fprintf(stderr, "test_dvs_source: %d checks failed\n", ft_test_failures);
        return 1;
    }
    printf("test_dvs_source: all checks passed\n");
    return 0;
}

/* Fuzz test of every decoder, built with ASan + UBSan (abort on any finding).
 *
 * fuzz_decoders [iterations] [vectors dir]: fixed seed. Inputs are random bytes and mutations of
 * valid messages (the built-in samples plus, when given, every vector of the golden files): bit
 * flips, truncations, byte overwrites, NaN/inf float patterns, length and count fields set to
 * extremes (with the header length fixed up so the deeper checks are reached), extensions, and
 * for serial frames mutations of the body with a correct CRC. Each input goes through every
 * decoder. Oracles beyond "no crash, no UB, no read past len": a decoder returns a known error;
 * an accepted message re-encodes (same size for UDP, same bytes for serial and DVS words) and the
 * re-encoding is accepted again; the byte receiver never holds more than FT_TL_MAX_FRAME bytes. */
#define _POSIX_C_SOURCE 200809L
#include <stdlib.h>

#include "check.h"
#include "samples.h"
#include "vector_runner.h"

static uint64_t rng_state = 0x9E3779B97F4A7C15ull;

static uint64_t rnd(void) { /* xorshift64* */
    rng_state ^= rng_state >> 12;
    rng_state ^= rng_state << 25;
    rng_state ^= rng_state >> 27;
    return rng_state * 2685821657736338717ull;
}
static size_t rnd_below(size_t n) {
    return n ? (size_t)(rnd() % n) : 0;
}

#define MAX_INPUT 2048
#define MAX_SEEDS 1024

typedef struct {
    uint8_t b[MAX_INPUT];
    size_t len;
    int serial; /* a serial frame without delimiter */
} seed_t;

static seed_t seeds[MAX_SEEDS];
static size_t n_seeds;

static void add_seed(const uint8_t *b, size_t len, int serial) {
    if (n_seeds >= MAX_SEEDS || len > MAX_INPUT)
        return;
    memcpy(seeds[n_seeds].b, b, len);
    seeds[n_seeds].len = len;
    seeds[n_seeds].serial = serial;
    n_seeds++;
}

/* Every line of <dir>/<family>.tsv becomes a seed (valid and invalid alike). */
static void load_vector_seeds(const char *dir) {
    size_t f;
    for (f = 0; f < VR_N_FAMILIES; f++) {
        char path[4096], line[65536];
        FILE *fp;
        snprintf(path, sizeof path, "%s/%s.tsv", dir, vr_families[f].name);
        fp = fopen(path, "rb");
        if (!fp)
            continue;
        while (fgets(line, sizeof line, fp)) {
            char *a = strchr(line, '\t'), *b2, *c;
            static uint8_t data[MAX_INPUT];
            long n;
            if (line[0] == '#' || !a || !(b2 = strchr(a + 1, '\t')) || !(c = strchr(b2 + 1, '\t')))
                continue;
            *c = 0;
            n = vr_unhex(b2 + 1, data, sizeof data);
            if (n < 0)
                continue;
            if (vr_families[f].udp_type < 0 && strcmp(vr_families[f].name, "trigger_link") == 0) {
                if (n > 0 && data[n - 1] == 0)
                    add_seed(data, (size_t)n - 1, 1);
            } else {
                add_seed(data, (size_t)n, 0);
            }
        }
        fclose(fp);
    }
}

static const uint16_t extremes16[] = {0,    1,    2,    7,    8,      9,      27,     28,
                                      31,   32,   33,   51,   52,     255,    256,    1427,
                                      1428, 1429, 1464, 1465, 0x7FFF, 0x8000, 0xFFFE, 0xFFFF};
static const uint32_t float_bits[] = {0x7F800000u, 0xFF800000u, 0x7FC00000u, 0xFFC00001u,
                                      0x7F800001u, 0x00000001u, 0x80000000u, 0x7F7FFFFFu};

static void fix_udp_length(uint8_t *b, size_t len) {
    if (len >= 8)
        ft_st_u16(b + 4, (uint16_t)(len - 8));
}

/* Builds one fuzz input into b; returns its length. */
static size_t make_input(uint8_t *b, int *serial) {
    size_t len, i, k;
    const seed_t *s;
    int how = (int)rnd_below(10);
    *serial = 0;
    if (how == 0 || n_seeds == 0) { /* random bytes, sometimes with a valid UDP header */
        len = rnd_below(1600);
        for (i = 0; i < len; i++)
            b[i] = (uint8_t)rnd();
        if (len >= 8 && rnd_below(2)) {
            static const uint8_t types[] = {1, 2, 3, 4, 5, 0x10, 0x11, 0x20};
            b[0] = 'F';
            b[1] = 'T';
            b[2] = 1;
            b[3] = types[rnd_below(sizeof types)];
            fix_udp_length(b, len);
        }
        return len;
    }
    s = &seeds[rnd_below(n_seeds)];
    memcpy(b, s->b, s->len);
    len = s->len;
    *serial = s->serial;
    switch (how) {
    case 1: /* bit flips */
        for (k = 1 + rnd_below(8); k > 0 && len; k--)
            b[rnd_below(len)] ^= (uint8_t)(1u << rnd_below(8));
        break;
    case 2: /* truncation */
        len = rnd_below(len + 1);
        break;
    case 3: /* a u16 field (count, length, size) set to an extreme, header length fixed */
        if (len >= 2) {
            size_t off = rnd_below(len - 1);
            if (!*serial && len >= 12 && rnd_below(2)) {
                static const size_t count_offs[] = {10, 28, 40,
                                                    4}; /* n_points.., n_objects, chunk */
                off = count_offs[rnd_below(4)];
                if (off + 2 > len)
                    off = 10;
            }
            ft_st_u16(b + off, extremes16[rnd_below(sizeof extremes16 / sizeof extremes16[0])]);
            if (!*serial && off != 4 && rnd_below(4))
                fix_udp_length(b, len);
        }
        break;
    case 4: /* overwrite some bytes */
        for (k = 1 + rnd_below(6); k > 0 && len; k--)
            b[rnd_below(len)] = (uint8_t)rnd();
        if (!*serial && rnd_below(2))
            fix_udp_length(b, len);
        break;
    case 5: /* NaN / inf / odd float patterns at 4-aligned payload offsets */
        if (len >= 12) {
            size_t off = 8 + 4 * rnd_below((len - 8) / 4);
            if (off + 4 <= len)
                ft_st_u32(b + off, float_bits[rnd_below(8)]);
        }
        break;
    case 6: /* extend with random bytes (and fix the header length) */
        k = rnd_below(200);
        if (len + k > 1600)
            k = 0;
        for (i = 0; i < k; i++)
            b[len + i] = (uint8_t)rnd();
        len += k;
        if (!*serial)
            fix_udp_length(b, len);
        break;
    case 7:
    case 8: /* serial: mutate the body, keep the CRC right, re-COBS */
        if (*serial) {
            uint8_t body[300];
            size_t bl, el;
            if (ft_cobs_decode(b, len, body, sizeof body, &bl) == FT_OK && bl >= 2) {
                size_t nb = bl;
                if (rnd_below(3) == 0) { /* change the size */
                    nb = rnd_below(80);
                    for (i = bl; i < nb; i++)
                        body[i] = (uint8_t)rnd();
                }
                for (k = rnd_below(3); k > 0 && nb > 2; k--)
                    body[rnd_below(nb - 2)] = (uint8_t)rnd();
                if (nb >= 2)
                    ft_st_u16(body + nb - 2, ft_crc16(body, nb - 2));
                if (ft_cobs_encode(body, nb, b, MAX_INPUT, &el) == FT_OK)
                    len = el;
            }
        } else if (len > 8) { /* UDP: a random payload byte, header length fixed */
            b[8 + rnd_below(len - 8)] ^= (uint8_t)rnd();
            fix_udp_length(b, len);
        }
        break;
    default: /* a stream for the byte receiver: seed bytes with zeros sprinkled in */
        for (k = rnd_below(4); k > 0 && len; k--)
            b[rnd_below(len)] = 0;
        break;
    }
    return len;
}

static ft_any_decoder udp_decoder(uint8_t type) {
    switch (type) {
    case FT_MSG_FEATURES:
        return dec_features;
    case FT_MSG_STATUS:
        return dec_status;
    case FT_MSG_CONTROL:
        return dec_control;
    case FT_MSG_CONTROL_ACK:
        return dec_control_ack;
    case FT_MSG_IMAGE:
        return dec_image;
    case FT_MSG_DVS_CLUSTERS:
        return dec_dvs_clusters;
    case FT_MSG_DVS_WINGBEAT:
        return dec_dvs_wingbeat;
    default:
        return dec_live;
    }
}

/* Oracles on an accepted UDP message: it re-encodes to the same size and is accepted again. */
static void check_udp_roundtrip(const uint8_t *b, size_t len) {
    static uint8_t out[MAX_INPUT];
    size_t ol = 0;
    uint8_t type;
    ft_err e = FT_E_NO_SPACE;
    if (ft_peek_type(b, len, &type) != FT_OK)
        return;
    switch (type) {
    case FT_MSG_FEATURES: {
        ft_features_hdr h;
        ft_point p[FT_FEATURES_MAX_POINTS];
        if (ft_features_decode(b, len, &h, p) != FT_OK)
            return;
        e = ft_features_encode(out, sizeof out, &h, p, &ol);
        break;
    }
    case FT_MSG_STATUS: {
        ft_status m;
        if (ft_status_decode(b, len, &m) != FT_OK)
            return;
        e = ft_status_encode(out, sizeof out, &m, &ol);
        break;
    }
    case FT_MSG_CONTROL: {
        ft_control m;
        if (ft_control_decode(b, len, &m) != FT_OK)
            return;
        e = ft_control_encode(out, sizeof out, &m, &ol);
        break;
    }
    case FT_MSG_CONTROL_ACK: {
        ft_control_ack m;
        if (ft_control_ack_decode(b, len, &m) != FT_OK)
            return;
        e = ft_control_ack_encode(out, sizeof out, &m, &ol);
        break;
    }
    case FT_MSG_IMAGE: {
        ft_image m;
        if (ft_image_decode(b, len, &m) != FT_OK)
            return;
        e = ft_image_encode(out, sizeof out, &m, &ol);
        break;
    }
    case FT_MSG_DVS_CLUSTERS: {
        ft_dvs_clusters_hdr h;
        ft_dvs_cluster c[FT_DVS_MAX_CLUSTERS];
        if (ft_dvs_clusters_decode(b, len, &h, c) != FT_OK)
            return;
        e = ft_dvs_clusters_encode(out, sizeof out, &h, c, &ol);
        break;
    }
    case FT_MSG_DVS_WINGBEAT: {
        ft_dvs_wingbeat_hdr h;
        ft_wing_edge w[FT_DVS_MAX_EDGES];
        if (ft_dvs_wingbeat_decode(b, len, &h, w) != FT_OK)
            return;
        e = ft_dvs_wingbeat_encode(out, sizeof out, &h, w, &ol);
        break;
    }
    case FT_MSG_LIVE_ESTIMATES: {
        ft_live_hdr h;
        ft_live_object o[FT_LIVE_MAX_OBJECTS];
        if (ft_live_estimates_decode(b, len, &h, o) != FT_OK)
            return;
        e = ft_live_estimates_encode(out, sizeof out, &h, o, &ol);
        break;
    }
    default:
        return;
    }
    CHECK_ERR(e, FT_OK);
    CHECK(ol == len);
    if (e == FT_OK) {
        uint8_t t2;
        CHECK_ERR(ft_peek_type(out, ol, &t2), FT_OK);
        CHECK(t2 == type);
        CHECK_ERR(udp_decoder(type)(out, ol), FT_OK);
    }
}

/* An accepted serial frame re-encodes to the same bytes (the INFO reserved u16 is written 0). */
static void check_serial_roundtrip(const uint8_t *b, size_t len) {
    uint8_t id, seq, pl[FT_TL_MAX_PAYLOAD], plen, wire[FT_TL_MAX_WIRE];
    size_t wl;
    if (dec_serial(b, len) != FT_OK)
        return;
    ft_tl_decode(b, len, &id, &seq, pl, &plen);
    if (id == FT_TL_INFO)
        pl[6] = pl[7] = 0;
    CHECK_ERR(ft_tl_encode(wire, sizeof wire, id, seq, pl, plen, &wl), FT_OK);
    CHECK(wl == len + 1 && (id == FT_TL_INFO || memcmp(wire, b, len) == 0));
}

static void check_dvs_roundtrip(const uint8_t *b, size_t len) {
    size_t i, ne;
    if (ft_dvs_packet_check(b, len, &ne) != FT_OK)
        return;
    for (i = 0; i + 4 <= len; i += 4) {
        ft_dvs_word w;
        uint8_t o[4];
        CHECK_ERR(ft_dvs_word_decode(b + i, &w), FT_OK);
        CHECK_ERR(ft_dvs_word_encode(o, &w), FT_OK);
        CHECK(memcmp(o, b + i, 4) == 0);
    }
}

int main(int argc, char **argv) {
    static ft_sample samples[FT_MAX_SAMPLES];
    static uint8_t in[MAX_INPUT + 256];
    long iterations = argc > 1 ? atol(argv[1]) : 300000;
    long it, accepted[FT_N_DECODERS] = {0};
    size_t i, ns = ft_make_samples(samples);
    CHECK(ns > 0);
    for (i = 0; i < ns; i++)
        add_seed(samples[i].bytes, samples[i].len, samples[i].dec == dec_serial);
    if (argc > 2)
        load_vector_seeds(argv[2]);
    printf("fuzz: %zu seeds, %ld inputs, seed 0x%016llx\n", n_seeds, iterations,
           (unsigned long long)rng_state);
    for (it = 0; it < iterations; it++) {
        int serial;
        size_t len = make_input(in, &serial), d;
        /* Copy to an exact-size heap block so that ASan sees any read past len. */
        uint8_t *exact = malloc(len ? len : 1);
        if (!exact)
            return 1;
        memcpy(exact, in, len);
        for (d = 0; d < FT_N_DECODERS; d++) {
            ft_err e = ft_decoders[d].dec(exact, len);
            if ((int)e < 0 || e > FT_E_BAD_CRC) { /* NO_SPACE is no decoder's answer */
                fprintf(stderr, "decoder %s gave %d\n", ft_decoders[d].name, (int)e);
                CHECK(0);
            }
            if (e == FT_OK)
                accepted[d]++;
        }
        check_udp_roundtrip(exact, len);
        check_serial_roundtrip(exact, len);
        check_dvs_roundtrip(exact, len);
        free(exact);
        if (ft_test_failures > 20)
            break;
    }
    printf("accepted per decoder:");
    for (i = 0; i < FT_N_DECODERS; i++)
        printf(" %s=%ld", ft_decoders[i].name, accepted[i]);
    printf("\n");
    return ft_test_report("fuzz_decoders");
}

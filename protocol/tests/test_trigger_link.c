/* Unit tests of wire.h and trigger_link.h: CRC, COBS edge cases, frame encode/decode and every
 * check of the decoder in SPEC order, typed messages, the byte-at-a-time receiver. */
#include <string.h>

#include "flytrack/trigger_link.h"
#include "check.h"

static void test_wire(void) {
    uint8_t b[8];
    ft_st_u16(b, 0xBEEF);
    CHECK(b[0] == 0xEF && b[1] == 0xBE);
    CHECK(ft_ld_u16(b) == 0xBEEF);
    ft_st_u32(b, 0x01020304u);
    CHECK(b[0] == 4 && b[3] == 1 && ft_ld_u32(b) == 0x01020304u);
    ft_st_u64(b, 0x0102030405060708ull);
    CHECK(b[0] == 8 && b[7] == 1 && ft_ld_u64(b) == 0x0102030405060708ull);
    ft_st_i64(b, -1);
    CHECK(ft_ld_i64(b) == -1);
    ft_st_i64(b, INT64_MIN);
    CHECK(ft_ld_i64(b) == INT64_MIN);
    ft_st_i64(b, INT64_MAX);
    CHECK(ft_ld_i64(b) == INT64_MAX);
    CHECK(strcmp(ft_err_name(FT_E_NO_SPACE), "NO_SPACE") == 0);
    CHECK(strcmp(ft_err_name(FT_E_LENGTH_MISMATCH), "LENGTH_MISMATCH") == 0);

    {
        uint8_t t[4] = {'a', 0, 0, 0}, bad[4] = {'a', 0, 'b', 0};
        char s[5];
        CHECK_ERR(ft_text_check(t, 4), FT_OK);
        CHECK_ERR(ft_text_check(bad, 4), FT_E_BAD_FIELD);
        CHECK_ERR(ft_text_store(t, 4, "abcd"), FT_OK);
        CHECK(memcmp(t, "abcd", 4) == 0);
        ft_text_load(s, t, 4);
        CHECK(strcmp(s, "abcd") == 0);
        {
            char toolong[5] = {'a', 'b', 'c', 'd', 'e'};
            CHECK_ERR(ft_text_store(t, 4, toolong), FT_E_BAD_FIELD);
        }
    }
}

static void test_crc(void) {
    const uint8_t s[] = "123456789";
    uint16_t c = FT_CRC16_INIT;
    size_t i;
    CHECK(ft_crc16(s, 9) == 0x29B1);
    for (i = 0; i < 9; i++)
        c = ft_crc16_update(c, s[i]);
    CHECK(c == 0x29B1);
    CHECK(ft_crc16(s, 0) == 0xFFFF);
}

/* Encodes src, checks the expected bytes (if given), decodes back, and checks the round trip. */
static void cobs_round(const uint8_t *src, size_t n, const uint8_t *want, size_t want_n) {
    uint8_t enc[600], dec[600];
    size_t el = 0, dl = 0;
    size_t i;
    CHECK_ERR(ft_cobs_encode(src, n, enc, sizeof enc, &el), FT_OK);
    if (want) {
        CHECK(el == want_n);
        CHECK(el == want_n && memcmp(enc, want, el) == 0);
    }
    for (i = 0; i < el; i++)
        CHECK(enc[i] != 0);
    CHECK(el <= n + n / 254 + 1);
    CHECK_ERR(ft_cobs_decode(enc, el, dec, sizeof dec, &dl), FT_OK);
    CHECK(dl == n && memcmp(dec, src, n) == 0);
    /* exact capacity works, one less is NO_SPACE */
    CHECK_ERR(ft_cobs_encode(src, n, enc, el, &el), FT_OK);
    if (el > 0)
        CHECK_ERR(ft_cobs_encode(src, n, enc, el - 1, &dl), FT_E_NO_SPACE);
    if (n > 0)
        CHECK_ERR(ft_cobs_decode(enc, el, dec, n - 1, &dl), FT_E_NO_SPACE);
    /* in place */
    CHECK_ERR(ft_cobs_decode(enc, el, enc, el, &dl), FT_OK);
    CHECK(dl == n && memcmp(enc, src, n) == 0);
}

static void test_cobs(void) {
    uint8_t src[600] = {0}, want[600];
    size_t i;
    {
        const uint8_t w[] = {0x01};
        cobs_round(src, 0, w, 1);
    }
    {
        const uint8_t s[] = {0x00}, w[] = {0x01, 0x01};
        cobs_round(s, 1, w, 2);
    }
    {
        const uint8_t s[] = {0x00, 0x00}, w[] = {0x01, 0x01, 0x01};
        cobs_round(s, 2, w, 3);
    }
    {
        const uint8_t s[] = {0x11, 0x22, 0x00, 0x33}, w[] = {0x03, 0x11, 0x22, 0x02, 0x33};
        cobs_round(s, 4, w, 5);
    }
    {
        const uint8_t s[] = {0x11, 0x00, 0x00, 0x00}, w[] = {0x02, 0x11, 0x01, 0x01, 0x01};
        cobs_round(s, 4, w, 5);
    }
    /* 254 non-zero bytes: one full block, no trailing code byte */
    for (i = 0; i < 254; i++)
        src[i] = (uint8_t)(i + 1);
    want[0] = 0xFF;
    memcpy(want + 1, src, 254);
    cobs_round(src, 254, want, 255);
    /* 255 non-zero bytes: a full block then a block of one */
    for (i = 0; i < 255; i++)
        src[i] = (uint8_t)(i % 255 + 1);
    want[0] = 0xFF;
    memcpy(want + 1, src, 254);
    want[255] = 0x02;
    want[256] = src[254];
    cobs_round(src, 255, want, 257);
    /* 254 non-zero then a zero */
    for (i = 0; i < 254; i++)
        src[i] = 0x55;
    src[254] = 0;
    want[0] = 0xFF;
    memcpy(want + 1, src, 254);
    want[255] = 0x01;
    want[256] = 0x01;
    cobs_round(src, 255, want, 257);
    /* a zero then 254 non-zero */
    src[0] = 0;
    for (i = 1; i < 255; i++)
        src[i] = 0x77;
    cobs_round(src, 255, NULL, 0);
    /* 600 bytes with zeros every so often, and all zeros */
    for (i = 0; i < 590; i++)
        src[i] = (uint8_t)(i % 300 == 299 ? 0 : (i * 7 + 1) | 1);
    cobs_round(src, 590, NULL, 0);
    memset(src, 0, 590);
    {
        uint8_t enc[600];
        size_t el;
        CHECK_ERR(ft_cobs_encode(src, 590, enc, 590, &el), FT_E_NO_SPACE);
        cobs_round(src, 500, NULL, 0);
    }
    /* a trailing 0x01 after a full block (non-canonical) still decodes */
    {
        uint8_t enc[300], dec[300];
        size_t dl;
        enc[0] = 0xFF;
        memset(enc + 1, 0x42, 254);
        enc[255] = 0x01;
        CHECK_ERR(ft_cobs_decode(enc, 256, dec, sizeof dec, &dl), FT_OK);
        CHECK(dl == 254);
    }
    /* bad COBS: a zero inside, a code past the end */
    {
        const uint8_t z[] = {0x03, 0x11, 0x00}, past[] = {0x05, 0x11, 0x22};
        uint8_t dec[8];
        size_t dl;
        CHECK_ERR(ft_cobs_decode(z, 3, dec, 8, &dl), FT_E_BAD_COBS);
        CHECK_ERR(ft_cobs_decode(past, 3, dec, 8, &dl), FT_E_BAD_COBS);
        CHECK_ERR(ft_cobs_decode(z, 0, dec, 8, &dl), FT_OK);
        CHECK(dl == 0);
    }
}

/* Builds a frame body by hand (for frames ft_tl_encode refuses to build) and COBS-encodes it. */
static size_t raw_frame(uint8_t *wire, const uint8_t *body, size_t n, int fix_crc) {
    uint8_t b[300];
    size_t el = 0;
    memcpy(b, body, n);
    if (fix_crc && n >= 2)
        ft_st_u16(b + n - 2, ft_crc16(b, n - 2));
    if (ft_cobs_encode(b, n, wire, 400, &el) != FT_OK)
        return 0;
    return el;
}

static void test_frames(void) {
    uint8_t wire[FT_TL_MAX_WIRE], pl[FT_TL_MAX_PAYLOAD], id, seq, plen;
    size_t wl = 0, cut;
    ft_tl_clock clk = {123456789u, 4321, 19999, 1}, clk2 = {0, 0, 0, 0};
    uint8_t p[FT_TL_CLOCK_SIZE];

    CHECK_ERR(ft_tl_pack_clock(p, &clk), FT_OK);
    CHECK_ERR(ft_tl_encode(wire, sizeof wire, FT_TL_CLOCK, 7, p, sizeof p, &wl), FT_OK);
    CHECK(wl == FT_TL_CLOCK_SIZE + 8 && wire[wl - 1] == 0);
    CHECK(memchr(wire, 0, wl - 1) == NULL);
    CHECK_ERR(ft_tl_decode(wire, wl - 1, &id, &seq, pl, &plen), FT_OK);
    CHECK(id == FT_TL_CLOCK && seq == 7 && plen == FT_TL_CLOCK_SIZE);
    CHECK_ERR(ft_tl_unpack_clock(pl, plen, &clk2), FT_OK);
    CHECK(clk2.frame_count == clk.frame_count && clk2.ticks == clk.ticks && clk2.top == clk.top &&
          clk2.running == 1);
    /* The streaming decoder agrees with COBS decode + CRC check. */
    {
        uint8_t body[80];
        size_t bl;
        CHECK_ERR(ft_cobs_decode(wire, wl - 1, body, sizeof body, &bl), FT_OK);
        CHECK(bl == FT_TL_CLOCK_SIZE + 6 && body[0] == 0x46 && body[1] == FT_PROTOCOL_VERSION &&
              body[2] == 0x84);
        CHECK(ft_ld_u16(body + bl - 2) == ft_crc16(body, bl - 2));
    }
    /* NO_SPACE at every cap below the need; LENGTH_MISMATCH on a wrong payload size */
    for (cut = 0; cut < wl; cut++)
        CHECK_ERR(ft_tl_encode(wire, cut, FT_TL_CLOCK, 7, p, sizeof p, &wl), FT_E_NO_SPACE);
    CHECK_ERR(ft_tl_encode(wire, sizeof wire, FT_TL_CLOCK, 7, p, 8, &wl), FT_E_LENGTH_MISMATCH);
    CHECK_ERR(ft_tl_encode(wire, sizeof wire, FT_TL_CLOCK, 7, p, sizeof p, &wl), FT_OK);
    /* Every truncation of the COBS bytes is rejected (never accepted as something else). */
    for (cut = 0; cut < wl - 1; cut++) {
        ft_err e = ft_tl_decode(wire, cut, &id, &seq, pl, &plen);
        CHECK(e != FT_OK);
    }
    CHECK_ERR(ft_tl_decode(wire, 0, &id, &seq, pl, &plen), FT_E_TRUNCATED);
    /* A zero inside the frame */
    {
        uint8_t w2[FT_TL_MAX_WIRE];
        memcpy(w2, wire, wl);
        w2[3] = 0;
        CHECK_ERR(ft_tl_decode(w2, wl - 1, &id, &seq, pl, &plen), FT_E_BAD_COBS);
        w2[0] = 0xFE; /* code byte past the end */
        memcpy(w2 + 1, wire + 1, wl - 1);
        CHECK_ERR(ft_tl_decode(w2, wl - 1, &id, &seq, pl, &plen), FT_E_BAD_COBS);
    }
    /* CRC flip */
    {
        uint8_t body[] = {0x46, FT_PROTOCOL_VERSION, 0x82, 9, 0x03, 0, 0};
        uint8_t w2[32];
        size_t n = raw_frame(w2, body, sizeof body, 1);
        CHECK_ERR(ft_tl_decode(w2, n, &id, &seq, pl, &plen), FT_OK);
        CHECK(id == 0x82 && seq == 9 && plen == 1 && pl[0] == 3);
        body[5] = 0x12;
        n = raw_frame(w2, body, sizeof body, 0);
        CHECK_ERR(ft_tl_decode(w2, n, &id, &seq, pl, &plen), FT_E_BAD_CRC);
        CHECK(id == 0x82 && seq == 9); /* attributable */
    }
    /* SPEC order: magic, version, msg_id, length; each with a good CRC */
    {
        uint8_t w2[32];
        const uint8_t bad_magic[] = {0x47, 2, 0xEE, 1, 0, 0};
        const uint8_t bad_version[] = {0x46, FT_PROTOCOL_VERSION + 1, 0xEE, 1, 0, 0};
        const uint8_t unknown[] = {0x46, FT_PROTOCOL_VERSION, 0xEE, 1, 5, 0, 0};
        const uint8_t too_short[] = {0x46, FT_PROTOCOL_VERSION, 0x82, 1, 0, 0};
        const uint8_t too_long[] = {0x46, FT_PROTOCOL_VERSION, 0x03, 1, 5, 0, 0};
        const uint8_t five[] = {0x46, FT_PROTOCOL_VERSION, 0x03, 1, 0};
        size_t n;
        n = raw_frame(w2, bad_magic, sizeof bad_magic, 1);
        CHECK_ERR(ft_tl_decode(w2, n, &id, &seq, pl, &plen), FT_E_BAD_MAGIC);
        n = raw_frame(w2, bad_version, sizeof bad_version, 1);
        CHECK_ERR(ft_tl_decode(w2, n, &id, &seq, pl, &plen), FT_E_BAD_VERSION);
        n = raw_frame(w2, unknown, sizeof unknown, 1);
        CHECK_ERR(ft_tl_decode(w2, n, &id, &seq, pl, &plen), FT_E_UNKNOWN_TYPE);
        n = raw_frame(w2, too_short, sizeof too_short, 1);
        CHECK_ERR(ft_tl_decode(w2, n, &id, &seq, pl, &plen), FT_E_LENGTH_MISMATCH);
        n = raw_frame(w2, too_long, sizeof too_long, 1);
        CHECK_ERR(ft_tl_decode(w2, n, &id, &seq, pl, &plen), FT_E_LENGTH_MISMATCH);
        n = raw_frame(w2, five, sizeof five, 1);
        CHECK_ERR(ft_tl_decode(w2, n, &id, &seq, pl, &plen), FT_E_TRUNCATED);
    }
    /* A body far longer than 64 bytes with a valid CRC: no write past the payload buffer. */
    {
        uint8_t body[200], w2[400];
        uint8_t guard[FT_TL_MAX_PAYLOAD + 8];
        size_t n;
        memset(body, 0xAB, sizeof body);
        body[0] = 0x46;
        body[1] = FT_PROTOCOL_VERSION;
        body[2] = FT_TL_INFO;
        n = raw_frame(w2, body, sizeof body, 1);
        memset(guard, 0xCC, sizeof guard);
        CHECK_ERR(ft_tl_decode(w2, n, &id, &seq, guard, &plen), FT_E_LENGTH_MISMATCH);
        CHECK(guard[FT_TL_MAX_PAYLOAD] == 0xCC);
    }
}

static void test_messages(void) {
    uint8_t p[FT_TL_MAX_PAYLOAD], wire[FT_TL_MAX_WIRE], pl[FT_TL_MAX_PAYLOAD], id, seq, plen;
    size_t wl;
    {
        ft_tl_info a = {1, 0, 3, 2, FT_TL_MCU_ATMEGA328P, 4, 16000000u, "trigger-box-01"}, b;
        CHECK_ERR(ft_tl_pack_info(p, &a), FT_OK);
        CHECK_ERR(ft_tl_encode(wire, sizeof wire, FT_TL_INFO, 1, p, FT_TL_INFO_SIZE, &wl), FT_OK);
        CHECK(wl <= FT_TL_MAX_WIRE);
        CHECK_ERR(ft_tl_decode(wire, wl - 1, &id, &seq, pl, &plen), FT_OK);
        CHECK_ERR(ft_tl_unpack_info(pl, plen, &b), FT_OK);
        CHECK(b.f_cpu == 16000000u && b.mcu == 1 && b.n_outputs == 4 && b.fw_minor == 3);
        CHECK(strcmp(b.name, "trigger-box-01") == 0);
        pl[4] = 3;
        CHECK_ERR(ft_tl_unpack_info(pl, plen, &b), FT_E_BAD_FIELD);
        pl[4] = 1;
        pl[12 + 15] = 'x'; /* after the first NUL */
        CHECK_ERR(ft_tl_unpack_info(pl, plen, &b), FT_E_BAD_FIELD);
        CHECK_ERR(ft_tl_unpack_info(pl, plen - 1, &b), FT_E_LENGTH_MISMATCH);
        a.mcu = 0;
        CHECK_ERR(ft_tl_pack_info(p, &a), FT_E_BAD_FIELD);
    }
    {
        ft_tl_set_rate a = {3, 24999}, b;
        CHECK_ERR(ft_tl_pack_set_rate(p, &a), FT_OK);
        CHECK_ERR(ft_tl_unpack_set_rate(p, 3, &b), FT_OK);
        CHECK(b.prescaler_code == 3 && b.top == 24999);
        p[0] = 6;
        CHECK_ERR(ft_tl_unpack_set_rate(p, 3, &b), FT_E_BAD_FIELD);
        p[0] = 0;
        CHECK_ERR(ft_tl_unpack_set_rate(p, 3, &b), FT_E_BAD_FIELD);
        a.prescaler_code = 0;
        CHECK_ERR(ft_tl_pack_set_rate(p, &a), FT_E_BAD_FIELD);
    }
    {
        ft_tl_rate a = {16000000u, 5, 155}, b;
        CHECK_ERR(ft_tl_pack_rate(p, &a), FT_OK);
        CHECK_ERR(ft_tl_unpack_rate(p, 7, &b), FT_OK);
        CHECK(b.f_cpu == 16000000u && b.prescaler_code == 5 && b.top == 155);
    }
    {
        ft_tl_pulse a = {2, FT_TL_PULSE_NOW, 100}, b;
        CHECK_ERR(ft_tl_pack_pulse(p, &a), FT_OK);
        CHECK_ERR(ft_tl_unpack_pulse(p, 7, &b), FT_OK);
        CHECK(b.channel == 2 && b.frame == 0xFFFFFFFFu && b.width_ticks == 100);
    }
    {
        ft_tl_set_output a = {1, 1}, b;
        CHECK_ERR(ft_tl_pack_set_output(p, &a), FT_OK);
        CHECK_ERR(ft_tl_unpack_set_output(p, 2, &b), FT_OK);
        p[1] = 2;
        CHECK_ERR(ft_tl_unpack_set_output(p, 2, &b), FT_E_BAD_FIELD);
    }
    {
        ft_tl_set_name a, b;
        memcpy(a.name, "0123456789abcdef", 17); /* fills the field: no NUL on the wire */
        CHECK_ERR(ft_tl_pack_set_name(p, &a), FT_OK);
        CHECK(memcmp(p, "0123456789abcdef", 16) == 0);
        CHECK_ERR(ft_tl_unpack_set_name(p, 16, &b), FT_OK);
        CHECK(strcmp(b.name, "0123456789abcdef") == 0);
    }
    {
        ft_tl_event a = {1, 1, 77, 500}, b;
        CHECK_ERR(ft_tl_pack_event(p, &a), FT_OK);
        CHECK_ERR(ft_tl_unpack_event(p, 8, &b), FT_OK);
        CHECK(b.channel == 1 && b.edge == 1 && b.frame_count == 77 && b.ticks == 500);
        p[1] = 2;
        CHECK_ERR(ft_tl_unpack_event(p, 8, &b), FT_E_BAD_FIELD);
    }
    {
        ft_tl_error a = {FT_TL_ERR_BAD_CRC, 0x07}, b;
        ft_tl_ack c = {0x03}, d;
        CHECK_ERR(ft_tl_pack_error(p, &a), FT_OK);
        CHECK_ERR(ft_tl_unpack_error(p, 2, &b), FT_OK);
        CHECK(b.code == 1 && b.msg_id == 7);
        CHECK_ERR(ft_tl_pack_ack(p, &c), FT_OK);
        CHECK_ERR(ft_tl_unpack_ack(p, 1, &d), FT_OK);
        CHECK(d.acked_id == 3);
    }
    CHECK(ft_tl_payload_size(0x00) == -1 && ft_tl_payload_size(0x87) == -1);
    CHECK(ft_tl_payload_size(FT_TL_GET_INFO) == 0 && ft_tl_payload_size(FT_TL_INFO) == 28);
    CHECK(ft_tl_err_code(FT_E_BAD_CRC) == FT_TL_ERR_BAD_CRC);
    CHECK(ft_tl_err_code(FT_E_BAD_VERSION) == FT_TL_ERR_BAD_VERSION);
}

static void test_rx(void) {
    ft_tl_rx rx;
    uint8_t wire[FT_TL_MAX_WIRE], id, seq, plen, pl[FT_TL_MAX_PAYLOAD];
    size_t wl, i;
    int r = 0, frames = 0;
    ft_tl_rx_init(&rx);
    CHECK_ERR(ft_tl_encode(wire, sizeof wire, FT_TL_START, 42, NULL, 0, &wl), FT_OK);
    /* leading delimiters are skipped, then two frames back to back */
    CHECK(ft_tl_rx_push(&rx, 0) == FT_TL_RX_NONE);
    for (i = 0; i < 2 * wl; i++) {
        r = ft_tl_rx_push(&rx, wire[i % wl]);
        if (r == FT_TL_RX_FRAME) {
            frames++;
            CHECK(rx.len == wl - 1);
            CHECK_ERR(ft_tl_decode(rx.buf, rx.len, &id, &seq, pl, &plen), FT_OK);
            CHECK(id == FT_TL_START && seq == 42);
        } else {
            CHECK(r == FT_TL_RX_NONE);
        }
    }
    CHECK(frames == 2);
    /* exactly FT_TL_MAX_FRAME bytes is still a frame */
    for (i = 0; i < FT_TL_MAX_FRAME; i++)
        CHECK(ft_tl_rx_push(&rx, 0x11) == FT_TL_RX_NONE);
    CHECK(ft_tl_rx_push(&rx, 0) == FT_TL_RX_FRAME && rx.len == FT_TL_MAX_FRAME);
    /* one more is TOO_LONG, reported once at its delimiter, and never overflows */
    for (i = 0; i < 1000; i++)
        CHECK(ft_tl_rx_push(&rx, 0x22) == FT_TL_RX_NONE);
    CHECK(rx.len <= FT_TL_MAX_FRAME);
    CHECK(ft_tl_rx_push(&rx, 0) == FT_TL_RX_TOO_LONG);
    /* then it resynchronises */
    frames = 0;
    for (i = 0; i < wl; i++)
        if (ft_tl_rx_push(&rx, wire[i]) == FT_TL_RX_FRAME)
            frames++;
    CHECK(frames == 1 && rx.len == wl - 1);
}

int main(void) {
    test_wire();
    test_crc();
    test_cobs();
    test_frames();
    test_messages();
    test_rx();
    return ft_test_report("test_trigger_link");
}

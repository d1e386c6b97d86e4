/* FlyTrack trigger firmware: the serial link of protocol/SPEC.md section 3 on top of the frame
 * timer.
 *
 * The main loop feeds received bytes to the COBS receiver, answers each request, and sends queued
 * input events. Bad frames get an ERROR reply when they can be attributed (a header was decoded)
 * and are dropped otherwise; the receiver is back in step at the next delimiter. The watchdog
 * resets the chip if the loop ever stops running.
 */
#include <avr/eeprom.h>
#include <avr/interrupt.h>
#include <avr/io.h>
#include <avr/wdt.h>
#include <string.h>

#include "board.h"
#include "flytrack/trigger_link.h"
#include "frame_timer.h"
#include "serial.h"

#define FW_MAJOR 1
#define FW_MINOR 0
#define FW_PATCH 0

#define EE_MAGIC 0xA7
#define DEFAULT_NAME "flytrack-trigger"

/* EEPROM layout: magic byte, then the 16-byte name field exactly as on the wire. */
static uint8_t EEMEM ee_magic;
static uint8_t EEMEM ee_name[FT_TL_NAME_LEN];

static ft_tl_rx s_rx;
static uint8_t s_event_seq;
static char s_name[FT_TL_NAME_LEN + 1];

/* The watchdog stays enabled across a watchdog reset on these chips: turn it off first thing. */
void wdt_early_off(void) __attribute__((naked, used, section(".init3")));
void wdt_early_off(void) {
    MCUSR = 0;
    wdt_disable();
}

static void load_name(void) {
    uint8_t raw[FT_TL_NAME_LEN];
    if (eeprom_read_byte(&ee_magic) == EE_MAGIC) {
        eeprom_read_block(raw, ee_name, FT_TL_NAME_LEN);
        if (ft_text_check(raw, FT_TL_NAME_LEN) == FT_OK) {
            ft_text_load(s_name, raw, FT_TL_NAME_LEN);
            return;
        }
    }
    strcpy(s_name, DEFAULT_NAME);
}

static void send(uint8_t msg_id, uint8_t seq, const uint8_t *payload, uint8_t len) {
    uint8_t wire[FT_TL_MAX_WIRE];
    size_t n;
    if (ft_tl_encode(wire, sizeof wire, msg_id, seq, payload, len, &n) == FT_OK)
        serial_write(wire, (uint8_t)n);
}

static void send_error(uint8_t seq, uint8_t code, uint8_t msg_id) {
    uint8_t p[FT_TL_ERROR_SIZE];
    ft_tl_error e;
    e.code = code;
    e.msg_id = msg_id;
    ft_tl_pack_error(p, &e);
    send(FT_TL_ERROR, seq, p, sizeof p);
}

static void send_ack(uint8_t seq, uint8_t msg_id) {
    send(FT_TL_ACK, seq, &msg_id, 1);
}

static void send_rate(uint8_t seq) {
    uint8_t p[FT_TL_RATE_SIZE];
    ft_tl_rate r;
    r.f_cpu = F_CPU;
    ft_timer_get_rate(&r.prescaler_code, &r.top);
    ft_tl_pack_rate(p, &r);
    send(FT_TL_RATE, seq, p, sizeof p);
}

static void send_timer_result(uint8_t seq, uint8_t msg_id, uint8_t rc) {
    if (rc == FT_TIMER_OK)
        send_ack(seq, msg_id);
    else
        send_error(seq, rc == FT_TIMER_BUSY ? FT_TL_ERR_BUSY : FT_TL_ERR_BAD_ARG, msg_id);
}

static void set_output(uint8_t ch, uint8_t level) {
    volatile uint8_t *port;
    uint8_t bit;
    switch (ch) {
    case 0:
        port = &PULSE_PORT;
        bit = _BV(PULSE_BIT);
        break;
    case 1:
        port = &OUT1_PORT;
        bit = _BV(OUT1_BIT);
        break;
    case 2:
        port = &OUT2_PORT;
        bit = _BV(OUT2_BIT);
        break;
    default:
        port = &OUT3_PORT;
        bit = _BV(OUT3_BIT);
        break;
    }
    {
        uint8_t sreg = SREG;
        cli();
        if (level)
            *port |= bit;
        else
            *port &= (uint8_t)~bit;
        SREG = sreg;
    }
}

static void handle(uint8_t msg_id, uint8_t seq, const uint8_t *payload, uint8_t len) {
    switch (msg_id) {
    case FT_TL_GET_INFO: {
        uint8_t p[FT_TL_INFO_SIZE];
        ft_tl_info info;
        info.protocol_version = FT_PROTOCOL_VERSION;
        info.fw_major = FW_MAJOR;
        info.fw_minor = FW_MINOR;
        info.fw_patch = FW_PATCH;
        info.mcu = FT_MCU_ID;
        info.n_outputs = FT_N_OUTPUTS;
        info.f_cpu = F_CPU;
        memcpy(info.name, s_name, sizeof info.name);
        ft_tl_pack_info(p, &info);
        send(FT_TL_INFO, seq, p, sizeof p);
        break;
    }
    case FT_TL_SET_RATE: {
        ft_tl_set_rate r;
        uint8_t rc;
        if (ft_tl_unpack_set_rate(payload, len, &r) != FT_OK) {
            send_error(seq, FT_TL_ERR_BAD_ARG, msg_id);
            break;
        }
        rc = ft_timer_set_rate(r.prescaler_code, r.top);
        if (rc == FT_TIMER_OK)
            send_rate(seq);
        else
            send_timer_result(seq, msg_id, rc);
        break;
    }
    case FT_TL_START:
        ft_timer_start();
        send_ack(seq, msg_id);
        break;
    case FT_TL_STOP:
        ft_timer_stop();
        send_ack(seq, msg_id);
        break;
    case FT_TL_STOP_RESET:
        ft_timer_stop_reset();
        send_ack(seq, msg_id);
        break;
    case FT_TL_CLOCK_QUERY: {
        uint8_t p[FT_TL_CLOCK_SIZE];
        ft_tl_clock c;
        uint8_t cs;
        ft_timer_clock(&c.frame_count, &c.ticks);
        ft_timer_get_rate(&cs, &c.top);
        c.running = ft_timer_running();
        ft_tl_pack_clock(p, &c);
        send(FT_TL_CLOCK, seq, p, sizeof p);
        break;
    }
    case FT_TL_PULSE: {
        ft_tl_pulse pu;
        if (ft_tl_unpack_pulse(payload, len, &pu) != FT_OK || pu.channel != 0)
            /* only channel 0 has a hardware compare unit for exact pulses */
            send_error(seq, FT_TL_ERR_BAD_ARG, msg_id);
        else
            send_timer_result(seq, msg_id, ft_timer_pulse(pu.frame, pu.width_ticks));
        break;
    }
    case FT_TL_SET_OUTPUT: {
        ft_tl_set_output o;
        if (ft_tl_unpack_set_output(payload, len, &o) != FT_OK || o.channel >= FT_N_OUTPUTS) {
            send_error(seq, FT_TL_ERR_BAD_ARG, msg_id);
            break;
        }
        set_output(o.channel, o.level);
        send_ack(seq, msg_id);
        break;
    }
    case FT_TL_SET_NAME: {
        ft_tl_set_name n;
        if (ft_tl_unpack_set_name(payload, len, &n) != FT_OK) {
            send_error(seq, FT_TL_ERR_BAD_ARG, msg_id);
            break;
        }
        memcpy(s_name, n.name, sizeof s_name);
        eeprom_update_block(payload, ee_name, FT_TL_NAME_LEN);
        eeprom_update_byte(&ee_magic, EE_MAGIC);
        send_ack(seq, msg_id);
        break;
    }
    default:
        /* A reply id sent to the device: a valid frame, but not a request. */
        send_error(seq, FT_TL_ERR_UNKNOWN_TYPE, msg_id);
        break;
    }
}

static void on_frame(const uint8_t *frame, uint8_t len) {
    uint8_t payload[FT_TL_MAX_PAYLOAD];
    uint8_t msg_id, seq, plen;
    ft_err e = ft_tl_decode(frame, len, &msg_id, &seq, payload, &plen);
    if (e == FT_OK) {
        handle(msg_id, seq, payload, plen);
        return;
    }
    /* Garbage that is not even COBS, or too short to hold a header, cannot be attributed. */
    if (e == FT_E_BAD_COBS || e == FT_E_TRUNCATED)
        return;
    send_error(seq, ft_tl_err_code(e), msg_id);
}

int main(void) {
    uint8_t b;
    ft_event_t ev;
    for (b = 1; b <= 3; b++)
        set_output(b, 0);
    OUT1_DDR |= _BV(OUT1_BIT);
    OUT2_DDR |= _BV(OUT2_BIT);
    OUT3_DDR |= _BV(OUT3_BIT);
    load_name();
    ft_tl_rx_init(&s_rx);
    ft_timer_init();
    serial_init();
    wdt_enable(WDTO_500MS);
    sei();
    for (;;) {
        wdt_reset();
        while (serial_read(&b)) {
            int r = ft_tl_rx_push(&s_rx, b);
            if (r == FT_TL_RX_FRAME)
                on_frame(s_rx.buf, s_rx.len);
            else if (r == FT_TL_RX_TOO_LONG)
                send_error(0, FT_TL_ERR_TOO_LONG, 0);
            wdt_reset();
        }
        if (ft_timer_pop_event(&ev)) {
            uint8_t p[FT_TL_EVENT_SIZE];
            ft_tl_event e;
            e.channel = ev.channel;
            e.edge = ev.edge;
            e.frame_count = ev.frame_count;
            e.ticks = ev.ticks;
            ft_tl_pack_event(p, &e);
            send(FT_TL_EVENT, s_event_seq++, p, sizeof p);
        }
    }
}

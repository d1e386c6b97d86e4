/* Built with avr-gcc for an ATmega328P (ctest protocol_avr_build): proves wire.h and
 * trigger_link.h compile for the AVR under -Wall -Wextra -Werror, and measures the code size of a
 * firmware-like use of the trigger-link codec (receive, decode, unpack, reply). The volatile bytes
 * stand in for the UART data register so that nothing is optimised away. */
#include "flytrack/trigger_link.h"

volatile uint8_t ft_uart_in;
volatile uint8_t ft_uart_out;

static void send(const uint8_t *p, size_t n) {
    size_t i;
    for (i = 0; i < n; i++)
        ft_uart_out = p[i];
}

int main(void) {
    static ft_tl_rx rx;
    uint8_t pl[FT_TL_MAX_PAYLOAD], out[FT_TL_MAX_PAYLOAD], wire[FT_TL_MAX_WIRE];
    uint8_t id, seq, plen;
    size_t wl;
    ft_tl_rx_init(&rx);
    for (;;) {
        int r = ft_tl_rx_push(&rx, ft_uart_in);
        ft_err e;
        uint8_t rid = FT_TL_ACK, rlen = FT_TL_ACK_SIZE;
        if (r == FT_TL_RX_NONE)
            continue;
        if (r == FT_TL_RX_TOO_LONG) {
            ft_tl_error er = {FT_TL_ERR_TOO_LONG, 0};
            ft_tl_pack_error(out, &er);
            if (ft_tl_encode(wire, sizeof wire, FT_TL_ERROR, 0, out, FT_TL_ERROR_SIZE, &wl) ==
                FT_OK)
                send(wire, wl);
            continue;
        }
        e = ft_tl_decode(rx.buf, rx.len, &id, &seq, pl, &plen);
        if (e == FT_OK) {
            switch (id) {
            case FT_TL_SET_RATE: {
                ft_tl_set_rate m;
                e = ft_tl_unpack_set_rate(pl, plen, &m);
                break;
            }
            case FT_TL_PULSE: {
                ft_tl_pulse m;
                e = ft_tl_unpack_pulse(pl, plen, &m);
                break;
            }
            case FT_TL_SET_OUTPUT: {
                ft_tl_set_output m;
                e = ft_tl_unpack_set_output(pl, plen, &m);
                break;
            }
            case FT_TL_SET_NAME: {
                ft_tl_set_name m;
                e = ft_tl_unpack_set_name(pl, plen, &m);
                break;
            }
            case FT_TL_GET_INFO: {
                ft_tl_info m = {1, 0, 1, 0, FT_TL_MCU_ATMEGA328P, 4, 16000000ul, "trigger"};
                e = ft_tl_pack_info(out, &m);
                rid = FT_TL_INFO;
                rlen = FT_TL_INFO_SIZE;
                break;
            }
            case FT_TL_CLOCK_QUERY: {
                ft_tl_clock m = {ft_uart_in, ft_uart_in, 0xFFFF, 1};
                e = ft_tl_pack_clock(out, &m);
                rid = FT_TL_CLOCK;
                rlen = FT_TL_CLOCK_SIZE;
                break;
            }
            default:
                break;
            }
            if (rid == FT_TL_ACK) {
                ft_tl_ack a = {id};
                ft_tl_pack_ack(out, &a);
            }
        }
        if (e != FT_OK) {
            ft_tl_error er = {ft_tl_err_code(e), id};
            ft_tl_pack_error(out, &er);
            rid = FT_TL_ERROR;
            rlen = FT_TL_ERROR_SIZE;
        }
        if (ft_tl_encode(wire, sizeof wire, rid, seq, out, rlen, &wl) == FT_OK)
            send(wire, wl);
    }
}

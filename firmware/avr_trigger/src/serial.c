#include "serial.h"

#include <avr/interrupt.h>
#include <avr/io.h>
#include <avr/wdt.h>

#include "board.h"

#define BAUD 115200UL
#define RX_SIZE 128 /* power of two; two longest frames */

static volatile uint8_t s_rx[RX_SIZE];
static volatile uint8_t s_rx_head, s_rx_tail;
static volatile uint16_t s_overruns;

void serial_init(void) {
    /* Double speed: UBRR 16 gives 117647 baud at 16 MHz (2.1 % off, what the Arduino core uses). */
    UART_UBRR = (uint16_t)((F_CPU / (8UL * BAUD)) - 1UL);
    UART_UCSRA = _BV(UART_U2X);
    UART_UCSRC = _BV(UART_UCSZ1) | _BV(UART_UCSZ0);
    UART_UCSRB = _BV(UART_RXEN) | _BV(UART_TXEN) | _BV(UART_RXCIE);
}

ISR(UART_RX_vect) {
    uint8_t b = UART_UDR;
    uint8_t next = (uint8_t)((s_rx_head + 1) & (RX_SIZE - 1));
    if (next == s_rx_tail) {
        s_overruns++;
        return;
    }
    s_rx[s_rx_head] = b;
    s_rx_head = next;
}

uint8_t serial_read(uint8_t *b) {
    uint8_t tail = s_rx_tail;
    if (tail == s_rx_head)
        return 0;
    *b = s_rx[tail];
    s_rx_tail = (uint8_t)((tail + 1) & (RX_SIZE - 1));
    return 1;
}

void serial_write(const uint8_t *p, uint8_t n) {
    while (n--) {
        while (!(UART_UCSRA & _BV(UART_UDRE)))
            ;
        UART_UDR = *p++;
    }
}

uint16_t serial_overruns(void) {
    uint16_t n;
    uint8_t sreg = SREG;
    cli();
    n = s_overruns;
    SREG = sreg;
    return n;
}

/* strawlab_box: a stand-in for the strawlab triggerbox firmware (version 14, Arduino Nano,
 * ATmega328P at 16 MHz), so that FlyTrack's strawlab driver can be tested in simavr against what
 * that box does on the wire. Written for FlyTrack from the box's documented behaviour; it shares
 * no code with the original (an Arduino sketch). What a host sees, and this reproduces:
 *
 * Boot. The UART starts at 9600 baud (U2X, UBRR 207) for a name handshake: for 5 s, every 20 ms,
 * one received byte is taken and dropped unless it is 'N'; an 'N' and the byte after it are
 * handled as a name command (below) and end the handshake. Then 0.5 s of nothing, the transmitter
 * drained, the UART switched off (what it had received is lost) and on again at "115200" baud:
 * UBRR 16 with U2X, which is 16 MHz / 136 = 117647 baud on the wire. All told ~5.55 s after
 * reset before the box answers a command. Timer1 then runs at 25 fps (prescaler 64, TOP 10000).
 *
 * Commands: two bytes, taken whenever two are waiting (no framing: one stray byte shifts every
 * later pair). 'P' x: clock sample, replied 'P'. 'V' x: replied 'V' with value 14. 'S' '0': stop,
 * TCNT1 and the pulse count zeroed; 'S' '1': start; 'S' '2': stop only. 'T' '=' + u16 LE TOP +
 * '1' (prescaler 8) or '2' (64): TOP set at once, the prescaler at the next start. 'O' '=' + u16 +
 * u16 (analog outputs) + u8 x: replied 'O' with value x. 'N' '?': the 8 name bytes from EEPROM,
 * then their CRC-8/Maxim in upper-case hex without leading zero (one or two characters), no
 * header, no length, no checksum. 'N' '=' + 8 bytes + 2 hex characters: the name is stored when
 * the CRC matches. Anything else: both bytes dropped. The bytes after 'T=' and 'O=' are waited for
 * in steps of 10 ms, so those commands take tens of ms.
 *
 * Replies 'P', 'V', 'O': header, length 7, {u8 value, u32 pulse count, u16 TCNT1} little-endian,
 * then the sum of those 7 bytes mod 256. Count and TCNT1 are read together with interrupts off.
 *
 * Frame timer: Timer1 fast PWM, TOP = ICR1, OC1A (D9) set at BOTTOM and cleared at the match with
 * OCR1A = 1000. The pulse count is incremented in the OCR1A match interrupt, that is once TCNT1
 * has passed 1000 (and the interrupt has run), not at the wrap: a sample with TCNT1 <= 1000 has
 * the count of the frames before the one under way.
 *
 * Timer0 runs as the Arduino core runs it (prescaler 64, overflow interrupt every 1.024 ms): it
 * is the box's millisecond clock and, as on the box, its interrupt can hold the Timer1 one back.
 *
 * Left out (no effect on the wire): the status LEDs, the MCP4822 DAC behind 'O=' (the values are
 * read and dropped), and the original's OC1B output on D10.
 */
#include <avr/eeprom.h>
#include <avr/interrupt.h>
#include <avr/io.h>
#include <stdint.h>

#define BOX_VERSION 14
#define NAME_LEN 8
#define TRIGGER_MARK 1000 /* OCR1A */
#define BOOT_TOP 10000    /* 25 fps at prescaler 64 */
#define UBRR_9600 207     /* with U2X: 9615 baud */
#define UBRR_115200 16    /* with U2X: 117647 baud */

#define TCCR1B_STOPPED (_BV(WGM13) | _BV(WGM12))
#define CS_DIV8 _BV(CS11)
#define CS_DIV64 (_BV(CS11) | _BV(CS10))

/* The name the simulated box was given (a real one holds what `N=` last stored there). */
EEMEM uint8_t ee_name[NAME_LEN] = {'t', 'b', 'o', 'x', '-', 's', 'i', 'm'};

static volatile uint32_t s_count;      /* pulses counted at the OCR1A match */
static volatile uint32_t s_millis;     /* Timer0 clock */
static volatile uint16_t s_micros_acc; /* remainder of 1024 us overflows, us */
static uint8_t s_cs_running = CS_DIV64;

/* ------------------------------------------------------------------ UART, interrupt driven */
#define RING 64 /* power of two */
static volatile uint8_t s_rx[RING], s_tx[RING];
static volatile uint8_t s_rx_in, s_rx_out, s_tx_in, s_tx_out;
static uint8_t s_sent; /* a byte was sent since the UART was switched on */

ISR(USART_RX_vect) {
    uint8_t b = UDR0;
    uint8_t next = (uint8_t)((s_rx_in + 1) & (RING - 1));
    if (next != s_rx_out) { /* a full ring drops the new byte */
        s_rx[s_rx_in] = b;
        s_rx_in = next;
    }
}

ISR(USART_UDRE_vect) {
    if (s_tx_out == s_tx_in) {
        UCSR0B &= (uint8_t)~_BV(UDRIE0);
        return;
    }
    UDR0 = s_tx[s_tx_out];
    s_tx_out = (uint8_t)((s_tx_out + 1) & (RING - 1));
}

static void uart_on(uint16_t ubrr) {
    UBRR0 = ubrr;
    UCSR0A = _BV(U2X0);
    UCSR0C = _BV(UCSZ01) | _BV(UCSZ00);
    UCSR0B = _BV(RXEN0) | _BV(TXEN0) | _BV(RXCIE0);
    s_sent = 0;
}

static uint32_t millis(void);

/* Waits until the last byte has left, then switches the UART off; what it received is dropped. */
static void uart_off(void) {
    while (s_tx_out != s_tx_in || (UCSR0B & _BV(UDRIE0)))
        ;
    uint32_t t0 = millis();
    while (s_sent && !(UCSR0A & _BV(TXC0)) && millis() - t0 < 3)
        ;
    UCSR0B = 0;
    cli();
    s_rx_out = s_rx_in;
    sei();
}

static uint8_t rx_waiting(void) {
    return (uint8_t)((s_rx_in - s_rx_out) & (RING - 1));
}

static uint8_t rx_take(void) {
    uint8_t b = s_rx[s_rx_out];
    s_rx_out = (uint8_t)((s_rx_out + 1) & (RING - 1));
    return b;
}

static void tx_put(uint8_t b) {
    uint8_t next = (uint8_t)((s_tx_in + 1) & (RING - 1));
    while (next == s_tx_out) /* full: wait for the interrupt to make room */
        ;
    s_tx[s_tx_in] = b;
    s_tx_in = next;
    UCSR0A = _BV(U2X0) | _BV(TXC0); /* clears "transmit complete": a byte is on its way again */
    s_sent = 1;
    UCSR0B |= _BV(UDRIE0);
}

/* ------------------------------------------------------------------ time */
ISR(TIMER0_OVF_vect) {
    uint16_t acc = (uint16_t)(s_micros_acc + 1024u);
    uint32_t ms = s_millis;
    while (acc >= 1000u) {
        acc = (uint16_t)(acc - 1000u);
        ms++;
    }
    s_micros_acc = acc;
    s_millis = ms;
}

static uint32_t millis(void) {
    uint8_t sreg = SREG;
    cli();
    uint32_t ms = s_millis;
    SREG = sreg;
    return ms;
}

static void wait_ms(uint16_t ms) {
    uint32_t t0 = millis();
    while (millis() - t0 < ms)
        ;
}

/* A byte that is still on its way: looked for every 10 ms, as the original does. */
static uint8_t rx_take_waiting(void) {
    while (!rx_waiting())
        wait_ms(10);
    return rx_take();
}

/* ------------------------------------------------------------------ frame timer */
ISR(TIMER1_COMPA_vect) {
    s_count++;
}

static void frame_timer_boot(void) {
    uint8_t sreg = SREG;
    cli();
    OCR1A = TRIGGER_MARK;
    ICR1 = BOOT_TOP;
    TCCR1A = _BV(COM1A1) | _BV(WGM11); /* OC1A: set at BOTTOM, cleared at the match */
    TCCR1B = TCCR1B_STOPPED | CS_DIV64;
    TIMSK1 |= _BV(OCIE1A);
    SREG = sreg;
}

static void sample(uint32_t *count, uint16_t *ticks) {
    uint8_t sreg = SREG;
    cli();
    *count = s_count;
    *ticks = TCNT1;
    SREG = sreg;
}

static void reply(uint8_t header, uint8_t value) {
    uint32_t count;
    uint16_t ticks;
    sample(&count, &ticks);
    uint8_t payload[7] = {value,
                          (uint8_t)count,
                          (uint8_t)(count >> 8),
                          (uint8_t)(count >> 16),
                          (uint8_t)(count >> 24),
                          (uint8_t)ticks,
                          (uint8_t)(ticks >> 8)};
    uint8_t sum = 0;
    tx_put(header);
    tx_put(sizeof payload);
    for (uint8_t i = 0; i < sizeof payload; i++) {
        sum = (uint8_t)(sum + payload[i]);
        tx_put(payload[i]);
    }
    tx_put(sum);
}

/* ------------------------------------------------------------------ name */
/* CRC-8/Maxim (Dallas 1-Wire): reflected polynomial 0x31, initial value 0. */
static uint8_t crc8_maxim(const uint8_t *p, uint8_t n) {
    uint8_t crc = 0;
    while (n--) {
        crc ^= *p++;
        for (uint8_t k = 0; k < 8; k++)
            crc = (crc & 1) ? (uint8_t)((crc >> 1) ^ 0x8C) : (uint8_t)(crc >> 1);
    }
    return crc;
}

static int8_t hex_value(uint8_t c) {
    if (c >= '0' && c <= '9')
        return (int8_t)(c - '0');
    if (c >= 'A' && c <= 'F')
        return (int8_t)(c - 'A' + 10);
    if (c >= 'a' && c <= 'f')
        return (int8_t)(c - 'a' + 10);
    return -1;
}

static uint8_t rx_take_busy(void) {
    while (!rx_waiting())
        ;
    return rx_take();
}

static void name_command(uint8_t what) {
    uint8_t name[NAME_LEN];
    if (what == '?') {
        eeprom_read_block(name, ee_name, NAME_LEN);
        for (uint8_t i = 0; i < NAME_LEN; i++)
            tx_put(name[i]);
        uint8_t crc = crc8_maxim(name, NAME_LEN);
        static const char digits[] = "0123456789ABCDEF";
        if (crc >= 16)
            tx_put((uint8_t)digits[crc >> 4]);
        tx_put((uint8_t)digits[crc & 15]);
    } else if (what == '=') {
        for (uint8_t i = 0; i < NAME_LEN; i++)
            name[i] = rx_take_busy();
        uint8_t hi = rx_take_busy(), lo = rx_take_busy();
        /* Up to two hex digits, as far as they are hex digits. */
        int16_t crc = -1;
        if (hex_value(hi) >= 0) {
            crc = hex_value(hi);
            if (hex_value(lo) >= 0)
                crc = (int16_t)(crc * 16 + hex_value(lo));
        }
        if (crc == crc8_maxim(name, NAME_LEN))
            eeprom_update_block(name, ee_name, NAME_LEN);
    }
}

/* ------------------------------------------------------------------ boot and loop */
static void name_handshake(void) {
    uart_on(UBRR_9600);
    wait_ms(50);
    for (int16_t left = 5000;; left -= 20) {
        if (rx_waiting() && rx_take() == 'N') {
            name_command(rx_take_busy());
            break;
        }
        if (left <= 0)
            break;
        wait_ms(20);
    }
    wait_ms(500);
    uart_off();
}

static void command(uint8_t cmd, uint8_t value) {
    switch (cmd) {
    case 'P':
        reply('P', value);
        break;
    case 'V':
        reply('V', BOX_VERSION);
        break;
    case 'S':
        if (value == '0') {
            TCCR1B = TCCR1B_STOPPED;
            TCNT1 = 0;
            uint8_t sreg = SREG;
            cli();
            s_count = 0;
            SREG = sreg;
        } else if (value == '1') {
            TCCR1B = (uint8_t)(TCCR1B_STOPPED | s_cs_running);
        } else if (value == '2') {
            TCCR1B = TCCR1B_STOPPED;
        }
        break;
    case 'T':
        if (value == '=') {
            uint8_t lo = rx_take_waiting(), hi = rx_take_waiting(), key = rx_take_waiting();
            ICR1 = (uint16_t)(lo | ((uint16_t)hi << 8));
            if (key == '1')
                s_cs_running = CS_DIV8;
            else if (key == '2')
                s_cs_running = CS_DIV64;
        }
        break;
    case 'O':
        if (value == '=') {
            for (uint8_t i = 0; i < 4; i++)
                (void)rx_take_waiting(); /* two u16 DAC values: no DAC here */
            reply('O', rx_take_waiting());
        }
        break;
    case 'N':
        name_command(value);
        break;
    default:
        break;
    }
}

int main(void) {
    TCCR0A = _BV(WGM01) | _BV(WGM00);
    TCCR0B = _BV(CS01) | _BV(CS00);
    TIMSK0 = _BV(TOIE0);
    DDRB |= _BV(DDB1); /* D9, OC1A: the trigger */
    sei();
    name_handshake();
    uart_on(UBRR_115200);
    frame_timer_boot();
    for (;;) {
        if (rx_waiting() >= 2) {
            uint8_t cmd = rx_take();
            uint8_t value = rx_take();
            command(cmd, value);
        }
    }
}

/* Pin map of the DVS USB bridge on an ATmega32U4 at 16 MHz (hardware/README.md, "DVS bridge").
 *
 * The AER address lines are laid out so that two port reads give the DVS128 word's two address
 * bytes as they are: PINB = x << 1 | polarity (byte 0), PIND = y with PD7 = /REQ (byte 1; /REQ
 * reads 0 while a request is pending, and bit 7 is masked anyway, since it is the sync flag).
 * /REQ is wired to two pins: PD7 (its level, for the four-phase handshake) and PC7 = ICP3, so
 * Timer3's input-capture unit stamps every request's falling edge in hardware: the timestamp is
 * exact however late the firmware gets to the event (e.g. while it copies a USB packet).
 *
 * Timer3: CTC mode 4 (TOP = OCR3A = 32767) at f_cpu / 8 = 2 MHz, so one counter period is
 * 16384 us = the DVS128's 14-bit microsecond timestamp range; ts = ICR3 >> 1.
 * The sync input (the trigger firmware's frame output) is INT6 (PE6), rising edge; its handler
 * reads TCNT3 in its first instructions (fixed latency, compensated).
 */
#ifndef DVS_BOARD_H
#define DVS_BOARD_H

#include <avr/io.h>

#define F_TIMER (F_CPU / 8) /* Timer3 ticks per second: 2 per microsecond */
#define TS_TOP 32767u       /* 0x8000 ticks = 0x4000 us per counter period */
#define ADDR0_PIN PINB      /* PB0 = polarity, PB1..PB7 = x0..x6 */
#define ADDR1_PIN PIND      /* PD0..PD6 = y0..y6 */
#define REQ_PIN PIND        /* PD7 = /REQ level (also on PC7 = ICP3) */
#define REQ_BIT PD7
#define ICP_PORT PORTC /* PC7 = ICP3 = /REQ */
#define ICP_BIT PC7
#define ACK_PORT PORTC /* PC6 = /ACK, active low, driven by the bridge */
#define ACK_DDR DDRC
#define ACK_BIT PC6
#define SYNC_PORT PORTE /* PE6 = INT6: external sync in, rising edge */
#define SYNC_BIT PE6
/* DVS128 bias shift register (12 biases x 24 bits, MSB first) and array reset: port F */
#define BIAS_PORT PORTF
#define BIAS_DDR DDRF
#define BIAS_CLK PF4
#define BIAS_BIT PF5
#define BIAS_LATCH PF6
#define ARRAY_RESET PF7 /* active high pulse: resets every pixel of the sensor */

#endif /* DVS_BOARD_H */

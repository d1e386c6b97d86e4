/* Pin map and UART registers of the boards the trigger firmware runs on (hardware/README.md).
 *
 * Both MCUs use Timer1 in fast PWM mode 14 (TOP = ICR1), as the strawlab triggerbox does:
 *   OC1A -> frame trigger (hardware compare output, zero jitter)
 *   OC1B -> pulse channel 0 (hardware compare output: high-speed camera trigger)
 *   event input (photodiode, button): ATmega32U4 ICP3 (Timer3 input capture, lock-step with
 *   Timer1: exact); ATmega328P INT0, timestamped first thing in its interrupt (fixed latency,
 *   compensated)
 *   three plain GPIOs -> stimulus lines 1..3
 * With ICR1 as TOP the Timer1 input-capture unit is unavailable (datasheet: ICP1 is disconnected
 * when ICR1 defines TOP), hence Timer3's unit on the 32U4 and INT0 on the 328P (no other 16-bit
 * timer).
 */
#ifndef FT_BOARD_H
#define FT_BOARD_H

#include <avr/io.h>

#if defined(__AVR_ATmega328P__)
#define FT_MCU_ID 1 /* FT_TL_MCU_ATMEGA328P */
/* Arduino Nano / Uno */
#define TRIG_DDR DDRB
#define TRIG_PORT PORTB
#define TRIG_BIT PB1 /* D9 */
#define PULSE_DDR DDRB
#define PULSE_PORT PORTB
#define PULSE_BIT PB2 /* D10 */
#define EVT_PINR PIND
#define EVT_PORT PORTD
#define EVT_BIT PD2 /* D2 = INT0 */
#define FT_EVT_ICP 0
#define OUT1_DDR DDRD
#define OUT1_PORT PORTD
#define OUT1_BIT PD4 /* D4 */
#define OUT2_DDR DDRD
#define OUT2_PORT PORTD
#define OUT2_BIT PD5 /* D5 */
#define OUT3_DDR DDRD
#define OUT3_PORT PORTD
#define OUT3_BIT PD6 /* D6 */
/* USART0 on D0/D1, wired to the board's USB-serial chip */
#define UART_UBRR UBRR0
#define UART_UCSRA UCSR0A
#define UART_UCSRB UCSR0B
#define UART_UCSRC UCSR0C
#define UART_UDR UDR0
#define UART_U2X U2X0
#define UART_RXEN RXEN0
#define UART_TXEN TXEN0
#define UART_RXCIE RXCIE0
#define UART_UDRE UDRE0
#define UART_UCSZ0 UCSZ00
#define UART_UCSZ1 UCSZ01
#define UART_RX_vect USART_RX_vect

#elif defined(__AVR_ATmega32U4__)
#define FT_MCU_ID 2 /* FT_TL_MCU_ATMEGA32U4 */
/* Arduino Leonardo / Micro */
#define TRIG_DDR DDRB
#define TRIG_PORT PORTB
#define TRIG_BIT PB5 /* D9 */
#define PULSE_DDR DDRB
#define PULSE_PORT PORTB
#define PULSE_BIT PB6 /* D10 */
#define EVT_PINR PINC
#define EVT_PORT PORTC
#define EVT_BIT                                                                                    \
    PC7 /* D13 = ICP3 (the Leonardo's LED pin: the LED loads it, see hardware/README.md) */
#define FT_EVT_ICP 1
#define OUT1_DDR DDRD
#define OUT1_PORT PORTD
#define OUT1_BIT PD4 /* D4 */
#define OUT2_DDR DDRC
#define OUT2_PORT PORTC
#define OUT2_BIT PC6 /* D5 */
#define OUT3_DDR DDRD
#define OUT3_PORT PORTD
#define OUT3_BIT PD7 /* D6 */
/* USART1 on D0/D1 (the 32U4's native USB is not used: see hardware/README.md) */
#define UART_UBRR UBRR1
#define UART_UCSRA UCSR1A
#define UART_UCSRB UCSR1B
#define UART_UCSRC UCSR1C
#define UART_UDR UDR1
#define UART_U2X U2X1
#define UART_RXEN RXEN1
#define UART_TXEN TXEN1
#define UART_RXCIE RXCIE1
#define UART_UDRE UDRE1
#define UART_UCSZ0 UCSZ10
#define UART_UCSZ1 UCSZ11
#define UART_RX_vect USART1_RX_vect

#else
#error "flytrack trigger firmware: unsupported MCU (ATmega328P or ATmega32U4)"
#endif

#define FT_N_OUTPUTS 4 /* channel 0 = pulse (OC1B), 1..3 = stimulus lines */

#endif /* FT_BOARD_H */

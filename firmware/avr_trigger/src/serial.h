/* UART at 1 Mbaud 8N1: interrupt-driven receive ring, blocking transmit. */
#ifndef FT_SERIAL_H
#define FT_SERIAL_H

#include <stdint.h>

void serial_init(void);
/* Next received byte into *b; 0 when none is waiting. */
uint8_t serial_read(uint8_t *b);
void serial_write(const uint8_t *p, uint8_t n);
/* Bytes lost because the receive ring was full (the frame they belonged to then fails its CRC). */
uint16_t serial_overruns(void);

#endif /* FT_SERIAL_H */

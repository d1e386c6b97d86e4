/* The seam between the bridge and the 32U4's USB device controller.
 *
 * simavr cannot simulate the 32U4's USB controller (there is no host side to enumerate it), so the
 * bridge talks to USB only through these calls. Two implementations:
 *   usb_hw.c  - the real controller (registers as in the datasheet, chapter 21-22): enumeration,
 *               endpoint 0 control transfers, bulk-IN endpoint 0x86 (64 bytes, two banks).
 *               Built for the target (flytrack_dvs.hex); not run here.
 *   usb_sim.c - the simulator build: a three-register mailbox (GPIOR0..2) that the simavr harness
 *               (firmware/dvs_usb/harness/dvs_sim.c) serves: it collects bulk packets, paces them
 * at the full-speed bulk rate, and delivers vendor requests. Not a USB model. Only vendor requests
 * reach the bridge; standard requests stay inside usb_hw.c.
 */
#ifndef DVS_USB_SEAM_H
#define DVS_USB_SEAM_H

#include <stdint.h>

#define USB_BULK_IN_SIZE 64 /* bytes per bulk packet: 16 DVS words */

typedef struct {
    uint8_t bmRequestType, bRequest;
    uint16_t wValue, wIndex, wLength;
} usb_setup_t;

void usb_seam_init(void);
/* Inline (event path), below:
 *   usb_bulk_in_ready()  1 if an IN bank is free to be filled (then up to 64 bytes may be put)
 *   usb_bulk_in_put(b)   one byte into the bank being filled
 *   usb_bulk_in_send()   hands the bank to the host (a short packet if fewer than 64 bytes)
 *   usb_control_pending() a request waits (usb_control_poll would take it) */
/* 1 if a vendor request is waiting; fills *s and up to cap bytes of its OUT data stage. */
uint8_t usb_control_poll(usb_setup_t *s, uint8_t *data, uint8_t cap);
/* Ends the pending request: IN data (len bytes, none for an OUT request) and status stage. */
void usb_control_reply(const uint8_t *data, uint8_t len);
/* Ends the pending request with a STALL (unknown request, bad length). */
void usb_control_stall(void);

#ifdef DVS_SIM
/* Mailbox registers served by the harness (data-space addresses). The byte write uses STS, as the
 * real UEDATX write does, so the simulated cycle count per byte is the chip's. */
#define SIM_USB_STATUS                                                                             \
    0x3E                  /* GPIOR0: read = bit 0 IN bank free, bit 1 request waiting;             \
                             write = next control reply byte */
#define SIM_USB_DATA 0x4A /* GPIOR1: write = next bulk-IN byte, read = next request byte */
#define SIM_USB_CMD 0x4B  /* GPIOR2: write a SIM_CMD_* */
#define SIM_CMD_SEND 1
#define SIM_CMD_REPLY 2
#define SIM_CMD_STALL 3
static inline void usb_bulk_in_put(uint8_t b) {
    __asm__ volatile("sts %0, %1" ::"i"(SIM_USB_DATA), "r"(b));
}
static inline uint8_t usb_bulk_in_ready(void) {
    return *(volatile uint8_t *)SIM_USB_STATUS & 1u;
}
static inline void usb_bulk_in_send(void) {
    *(volatile uint8_t *)SIM_USB_CMD = SIM_CMD_SEND;
}
static inline uint8_t usb_control_pending(void) {
    return *(volatile uint8_t *)SIM_USB_STATUS & 2u;
}
#else
#include <avr/io.h>
/* Endpoint 6 is selected (UENUM = 6) whenever the bridge's main loop runs; usb_hw.c selects
 * endpoint 0 only inside usb_control_poll/reply/stall and restores it. */
static inline void usb_bulk_in_put(uint8_t b) {
    UEDATX = b;
}
static inline uint8_t usb_bulk_in_ready(void) {
    return (UEINTX & _BV(RWAL)) != 0;
}
static inline void usb_bulk_in_send(void) {
    UEINTX = (uint8_t) ~(_BV(FIFOCON) | _BV(TXINI)); /* bank to the host, next bank selected */
}
static inline uint8_t usb_control_pending(void) {
    UENUM = 0;
    uint8_t r = UEINTX & _BV(RXSTPI);
    UENUM = 6;
    return r;
}
#endif

#endif /* DVS_USB_SEAM_H */

/* usb_seam.h for the simulator: the harness serves a mailbox in GPIOR0..2 (see usb_seam.h).
 * This is the seam, not a model of the USB controller (simavr cannot run one with a host). */
#include "usb_seam.h"

#define REG(a) (*(volatile uint8_t *)(a))

void usb_seam_init(void) {}

uint8_t usb_control_poll(usb_setup_t *s, uint8_t *data, uint8_t cap) {
    uint8_t b[8], i;
    if (!(REG(SIM_USB_STATUS) & 2u))
        return 0;
    for (i = 0; i < 8; i++)
        b[i] = REG(SIM_USB_DATA);
    s->bmRequestType = b[0];
    s->bRequest = b[1];
    s->wValue = (uint16_t)(b[2] | b[3] << 8);
    s->wIndex = (uint16_t)(b[4] | b[5] << 8);
    s->wLength = (uint16_t)(b[6] | b[7] << 8);
    if (!(s->bmRequestType & 0x80)) /* OUT: the data stage follows */
        for (i = 0; i < s->wLength && i < cap; i++)
            data[i] = REG(SIM_USB_DATA);
    return 1;
}

void usb_control_reply(const uint8_t *data, uint8_t len) {
    while (len--)
        REG(SIM_USB_STATUS) = *data++;
    REG(SIM_USB_CMD) = SIM_CMD_REPLY;
}

void usb_control_stall(void) {
    REG(SIM_USB_CMD) = SIM_CMD_STALL;
}

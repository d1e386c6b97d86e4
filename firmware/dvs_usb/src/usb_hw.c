/* usb_seam.h on the real ATmega32U4 USB device controller (datasheet chapters 21-22), polled, no
 * interrupts. Not run here: simavr has no USB host to enumerate it (see usb_seam.h); it is built
 * for the target (flytrack_dvs.hex) so that it compiles against the real registers.
 *
 * Device: vendor class, one interface, bulk-IN endpoint 0x86 (64 bytes, two banks). The ids are the
 * DVS128's (iniVation VID 0x152A, PID 0x8400, bcdDevice 0x000E = type 0, firmware 14) so that jAER
 * and libcaer open the bridge as a DVS128. Standard requests are answered here; vendor requests go
 * to the bridge through usb_control_poll.
 */
#include <avr/io.h>
#include <avr/pgmspace.h>

#include "usb_seam.h"

#define EP0_SIZE 64
#define EP_IN_NUM 6

static const uint8_t PROGMEM dev_desc[18] = {18,   1,    0x00, 0x02, /* bcdUSB 2.00 */
                                             0xFF, 0x00, 0x00, EP0_SIZE,
                                             0x2A, 0x15, /* idVendor 0x152A */
                                             0x00, 0x84, /* idProduct 0x8400 */
                                             0x0E, 0x00, /* bcdDevice: type 0, firmware 14 */
                                             1,    2,    3,    1};
static const uint8_t PROGMEM conf_desc[25] = {
    9,
    2,
    25,
    0,
    1,
    1,
    0,
    0x80,
    50, /* configuration: 1 interface, bus powered, 100 mA */
    9,
    4,
    0,
    0,
    1,
    0xFF,
    0,
    0,
    0, /* interface 0: vendor class, 1 endpoint */
    7,
    5,
    0x80 | EP_IN_NUM,
    2,
    USB_BULK_IN_SIZE,
    0,
    0}; /* endpoint 0x86 bulk IN 64 */
static const uint8_t PROGMEM str0[4] = {4, 3, 0x09, 0x04};
static const char PROGMEM str1[] = "FlyTrack";
static const char PROGMEM str2[] = "DVS128 bridge (FlyTrack)";
static const char PROGMEM str3[] = "FT000001";

static void ep_select(uint8_t n) {
    UENUM = n;
}

static void ep0_setup(void) {
    ep_select(0);
    UECONX = _BV(EPEN);
    UECFG0X = 0;                                        /* control, OUT */
    UECFG1X = _BV(EPSIZE1) | _BV(EPSIZE0) | _BV(ALLOC); /* 64 bytes, one bank */
}

static void ep_in_setup(void) {
    ep_select(EP_IN_NUM);
    UECONX = _BV(EPEN);
    UECFG0X = _BV(EPTYPE1) | _BV(EPDIR);                             /* bulk IN */
    UECFG1X = _BV(EPSIZE1) | _BV(EPSIZE0) | _BV(EPBK0) | _BV(ALLOC); /* 64 bytes, two banks */
    UERST = _BV(EP_IN_NUM);
    UERST = 0;
}

void usb_seam_init(void) {
    UHWCON = _BV(UVREGE);
    USBCON = _BV(USBE) | _BV(FRZCLK);
    PLLCSR = _BV(PINDIV) | _BV(PLLE); /* 16 MHz crystal / 2 -> PLL 48 MHz */
    while (!(PLLCSR & _BV(PLOCK)))
        ;
    USBCON = _BV(USBE) | _BV(OTGPADE);
    UDCON = 0; /* attach, full speed */
    ep0_setup();
    ep_select(EP_IN_NUM);
}

static void ep0_wait_in(void) {
    while (!(UEINTX & _BV(TXINI)))
        ;
}

static void ep0_send_zlp(void) {
    ep0_wait_in();
    UEINTX = (uint8_t)~_BV(TXINI);
}

/* An IN data stage from flash (pgm) or RAM, at most `max` bytes, then the host's status stage. */
static void ep0_send(const uint8_t *p, uint8_t len, uint16_t max, uint8_t pgm) {
    if (len > max)
        len = (uint8_t)max;
    do {
        uint8_t n = len > EP0_SIZE ? EP0_SIZE : len;
        ep0_wait_in();
        len -= n;
        while (n--)
            UEDATX = pgm ? pgm_read_byte(p++) : *p++;
        UEINTX = (uint8_t)~_BV(TXINI);
    } while (len);
    while (!(UEINTX & _BV(RXOUTI)))
        ;
    UEINTX = (uint8_t)~_BV(RXOUTI);
}

static void send_string(const char *s, uint16_t max) {
    uint8_t buf[2 + 2 * 32], n = 0;
    char c;
    while ((c = (char)pgm_read_byte(s + n)) && n < 32) {
        buf[2 + 2 * n] = (uint8_t)c;
        buf[3 + 2 * n] = 0;
        n++;
    }
    buf[0] = (uint8_t)(2 + 2 * n);
    buf[1] = 3;
    ep0_send(buf, buf[0], max, 0);
}

static void stall(void) {
    UECONX |= _BV(STALLRQ);
}

/* Standard requests: answered here. Returns 0 for a request the bridge must see. */
static uint8_t standard(const usb_setup_t *s) {
    if ((s->bmRequestType & 0x60) != 0)
        return 0;
    switch (s->bRequest) {
    case 6: { /* GET_DESCRIPTOR */
        uint8_t type = (uint8_t)(s->wValue >> 8), idx = (uint8_t)s->wValue;
        if (type == 1)
            ep0_send(dev_desc, sizeof dev_desc, s->wLength, 1);
        else if (type == 2)
            ep0_send(conf_desc, sizeof conf_desc, s->wLength, 1);
        else if (type == 3 && idx == 0)
            ep0_send(str0, sizeof str0, s->wLength, 1);
        else if (type == 3 && idx <= 3)
            send_string(idx == 1 ? str1 : idx == 2 ? str2 : str3, s->wLength);
        else
            stall();
        return 1;
    }
    case 5: /* SET_ADDRESS: takes effect after the status stage */
        UDADDR = (uint8_t)(s->wValue & 0x7F);
        ep0_send_zlp();
        ep0_wait_in();
        UDADDR |= _BV(ADDEN);
        return 1;
    case 9: /* SET_CONFIGURATION */
        ep0_send_zlp();
        ep_in_setup();
        ep_select(0);
        return 1;
    case 8: { /* GET_CONFIGURATION */
        static const uint8_t one = 1;
        ep0_send(&one, 1, s->wLength, 0);
        return 1;
    }
    case 0: { /* GET_STATUS */
        static const uint8_t st[2] = {0, 0};
        ep0_send(st, 2, s->wLength, 0);
        return 1;
    }
    case 11: /* SET_INTERFACE */
    case 1:  /* CLEAR_FEATURE (endpoint halt) */
        if (s->bRequest == 1 && (s->bmRequestType & 0x1F) == 2) {
            ep_select((uint8_t)(s->wIndex & 0x07));
            UECONX |= _BV(STALLRQC) | _BV(RSTDT);
            ep_select(0);
        }
        ep0_send_zlp();
        return 1;
    default:
        stall();
        return 1;
    }
}

static usb_setup_t s_pending;

uint8_t usb_control_poll(usb_setup_t *s, uint8_t *data, uint8_t cap) {
    uint8_t b[8], i, r = 0;
    if (UDINT & _BV(EORSTI)) { /* bus reset: endpoint 0 again, the host reconfigures */
        UDINT &= (uint8_t)~_BV(EORSTI);
        ep0_setup();
    }
    ep_select(0);
    if (UEINTX & _BV(RXSTPI)) {
        for (i = 0; i < 8; i++)
            b[i] = UEDATX;
        UEINTX = (uint8_t)~_BV(RXSTPI);
        s->bmRequestType = b[0];
        s->bRequest = b[1];
        s->wValue = (uint16_t)(b[2] | b[3] << 8);
        s->wIndex = (uint16_t)(b[4] | b[5] << 8);
        s->wLength = (uint16_t)(b[6] | b[7] << 8);
        if (!standard(s)) {
            if (!(s->bmRequestType & 0x80) && s->wLength) { /* OUT data stage */
                while (!(UEINTX & _BV(RXOUTI)))
                    ;
                for (i = 0; i < s->wLength && i < cap && i < EP0_SIZE; i++)
                    data[i] = UEDATX;
                UEINTX = (uint8_t)~_BV(RXOUTI);
            }
            s_pending = *s;
            r = 1;
        }
    }
    if (!r)
        ep_select(EP_IN_NUM);
    return r; /* with r = 1 endpoint 0 stays selected until the reply */
}

void usb_control_reply(const uint8_t *data, uint8_t len) {
    if (s_pending.bmRequestType & 0x80)
        ep0_send(data, len, s_pending.wLength, 0);
    else
        ep0_send_zlp();
    ep_select(EP_IN_NUM);
}

void usb_control_stall(void) {
    stall();
    ep_select(EP_IN_NUM);
}

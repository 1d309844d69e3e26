/* USB descriptors of the RP2040 port: a CDC-ACM device (appears as /dev/ttyACM* on Linux, COMn on
 * Windows).  Replace the vendor and product ids with the lab's own before shipping a device. */
#include <string.h>

#include "pico/unique_id.h"
#include "tusb.h"

#define USB_VID 0x2E8A /* Raspberry Pi: use the lab's own vendor/product id in a product */
#define USB_PID 0x000A
#define EPNUM_CDC_NOTIF 0x81
#define EPNUM_CDC_OUT 0x02
#define EPNUM_CDC_IN 0x82

static const tusb_desc_device_t device = {
    .bLength = sizeof(tusb_desc_device_t),
    .bDescriptorType = TUSB_DESC_DEVICE,
    .bcdUSB = 0x0200,
    .bDeviceClass = TUSB_CLASS_MISC,
    .bDeviceSubClass = MISC_SUBCLASS_COMMON,
    .bDeviceProtocol = MISC_PROTOCOL_IAD,
    .bMaxPacketSize0 = CFG_TUD_ENDPOINT0_SIZE,
    .idVendor = USB_VID,
    .idProduct = USB_PID,
    .bcdDevice = 0x0100,
    .iManufacturer = 1,
    .iProduct = 2,
    .iSerialNumber = 3,
    .bNumConfigurations = 1,
};

enum { ITF_CDC = 0, ITF_CDC_DATA, ITF_COUNT };
#define CONFIG_LEN (TUD_CONFIG_DESC_LEN + TUD_CDC_DESC_LEN)

static const uint8_t configuration[] = {
    TUD_CONFIG_DESCRIPTOR(1, ITF_COUNT, 0, CONFIG_LEN, 0, 250),
    TUD_CDC_DESCRIPTOR(ITF_CDC, 4, EPNUM_CDC_NOTIF, 8, EPNUM_CDC_OUT, EPNUM_CDC_IN, 64),
};

const uint8_t *tud_descriptor_device_cb(void)
{
    return (const uint8_t *)&device;
}

const uint8_t *tud_descriptor_configuration_cb(uint8_t index)
{
    (void)index;
    return configuration;
}

const uint16_t *tud_descriptor_string_cb(uint8_t index, uint16_t langid)
{
    static uint16_t out[33];
    static char serial[2 * PICO_UNIQUE_BOARD_ID_SIZE_BYTES + 1];
    static const char *const strings[] = {NULL, "SINECAL", "DAQ bridge (ADS131M02)", serial, "DAQ bridge"};
    const char *s;
    size_t n, i;
    (void)langid;
    if (index == 0) {
        out[1] = 0x0409; /* English */
        n = 1;
    } else {
        if (index >= sizeof strings / sizeof strings[0]) {
            return NULL;
        }
        if (index == 3) {
            pico_get_unique_board_id_string(serial, sizeof serial);
        }
        s = strings[index];
        n = strlen(s);
        if (n > 32) {
            n = 32;
        }
        for (i = 0; i < n; i++) {
            out[1 + i] = (uint16_t)s[i];
        }
    }
    out[0] = (uint16_t)((TUSB_DESC_STRING << 8) | (2 * n + 2));
    return out;
}

/* The DAQ bridge's device side of docs/daq-protocol.md: SLIP framing, CRC-32, command handling
 * (IDN?, HW?, CONF, START, STOP, STAT?), sample frames with sequence numbers, the device FIFO and
 * its overflow accounting.  Portable C99; the hardware is reached only through bridge_hal.h.
 *
 * Usage (one instance, statically allocated):
 *
 *     static bridge b;
 *     static uint8_t fifo[192 * 1024];
 *     bridge_init(&b, &port_info, fifo, sizeof fifo);
 *     for (;;) bridge_poll(&b);
 */
#ifndef BRIDGE_H
#define BRIDGE_H

#include <stddef.h>
#include <stdint.h>

#include "bridge_hal.h"
#include "ring.h"
#include "slip.h"

#define BRIDGE_VENDOR "SINECAL"
#define BRIDGE_FIRMWARE_VERSION "1.0"

/* Largest frame (samples per channel) a build accepts; the protocol allows 16..4096.  A port short
 * of RAM may build with -DBRIDGE_MAX_FRAME=1024: CONF then refuses larger frames with ERR 2. */
#ifndef BRIDGE_MAX_FRAME
#define BRIDGE_MAX_FRAME 4096
#endif
#define BRIDGE_MIN_FRAME 16
#define BRIDGE_MIN_RATE_HZ 100.0
#define BRIDGE_MAX_RATE_HZ 1000000.0
#define BRIDGE_MIN_RANGE_V 0.1
#define BRIDGE_MAX_RANGE_V 10.0
/* `rate_exact` must lie within this fraction of the asked `rate` (else CONF answers ERR 2). */
#define BRIDGE_RATE_TOLERANCE 0.01

#define BRIDGE_PKT_SAMPLES 0x01u
#define BRIDGE_PKT_REPLY 0x02u
#define BRIDGE_PKT_COMMAND 0x10u
#define BRIDGE_FRAME_HEADER 7u /* type, seq u32, count u16 */
#define BRIDGE_CRC_SIZE 4u
#define BRIDGE_FRAME_BYTES(n) (BRIDGE_FRAME_HEADER + 4u * (size_t)(n) + BRIDGE_CRC_SIZE)

#define BRIDGE_MAX_COMMAND 256u /* bytes of command text (with its tag) */
#define BRIDGE_MAX_REPLY 320u   /* bytes of reply text (with its tag) */
/* FIFO space kept for replies: a frame is queued only if one worst-case reply still fits after it,
 * and a command is read only if its reply fits: replies are never dropped. */
#define BRIDGE_REPLY_RESERVE (2u * (1u + BRIDGE_MAX_REPLY + BRIDGE_CRC_SIZE) + 2u)
/* A command chunk that stays unfinished this long (no END) is ended as if END had come. */
#define BRIDGE_RX_TIMEOUT_US 200000u
/* ADC pairs taken per bridge_poll() at most (keeps commands answered while catching up). */
#define BRIDGE_POLL_PAIRS 2048u

/* What the port is; reported by IDN? and HW?. */
typedef struct {
    const char *model;         /* IDN? model, e.g. "DAQ-BRIDGE-RP2040" */
    const char *serial;        /* IDN? serial number, e.g. from the flash's unique id */
    const char *adc;           /* ADC part, e.g. "ADS131M02" */
    unsigned adc_bits;         /* resolution of the codes hal_adc_read() returns, 8..32 */
    double clock_hz;           /* the ADC's master clock, Hz */
    double rate_min_hz;        /* slowest and fastest sample rate the ADC achieves (within */
    double rate_max_hz;        /*   the protocol's 100 .. 1 000 000 Hz) */
    const char *link;          /* "uart" or "usb-cdc" */
    uint32_t link_bytes_per_s; /* bytes/s the link carries to the host (uart: baud/10; usb-cdc: measured) */
} bridge_port_info;

/* Why a frame was dropped (for the port's on_drop hook). */
typedef enum {
    BRIDGE_DROP_FIFO = 1, /* the device FIFO was full: the host did not read fast enough */
    BRIDGE_DROP_ADC = 2   /* samples of the frame were lost before the core saw them (missed pairs) */
} bridge_drop_reason;

typedef struct bridge bridge;

/* Optional hook: frames first .. first+count-1 were dropped (their seq consumed). */
typedef void (*bridge_drop_hook)(void *ctx, uint64_t first_frame, uint64_t count, bridge_drop_reason why);

struct bridge {
    const bridge_port_info *info;
    /* configuration */
    double rate_hz;      /* as asked (CONF rate=) */
    bridge_adc_setting adc; /* as the ADC does it: adc.rate_hz is rate_exact */
    uint16_t frame;      /* samples per channel per frame */
    /* stream */
    int streaming;
    uint64_t frames;     /* frames produced since START (delivered or not); seq = frames mod 2^32 */
    uint32_t overflows;  /* frames dropped since START */
    uint16_t fill;       /* samples in the frame being built */
    int frame_lost;      /* the frame being built already lost samples */
    uint8_t frame_buf[BRIDGE_FRAME_BYTES(BRIDGE_MAX_FRAME)];
    /* link */
    bridge_ring tx;
    slip_rx rx;
    uint8_t rx_buf[1u + BRIDGE_MAX_COMMAND + BRIDGE_CRC_SIZE];
    uint8_t in_buf[64];  /* bytes read from the HAL, not yet parsed */
    size_t in_len, in_pos;
    uint32_t rx_last_us; /* tick of the last byte of an unfinished chunk */
    char reply[BRIDGE_MAX_REPLY + 1];
    size_t reply_len;
    uint8_t packet[1u + BRIDGE_MAX_REPLY + BRIDGE_CRC_SIZE];
    bridge_drop_hook on_drop;
    void *on_drop_ctx;
};

/* Set up with the port's description and its FIFO memory (at least a few frames: 64 KiB or more
 * for 20 kHz).  Configures the ADC for the default rate=20000 frame=256 range_disp=10
 * range_force=10; returns NULL, or the HAL's message if it refused that. */
const char *bridge_init(bridge *b, const bridge_port_info *info, uint8_t *fifo, size_t fifo_size);

/* Do everything that is due: take ADC pairs into frames, read and answer commands, hand queued
 * bytes to the link.  Call it as often as possible from the main loop. */
void bridge_poll(bridge *b);

/* One protocol sample from an ADC code of `bits` bits: rounded to 16 bits, saturated. */
int16_t bridge_code16(int32_t code, unsigned bits);

/* Handle one command packet's text (without type and CRC) and queue its reply: what bridge_poll()
 * does for every good command packet (exposed for the self-test). */
void bridge_command(bridge *b, const char *text, size_t len);

#endif

/* SLIP framing (RFC 1055) as docs/daq-protocol.md (section 1) uses it: END before and after every
 * packet; in the packet 0xC0 -> DB DC and 0xDB -> DB DD. */
#ifndef BRIDGE_SLIP_H
#define BRIDGE_SLIP_H

#include <stddef.h>
#include <stdint.h>

#include "ring.h"

#define SLIP_END 0xC0u
#define SLIP_ESC 0xDBu
#define SLIP_ESC_END 0xDCu
#define SLIP_ESC_ESC 0xDDu

/* Bytes `n` packet bytes take on the wire: both END bytes plus one per byte that needs escaping. */
size_t slip_wire_length(const uint8_t *packet, size_t n);

/* Queue END | escaped packet | END; the caller has checked that slip_wire_length() bytes are free. */
void slip_put(bridge_ring *r, const uint8_t *packet, size_t n);

/* Receiving side: feed bytes one at a time, a packet ends at END. */
typedef enum {
    SLIP_RX_NONE = 0, /* byte consumed, no packet ended */
    SLIP_RX_PACKET    /* an END closed a non-empty chunk: see slip_rx.len and slip_rx.error */
} slip_rx_result;

typedef enum {
    SLIP_OK = 0,
    SLIP_BAD_ESCAPE, /* an ESC not followed by 0xDC or 0xDD */
    SLIP_TOO_LONG    /* more bytes than the buffer holds: the rest were discarded */
} slip_error;

typedef struct {
    uint8_t *buf;
    size_t size;
    size_t len;       /* un-escaped bytes so far */
    size_t raw;       /* wire bytes of the chunk so far (0 = between packets) */
    int escaped;      /* the previous byte was ESC */
    slip_error error; /* the first error of this chunk */
} slip_rx;

void slip_rx_init(slip_rx *rx, uint8_t *buf, size_t size);
slip_rx_result slip_rx_byte(slip_rx *rx, uint8_t byte);

/* End the current chunk as if END had arrived (a time-out); SLIP_RX_PACKET if it held anything. */
slip_rx_result slip_rx_flush(slip_rx *rx);

/* Start the next chunk (after a packet was handled). */
void slip_rx_reset(slip_rx *rx);

#endif

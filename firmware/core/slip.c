/* SLIP framing (see slip.h). */
#include "slip.h"

size_t slip_wire_length(const uint8_t *packet, size_t n)
{
    size_t i;
    size_t wire = n + 2;
    for (i = 0; i < n; i++) {
        if (packet[i] == SLIP_END || packet[i] == SLIP_ESC) {
            wire++;
        }
    }
    return wire;
}

void slip_put(bridge_ring *r, const uint8_t *packet, size_t n)
{
    size_t i;
    bridge_ring_put(r, SLIP_END);
    for (i = 0; i < n; i++) {
        if (packet[i] == SLIP_END) {
            bridge_ring_put(r, SLIP_ESC);
            bridge_ring_put(r, SLIP_ESC_END);
        } else if (packet[i] == SLIP_ESC) {
            bridge_ring_put(r, SLIP_ESC);
            bridge_ring_put(r, SLIP_ESC_ESC);
        } else {
            bridge_ring_put(r, packet[i]);
        }
    }
    bridge_ring_put(r, SLIP_END);
}

void slip_rx_init(slip_rx *rx, uint8_t *buf, size_t size)
{
    rx->buf = buf;
    rx->size = size;
    slip_rx_reset(rx);
}

void slip_rx_reset(slip_rx *rx)
{
    rx->len = 0;
    rx->raw = 0;
    rx->escaped = 0;
    rx->error = SLIP_OK;
}

static void fail(slip_rx *rx, slip_error error)
{
    if (rx->error == SLIP_OK) {
        rx->error = error;
    }
}

slip_rx_result slip_rx_flush(slip_rx *rx)
{
    if (rx->raw == 0) {
        return SLIP_RX_NONE; /* an empty chunk (two END bytes in a row) is ignored */
    }
    if (rx->escaped) {
        fail(rx, SLIP_BAD_ESCAPE); /* ESC END */
        rx->escaped = 0;
    }
    return SLIP_RX_PACKET;
}

slip_rx_result slip_rx_byte(slip_rx *rx, uint8_t byte)
{
    if (byte == SLIP_END) {
        return slip_rx_flush(rx);
    }
    rx->raw++;
    if (rx->escaped) {
        rx->escaped = 0;
        if (byte == SLIP_ESC_END) {
            byte = SLIP_END;
        } else if (byte == SLIP_ESC_ESC) {
            byte = SLIP_ESC;
        } else {
            fail(rx, SLIP_BAD_ESCAPE);
            return SLIP_RX_NONE;
        }
    } else if (byte == SLIP_ESC) {
        rx->escaped = 1;
        return SLIP_RX_NONE;
    }
    if (rx->len < rx->size) {
        rx->buf[rx->len++] = byte;
    } else {
        fail(rx, SLIP_TOO_LONG);
    }
    return SLIP_RX_NONE;
}

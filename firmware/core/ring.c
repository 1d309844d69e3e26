/* Byte FIFO (see ring.h). */
#include "ring.h"

void bridge_ring_init(bridge_ring *r, uint8_t *buf, size_t size)
{
    r->buf = buf;
    r->size = size;
    r->head = 0;
    r->used = 0;
}

size_t bridge_ring_free(const bridge_ring *r)
{
    return r->size - r->used;
}

void bridge_ring_put(bridge_ring *r, uint8_t byte)
{
    size_t tail = r->head + r->used;
    if (tail >= r->size) {
        tail -= r->size;
    }
    r->buf[tail] = byte;
    r->used++;
}

const uint8_t *bridge_ring_peek(const bridge_ring *r, size_t *n)
{
    size_t contiguous = r->size - r->head;
    *n = r->used < contiguous ? r->used : contiguous;
    return r->buf + r->head;
}

void bridge_ring_consume(bridge_ring *r, size_t n)
{
    if (n > r->used) {
        n = r->used;
    }
    r->head += n;
    if (r->head >= r->size) {
        r->head -= r->size;
    }
    r->used -= n;
    if (r->used == 0) {
        r->head = 0; /* keeps the next packet contiguous: fewer, larger writes */
    }
}

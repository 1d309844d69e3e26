/* Byte FIFO (see ring.h). */
#include "ring.h"

void ring_init(ring *r, uint8_t *buf, size_t size)
{
    r->buf = buf;
    r->size = size;
    r->head = 0;
    r->used = 0;
}

size_t ring_free(const ring *r)
{
    return r->size - r->used;
}

void ring_put(ring *r, uint8_t byte)
{
    size_t tail = r->head + r->used;
    if (tail >= r->size) {
        tail -= r->size;
    }
    r->buf[tail] = byte;
    r->used++;
}

const uint8_t *ring_peek(const ring *r, size_t *n)
{
    size_t contiguous = r->size - r->head;
    *n = r->used < contiguous ? r->used : contiguous;
    return r->buf + r->head;
}

void ring_consume(ring *r, size_t n)
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

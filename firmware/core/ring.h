/* A byte FIFO over memory the port provides (the bridge's device FIFO: frames and replies queued
 * for the link).  Single-threaded: the core fills and drains it from bridge_poll(). */
#ifndef BRIDGE_RING_H
#define BRIDGE_RING_H

#include <stddef.h>
#include <stdint.h>

typedef struct {
    uint8_t *buf;
    size_t size; /* capacity in bytes */
    size_t head; /* next byte to send */
    size_t used; /* bytes queued */
} bridge_ring;

void bridge_ring_init(bridge_ring *r, uint8_t *buf, size_t size);
size_t bridge_ring_free(const bridge_ring *r);

/* Append one byte; the caller has checked bridge_ring_free(). */
void bridge_ring_put(bridge_ring *r, uint8_t byte);

/* The queued bytes that are contiguous in memory from the head (for one write call). */
const uint8_t *bridge_ring_peek(const bridge_ring *r, size_t *n);

/* Drop `n` bytes from the head (they were sent). */
void bridge_ring_consume(bridge_ring *r, size_t n);

#endif

/* The hardware abstraction layer: what a port implements under the protocol core.
 *
 * Seven functions, all called from bridge_poll() in the main loop (never from an interrupt); none
 * may block.  A port on a microcontroller typically fills a small ring of ADC pairs from the ADC's
 * data-ready interrupt (or DMA) and a transmit buffer drained by the UART or USB stack; these
 * functions move data in and out of those rings.  firmware/README.md shows them for an RP2040 with
 * an ADS131M02; port/host/ implements them on POSIX for CI.
 */
#ifndef BRIDGE_HAL_H
#define BRIDGE_HAL_H

#include <stddef.h>
#include <stdint.h>

/* An ADC setting: sample rate per channel (Hz) and the +-V input range of each channel. */
typedef struct {
    double rate_hz;
    double range_disp_v;
    double range_force_v;
} bridge_adc_setting;

/* One pair of simultaneous samples as the ADC delivers them: two's complement codes of
 * bridge_port_info.adc_bits bits (full scale +-2^(bits-1) for +-range V).  `missed` counts the
 * pairs the ADC converted but the port lost just before this one (its sample ring overran because
 * the main loop was late); 0 normally.  The core turns missed samples into whole lost frames so that
 * every later sample keeps its index. */
typedef struct {
    int32_t disp;
    int32_t force;
    uint32_t missed;
} bridge_adc_pair;

/* Set the ADC up for `want` (already checked against the protocol's bounds).  Returns NULL and
 * stores what the ADC will actually do in `got`: the nearest sample rate its clock and dividers
 * achieve and the ranges its gains give.  Or returns a message saying what it cannot do (it becomes
 * the text of an ERR 2 reply: "expected ..., got ...").  Called while idle only. */
const char *hal_adc_configure(const bridge_adc_setting *want, bridge_adc_setting *got);

/* Start converting: the next pair hal_adc_read() returns is sample 0 of the stream. */
void hal_adc_start(void);

/* Stop converting; pairs not yet read are discarded. */
void hal_adc_stop(void);

/* 1 and the oldest unread pair, or 0 if none is ready. */
int hal_adc_read(bridge_adc_pair *pair);

/* Hand bytes to the link (UART or USB-CDC transmit buffer); returns how many it took now (0..n). */
size_t hal_write(const uint8_t *data, size_t n);

/* Bytes received from the host since the last call, at most `max`; 0 if none. */
size_t hal_read(uint8_t *data, size_t max);

/* A free-running microsecond counter (wraps at 2^32). */
uint32_t hal_ticks_us(void);

#endif

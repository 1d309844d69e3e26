/* An ADC emulated from a free-running timer, for the ports without a converter (host, QEMU).
 *
 * The converter runs from `clock_hz` through an integer divider: the exact rate is
 * clock / round(clock / rate) (the `rate_exact` of CONF).  Pair k of a stream becomes due at
 * start + k / rate (timer ticks of `tick_hz`), and due pairs wait in a ring of `ring` pairs, as a
 * DRDY interrupt would leave them: a reader later than the ring holds loses the oldest pairs, and
 * the next pair says how many (`missed`).  Fault injection: up to TIMED_ADC_MAX_SKIPS runs of
 * samples lost at given stream indices.  Samples come from `synth` (synth.h).
 */
#ifndef PORT_TIMED_ADC_H
#define PORT_TIMED_ADC_H

#include <stdint.h>

#include "bridge_hal.h"
#include "synth.h"

#define TIMED_ADC_MAX_SKIPS 8

typedef struct {
    synth source;
    double tick_hz;
    double clock_hz;
    double rate_hz; /* exact */
    uint64_t ring;
    int running;
    uint64_t t0;
    uint64_t produced; /* pairs handed out (or lost) since start */
    uint64_t due;      /* pairs converted at the last look at the timer */
    uint64_t skip_first[TIMED_ADC_MAX_SKIPS], skip_count[TIMED_ADC_MAX_SKIPS];
    int nskips;
} timed_adc;

void timed_adc_init(timed_adc *a, double tick_hz, double clock_hz, uint64_t ring);

/* Lose `count` samples from stream index `first` on (0 if the table is full). */
int timed_adc_skip(timed_adc *a, uint64_t first, uint64_t count);

/* The HAL's hal_adc_configure (any rate the divider reaches; ranges as asked). */
const char *timed_adc_configure(timed_adc *a, const bridge_adc_setting *want, bridge_adc_setting *got);

void timed_adc_start(timed_adc *a, uint64_t now_ticks);
void timed_adc_stop(timed_adc *a);

/* The HAL's hal_adc_read; `now` reads the timer (called only when no converted pair is waiting). */
int timed_adc_read(timed_adc *a, uint64_t (*now)(void), bridge_adc_pair *pair);

#endif

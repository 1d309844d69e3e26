/* An ADC emulated from a free-running timer (see timed_adc.h). */
#include "timed_adc.h"

#include <stddef.h>

void timed_adc_init(timed_adc *a, double tick_hz, double clock_hz, uint64_t ring)
{
    a->tick_hz = tick_hz;
    a->clock_hz = clock_hz;
    a->rate_hz = 20000.0;
    a->ring = ring;
    a->running = 0;
    a->t0 = a->produced = a->due = 0u;
    a->nskips = 0;
}

int timed_adc_skip(timed_adc *a, uint64_t first, uint64_t count)
{
    if (a->nskips == TIMED_ADC_MAX_SKIPS) {
        return 0;
    }
    a->skip_first[a->nskips] = first;
    a->skip_count[a->nskips++] = count;
    return 1;
}

const char *timed_adc_configure(timed_adc *a, const bridge_adc_setting *want, bridge_adc_setting *got)
{
    double divider = (double)(uint64_t)(a->clock_hz / want->rate_hz + 0.5);
    if (divider < 1.0) {
        divider = 1.0;
    }
    *got = *want;
    got->rate_hz = a->clock_hz / divider;
    a->rate_hz = got->rate_hz;
    return NULL;
}

void timed_adc_start(timed_adc *a, uint64_t now_ticks)
{
    a->running = 1;
    a->t0 = now_ticks;
    a->produced = 0u;
    a->due = 0u;
}

void timed_adc_stop(timed_adc *a)
{
    a->running = 0;
}

int timed_adc_read(timed_adc *a, uint64_t (*now)(void), bridge_adc_pair *pair)
{
    int i;
    uint64_t missed = 0u;
    if (!a->running) {
        return 0;
    }
    if (a->produced >= a->due) {
        a->due = (uint64_t)((double)(now() - a->t0) * a->rate_hz / a->tick_hz);
        if (a->produced >= a->due) {
            return 0;
        }
    }
    for (i = 0; i < a->nskips; i++) {
        if (a->skip_first[i] == a->produced) {
            missed += a->skip_count[i];
            a->produced += a->skip_count[i];
        }
    }
    if (a->due > a->produced + a->ring) { /* the reader was late: the ring overran */
        missed += a->due - a->ring - a->produced;
        a->produced = a->due - a->ring;
    }
    synth_pair(&a->source, a->rate_hz, a->produced, &pair->disp, &pair->force);
    pair->missed = missed > 0xFFFFFFFFu ? 0xFFFFFFFFu : (uint32_t)missed;
    a->produced++;
    return 1;
}

/* Deterministic synthetic ADC source (see synth.h). */
#include "synth.h"

#include <math.h>

#define TWO_PI 6.283185307179586
#define FULL_SCALE_24 8388608.0

static uint32_t xorshift32(uint32_t x)
{
    x ^= x << 13;
    x ^= x >> 17;
    x ^= x << 5;
    return x;
}

void synth_init(synth *s, int counter, uint32_t seed)
{
    uint32_t x = xorshift32(seed != 0u ? seed : 0x9E3779B9u);
    s->counter = counter;
    s->f_hz = 5.0 + (double)(x % 2000u) * 0.01;
    x = xorshift32(x);
    s->phase_rad = -(0.1 + (double)(x % 1000u) * 0.001);
}

void synth_pair(const synth *s, double rate_hz, uint64_t index, int32_t *disp, int32_t *force)
{
    if (s->counter) {
        int32_t c = (int32_t)(index % 65536u);
        if (c > 32767) {
            c -= 65536;
        }
        *disp = c * 256;
        *force = (-1 - c) * 256;
    } else {
        double w = TWO_PI * s->f_hz * (double)index / rate_hz;
        *disp = (int32_t)lround(0.6 * FULL_SCALE_24 * sin(w));
        *force = (int32_t)lround(0.4 * FULL_SCALE_24 * sin(w + s->phase_rad));
    }
}

/* The emulated ports' deterministic sample source (stands in for the bridge's ADC: host, QEMU).
 *
 * `sine` (default): two sines at one frequency, as a crank rig gives them, as 24-bit codes:
 *     disp(i)  = lround(0.6 * 2^23 * sin(2*pi*f*i/rate))
 *     force(i) = lround(0.4 * 2^23 * sin(2*pi*f*i/rate + phase))
 * with i the stream's sample index (0 at START), rate the ADC's exact rate, and f and phase drawn
 * from `seed` by xorshift32 (x ^= x << 13; x ^= x >> 17; x ^= x << 5; seed 0 starts from
 * 0x9E3779B9): x1 = xorshift(seed), f = 5 + (x1 % 2000) * 0.01 Hz; x2 = xorshift(x1),
 * phase = -(0.1 + (x2 % 1000) * 0.001) rad.
 * `counter`: disp(i) = (i mod 2^16 as int16) * 256, force(i) = (-1 - that int16) * 256: after the
 * core's 24 -> 16-bit rounding the protocol samples are exactly the counter and its complement.
 */
#ifndef PORT_SYNTH_H
#define PORT_SYNTH_H

#include <stdint.h>

typedef struct {
    int counter;
    double f_hz;
    double phase_rad;
} synth;

void synth_init(synth *s, int counter, uint32_t seed);
void synth_pair(const synth *s, double rate_hz, uint64_t index, int32_t *disp, int32_t *force);

#endif

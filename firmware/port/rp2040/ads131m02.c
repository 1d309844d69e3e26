/* The ADS131M02's arithmetic (see ads131m02.h). */
#include "ads131m02.h"

static const unsigned osr_table[8] = {128u, 256u, 512u, 1024u, 2048u, 4096u, 8192u, 16256u};

uint16_t ads131m02_rreg(unsigned address, unsigned count)
{
    return (uint16_t)(0xA000u | ((address & 0x3Fu) << 7) | ((count - 1u) & 0x7Fu));
}

uint16_t ads131m02_wreg(unsigned address, unsigned count)
{
    return (uint16_t)(0x6000u | ((address & 0x3Fu) << 7) | ((count - 1u) & 0x7Fu));
}

void ads131m02_word(uint8_t out[3], uint16_t value)
{
    out[0] = (uint8_t)(value >> 8);
    out[1] = (uint8_t)(value & 0xFFu);
    out[2] = 0u;
}

int32_t ads131m02_code(const uint8_t word[3])
{
    uint32_t raw = ((uint32_t)word[0] << 16) | ((uint32_t)word[1] << 8) | (uint32_t)word[2];
    return raw >= 0x800000u ? (int32_t)raw - 0x1000000 : (int32_t)raw;
}

void ads131m02_frame(const uint8_t frame[ADS131M02_FRAME_BYTES], int32_t *ch0, int32_t *ch1)
{
    *ch0 = ads131m02_code(frame + ADS131M02_WORD_BYTES);
    *ch1 = ads131m02_code(frame + 2u * ADS131M02_WORD_BYTES);
}

uint16_t ads131m02_clock_reg(unsigned osr_code)
{
    return (uint16_t)(0x0200u | 0x0100u | ((osr_code & 7u) << 2) | 0x2u); /* CH1_EN, CH0_EN, OSR, PWR=HR */
}

uint16_t ads131m02_gain_reg(unsigned gain_code0, unsigned gain_code1)
{
    return (uint16_t)(((gain_code1 & 7u) << 4) | (gain_code0 & 7u));
}

static double distance(double a, double b)
{
    return a > b ? a - b : b - a;
}

int ads131m02_plan_rate(double source_hz, double want_hz, uint32_t div_min, uint32_t div_max, ads131m02_timing *t)
{
    int found = 0;
    unsigned k;
    for (k = 0; k < 8u; k++) {
        double ideal = source_hz / (2.0 * (double)osr_table[k] * want_hz);
        double candidates[2];
        unsigned c;
        candidates[0] = (double)(uint32_t)ideal; /* floor (ideal > 0) */
        candidates[1] = candidates[0] + 1.0;
        for (c = 0; c < 2u; c++) {
            double d = candidates[c];
            double rate;
            if (d < (double)div_min || d > (double)div_max) {
                continue;
            }
            rate = source_hz / d / 2.0 / (double)osr_table[k];
            if (!found || distance(rate, want_hz) < distance(t->rate_hz, want_hz)
                || (distance(rate, want_hz) == distance(t->rate_hz, want_hz) && osr_table[k] > t->osr)) {
                found = 1;
                t->divider = (uint32_t)d;
                t->osr = osr_table[k];
                t->osr_code = k;
                t->clkin_hz = source_hz / d;
                t->rate_hz = rate;
            }
        }
    }
    return found;
}

double ads131m02_rate_max(double source_hz, uint32_t div_min)
{
    return source_hz / (double)div_min / 2.0 / (double)osr_table[0];
}

double ads131m02_rate_min(double source_hz, uint32_t div_max)
{
    return source_hz / (double)div_max / 2.0 / (double)osr_table[7];
}

int ads131m02_gain_code(double full_scale_v, double want_v, double *got_v)
{
    int code;
    if (want_v > full_scale_v) {
        return -1;
    }
    for (code = 7; code > 0; code--) {
        if (full_scale_v / (double)(1u << code) >= want_v) {
            break;
        }
    }
    *got_v = full_scale_v / (double)(1u << code);
    return code;
}

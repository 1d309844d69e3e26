/* The ADS131M02's arithmetic, free of any MCU API (built and tested on the host by test/selftest.c):
 * command words, the 24-bit SPI frame, the (CLKIN divider, OSR) plan for a sample rate and the PGA
 * gain for an input range.  Register and bit names follow the TI datasheet.
 */
#ifndef ADS131M02_H
#define ADS131M02_H

#include <stddef.h>
#include <stdint.h>

#define ADS131M02_CMD_NULL 0x0000u
#define ADS131M02_CMD_RESET 0x0011u
#define ADS131M02_CMD_STANDBY 0x0022u
#define ADS131M02_CMD_WAKEUP 0x0033u
#define ADS131M02_REG_ID 0x00u
#define ADS131M02_REG_STATUS 0x01u
#define ADS131M02_REG_MODE 0x02u
#define ADS131M02_REG_CLOCK 0x03u
#define ADS131M02_REG_GAIN 0x04u
#define ADS131M02_WORD_BYTES 3u  /* 24-bit words (MODE.WLENGTH = 01, the reset default) */
#define ADS131M02_FRAME_BYTES 12u /* response (STATUS), channel 0, channel 1, CRC */
#define ADS131M02_FULL_SCALE_V 1.2 /* +-1.2 V / gain with the internal reference */

/* RREG / WREG command words: 101a aaaa annn nnnn / 011a aaaa annn nnnn (n = registers - 1). */
uint16_t ads131m02_rreg(unsigned address, unsigned count);
uint16_t ads131m02_wreg(unsigned address, unsigned count);

/* A 16-bit command or register value as one 24-bit word on DIN (MSB first, padded with zeros). */
void ads131m02_word(uint8_t out[3], uint16_t value);

/* A 24-bit two's complement code, MSB first, as int32. */
int32_t ads131m02_code(const uint8_t word[3]);

/* The two channels of a 12-byte frame read after DRDY. */
void ads131m02_frame(const uint8_t frame[ADS131M02_FRAME_BYTES], int32_t *ch0, int32_t *ch1);

/* CLOCK register: both channels on, OSR, high-resolution power mode. */
uint16_t ads131m02_clock_reg(unsigned osr_code);

/* GAIN register (GAIN1): PGAGAIN1 in bits 6:4, PGAGAIN0 in bits 2:0 (codes 0..7 = gain 1..128). */
uint16_t ads131m02_gain_reg(unsigned gain_code0, unsigned gain_code1);

typedef struct {
    uint32_t divider; /* CLKIN = source / divider */
    unsigned osr;     /* 128 .. 16256 */
    unsigned osr_code; /* CLOCK.OSR, 0 .. 7 */
    double clkin_hz;
    double rate_hz;   /* CLKIN / 2 / OSR */
} ads131m02_timing;

/* The (divider, OSR) whose rate is nearest `want_hz`, with divider in div_min..div_max (the CLKIN
 * range the board allows); on a tie the larger OSR (less noise).  Returns 0 if no divider fits. */
int ads131m02_plan_rate(double source_hz, double want_hz, uint32_t div_min, uint32_t div_max, ads131m02_timing *t);

/* The fastest and slowest rates any (divider, OSR) gives. */
double ads131m02_rate_max(double source_hz, uint32_t div_min);
double ads131m02_rate_min(double source_hz, uint32_t div_max);

/* The PGA gain (code 0..7) giving the smallest range that still covers `want_v`, the range at the
 * bridge's input being full_scale_v / gain; stores that range in *got_v.  Returns -1 if even gain 1
 * does not cover want_v. */
int ads131m02_gain_code(double full_scale_v, double want_v, double *got_v);

#endif

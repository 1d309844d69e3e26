/* RP2040 + ADS131M02 port of the bridge firmware: the HAL (core/bridge_hal.h) on pico-sdk and
 * TinyUSB, and main().  See firmware/README.md ("Port: RP2040 with an ADS131M02") for the wiring,
 * clocks and bring-up.
 *
 * Core 1 polls DRDY and reads each 12-byte SPI frame into a single-producer/single-consumer ring of
 * pairs, and owns the SPI bus (core 0's register writes go through it); core 0 runs TinyUSB and
 * bridge_poll().  Written against pico-sdk 1.5 and its TinyUSB; not
 * built in CI (no pico-sdk there); ads131m02.c, the arithmetic, is (test/selftest.c).
 */
#include <stdio.h>
#include <string.h>

#include "hardware/clocks.h"
#include "hardware/gpio.h"
#include "hardware/spi.h"
#include "hardware/sync.h"
#include "pico/multicore.h"
#include "pico/stdlib.h"
#include "pico/unique_id.h"
#include "tusb.h"

#include "ads131m02.h"
#include "bridge.h"

#define PIN_MISO 16
#define PIN_CS 17
#define PIN_SCK 18
#define PIN_MOSI 19
#define PIN_DRDY 20
#define PIN_CLKIN 21 /* CLK_GPOUT0 */
#define PIN_SYNC_RESET 22
#define SPI_HZ 16000000u
#define SYS_CLOCK_KHZ 128000u /* 12 MHz crystal x 128 / 6 / 2: 20 kHz is exact (5.12 MHz / 2 / 128) */
#define DIV_MIN 16u           /* CLKIN at most 8 MHz */
#define DIV_MAX 400u          /* CLKIN at least 0.32 MHz */
/* the bridge's input range at gain 1: the front end divides +-10 V down to the ADC's +-1.2 V */
#define FRONT_END_FULL_SCALE_V 10.0
#define RING_PAIRS 2048u /* a power of two; 0.1 s at 20 kHz */
#define FIFO_BYTES (160u * 1024u)

/* ------------------------------------------------------------------ ADC: core 1 and the ring */
static bridge_adc_pair ring[RING_PAIRS];
static volatile uint32_t ring_head; /* written by core 1 only */
static volatile uint32_t ring_tail; /* written by core 0 only */
static volatile uint32_t converting;
static uint32_t missed; /* core 1 only: pairs not stored since the last stored one */

static void adc_transfer(const uint8_t *tx, uint8_t *rx)
{
    gpio_put(PIN_CS, 0);
    spi_write_read_blocking(spi0, tx, rx, ADS131M02_FRAME_BYTES);
    gpio_put(PIN_CS, 1);
}

/* Send one command (plus register words) in a frame; the reply comes in the next frame. */
static void adc_command(uint16_t command, const uint16_t *values, unsigned n)
{
    uint8_t tx[ADS131M02_FRAME_BYTES] = {0};
    uint8_t rx[ADS131M02_FRAME_BYTES];
    unsigned i;
    ads131m02_word(tx, command);
    for (i = 0; i < n && i < 3u; i++) {
        ads131m02_word(tx + ADS131M02_WORD_BYTES * (i + 1u), values[i]);
    }
    adc_transfer(tx, rx);
}

/* Once core 1 runs it owns the SPI bus: core 0 posts a register write and waits for it to be done. */
static volatile uint32_t core1_running;
static volatile uint32_t reg_request; /* 0, or 1 << 31 | address << 16 | value */

static void adc_write_reg(unsigned address, uint16_t value)
{
    if (!core1_running) {
        adc_command(ads131m02_wreg(address, 1u), &value, 1u);
        return;
    }
    reg_request = 0x80000000u | ((uint32_t)address << 16) | value;
    while (reg_request != 0u) {
        tight_loop_contents();
    }
}

static void serve_reg_request(void)
{
    uint32_t r = reg_request;
    if (r != 0u) {
        uint16_t value = (uint16_t)(r & 0xFFFFu);
        adc_command(ads131m02_wreg((r >> 16) & 0x3Fu, 1u), &value, 1u);
        reg_request = 0u;
    }
}

static void core1_main(void)
{
    static const uint8_t null_frame[ADS131M02_FRAME_BYTES] = {0}; /* NULL command: STATUS, ch0, ch1, CRC */
    uint8_t rx[ADS131M02_FRAME_BYTES];
    core1_running = 1u;
    for (;;) {
        uint32_t head;
        if (gpio_get(PIN_DRDY)) {
            serve_reg_request(); /* between conversions only (CONF comes while idle) */
            continue;            /* DRDY is active low */
        }
        adc_transfer(null_frame, rx); /* reading the frame releases DRDY */
        if (!converting) {
            continue;
        }
        head = ring_head;
        if (head - ring_tail >= RING_PAIRS) {
            missed++; /* core 0 is late: this pair is lost, the next stored one says so */
            continue;
        }
        ads131m02_frame(rx, &ring[head % RING_PAIRS].disp, &ring[head % RING_PAIRS].force);
        ring[head % RING_PAIRS].missed = missed;
        missed = 0;
        __dmb(); /* the pair is in RAM before core 0 can see the new head */
        ring_head = head + 1u;
    }
}

/* ------------------------------------------------------------------ HAL */
static bridge_port_info info = {"DAQ-BRIDGE-RP2040", "", "ADS131M02", 24u, 5120000.0, 100.0, 31250.0,
                                "usb-cdc", 500000u /* placeholder: measure it (README, link throughput) */};
static char serial[2 * PICO_UNIQUE_BOARD_ID_SIZE_BYTES + 1];
static char refusal[96];

const char *hal_adc_configure(const bridge_adc_setting *want, bridge_adc_setting *got)
{
    ads131m02_timing t;
    int g0, g1;
    if (!ads131m02_plan_rate((double)clock_get_hz(clk_sys), want->rate_hz, DIV_MIN, DIV_MAX, &t)) {
        snprintf(refusal, sizeof refusal, "bad value for rate: expected %g..%g Hz, got '%g'", info.rate_min_hz,
                 info.rate_max_hz, want->rate_hz);
        return refusal;
    }
    g0 = ads131m02_gain_code(FRONT_END_FULL_SCALE_V, want->range_disp_v, &got->range_disp_v);
    g1 = ads131m02_gain_code(FRONT_END_FULL_SCALE_V, want->range_force_v, &got->range_force_v);
    if (g0 < 0 || g1 < 0) {
        snprintf(refusal, sizeof refusal, "bad value for %s: expected at most %g V, got '%g'",
                 g0 < 0 ? "range_disp" : "range_force", FRONT_END_FULL_SCALE_V,
                 g0 < 0 ? want->range_disp_v : want->range_force_v);
        return refusal;
    }
    got->rate_hz = t.rate_hz;
    clock_gpio_init(PIN_CLKIN, CLOCKS_CLK_GPOUT0_CTRL_AUXSRC_VALUE_CLK_SYS, (float)t.divider);
    info.clock_hz = t.clkin_hz;
    adc_write_reg(ADS131M02_REG_CLOCK, ads131m02_clock_reg(t.osr_code));
    adc_write_reg(ADS131M02_REG_GAIN, ads131m02_gain_reg((unsigned)g0, (unsigned)g1));
    return NULL;
}

void hal_adc_start(void)
{
    ring_tail = ring_head; /* pairs converted while idle are not part of the stream */
    gpio_put(PIN_SYNC_RESET, 0); /* a short pulse resynchronises the filters: sample 0 is settled */
    busy_wait_us_32(2);
    gpio_put(PIN_SYNC_RESET, 1);
    __dmb();
    converting = 1u;
}

void hal_adc_stop(void)
{
    converting = 0u;
}

int hal_adc_read(bridge_adc_pair *pair)
{
    uint32_t tail = ring_tail;
    if (tail == ring_head) {
        return 0;
    }
    __dmb();
    *pair = ring[tail % RING_PAIRS];
    ring_tail = tail + 1u;
    return 1;
}

size_t hal_write(const uint8_t *data, size_t n)
{
    uint32_t room = tud_cdc_write_available();
    uint32_t w;
    if (!tud_cdc_connected() || room == 0u) {
        return 0;
    }
    w = tud_cdc_write(data, n < room ? (uint32_t)n : room);
    tud_cdc_write_flush();
    return w;
}

size_t hal_read(uint8_t *data, size_t max)
{
    return tud_cdc_available() ? tud_cdc_read(data, (uint32_t)max) : 0u;
}

uint32_t hal_ticks_us(void)
{
    return time_us_32();
}

/* ------------------------------------------------------------------ main */
static bridge b;
static uint8_t fifo[FIFO_BYTES];

int main(void)
{
    set_sys_clock_khz(SYS_CLOCK_KHZ, true);
    pico_get_unique_board_id_string(serial, sizeof serial);
    info.serial = serial;

    spi_init(spi0, SPI_HZ);
    spi_set_format(spi0, 8, SPI_CPOL_0, SPI_CPHA_1, SPI_MSB_FIRST); /* SPI mode 1 */
    gpio_set_function(PIN_MISO, GPIO_FUNC_SPI);
    gpio_set_function(PIN_SCK, GPIO_FUNC_SPI);
    gpio_set_function(PIN_MOSI, GPIO_FUNC_SPI);
    gpio_init(PIN_CS);
    gpio_set_dir(PIN_CS, GPIO_OUT);
    gpio_put(PIN_CS, 1);
    gpio_init(PIN_DRDY);
    gpio_set_dir(PIN_DRDY, GPIO_IN);
    gpio_init(PIN_SYNC_RESET);
    gpio_set_dir(PIN_SYNC_RESET, GPIO_OUT);

    /* CLKIN first (the ADC needs it to leave reset), then a reset pulse longer than 2048 CLKIN periods */
    clock_gpio_init(PIN_CLKIN, CLOCKS_CLK_GPOUT0_CTRL_AUXSRC_VALUE_CLK_SYS, 25.0f);
    gpio_put(PIN_SYNC_RESET, 0);
    sleep_ms(1);
    gpio_put(PIN_SYNC_RESET, 1);
    sleep_ms(1);

    tusb_init();
    if (bridge_init(&b, &info, fifo, sizeof fifo) != NULL) {
        for (;;) {
            tight_loop_contents(); /* the port cannot do its own default setting: a build error */
        }
    }
    info.rate_min_hz = ads131m02_rate_min((double)clock_get_hz(clk_sys), DIV_MAX);
    if (info.rate_min_hz < BRIDGE_MIN_RATE_HZ) {
        info.rate_min_hz = BRIDGE_MIN_RATE_HZ;
    }
    info.rate_max_hz = ads131m02_rate_max((double)clock_get_hz(clk_sys), DIV_MIN);
    multicore_launch_core1(core1_main);
    for (;;) {
        tud_task();
        bridge_poll(&b);
    }
}

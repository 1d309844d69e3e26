/* Self-test of the portable core against a scripted HAL: CRC-32 (check value, table against the
 * bitwise definition), SLIP, 24 -> 16-bit conversion, frame layout, sequence wrap, lost samples as
 * whole lost frames, FIFO overflow and the reply reserve.  `make check` runs it; exit status 0 when
 * every check holds.  (The end-to-end tests against the Python driver are tests/test_firmware.py.)
 */
#include <stdio.h>
#include <string.h>

#include "ads131m02.h"
#include "bridge.h"
#include "crc32.h"
#include "slip.h"

static int failures;

#define CHECK(cond)                                                           \
    do {                                                                      \
        if (!(cond)) {                                                        \
            fprintf(stderr, "%s:%d: check failed: %s\n", __FILE__, __LINE__, #cond); \
            failures++;                                                       \
        }                                                                     \
    } while (0)

/* ------------------------------------------------------------------ scripted HAL */
static struct {
    int running;
    uint32_t pending;   /* pairs ready to read */
    uint32_t next;      /* index of the next pair */
    uint32_t miss_at, miss_count;
    uint8_t out[1 << 16];
    size_t out_len;
    size_t write_limit; /* bytes hal_write takes per call */
    const uint8_t *in;
    size_t in_len;
    uint32_t ticks;
} hal;

const char *hal_adc_configure(const bridge_adc_setting *want, bridge_adc_setting *got)
{
    *got = *want;
    got->rate_hz = 16e6 / (double)(long)(16e6 / want->rate_hz + 0.5);
    return NULL;
}

void hal_adc_start(void)
{
    hal.running = 1;
    hal.next = 0;
}

void hal_adc_stop(void)
{
    hal.running = 0;
}

int hal_adc_read(bridge_adc_pair *p)
{
    if (!hal.running || hal.pending == 0) {
        return 0;
    }
    p->missed = 0;
    if (hal.miss_count > 0 && hal.next == hal.miss_at) {
        p->missed = hal.miss_count;
        hal.next += hal.miss_count;
    }
    p->disp = (int32_t)hal.next * 256;
    p->force = -(int32_t)hal.next * 256;
    hal.next++;
    hal.pending--;
    return 1;
}

size_t hal_write(const uint8_t *data, size_t n)
{
    size_t room = sizeof hal.out - hal.out_len;
    if (n > hal.write_limit) {
        n = hal.write_limit;
    }
    if (n > room) {
        n = room;
    }
    memcpy(hal.out + hal.out_len, data, n);
    hal.out_len += n;
    return n;
}

size_t hal_read(uint8_t *data, size_t max)
{
    size_t n = hal.in_len < max ? hal.in_len : max;
    memcpy(data, hal.in, n);
    hal.in += n;
    hal.in_len -= n;
    return n;
}

uint32_t hal_ticks_us(void)
{
    return hal.ticks;
}

/* ------------------------------------------------------------------ helpers */
static uint32_t bitwise_crc32(const uint8_t *d, size_t n)
{
    uint32_t c = 0xFFFFFFFFu;
    size_t i;
    int k;
    for (i = 0; i < n; i++) {
        c ^= d[i];
        for (k = 0; k < 8; k++) {
            c = (c >> 1) ^ ((c & 1u) ? 0xEDB88320u : 0u);
        }
    }
    return c ^ 0xFFFFFFFFu;
}

/* Split hal.out into un-escaped packets; returns how many, their bytes in pk[i] (lengths in len). */
static size_t packets(uint8_t pk[][2048], size_t *len, size_t max)
{
    slip_rx rx;
    size_t i, n = 0;
    uint8_t buf[2048];
    slip_rx_init(&rx, buf, sizeof buf);
    for (i = 0; i < hal.out_len && n < max; i++) {
        if (slip_rx_byte(&rx, hal.out[i]) == SLIP_RX_PACKET) {
            memcpy(pk[n], buf, rx.len);
            len[n++] = rx.len;
            slip_rx_reset(&rx);
        }
    }
    return n;
}

static void command(bridge *b, const char *text)
{
    static uint8_t pkt[300];
    static uint8_t wire[700];
    bridge_ring r;
    size_t n = strlen(text), w;
    uint32_t crc;
    pkt[0] = BRIDGE_PKT_COMMAND;
    memcpy(pkt + 1, text, n);
    crc = crc32(pkt, n + 1);
    pkt[n + 1] = (uint8_t)crc;
    pkt[n + 2] = (uint8_t)(crc >> 8);
    pkt[n + 3] = (uint8_t)(crc >> 16);
    pkt[n + 4] = (uint8_t)(crc >> 24);
    bridge_ring_init(&r, wire, sizeof wire);
    slip_put(&r, pkt, n + 5);
    w = r.used;
    hal.in = wire;
    hal.in_len = w;
    bridge_poll(b);
}

static uint32_t le32(const uint8_t *p)
{
    return (uint32_t)p[0] | ((uint32_t)p[1] << 8) | ((uint32_t)p[2] << 16) | ((uint32_t)p[3] << 24);
}

/* ------------------------------------------------------------------ tests */
static void test_crc(void)
{
    static const uint8_t check[] = "123456789";
    uint8_t data[1000];
    size_t i;
    uint32_t state;
    CHECK(crc32(check, 9) == CRC32_CHECK);
    CHECK(CRC32_CHECK == 0xCBF43926u);
    printf("crc32(\"123456789\") = 0x%08lX\n", (unsigned long)crc32(check, 9));
    for (i = 0; i < sizeof data; i++) {
        data[i] = (uint8_t)((i * 7u + 3u) ^ (i >> 3));
    }
    for (i = 0; i < 256; i++) { /* every table entry, through one-byte CRCs */
        uint8_t byte = (uint8_t)i;
        CHECK(crc32(&byte, 1) == bitwise_crc32(&byte, 1));
    }
    CHECK(crc32(data, sizeof data) == bitwise_crc32(data, sizeof data));
    state = crc32_update(CRC32_INIT, data, 333);
    state = crc32_update(state, data + 333, sizeof data - 333);
    CHECK(crc32_final(state) == crc32(data, sizeof data));
}

static void test_slip(void)
{
    static const uint8_t raw[] = {0x01, 0xC0, 0x02, 0xDB, 0x03, 0xDB, 0xDC};
    static const uint8_t wire[] = {0xC0, 0x01, 0xDB, 0xDC, 0x02, 0xDB, 0xDD, 0x03, 0xDB, 0xDD, 0xDC, 0xC0};
    uint8_t mem[64], buf[4];
    bridge_ring r;
    slip_rx rx;
    size_t i;
    bridge_ring_init(&r, mem, sizeof mem);
    CHECK(slip_wire_length(raw, sizeof raw) == sizeof wire);
    slip_put(&r, raw, sizeof raw);
    CHECK(r.used == sizeof wire && memcmp(r.buf, wire, sizeof wire) == 0);
    {
        uint8_t back[16];
        slip_rx_init(&rx, back, sizeof back);
        CHECK(slip_rx_byte(&rx, SLIP_END) == SLIP_RX_NONE); /* empty chunk ignored */
        for (i = 1; i < sizeof wire; i++) {
            if (slip_rx_byte(&rx, wire[i]) == SLIP_RX_PACKET) {
                break;
            }
        }
        CHECK(i == sizeof wire - 1 && rx.error == SLIP_OK && rx.len == sizeof raw);
        CHECK(memcmp(back, raw, sizeof raw) == 0);
    }
    slip_rx_init(&rx, buf, sizeof buf);
    (void)slip_rx_byte(&rx, 0xDB);
    (void)slip_rx_byte(&rx, 0x41);
    CHECK(slip_rx_byte(&rx, SLIP_END) == SLIP_RX_PACKET && rx.error == SLIP_BAD_ESCAPE);
    slip_rx_reset(&rx);
    for (i = 0; i < 6; i++) {
        (void)slip_rx_byte(&rx, 0x41);
    }
    CHECK(slip_rx_flush(&rx) == SLIP_RX_PACKET && rx.error == SLIP_TOO_LONG && rx.len == sizeof buf);
}

static void test_code16(void)
{
    CHECK(bridge_code16(0x7FFFFF, 24) == 32767);      /* rounds up to 32768: saturated */
    CHECK(bridge_code16(-0x800000, 24) == -32768);
    CHECK(bridge_code16(383, 24) == 1);                /* 1.496 -> 1 */
    CHECK(bridge_code16(384, 24) == 2);                /* 1.5 -> 2 (half up) */
    CHECK(bridge_code16(-384, 24) == -1);              /* -1.5 -> -1 (half up) */
    CHECK(bridge_code16(-385, 24) == -2);
    CHECK(bridge_code16(-1234, 16) == -1234);
    CHECK(bridge_code16(-5, 12) == -80);
    CHECK(bridge_code16(0x7FFFFFFF, 32) == 32767);
}

static bridge b;
static uint8_t fifo[1 << 15];
static uint8_t pk[64][2048];
static size_t len[64];

static void test_frames_and_wrap(void)
{
    static const bridge_port_info info = {"T", "SN", "ADC", 24u, 16e6, 100.0, 1e6, "uart", 300000u};
    size_t n, i;
    memset(&hal, 0, sizeof hal);
    hal.write_limit = sizeof hal.out;
    CHECK(bridge_init(&b, &info, fifo, sizeof fifo) == NULL);
    command(&b, "#7 CONF frame=16 rate=20000");
    command(&b, "START");
    b.frames = 0xFFFFFFFFu; /* the next frame carries seq 0xFFFFFFFF, the one after it seq 0 */
    hal.pending = 32;
    bridge_poll(&b);
    n = packets(pk, len, 64);
    CHECK(n == 4);
    CHECK(len[0] > 5 && memcmp(pk[0] + 1, "#7 OK CONF rate=20000 rate_exact=20000 frame=16", 47) == 0);
    CHECK(len[2] == BRIDGE_FRAME_BYTES(16) && pk[2][0] == 1 && le32(pk[2] + 1) == 0xFFFFFFFFu);
    CHECK(len[3] == BRIDGE_FRAME_BYTES(16) && le32(pk[3] + 1) == 0u);
    CHECK(pk[3][5] == 16 && pk[3][6] == 0);
    /* sample 16 of the stream: disp 16, force -16, little-endian */
    CHECK(pk[3][7] == 16 && pk[3][8] == 0 && pk[3][9] == 0xF0 && pk[3][10] == 0xFF);
    for (i = 2; i < 4; i++) {
        CHECK(le32(pk[i] + len[i] - 4) == bitwise_crc32(pk[i], len[i] - 4));
    }
    CHECK(b.frames == 0x100000001ull);
    hal.out_len = 0;
    command(&b, "STOP");
    n = packets(pk, len, 64);
    CHECK(n == 1 && memcmp(pk[0] + 1, "OK STOP frames=4294967297 samples=68719476752", 45) == 0);
}

static void test_missed_samples_lose_whole_frames(void)
{
    static const bridge_port_info info = {"T", "SN", "ADC", 24u, 16e6, 100.0, 1e6, "uart", 300000u};
    size_t n;
    memset(&hal, 0, sizeof hal);
    hal.write_limit = sizeof hal.out;
    CHECK(bridge_init(&b, &info, fifo, sizeof fifo) == NULL);
    command(&b, "CONF frame=16");
    command(&b, "START");
    hal.miss_at = 20;    /* samples 20..59 never reach the core: frames 1, 2 and 3 (16..63) are lost */
    hal.miss_count = 40;
    hal.pending = 64 - 40;
    bridge_poll(&b);
    CHECK(b.frames == 4 && b.overflows == 3);
    hal.pending = 16;
    bridge_poll(&b);
    n = packets(pk, len, 64);
    CHECK(n == 4); /* CONF, START replies, frames 0 and 4 */
    CHECK(le32(pk[2] + 1) == 0 && le32(pk[3] + 1) == 4);
    CHECK(pk[3][7] == 64 && pk[3][8] == 0); /* frame 4 starts with sample 64 */
}

static void test_fifo_overflow_keeps_replies(void)
{
    static const bridge_port_info info = {"T", "SN", "ADC", 24u, 16e6, 100.0, 1e6, "uart", 300000u};
    size_t n, i, frames = 0;
    memset(&hal, 0, sizeof hal);
    hal.write_limit = 0; /* the link takes nothing: the FIFO fills */
    CHECK(bridge_init(&b, &info, fifo, sizeof fifo) == NULL);
    command(&b, "CONF frame=256");
    command(&b, "START");
    hal.pending = 256 * 40; /* 40 frames of ~1035 bytes into a 32 KiB FIFO */
    bridge_poll(&b);
    bridge_poll(&b);
    bridge_poll(&b);
    bridge_poll(&b);
    bridge_poll(&b);
    CHECK(b.frames == 40 && b.overflows > 0 && b.overflows < 40);
    command(&b, "STAT?");
    command(&b, "STOP");
    hal.write_limit = sizeof hal.out;
    bridge_poll(&b); /* sends what is queued; STOP waited for room for its reply */
    bridge_poll(&b);
    n = packets(pk, len, 64);
    for (i = 0; i < n; i++) {
        frames += pk[i][0] == BRIDGE_PKT_SAMPLES;
    }
    CHECK(frames == 40u - b.overflows);
    CHECK(n == frames + 4u && pk[n - 1][0] == BRIDGE_PKT_REPLY);
    CHECK(memcmp(pk[n - 1] + 1, "OK STOP frames=40 samples=10240", 31) == 0);
}

static void test_commands(void)
{
    static const bridge_port_info info = {"MODEL", "SN9", "ADS131M02", 24u, 8192000.0, 250.0, 32000.0,
                                          "usb-cdc", 900000u};
    static const char *expect[] = {
        "#1 OK SINECAL,MODEL,SN9,1.0",
        "#2 OK HW adc=ADS131M02 bits=24 channels=disp,force clock_hz=8192000 rate_min=250 rate_max=32000 "
        "link=usb-cdc link_bytes_per_s=900000",
        "ERR 1 empty command: expected IDN?, HW?, CONF, START, STOP or STAT?",
        "#3 ERR 1 unknown command 'idn?': expected IDN?, HW?, CONF, START, STOP or STAT?",
        "ERR 2 bad tag: expected '#' and 1..15 printable ASCII characters without spaces, got '#'",
        "#4 ERR 2 bad value for frame: expected integer 16..2048 (this bridge's largest), got '15'", /* 32 KiB FIFO */
        "#5 OK CONF rate=20000 rate_exact=20000 frame=256 range_disp=10 range_force=0.5 channels=disp,force",
        "#6 ERR 2 bad value for rate: expected 250..32000 Hz, got '0x4E20'",
        "#7 OK STOP frames=0 samples=0 (was idle)",
        "#8 ERR 2 bad argument: expected none after START, got 'now'",
        "#9 ERR 2 bad value for rate: expected 250..32000 Hz, got '32001'",
    };
    static const char *send[] = {"#1 IDN?", "#2 HW?", "", "#3 idn?", "# IDN?", "#4 CONF frame=15",
                                 "#5 CONF range_force=0.5", "#6 CONF rate=0x4E20", "#7 STOP", "#8 START now",
                                 "#9 CONF rate=32001"};
    size_t i, n;
    memset(&hal, 0, sizeof hal);
    hal.write_limit = sizeof hal.out;
    CHECK(bridge_init(&b, &info, fifo, sizeof fifo) == NULL);
    for (i = 0; i < sizeof send / sizeof send[0]; i++) {
        command(&b, send[i]);
    }
    n = packets(pk, len, 64);
    CHECK(n == sizeof expect / sizeof expect[0]);
    for (i = 0; i < n && i < sizeof expect / sizeof expect[0]; i++) {
        size_t want = strlen(expect[i]);
        if (len[i] != want + 5 || memcmp(pk[i] + 1, expect[i], want) != 0) {
            fprintf(stderr, "reply %lu: expected '%s', got '%.*s'\n", (unsigned long)i, expect[i],
                    (int)(len[i] > 5 ? len[i] - 5 : 0), (const char *)pk[i] + 1);
            failures++;
        }
    }
}

static void test_unfinished_command_times_out(void)
{
    static const bridge_port_info info = {"T", "SN", "ADC", 24u, 16e6, 100.0, 1e6, "uart", 300000u};
    static const uint8_t torn[] = {0xC0, 0x10, 'S', 'T'};
    size_t n;
    memset(&hal, 0, sizeof hal);
    hal.write_limit = sizeof hal.out;
    CHECK(bridge_init(&b, &info, fifo, sizeof fifo) == NULL);
    hal.in = torn;
    hal.in_len = sizeof torn;
    bridge_poll(&b);
    hal.ticks = BRIDGE_RX_TIMEOUT_US - 1u;
    bridge_poll(&b);
    CHECK(hal.out_len == 0);
    hal.ticks = BRIDGE_RX_TIMEOUT_US + 1u;
    bridge_poll(&b);
    n = packets(pk, len, 64);
    CHECK(n == 1 && memcmp(pk[0] + 1, "ERR 4 malformed command packet: expected at least 5 bytes", 57) == 0);
}

static void test_ads131m02(void)
{
    static const uint8_t min[3] = {0x80, 0x00, 0x00}, max[3] = {0x7F, 0xFF, 0xFF}, m1[3] = {0xFF, 0xFF, 0xFF};
    static const uint8_t frame[12] = {0x05, 0x00, 0x00, 0x00, 0x01, 0x00, 0xFF, 0xFE, 0x00, 0x12, 0x34, 0x00};
    static const struct {
        double want;
        uint32_t divider;
        unsigned osr;
        double rate;
    } plans[] = {{20000.0, 25u, 128u, 20000.0},
                 {10000.0, 25u, 256u, 10000.0}, /* tie with /50 at OSR 128: the larger OSR */
                 {25000.0, 20u, 128u, 25000.0},
                 {31250.0, 16u, 128u, 31250.0},
                 {32000.0, 16u, 128u, 31250.0}, /* the nearest is 2.3 % off: the core refuses it */
                 {1000.0, 125u, 512u, 1000.0}};
    uint8_t word[3];
    int32_t ch0, ch1;
    double got;
    size_t i;
    ads131m02_timing t;
    CHECK(ads131m02_code(min) == -8388608 && ads131m02_code(max) == 8388607 && ads131m02_code(m1) == -1);
    ads131m02_frame(frame, &ch0, &ch1);
    CHECK(ch0 == 256 && ch1 == -512);
    CHECK(ads131m02_rreg(ADS131M02_REG_ID, 1) == 0xA000u && ads131m02_wreg(ADS131M02_REG_CLOCK, 1) == 0x6180u);
    CHECK(ads131m02_wreg(ADS131M02_REG_MODE, 3) == 0x6102u);
    ads131m02_word(word, 0x6180u);
    CHECK(word[0] == 0x61 && word[1] == 0x80 && word[2] == 0x00);
    CHECK(ads131m02_clock_reg(3) == 0x030Eu); /* the register's reset value: OSR 1024, high resolution */
    CHECK(ads131m02_gain_reg(6, 1) == 0x16u);
    for (i = 0; i < sizeof plans / sizeof plans[0]; i++) {
        CHECK(ads131m02_plan_rate(128e6, plans[i].want, 16u, 400u, &t));
        CHECK(t.divider == plans[i].divider && t.osr == plans[i].osr && t.rate_hz == plans[i].rate);
        CHECK(t.clkin_hz == 128e6 / plans[i].divider && t.rate_hz == t.clkin_hz / 2.0 / t.osr);
    }
    CHECK(!ads131m02_plan_rate(128e6, 20000.0, 500u, 400u, &t));
    CHECK(ads131m02_rate_max(128e6, 16u) == 31250.0);
    CHECK(ads131m02_gain_code(10.0, 10.0, &got) == 0 && got == 10.0);
    CHECK(ads131m02_gain_code(10.0, 5.0, &got) == 1 && got == 5.0);
    CHECK(ads131m02_gain_code(10.0, 0.1, &got) == 6 && got == 0.15625);
    CHECK(ads131m02_gain_code(10.0, 0.05, &got) == 7 && got == 0.078125); /* below the protocol's 0.1 V anyway */
    CHECK(ads131m02_gain_code(10.0, 11.0, &got) == -1);
}

int main(void)
{
    test_ads131m02();
    test_crc();
    test_slip();
    test_code16();
    test_frames_and_wrap();
    test_missed_samples_lose_whole_frames();
    test_fifo_overflow_keeps_replies();
    test_commands();
    test_unfinished_command_times_out();
    if (failures > 0) {
        fprintf(stderr, "selftest: %d check(s) failed\n", failures);
        return 1;
    }
    printf("selftest: all checks passed\n");
    return 0;
}

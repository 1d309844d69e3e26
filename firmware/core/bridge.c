/* The DAQ bridge's device side of docs/daq-protocol.md (see bridge.h).
 *
 * Data path: hal_adc_read() pairs -> bridge_code16() -> frame_buf (type, seq, count, samples, CRC)
 * -> SLIP into the device FIFO (whole frames, or the frame is dropped and its seq consumed) ->
 * hal_write().  Command path: hal_read() -> SLIP decoder -> CRC and type check -> tag -> command
 * -> one reply packet queued behind whatever the FIFO holds (so STOP's reply follows the last frame).
 */
#include "bridge.h"

#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "crc32.h"

#define MAX_WORDS 16u
#define MAX_TAG 16u   /* '#' and 1..15 characters */
#define MAX_ECHO 40u  /* characters of received text quoted in an error message */

typedef struct {
    const char *s;
    size_t n;
} word;

/* ------------------------------------------------------------------ reply text */
static void rp_str(bridge *b, const char *s)
{
    while (*s != '\0' && b->reply_len < BRIDGE_MAX_REPLY) {
        b->reply[b->reply_len++] = *s++;
    }
    b->reply[b->reply_len] = '\0';
}

static void rp_mem(bridge *b, const char *s, size_t n)
{
    size_t i;
    for (i = 0; i < n && b->reply_len < BRIDGE_MAX_REPLY; i++) {
        b->reply[b->reply_len++] = s[i];
    }
    b->reply[b->reply_len] = '\0';
}

static void rp_u64(bridge *b, uint64_t v)
{
    char digits[21];
    size_t n = 0;
    do {
        digits[n++] = (char)('0' + (int)(v % 10u));
        v /= 10u;
    } while (v != 0u);
    while (n > 0u && b->reply_len < BRIDGE_MAX_REPLY) {
        b->reply[b->reply_len++] = digits[--n];
    }
    b->reply[b->reply_len] = '\0';
}

static void rp_hex(bridge *b, uint32_t v, unsigned digits)
{
    static const char hex[] = "0123456789ABCDEF";
    rp_str(b, "0x");
    while (digits-- > 0u) {
        char c[2];
        c[0] = hex[(v >> (4u * digits)) & 0xFu];
        c[1] = '\0';
        rp_str(b, c);
    }
}

/* A decimal number with up to 10 significant digits: 20000, 0.1, 19980.4878. */
static void rp_num(bridge *b, double v)
{
    char s[32];
    (void)snprintf(s, sizeof s, "%.10g", v);
    rp_str(b, s);
}

/* Received text in quotes, cut at MAX_ECHO characters (the text is printable ASCII already). */
static void rp_quoted(bridge *b, const char *s, size_t n)
{
    rp_str(b, "'");
    if (n > MAX_ECHO) {
        rp_mem(b, s, MAX_ECHO);
        rp_str(b, "...");
    } else {
        rp_mem(b, s, n);
    }
    rp_str(b, "'");
}

static void rp_begin(bridge *b, const char *tag, size_t tag_len)
{
    b->reply_len = 0;
    b->reply[0] = '\0';
    if (tag != NULL) {
        rp_mem(b, tag, tag_len);
        rp_str(b, " ");
    }
}

/* Queue the reply text as one packet (type 0x02).  The caller made sure BRIDGE_REPLY_RESERVE bytes
 * were free, so this always fits: replies are never dropped. */
static void rp_send(bridge *b)
{
    uint32_t crc;
    size_t n = 1u + b->reply_len;
    b->packet[0] = BRIDGE_PKT_REPLY;
    memcpy(b->packet + 1, b->reply, b->reply_len);
    crc = crc32(b->packet, n);
    b->packet[n++] = (uint8_t)(crc & 0xFFu);
    b->packet[n++] = (uint8_t)((crc >> 8) & 0xFFu);
    b->packet[n++] = (uint8_t)((crc >> 16) & 0xFFu);
    b->packet[n++] = (uint8_t)((crc >> 24) & 0xFFu);
    slip_put(&b->tx, b->packet, n);
}

static void rp_config(bridge *b)
{
    rp_str(b, "rate=");
    rp_num(b, b->rate_hz);
    rp_str(b, " rate_exact=");
    rp_num(b, b->adc.rate_hz);
    rp_str(b, " frame=");
    rp_u64(b, b->frame);
    rp_str(b, " range_disp=");
    rp_num(b, b->adc.range_disp_v);
    rp_str(b, " range_force=");
    rp_num(b, b->adc.range_force_v);
    rp_str(b, " channels=disp,force");
}

/* ------------------------------------------------------------------ samples and frames */
int16_t bridge_code16(int32_t code, unsigned bits)
{
    int64_t v = code;
    if (bits > 16u) {
        /* round half up: floor((code + 2^(s-1)) / 2^s), without shifting a negative number */
        int64_t div = (int64_t)1 << (bits - 16u);
        int64_t n = v + div / 2;
        v = n / div;
        if (n % div != 0 && n < 0) {
            v -= 1;
        }
    } else if (bits < 16u) {
        v *= (int64_t)1 << (16u - bits);
    }
    if (v > 32767) {
        v = 32767;
    } else if (v < -32768) {
        v = -32768;
    }
    return (int16_t)v;
}

static void put_u16(uint8_t *p, uint16_t v)
{
    p[0] = (uint8_t)(v & 0xFFu);
    p[1] = (uint8_t)(v >> 8);
}

static void put_u32(uint8_t *p, uint32_t v)
{
    put_u16(p, (uint16_t)(v & 0xFFFFu));
    put_u16(p + 2, (uint16_t)(v >> 16));
}

static void dropped(bridge *b, uint64_t first, uint64_t count, bridge_drop_reason why)
{
    uint64_t total = (uint64_t)b->overflows + count;
    b->overflows = total > 0xFFFFFFFFu ? 0xFFFFFFFFu : (uint32_t)total;
    if (b->on_drop != NULL) {
        b->on_drop(b->on_drop_ctx, first, count, why);
    }
}

/* Close the frame being built: queue it whole, or drop it (its seq is consumed either way). */
static void end_frame(bridge *b)
{
    uint64_t index = b->frames;
    if (b->frame_lost) {
        dropped(b, index, 1u, BRIDGE_DROP_ADC);
    } else {
        size_t n = BRIDGE_FRAME_BYTES(b->frame) - BRIDGE_CRC_SIZE;
        uint32_t crc;
        size_t wire;
        b->frame_buf[0] = BRIDGE_PKT_SAMPLES;
        put_u32(b->frame_buf + 1, (uint32_t)(index & 0xFFFFFFFFu));
        put_u16(b->frame_buf + 5, b->frame);
        crc = crc32(b->frame_buf, n);
        put_u32(b->frame_buf + n, crc);
        n += BRIDGE_CRC_SIZE;
        wire = slip_wire_length(b->frame_buf, n);
        if (bridge_ring_free(&b->tx) >= wire + BRIDGE_REPLY_RESERVE) {
            slip_put(&b->tx, b->frame_buf, n);
        } else {
            dropped(b, index, 1u, BRIDGE_DROP_FIFO);
        }
    }
    b->frames++;
    b->fill = 0;
    b->frame_lost = 0;
}

/* `missed` samples before the next pair never reached the core: the frames they fall in are lost. */
static void skip_samples(bridge *b, uint32_t missed)
{
    uint32_t room = (uint32_t)(b->frame - b->fill);
    uint64_t whole;
    if (missed < room) {
        b->fill = (uint16_t)(b->fill + missed);
        b->frame_lost = 1;
        return;
    }
    missed -= room;
    b->frame_lost = 1;
    end_frame(b);
    whole = missed / b->frame;
    if (whole > 0u) {
        dropped(b, b->frames, whole, BRIDGE_DROP_ADC);
        b->frames += whole;
    }
    b->fill = (uint16_t)(missed % b->frame);
    b->frame_lost = b->fill > 0u;
}

static void add_pair(bridge *b, const bridge_adc_pair *p)
{
    if (p->missed > 0u) {
        skip_samples(b, p->missed);
    }
    if (!b->frame_lost) {
        uint8_t *s = b->frame_buf + BRIDGE_FRAME_HEADER + 4u * (size_t)b->fill;
        put_u16(s, (uint16_t)bridge_code16(p->disp, b->info->adc_bits));
        put_u16(s + 2, (uint16_t)bridge_code16(p->force, b->info->adc_bits));
    }
    b->fill++;
    if (b->fill == b->frame) {
        end_frame(b);
    }
}

/* Take up to `max` pairs from the ADC; returns how many came (pairs while idle are discarded). */
static uint32_t take_pairs(bridge *b, uint32_t max)
{
    uint32_t n;
    bridge_adc_pair p;
    for (n = 0; n < max && hal_adc_read(&p); n++) {
        if (b->streaming) {
            add_pair(b, &p);
        }
    }
    return n;
}

/* ------------------------------------------------------------------ commands */
static int word_is(const word *w, const char *s)
{
    return strlen(s) == w->n && memcmp(w->s, s, w->n) == 0;
}

/* A decimal number (digits, '.', exponent): no hex, inf or nan, the whole word. */
static int parse_number(const char *s, size_t n, double *out)
{
    char buf[32];
    char *end;
    size_t i;
    if (n == 0u || n >= sizeof buf) {
        return 0;
    }
    for (i = 0; i < n; i++) {
        char c = s[i];
        if (!((c >= '0' && c <= '9') || c == '.' || c == 'e' || c == 'E' || c == '+' || c == '-')) {
            return 0;
        }
    }
    memcpy(buf, s, n);
    buf[n] = '\0';
    *out = strtod(buf, &end);
    return end == buf + n;
}

static int parse_uint(const char *s, size_t n, unsigned long *out)
{
    size_t i;
    unsigned long v = 0;
    if (n == 0u || n > 9u) {
        return 0;
    }
    for (i = 0; i < n; i++) {
        if (s[i] < '0' || s[i] > '9') {
            return 0;
        }
        v = v * 10u + (unsigned long)(s[i] - '0');
    }
    *out = v;
    return 1;
}

static void err_value(bridge *b, const char *key, const char *expected, const char *got, size_t got_len)
{
    rp_str(b, "ERR 2 bad value for ");
    rp_str(b, key);
    rp_str(b, ": expected ");
    rp_str(b, expected);
    rp_str(b, ", got ");
    rp_quoted(b, got, got_len);
}

static double rel_diff(double a, double b)
{
    double d = a > b ? a - b : b - a;
    return d / b;
}

/* CONF key=value ...: all or nothing; the reply is the full effective configuration. */
static void cmd_conf(bridge *b, const word *args, size_t nargs)
{
    double rate = b->rate_hz;
    unsigned long frame = b->frame;
    bridge_adc_setting want = b->adc;
    bridge_adc_setting got;
    const char *refused;
    size_t i;
    size_t max_frame = BRIDGE_MAX_FRAME;
    /* the protocol's bounds, narrowed to what this ADC achieves (HW? rate_min, rate_max) */
    double rate_lo = b->info->rate_min_hz > BRIDGE_MIN_RATE_HZ ? b->info->rate_min_hz : BRIDGE_MIN_RATE_HZ;
    double rate_hi = b->info->rate_max_hz < BRIDGE_MAX_RATE_HZ ? b->info->rate_max_hz : BRIDGE_MAX_RATE_HZ;
    /* a frame must fit the FIFO beside the reply reserve even if every byte is escaped */
    while (max_frame > BRIDGE_MIN_FRAME
           && 2u * BRIDGE_FRAME_BYTES(max_frame) + 2u + BRIDGE_REPLY_RESERVE > b->tx.size) {
        max_frame /= 2u;
    }
    want.rate_hz = rate;
    if (b->streaming) {
        rp_str(b, "ERR 3 busy: expected STOP before CONF, got CONF while streaming");
        return;
    }
    for (i = 0; i < nargs; i++) {
        const char *eq = memchr(args[i].s, '=', args[i].n);
        word key, value;
        double x;
        if (eq == NULL) {
            key.s = args[i].s;
            key.n = 0;
        } else {
            key.s = args[i].s;
            key.n = (size_t)(eq - args[i].s);
        }
        value.s = eq == NULL ? NULL : eq + 1;
        value.n = eq == NULL ? 0u : args[i].n - key.n - 1u;
        if (word_is(&key, "rate")) {
            if (!parse_number(value.s, value.n, &x) || !(x >= rate_lo && x <= rate_hi)) {
                char expected[64];
                (void)snprintf(expected, sizeof expected, "%.10g..%.10g Hz", rate_lo, rate_hi);
                err_value(b, "rate", expected, value.s, value.n);
                return;
            }
            rate = want.rate_hz = x;
        } else if (word_is(&key, "frame")) {
            unsigned long f;
            if (!parse_uint(value.s, value.n, &f) || f < BRIDGE_MIN_FRAME || f > max_frame) {
                char expected[64];
                (void)snprintf(expected, sizeof expected, "integer %u..%lu%s", (unsigned)BRIDGE_MIN_FRAME,
                               (unsigned long)max_frame, max_frame < 4096u ? " (this bridge's largest)" : "");
                err_value(b, "frame", expected, value.s, value.n);
                return;
            }
            frame = f;
        } else if (word_is(&key, "range_disp") || word_is(&key, "range_force")) {
            int disp = word_is(&key, "range_disp");
            if (!parse_number(value.s, value.n, &x) || !(x >= BRIDGE_MIN_RANGE_V && x <= BRIDGE_MAX_RANGE_V)) {
                err_value(b, disp ? "range_disp" : "range_force", "0.1..10 V", value.s, value.n);
                return;
            }
            if (disp) {
                want.range_disp_v = x;
            } else {
                want.range_force_v = x;
            }
        } else if (word_is(&key, "channels")) {
            if (!word_is(&value, "disp,force")) {
                err_value(b, "channels", "disp,force", value.s, value.n);
                return;
            }
        } else {
            rp_str(b, "ERR 2 bad argument: expected key=value with key in rate, frame, range_disp, range_force, "
                      "channels, got ");
            rp_quoted(b, args[i].s, args[i].n);
            return;
        }
    }
    if (nargs > 0u) {
        refused = hal_adc_configure(&want, &got);
        if (refused != NULL) {
            rp_str(b, "ERR 2 ");
            rp_str(b, refused);
            return;
        }
        if (rel_diff(got.rate_hz, rate) > BRIDGE_RATE_TOLERANCE) {
            rp_str(b, "ERR 2 bad value for rate: expected a rate within 1 % of one the ADC achieves (nearest: ");
            rp_num(b, got.rate_hz);
            rp_str(b, " Hz), got '");
            rp_num(b, rate);
            rp_str(b, "'");
            (void)hal_adc_configure(&b->adc, &got); /* back to the setting in force */
            return;
        }
        b->rate_hz = rate;
        b->adc = got;
        b->frame = (uint16_t)frame;
    }
    rp_str(b, "OK CONF ");
    rp_config(b);
}

static void cmd_start(bridge *b)
{
    if (b->streaming) {
        rp_str(b, "ERR 3 busy: expected STOP before START, got START while streaming");
        return;
    }
    b->frames = 0;
    b->overflows = 0;
    b->fill = 0;
    b->frame_lost = 0;
    rp_str(b, "OK START seq=0 ");
    rp_config(b);
    hal_adc_start();
    b->streaming = 1;
}

static void cmd_stop(bridge *b)
{
    int was_streaming = b->streaming;
    if (was_streaming) {
        while (take_pairs(b, BRIDGE_POLL_PAIRS) == BRIDGE_POLL_PAIRS) {
            /* frames of samples converted before STOP came are produced first */
        }
        hal_adc_stop();
        b->streaming = 0; /* a partly filled frame is not produced */
    }
    rp_str(b, "OK STOP frames=");
    rp_u64(b, b->frames);
    rp_str(b, " samples=");
    rp_u64(b, b->frames * b->frame);
    if (!was_streaming) {
        rp_str(b, " (was idle)");
    }
}

static void cmd_stat(bridge *b)
{
    rp_str(b, b->streaming ? "OK STAT state=streaming frames=" : "OK STAT state=idle frames=");
    rp_u64(b, b->frames);
    rp_str(b, " overflows=");
    rp_u64(b, b->overflows);
    rp_str(b, " ");
    rp_config(b);
}

static void cmd_hw(bridge *b)
{
    const bridge_port_info *p = b->info;
    rp_str(b, "OK HW adc=");
    rp_str(b, p->adc);
    rp_str(b, " bits=");
    rp_u64(b, p->adc_bits);
    rp_str(b, " channels=disp,force clock_hz=");
    rp_num(b, p->clock_hz);
    rp_str(b, " rate_min=");
    rp_num(b, p->rate_min_hz);
    rp_str(b, " rate_max=");
    rp_num(b, p->rate_max_hz);
    rp_str(b, " link=");
    rp_str(b, p->link);
    rp_str(b, " link_bytes_per_s=");
    rp_u64(b, p->link_bytes_per_s);
}

static void dispatch(bridge *b, const word *w, size_t n)
{
    if (n == 0u) {
        rp_str(b, "ERR 1 empty command: expected IDN?, HW?, CONF, START, STOP or STAT?");
        return;
    }
    if (word_is(&w[0], "CONF")) {
        cmd_conf(b, w + 1, n - 1u);
        return;
    }
    if (!word_is(&w[0], "IDN?") && !word_is(&w[0], "HW?") && !word_is(&w[0], "START")
        && !word_is(&w[0], "STOP") && !word_is(&w[0], "STAT?")) {
        rp_str(b, "ERR 1 unknown command ");
        rp_quoted(b, w[0].s, w[0].n);
        rp_str(b, ": expected IDN?, HW?, CONF, START, STOP or STAT?");
        return;
    }
    if (n > 1u) {
        rp_str(b, "ERR 2 bad argument: expected none after ");
        rp_mem(b, w[0].s, w[0].n);
        rp_str(b, ", got ");
        rp_quoted(b, w[1].s, w[1].n);
        return;
    }
    if (word_is(&w[0], "IDN?")) {
        rp_str(b, "OK " BRIDGE_VENDOR ",");
        rp_str(b, b->info->model);
        rp_str(b, ",");
        rp_str(b, b->info->serial);
        rp_str(b, "," BRIDGE_FIRMWARE_VERSION);
    } else if (word_is(&w[0], "HW?")) {
        cmd_hw(b);
    } else if (word_is(&w[0], "START")) {
        cmd_start(b);
    } else if (word_is(&w[0], "STOP")) {
        cmd_stop(b);
    } else {
        cmd_stat(b);
    }
}

void bridge_command(bridge *b, const char *text, size_t len)
{
    word words[MAX_WORDS];
    size_t nwords = 0;
    size_t i = 0;
    for (i = 0; i < len; i++) {
        if (text[i] < 0x20 || text[i] > 0x7E) {
            rp_begin(b, NULL, 0);
            rp_str(b, "ERR 4 malformed command packet: expected printable ASCII text, got byte ");
            rp_hex(b, (uint8_t)text[i], 2u);
            rp_str(b, " at offset ");
            rp_u64(b, i);
            rp_send(b);
            return;
        }
    }
    i = 0;
    if (len > 0u && text[0] == '#') {
        const char *space = memchr(text, ' ', len);
        size_t tag_len = space == NULL ? len : (size_t)(space - text);
        if (tag_len < 2u || tag_len > MAX_TAG) {
            rp_begin(b, NULL, 0);
            rp_str(b, "ERR 2 bad tag: expected '#' and 1..15 printable ASCII characters without spaces, got ");
            rp_quoted(b, text, tag_len);
            rp_send(b);
            return;
        }
        rp_begin(b, text, tag_len);
        i = tag_len;
    } else {
        rp_begin(b, NULL, 0);
    }
    while (i < len) {
        size_t start;
        while (i < len && text[i] == ' ') {
            i++;
        }
        if (i == len) {
            break;
        }
        start = i;
        while (i < len && text[i] != ' ') {
            i++;
        }
        if (nwords == MAX_WORDS) {
            rp_str(b, "ERR 2 too many words: expected at most 16, got more");
            rp_send(b);
            return;
        }
        words[nwords].s = text + start;
        words[nwords].n = i - start;
        nwords++;
    }
    dispatch(b, words, nwords);
    rp_send(b);
}

/* ------------------------------------------------------------------ link */
static void malformed(bridge *b, const char *what)
{
    rp_begin(b, NULL, 0);
    rp_str(b, "ERR 4 malformed command packet: ");
    rp_str(b, what);
}

/* A chunk between two END bytes arrived (or timed out): check it, then answer it. */
static void handle_packet(bridge *b)
{
    const slip_rx *rx = &b->rx;
    if (rx->error == SLIP_BAD_ESCAPE) {
        malformed(b, "expected 0xDC or 0xDD after ESC (0xDB), got another byte");
    } else if (rx->error == SLIP_TOO_LONG) {
        malformed(b, "expected at most ");
        rp_u64(b, rx->size);
        rp_str(b, " bytes (type, command text, CRC), got more");
    } else if (rx->len < 1u + BRIDGE_CRC_SIZE) {
        malformed(b, "expected at least 5 bytes (type, CRC), got ");
        rp_u64(b, rx->len);
    } else {
        size_t n = rx->len - BRIDGE_CRC_SIZE;
        uint32_t want = crc32(rx->buf, n);
        uint32_t got = (uint32_t)rx->buf[n] | ((uint32_t)rx->buf[n + 1u] << 8)
                       | ((uint32_t)rx->buf[n + 2u] << 16) | ((uint32_t)rx->buf[n + 3u] << 24);
        if (want != got) {
            malformed(b, "expected CRC ");
            rp_hex(b, want, 8u);
            rp_str(b, ", got ");
            rp_hex(b, got, 8u);
        } else if (rx->buf[0] != BRIDGE_PKT_COMMAND) {
            malformed(b, "expected type 0x10 (command), got ");
            rp_hex(b, rx->buf[0], 2u);
        } else {
            bridge_command(b, (const char *)rx->buf + 1, n - 1u);
            slip_rx_reset(&b->rx);
            return;
        }
    }
    rp_send(b);
    slip_rx_reset(&b->rx);
}

static void read_commands(bridge *b)
{
    while (bridge_ring_free(&b->tx) >= BRIDGE_REPLY_RESERVE) {
        if (b->in_pos == b->in_len) {
            b->in_pos = 0;
            b->in_len = hal_read(b->in_buf, sizeof b->in_buf);
            if (b->in_len == 0u) {
                break;
            }
            b->rx_last_us = hal_ticks_us();
        }
        if (slip_rx_byte(&b->rx, b->in_buf[b->in_pos++]) == SLIP_RX_PACKET) {
            handle_packet(b);
        }
    }
    if (b->rx.raw > 0u && b->in_pos == b->in_len && bridge_ring_free(&b->tx) >= BRIDGE_REPLY_RESERVE
        && (uint32_t)(hal_ticks_us() - b->rx_last_us) > BRIDGE_RX_TIMEOUT_US) {
        if (slip_rx_flush(&b->rx) == SLIP_RX_PACKET) {
            handle_packet(b);
        }
    }
}

static void send_queued(bridge *b)
{
    for (;;) {
        size_t n, sent;
        const uint8_t *p = bridge_ring_peek(&b->tx, &n);
        if (n == 0u) {
            return;
        }
        sent = hal_write(p, n);
        bridge_ring_consume(&b->tx, sent);
        if (sent < n) {
            return;
        }
    }
}

/* ------------------------------------------------------------------ API */
const char *bridge_init(bridge *b, const bridge_port_info *info, uint8_t *fifo, size_t fifo_size)
{
    bridge_adc_setting want;
    const char *refused;
    memset(b, 0, sizeof *b);
    b->info = info;
    bridge_ring_init(&b->tx, fifo, fifo_size);
    slip_rx_init(&b->rx, b->rx_buf, sizeof b->rx_buf);
    b->frame = 256;
    b->rate_hz = 20000.0;
    want.rate_hz = 20000.0;
    want.range_disp_v = 10.0;
    want.range_force_v = 10.0;
    b->adc = want;
    refused = hal_adc_configure(&want, &b->adc);
    if (refused != NULL) {
        b->adc = want;
    }
    return refused;
}

void bridge_poll(bridge *b)
{
    (void)take_pairs(b, BRIDGE_POLL_PAIRS);
    read_commands(b);
    send_queued(b);
}

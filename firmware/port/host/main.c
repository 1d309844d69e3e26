/* Host (POSIX) port of the bridge firmware: the protocol core on a pty, on stdin/stdout or on a
 * serial device, with a timer-driven synthetic ADC.  For CI and for trying the station against the
 * firmware without hardware:
 *
 *     ./build/bridge-host --pty            # prints "PTY /dev/pts/N"; the station opens that path
 *     socat EXEC:'./build/bridge-host --stdio' PTY,link=/tmp/daq,raw
 *
 * The ADC is emulated (port/common/timed_adc.h) as a converter clocked at --adc-clock-hz with an
 * integer divider, pairs due in real time (CLOCK_MONOTONIC) waiting in a ring of --adc-ring pairs.
 * Fault injection: --adc-skip FIRST:COUNT (samples lost before the core sees them) and
 * --tx-block-at FRAME --tx-block-ms MS (the link stops taking bytes: the FIFO overflows).
 * Dropped frames are logged on stderr as "drop first=F count=N reason=fifo|adc".
 */
#define _XOPEN_SOURCE 600 /* posix_openpt, grantpt, unlockpt, ptsname */

#include <errno.h>
#include <fcntl.h>
#include <math.h>
#include <poll.h>
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <termios.h>
#include <time.h>
#include <unistd.h>

#include "bridge.h"
#include "timed_adc.h"

static struct {
    int fd_in, fd_out;
    int eof;          /* input closed */
    int write_failed; /* output gone */
    timed_adc adc;
    /* link */
    long tx_block_at; /* frame index, -1 = never */
    double tx_block_s;
    double tx_blocked_until;
    int tx_block_done;
} host;

static bridge b;
static volatile sig_atomic_t stop_requested;

static uint64_t now_ns(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (uint64_t)ts.tv_sec * 1000000000u + (uint64_t)ts.tv_nsec;
}

static double now_s(void)
{
    return (double)now_ns() * 1e-9;
}

/* ------------------------------------------------------------------ HAL */
const char *hal_adc_configure(const bridge_adc_setting *want, bridge_adc_setting *got)
{
    return timed_adc_configure(&host.adc, want, got);
}

void hal_adc_start(void)
{
    timed_adc_start(&host.adc, now_ns());
}

void hal_adc_stop(void)
{
    timed_adc_stop(&host.adc);
}

int hal_adc_read(bridge_adc_pair *pair)
{
    return timed_adc_read(&host.adc, now_ns, pair);
}

size_t hal_write(const uint8_t *data, size_t n)
{
    ssize_t w;
    if (host.tx_block_at >= 0 && !host.tx_block_done && b.streaming && b.frames >= (uint64_t)host.tx_block_at) {
        host.tx_block_done = 1;
        host.tx_blocked_until = now_s() + host.tx_block_s;
        fprintf(stderr, "tx blocked at frame=%llu for %.3f s\n", (unsigned long long)b.frames, host.tx_block_s);
    }
    if (host.tx_blocked_until > 0.0) {
        if (now_s() < host.tx_blocked_until) {
            return 0;
        }
        host.tx_blocked_until = 0.0;
    }
    w = write(host.fd_out, data, n);
    if (w < 0) {
        if (errno != EAGAIN && errno != EWOULDBLOCK && errno != EINTR) {
            fprintf(stderr, "write failed: %s\n", strerror(errno));
            host.write_failed = 1;
        }
        return 0;
    }
    return (size_t)w;
}

size_t hal_read(uint8_t *data, size_t max)
{
    ssize_t r = read(host.fd_in, data, max);
    if (r > 0) {
        return (size_t)r;
    }
    if (r == 0 || (errno != EAGAIN && errno != EWOULDBLOCK && errno != EINTR)) {
        host.eof = 1; /* stdin closed (or the device went away) */
    }
    return 0;
}

uint32_t hal_ticks_us(void)
{
    return (uint32_t)(now_ns() / 1000u);
}

/* ------------------------------------------------------------------ set-up */
static void on_drop(void *ctx, uint64_t first, uint64_t count, bridge_drop_reason why)
{
    (void)ctx;
    fprintf(stderr, "drop first=%llu count=%llu reason=%s\n", (unsigned long long)first,
            (unsigned long long)count, why == BRIDGE_DROP_FIFO ? "fifo" : "adc");
}

static void make_raw(int fd)
{
    struct termios t;
    if (tcgetattr(fd, &t) != 0) {
        return; /* not a terminal (a pipe): nothing to do */
    }
    t.c_iflag &= ~(tcflag_t)(IGNBRK | BRKINT | PARMRK | ISTRIP | INLCR | IGNCR | ICRNL | IXON | IXOFF);
    t.c_oflag &= ~(tcflag_t)OPOST;
    t.c_lflag &= ~(tcflag_t)(ECHO | ECHONL | ICANON | ISIG | IEXTEN);
    t.c_cflag &= ~(tcflag_t)(CSIZE | PARENB);
    t.c_cflag |= CS8;
    t.c_cc[VMIN] = 1;
    t.c_cc[VTIME] = 0;
    (void)tcsetattr(fd, TCSANOW, &t);
}

static void set_nonblocking(int fd)
{
    int flags = fcntl(fd, F_GETFL);
    if (flags >= 0) {
        (void)fcntl(fd, F_SETFL, flags | O_NONBLOCK);
    }
}

static int open_pty(void)
{
    int master = posix_openpt(O_RDWR | O_NOCTTY);
    const char *name;
    int slave;
    if (master < 0 || grantpt(master) != 0 || unlockpt(master) != 0 || (name = ptsname(master)) == NULL) {
        fprintf(stderr, "cannot open a pty: %s\n", strerror(errno));
        exit(1);
    }
    /* keep the slave open: the master never sees EIO while no station has the port open */
    slave = open(name, O_RDWR | O_NOCTTY);
    if (slave < 0) {
        fprintf(stderr, "cannot open %s: %s\n", name, strerror(errno));
        exit(1);
    }
    make_raw(slave);
    make_raw(master);
    printf("PTY %s\n", name);
    fflush(stdout);
    return master;
}

static void usage(void)
{
    fputs("usage: bridge-host (--pty | --stdio | --tty PATH) [--source sine|counter] [--seed N]\n"
          "       [--fifo-bytes N] [--adc-clock-hz HZ] [--adc-ring PAIRS] [--adc-skip FIRST:COUNT]...\n"
          "       [--tx-block-at FRAME --tx-block-ms MS] [--link uart|usb-cdc] [--link-bytes-per-s N]\n"
          "       [--serial SN]\n",
          stderr);
    exit(2);
}

static double number_arg(const char *opt, const char *s, double lo, double hi)
{
    char *end;
    double v = strtod(s, &end);
    if (*s == '\0' || *end != '\0' || !(v >= lo && v <= hi)) {
        fprintf(stderr, "%s: expected a number in %g..%g, got '%s'\n", opt, lo, hi, s);
        exit(2);
    }
    return v;
}

static void on_signal(int sig)
{
    (void)sig;
    stop_requested = 1;
}

int main(int argc, char **argv)
{
    static bridge_port_info info = {"DAQ-BRIDGE-HOST", "HOST0001", "SYNTHETIC", 24u, 16e6,
                                    100.0, 1e6, "usb-cdc", 4000000u};
    size_t fifo_bytes = (size_t)1 << 20;
    uint8_t *fifo;
    const char *refused;
    const char *mode = NULL, *tty = NULL;
    int counter = 0;
    uint32_t seed = 1;
    double clock_hz = 16e6;
    uint64_t adc_ring = 65536;
    unsigned long long skips[TIMED_ADC_MAX_SKIPS][2];
    int nskips = 0;
    pid_t parent = getppid();
    double last_parent_check = 0.0;
    int i;

    host.tx_block_at = -1;
    for (i = 1; i < argc; i++) {
        const char *a = argv[i];
        const char *v = i + 1 < argc ? argv[i + 1] : NULL;
        if (strcmp(a, "--pty") == 0 || strcmp(a, "--stdio") == 0) {
            mode = a;
            continue;
        }
        if (v == NULL) {
            usage();
        }
        i++;
        if (strcmp(a, "--tty") == 0) {
            mode = a;
            tty = v;
        } else if (strcmp(a, "--source") == 0) {
            if (strcmp(v, "counter") != 0 && strcmp(v, "sine") != 0) {
                usage();
            }
            counter = strcmp(v, "counter") == 0;
        } else if (strcmp(a, "--seed") == 0) {
            seed = (uint32_t)number_arg(a, v, 0, 4294967295.0);
        } else if (strcmp(a, "--fifo-bytes") == 0) {
            fifo_bytes = (size_t)number_arg(a, v, 4096, 1 << 28);
        } else if (strcmp(a, "--adc-clock-hz") == 0) {
            clock_hz = number_arg(a, v, 1e4, 1e9);
        } else if (strcmp(a, "--adc-ring") == 0) {
            adc_ring = (uint64_t)number_arg(a, v, 1, 1e9);
        } else if (strcmp(a, "--adc-skip") == 0) {
            unsigned long long first, count;
            char tail;
            if (sscanf(v, "%llu:%llu%c", &first, &count, &tail) != 2 || count == 0 || nskips == TIMED_ADC_MAX_SKIPS) {
                usage();
            }
            skips[nskips][0] = first;
            skips[nskips++][1] = count;
        } else if (strcmp(a, "--tx-block-at") == 0) {
            host.tx_block_at = (long)number_arg(a, v, 0, 1e9);
        } else if (strcmp(a, "--tx-block-ms") == 0) {
            host.tx_block_s = number_arg(a, v, 0, 1e6) * 1e-3;
        } else if (strcmp(a, "--link") == 0) {
            if (strcmp(v, "uart") != 0 && strcmp(v, "usb-cdc") != 0) {
                usage();
            }
            info.link = v;
        } else if (strcmp(a, "--link-bytes-per-s") == 0) {
            info.link_bytes_per_s = (uint32_t)number_arg(a, v, 1, 4e9);
        } else if (strcmp(a, "--serial") == 0) {
            info.serial = v;
        } else {
            usage();
        }
    }
    if (mode == NULL) {
        usage();
    }
    timed_adc_init(&host.adc, 1e9, clock_hz, adc_ring);
    synth_init(&host.adc.source, counter, seed);
    for (i = 0; i < nskips; i++) {
        (void)timed_adc_skip(&host.adc, skips[i][0], skips[i][1]);
    }
    info.clock_hz = clock_hz;
    info.rate_min_hz = clock_hz / floor(clock_hz / 100.0);
    info.rate_max_hz = clock_hz / ceil(clock_hz / 1e6);

    if (strcmp(mode, "--pty") == 0) {
        host.fd_in = host.fd_out = open_pty();
    } else if (strcmp(mode, "--tty") == 0) {
        host.fd_in = host.fd_out = open(tty, O_RDWR | O_NOCTTY);
        if (host.fd_in < 0) {
            fprintf(stderr, "cannot open %s: %s\n", tty, strerror(errno));
            return 1;
        }
        make_raw(host.fd_in);
    } else {
        host.fd_in = STDIN_FILENO;
        host.fd_out = STDOUT_FILENO;
        make_raw(STDIN_FILENO);
    }
    set_nonblocking(host.fd_in);
    set_nonblocking(host.fd_out);
    signal(SIGINT, on_signal);
    signal(SIGTERM, on_signal);
    signal(SIGPIPE, SIG_IGN);

    fifo = malloc(fifo_bytes);
    if (fifo == NULL) {
        fprintf(stderr, "cannot allocate a FIFO of %zu bytes\n", fifo_bytes);
        return 1;
    }
    refused = bridge_init(&b, &info, fifo, fifo_bytes);
    if (refused != NULL) {
        fprintf(stderr, "ADC refused the default setting: %s\n", refused);
        return 1;
    }
    b.on_drop = on_drop;

    while (!stop_requested && !host.eof && !host.write_failed) {
        struct pollfd p[2];
        nfds_t n = 1;
        double t;
        bridge_poll(&b);
        p[0].fd = host.fd_in;
        p[0].events = POLLIN;
        if (b.tx.used > 0u && host.tx_blocked_until == 0.0) {
            p[1].fd = host.fd_out;
            p[1].events = POLLOUT;
            n = 2;
        }
        (void)poll(p, n, b.streaming ? 1 : 10);
        t = now_s();
        if (t - last_parent_check > 0.1) { /* never outlive the program that started us */
            last_parent_check = t;
            if (getppid() != parent) {
                break;
            }
        }
    }
    if (host.eof && !stop_requested) { /* input closed: hand over what is queued (1 s at most) */
        double until = now_s() + 1.0;
        while (b.tx.used > 0u && !host.write_failed && now_s() < until) {
            bridge_poll(&b);
            (void)poll(NULL, 0, 1);
        }
    }
    free(fifo);
    return 0;
}

/* The bridge firmware on an emulated Cortex-M3 (QEMU's mps2-an385): the same core as on the RP2040,
 * with the host port's synthetic ADC (port/common) timed by the board's CMSDK timer, and the link on
 * the CMSDK UART0 (QEMU: -serial pty).  Run:
 *
 *     qemu-system-arm -M mps2-an385 -display none -monitor none -serial pty -kernel build/mps2/bridge-mps2.elf
 *
 * QEMU prints "char device redirected to /dev/pts/N"; the station's driver opens that path
 * (kind="uart": the emulated UART ignores its baud divider, QEMU moves bytes as fast as it runs).
 * Samples: the counter source (synth.h), so every sample is checkable.  The main loop sleeps (WFI)
 * between polls, woken by SysTick at 2 kHz and by each received byte.
 */
#include <stddef.h>
#include <stdint.h>

#include "bridge.h"
#include "timed_adc.h"

#define UART0_BASE 0x40004000u
#define TIMER0_BASE 0x40000000u
#define REG(addr) (*(volatile uint32_t *)(addr))
#define UART_DATA REG(UART0_BASE + 0x00u)
#define UART_STATE REG(UART0_BASE + 0x04u) /* bit 0: TX buffer full, bit 1: RX buffer full */
#define UART_CTRL REG(UART0_BASE + 0x08u)  /* bit 0: TX enable, bit 1: RX enable */
#define UART_INTSTATUS REG(UART0_BASE + 0x0Cu) /* write 1 to clear; bit 1: RX */
#define UART_BAUDDIV REG(UART0_BASE + 0x10u)
#define SYST_CSR REG(0xE000E010u)
#define SYST_RVR REG(0xE000E014u)
#define NVIC_ISER0 REG(0xE000E100u)
#define TIMER_CTRL REG(TIMER0_BASE + 0x00u)
#define TIMER_VALUE REG(TIMER0_BASE + 0x04u) /* counts down at PCLK */
#define TIMER_RELOAD REG(TIMER0_BASE + 0x08u)
#define PCLK_HZ 25000000.0

static timed_adc adc;
static uint64_t ticks;
static uint32_t last_value;

/* The 32-bit down-counter extended to 64 bits (called far more often than it wraps: 171 s). */
static uint64_t now_ticks(void)
{
    uint32_t v = TIMER_VALUE;
    ticks += (uint32_t)(last_value - v);
    last_value = v;
    return ticks;
}

const char *hal_adc_configure(const bridge_adc_setting *want, bridge_adc_setting *got)
{
    return timed_adc_configure(&adc, want, got);
}

void hal_adc_start(void)
{
    timed_adc_start(&adc, now_ticks());
}

void hal_adc_stop(void)
{
    timed_adc_stop(&adc);
}

int hal_adc_read(bridge_adc_pair *pair)
{
    return timed_adc_read(&adc, now_ticks, pair);
}

size_t hal_write(const uint8_t *data, size_t n)
{
    size_t i;
    for (i = 0; i < n && (UART_STATE & 1u) == 0u; i++) {
        UART_DATA = data[i];
    }
    return i;
}

size_t hal_read(uint8_t *data, size_t max)
{
    size_t i;
    for (i = 0; i < max && (UART_STATE & 2u) != 0u; i++) {
        data[i] = (uint8_t)UART_DATA;
    }
    return i;
}

uint32_t hal_ticks_us(void)
{
    return (uint32_t)(now_ticks() / 25u);
}

void uart0_rx_handler(void);
void uart0_rx_handler(void)
{
    UART_INTSTATUS = 2u; /* a byte came: the main loop reads it */
}

static bridge b;
static uint8_t fifo[256u * 1024u];

int main(void)
{
    static const bridge_port_info info = {"DAQ-BRIDGE-MPS2", "QEMU0001", "SYNTHETIC", 24u, PCLK_HZ,
                                          100.0, 1e6, "uart", 300000u /* 3 Mbaud / 10 */};
    TIMER_RELOAD = 0xFFFFFFFFu;
    TIMER_VALUE = 0xFFFFFFFFu;
    TIMER_CTRL = 1u;
    last_value = TIMER_VALUE;
    UART_BAUDDIV = 16u; /* the smallest divider QEMU's UART model accepts */
    UART_CTRL = 3u | 8u; /* TX, RX, RX interrupt */
    NVIC_ISER0 = 1u;     /* UART0 RX */
    SYST_RVR = 12499u;   /* 2 kHz at 25 MHz: the main loop sleeps (WFI) between polls */
    SYST_CSR = 7u;       /* enable, interrupt, processor clock */
    timed_adc_init(&adc, PCLK_HZ, PCLK_HZ, 4096u);
    synth_init(&adc.source, 1, 1u);
    if (bridge_init(&b, &info, fifo, sizeof fifo) != NULL) {
        return 1;
    }
    for (;;) {
        (void)now_ticks();
        bridge_poll(&b);
        __asm__ volatile("wfi"); /* until the next tick or byte: QEMU idles instead of spinning */
    }
}

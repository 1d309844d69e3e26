/* Start-up of the mps2-an385 port: the vector table and the reset handler (zero .bss, run main).
 * SysTick and the UART0 receive interrupt (IRQ 0) only wake the core from WFI (hal_mps2.c). */
#include <stdint.h>

extern void __stack_top(void); /* a linker symbol: the initial stack pointer (declared as a function to sit in the table) */
extern uint32_t __bss_start[], __bss_end[];
int main(void);
void reset_handler(void);
void fault_handler(void);
void wake_handler(void);
void uart0_rx_handler(void);

__attribute__((section(".vectors"), used)) static void (*const vectors[17])(void) = {
    __stack_top, reset_handler, fault_handler, fault_handler, fault_handler, fault_handler, fault_handler,
    0, 0, 0, 0, fault_handler, fault_handler, 0, fault_handler, wake_handler, /* 15: SysTick */
    uart0_rx_handler,                                                          /* 16: IRQ 0 */
};

void reset_handler(void)
{
    uint32_t *p;
    for (p = __bss_start; p < __bss_end; p++) {
        *p = 0u;
    }
    (void)main();
    for (;;) {
    }
}

void fault_handler(void)
{
    for (;;) {
    }
}

void wake_handler(void)
{
}

/*
 * Size-measurement image for a Cortex-M0+ (`make -C firmware cortex-m0plus`).  NOT a runnable
 * firmware: it has a vector table, a reset handler that sets up .data/.bss, and a HAL on a
 * PL011 UART's registers (the RP2040's UART0 at 0x40034000) with a SysTick millisecond
 * counter, but no clock, reset or pin set-up, and the LEDs go to a RAM buffer instead of a
 * WS2812 driver.  It exists so that the linker sees a whole program around the core and
 * arm-none-eabi-size reports what the protocol costs in flash and RAM.  The runnable board
 * target is the Arduino sketch in boards/pico/.
 */
#include <stdint.h>
#include <string.h>

#include "ring_device.h"

#define UART0_DR (*(volatile uint32_t *)0x40034000u)
#define UART0_FR (*(volatile uint32_t *)0x40034018u)
#define UART_FR_RXFE (1u << 4)
#define UART_FR_TXFF (1u << 5)

static volatile uint32_t ticks_ms;
static ring_device_t device;
volatile uint8_t led_frame[3 * RING_MAX_LEDS]; /* what a WS2812 driver would clock out */

uint16_t ring_hal_uart_read(uint8_t *buf, uint16_t max)
{
    uint16_t n = 0;
    while (n < max && !(UART0_FR & UART_FR_RXFE)) {
        buf[n++] = (uint8_t)UART0_DR;
    }
    return n;
}

void ring_hal_uart_write(const uint8_t *buf, uint16_t len)
{
    uint16_t i;
    for (i = 0; i < len; ++i) {
        while (UART0_FR & UART_FR_TXFF) {
        }
        UART0_DR = buf[i];
    }
}

void ring_hal_leds_show(const uint8_t *rgb, uint8_t count, uint8_t brightness)
{
    uint16_t i;
    for (i = 0; i < 3u * count; ++i) {
        led_frame[i] = ring_scale8(rgb[i], brightness);
    }
}

uint32_t ring_hal_millis(void)
{
    return ticks_ms;
}

void SysTick_Handler(void)
{
    ++ticks_ms;
}

int main(void)
{
    static const ring_config_t cfg = {24, RING_PROTOCOL_VERSION, RING_DEFAULT_FRAME_GAP_MS,
                                      "iristac-ring-m0plus/1"};
    ring_init(&device, &cfg);
    for (;;) {
        ring_poll(&device);
    }
}

/* ---- start-up: what a board support package normally provides ---------------------------- */
extern uint32_t _sidata, _sdata, _edata, _sbss, _ebss, _estack;

void Reset_Handler(void)
{
    memcpy(&_sdata, &_sidata, (size_t)((uint8_t *)&_edata - (uint8_t *)&_sdata));
    memset(&_sbss, 0, (size_t)((uint8_t *)&_ebss - (uint8_t *)&_sbss));
    main();
}

void Default_Handler(void)
{
    for (;;) {
    }
}

typedef void (*vector_t)(void);

__attribute__((section(".vectors"), used)) static const vector_t vectors[16] = {
    (vector_t)(uintptr_t)&_estack, Reset_Handler, Default_Handler, Default_Handler,
    0, 0, 0, 0, 0, 0, 0, Default_Handler, 0, 0, Default_Handler, SysTick_Handler,
};

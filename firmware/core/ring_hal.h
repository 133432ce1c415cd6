/*
 * The hardware interface of the IrisTac ring firmware: the four functions a board provides.
 * The protocol core (ring_device.c) calls nothing else outside <string.h>.
 */
#ifndef IRISTAC_RING_HAL_H
#define IRISTAC_RING_HAL_H

#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

/* Copy up to max received bytes into buf without waiting; return how many (0: none now). */
uint16_t ring_hal_uart_read(uint8_t *buf, uint16_t max);

/* Send len bytes.  The core always passes exactly one whole frame per call, so a board may
 * hand it to its driver as one unit (one USB packet, one DMA transfer). */
void ring_hal_uart_write(const uint8_t *buf, uint16_t len);

/* Show this state on the LEDs at once (all of them in one update: no tearing).
 * rgb is rgb[count][3] flattened (LED 0 first, R G B), the layout of a SET_ALL payload;
 * channel c of LED i emits in proportion to rgb[3i+c] * brightness / 255^2 (linear light:
 * the board does any gamma or PWM mapping its LEDs need; ring_scale8 helps 8-bit ones). */
void ring_hal_leds_show(const uint8_t *rgb, uint8_t count, uint8_t brightness);

/* Milliseconds since some fixed moment, wrapping at 2^32 (Arduino's millis()). */
uint32_t ring_hal_millis(void);

#ifdef __cplusplus
}
#endif

#endif /* IRISTAC_RING_HAL_H */

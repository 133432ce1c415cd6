// IrisTac LED-ring firmware for the Raspberry Pi Pico (RP2040) and 24 WS2812B / SK6812 LEDs.
//
// The protocol is the portable C core in firmware/core (copied next to this sketch into src/
// by `make -C firmware sketch`); this file is only the board: the serial port, the LED strip
// and the clock.  Wiring, pin-out and how to build and flash: firmware/README.md.
//
// Arduino core: "Raspberry Pi Pico/RP2040" by Earle F. Philhower (board "Raspberry Pi Pico").
// Library: Adafruit NeoPixel (>= 1.10: drives the LEDs with the RP2040's PIO, so interrupts and
// USB stay alive while the 24 LEDs are clocked out, about 0.75 ms).
//
// NOT YET RUN ON HARDWARE: see "What was and was not tested" in firmware/README.md.

#include <Adafruit_NeoPixel.h>

#include "src/ring_device.h"

// ---- configuration ------------------------------------------------------------------------
#ifndef RING_LED_PIN
#define RING_LED_PIN 2  // GP2 = physical pin 4: data to the level shifter, then DIN of LED 0
#endif
#define RING_LED_COUNT 24
// WS2812B and SK6812 (RGB) take GRB order at 800 kHz; an SK6812 RGBW ring needs NEO_GRBW.
#define RING_PIXEL_TYPE (NEO_GRB + NEO_KHZ800)
// 1: talk over UART0 (GP0 = TX, GP1 = RX) through a USB-serial adapter; 0: the Pico's own USB
// port (USB CDC, the baud rate is nominal).
#ifndef RING_USE_UART
#define RING_USE_UART 0
#endif
#define RING_BAUD 115200
#define RING_FIRMWARE_ID "iristac-ring-pico/1"

#if RING_USE_UART
#define RING_SERIAL Serial1
#else
#define RING_SERIAL Serial
#endif

static Adafruit_NeoPixel strip(RING_LED_COUNT, RING_LED_PIN, RING_PIXEL_TYPE);
static ring_device_t device;

// ---- the board: the four functions of ring_hal.h ------------------------------------------
extern "C" uint16_t ring_hal_uart_read(uint8_t *buf, uint16_t max)
{
    uint16_t n = 0;
    while (n < max && RING_SERIAL.available() > 0) {
        buf[n++] = (uint8_t)RING_SERIAL.read();
    }
    return n;
}

extern "C" void ring_hal_uart_write(const uint8_t *buf, uint16_t len)
{
    // One whole reply frame per call: push it out now, the host is waiting for it.
    RING_SERIAL.write(buf, len);
    RING_SERIAL.flush();
}

extern "C" void ring_hal_leds_show(const uint8_t *rgb, uint8_t count, uint8_t brightness)
{
    // WS2812B/SK6812 PWM is linear in the 8-bit level, so level x brightness / 255 is linear
    // light, as the protocol asks (no gamma table).
    for (uint8_t i = 0; i < count; ++i) {
        strip.setPixelColor(i, ring_scale8(rgb[3 * i], brightness),
                            ring_scale8(rgb[3 * i + 1], brightness),
                            ring_scale8(rgb[3 * i + 2], brightness));
    }
    // The LEDs take the new colours together at the reset pulse after the last bit: all 24
    // change in one update, so a camera frame never sees half a pattern.
    strip.show();
}

extern "C" uint32_t ring_hal_millis(void)
{
    return millis();
}

// ---- Arduino entry points -----------------------------------------------------------------
void setup()
{
    strip.begin();  // before ring_init, which latches all-off at power-on
    RING_SERIAL.begin(RING_BAUD);
    static const ring_config_t cfg = {RING_LED_COUNT, RING_PROTOCOL_VERSION,
                                      RING_DEFAULT_FRAME_GAP_MS, RING_FIRMWARE_ID};
    ring_init(&device, &cfg);
}

void loop()
{
    ring_poll(&device);
}

/*
 * The IrisTac ring device: executes the commands of docs/ring-protocol.md (HELLO, SET_ALL,
 * SET_ONE, SHOW, OFF, STATUS), answers retransmissions from its reply cache, NAKs damaged
 * frames and drops partial frames after an inter-byte timeout.  The Python twin is
 * RingDevice in pipeline/capture/emulator.py; both pass firmware/vectors/protocol.vec.
 *
 * Use: fill a ring_config_t, call ring_init once, then ring_poll from the main loop as often
 * as possible.  All state lives in the ring_device_t the caller provides (no heap, no
 * globals), so a board keeps one as a static variable.
 */
#ifndef IRISTAC_RING_DEVICE_H
#define IRISTAC_RING_DEVICE_H

#include <stdint.h>

#include "ring_hal.h"
#include "ring_protocol.h"

#ifdef __cplusplus
extern "C" {
#endif

/* LEDs a device can drive (the buffers are sized for it).  A SET_ALL payload of 3L + 1 bytes
 * must fit RING_MAX_PAYLOAD, so at most 66. */
#ifndef RING_MAX_LEDS
#define RING_MAX_LEDS 24
#endif
#if RING_MAX_LEDS < 1 || 3 * RING_MAX_LEDS + 1 > RING_MAX_PAYLOAD
#error "RING_MAX_LEDS must be in 1..66"
#endif

#define RING_FIRMWARE_ID_MAX 32u  /* bytes of the firmware id sent in the HELLO reply */
#define RING_STATUS_SIZE 10u      /* latch_count u32, shown_crc u16, rx errors u16, duplicates u16 */
#define RING_DEFAULT_FRAME_GAP_MS 2u
/* The longest reply: ACK payload = echoed command + version + LED count + firmware id. */
#define RING_MAX_REPLY (RING_OVERHEAD + 3u + RING_FIRMWARE_ID_MAX)

typedef struct {
    uint8_t led_count;    /* LEDs on the ring, 1..RING_MAX_LEDS (24 for IrisTac) */
    uint8_t version;      /* protocol version HELLO reports (RING_PROTOCOL_VERSION) */
    uint8_t frame_gap_ms; /* inter-byte timeout: 2 ms, or 20 character times if longer */
    const char *firmware_id; /* ASCII, NUL-terminated; the first 32 bytes are sent */
} ring_config_t;

typedef struct {
    ring_config_t cfg;
    ring_parser_t rx;
    uint32_t last_rx_ms;       /* when bytes last arrived (for the frame gap) */
    uint8_t pending[3u * RING_MAX_LEDS]; /* loaded by SET_ALL / SET_ONE */
    uint8_t pending_brightness;
    uint8_t shown[3u * RING_MAX_LEDS];   /* latched by SHOW / OFF */
    uint8_t shown_brightness;
    uint16_t shown_crc;        /* CRC-16 of the shown state as a SET_ALL payload */
    uint32_t latch_count;      /* SHOW/OFF latches since ring_init */
    uint16_t rx_errors;        /* frames dropped: bad CRC, bad length or frame gap (wraps) */
    uint16_t duplicates;       /* retransmissions answered from the reply cache (wraps) */
    uint32_t commands;         /* valid frames handled (executed or answered from the cache) */
    uint32_t resyncs;          /* partial frames dropped at a frame gap */
    uint32_t parser_errors;    /* rx.crc_errors + rx.length_errors already counted */
    uint8_t nak_due;           /* a frame was dropped since the last NAK BAD_CRC */
    /* Reply cache: the last executed frame (LEN SEQ CMD PAYLOAD) and the reply it got. */
    uint8_t cached;
    uint8_t last_frame[3u + RING_MAX_PAYLOAD];
    uint8_t reply[RING_MAX_REPLY];
    uint8_t reply_len;
} ring_device_t;

/* Reset dev to power-on (nothing loaded, nothing latched, counters 0) and show all LEDs off.
 * Returns 0, or -1 (and does nothing) when cfg is invalid. */
int ring_init(ring_device_t *dev, const ring_config_t *cfg);

/* Read every byte available now, execute and answer each complete frame in order, drop a
 * partial frame when the line was idle for longer than the frame gap, and send one
 * NAK BAD_CRC when any frame was dropped.  Call it from the main loop. */
void ring_poll(ring_device_t *dev);

/* CRC-16 of a state serialised as a SET_ALL payload (levels, then brightness). */
uint16_t ring_state_crc(const uint8_t *rgb, uint8_t count, uint8_t brightness);

/* level * brightness / 255, rounded: the 8-bit output of an LED driver without its own
 * brightness control. */
uint8_t ring_scale8(uint8_t level, uint8_t brightness);

#ifdef __cplusplus
}
#endif

#endif /* IRISTAC_RING_DEVICE_H */

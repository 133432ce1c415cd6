/*
 * IrisTac LED-ring serial protocol, version 1: constants, CRC-16, frame encoder and the
 * resynchronising frame parser.  Specified in docs/ring-protocol.md; the Python twin is
 * pipeline/capture/protocol.py.  Portable C99: <stdint.h> and <string.h> only, no heap.
 */
#ifndef IRISTAC_RING_PROTOCOL_H
#define IRISTAC_RING_PROTOCOL_H

#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

#define RING_PROTOCOL_VERSION 1u
#define RING_START 0xA5u
/* Longer frames are rejected at the header, so a false START in garbage never makes the
 * receiver wait for hundreds of bytes before it can resynchronise. */
#define RING_MAX_PAYLOAD 200u
#define RING_HEADER_SIZE 4u /* START LEN SEQ CMD */
#define RING_OVERHEAD 6u    /* header plus the CRC */
#define RING_MAX_FRAME (RING_MAX_PAYLOAD + RING_OVERHEAD)
#define RING_CRC_INIT 0xFFFFu

/* Command codes (host -> device) and reply codes (device -> host). */
enum ring_command {
    RING_CMD_HELLO = 0x01,
    RING_CMD_SET_ALL = 0x02,
    RING_CMD_SET_ONE = 0x03,
    RING_CMD_SHOW = 0x04,
    RING_CMD_OFF = 0x05,
    RING_CMD_STATUS = 0x06,
    RING_REPLY_ACK = 0x80,
    RING_REPLY_NAK = 0x81
};

/* Second payload byte of a NAK. */
enum ring_nak_code {
    RING_NAK_BAD_CRC = 0x01,
    RING_NAK_UNKNOWN_COMMAND = 0x02,
    RING_NAK_BAD_LENGTH = 0x03,
    RING_NAK_BAD_ARGUMENT = 0x04,
    RING_NAK_BUSY = 0x05
};

/* CRC-16/CCITT-FALSE (poly 0x1021, no reflection, no xor-out) of len bytes, continuing from
 * crc (pass RING_CRC_INIT to start).  ring_crc16("123456789", 9, RING_CRC_INIT) == 0x29B1. */
uint16_t ring_crc16(const uint8_t *data, uint16_t len, uint16_t crc);

/* Write the frame START LEN SEQ CMD PAYLOAD CRC into out (room for len + RING_OVERHEAD
 * bytes; payload may be NULL when len is 0).  Returns the frame size. */
uint16_t ring_encode_frame(uint8_t *out, uint8_t seq, uint8_t cmd, const uint8_t *payload,
                           uint8_t len);

/* One decoded frame.  The pointers point into the parser's buffer and stay valid until the
 * next call on that parser. */
typedef struct {
    uint8_t len;
    uint8_t seq;
    uint8_t cmd;
    const uint8_t *payload; /* len bytes */
    const uint8_t *raw;     /* the whole frame as received, len + RING_OVERHEAD bytes */
} ring_frame_t;

/* Incremental frame decoder that resynchronises after garbage (docs/ring-protocol.md,
 * "Receiving and resynchronisation"): on a false start (an impossible length or a CRC
 * mismatch) it drops only that START byte and rescans the bytes after it. */
typedef struct {
    uint8_t buf[RING_MAX_FRAME];
    uint16_t fill;     /* bytes buffered */
    uint16_t consumed; /* size of the frame handed out last; removed on the next call */
    uint32_t crc_errors;    /* candidate frames whose CRC did not match */
    uint32_t length_errors; /* candidate headers with LEN > RING_MAX_PAYLOAD */
    uint32_t skipped_bytes; /* bytes discarded while searching for a START */
} ring_parser_t;

void ring_parser_reset(ring_parser_t *p);

/* Append one received byte.  Call ring_parser_next until it returns 0 before pushing the
 * next byte: the buffer then always has room (it never holds more than one partial frame).
 * Returns 0 (and drops the byte) only when that rule was broken. */
int ring_parser_push(ring_parser_t *p, uint8_t byte);

/* Scan the buffered bytes: 1 and *frame filled when a complete CRC-valid frame was found
 * (oldest first), 0 when more bytes are needed. */
int ring_parser_next(ring_parser_t *p, ring_frame_t *frame);

/* Bytes buffered that are not part of a frame already handed out (a partial frame). */
uint16_t ring_parser_pending(const ring_parser_t *p);

/* One step of a resynchronisation after a frame gap: discard the first buffered byte (the
 * START of a partial frame that will never complete).  Then drain ring_parser_next, and
 * repeat while ring_parser_pending() is not 0. */
void ring_parser_drop(ring_parser_t *p);

#ifdef __cplusplus
}
#endif

#endif /* IRISTAC_RING_PROTOCOL_H */

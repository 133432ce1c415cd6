/* IrisTac ring device: command execution, reply cache, NAKs and frame-gap timeouts
 * (see ring_device.h and docs/ring-protocol.md). */
#include "ring_device.h"

#include <string.h>

uint16_t ring_state_crc(const uint8_t *rgb, uint8_t count, uint8_t brightness)
{
    uint16_t crc = ring_crc16(rgb, (uint16_t)(3u * count), RING_CRC_INIT);
    return ring_crc16(&brightness, 1, crc);
}

uint8_t ring_scale8(uint8_t level, uint8_t brightness)
{
    return (uint8_t)(((uint16_t)level * brightness + 127u) / 255u);
}

static void latch(ring_device_t *dev)
{
    uint8_t n = dev->cfg.led_count;
    memcpy(dev->shown, dev->pending, 3u * n);
    dev->shown_brightness = dev->pending_brightness;
    dev->shown_crc = ring_state_crc(dev->shown, n, dev->shown_brightness);
    ring_hal_leds_show(dev->shown, n, dev->shown_brightness);
}

int ring_init(ring_device_t *dev, const ring_config_t *cfg)
{
    if (cfg->led_count < 1 || cfg->led_count > RING_MAX_LEDS || cfg->firmware_id == 0) {
        return -1;
    }
    memset(dev, 0, sizeof *dev);
    dev->cfg = *cfg;
    if (dev->cfg.frame_gap_ms == 0) {
        dev->cfg.frame_gap_ms = RING_DEFAULT_FRAME_GAP_MS;
    }
    dev->last_rx_ms = ring_hal_millis();
    latch(dev); /* power-on: all off (not counted as a latch) */
    return 0;
}

static uint8_t put_u16(uint8_t *out, uint16_t v)
{
    out[0] = (uint8_t)(v & 0xFFu);
    out[1] = (uint8_t)(v >> 8);
    return 2;
}

static uint8_t put_status(const ring_device_t *dev, uint8_t *out)
{
    uint32_t n = dev->latch_count;
    out[0] = (uint8_t)(n & 0xFFu);
    out[1] = (uint8_t)((n >> 8) & 0xFFu);
    out[2] = (uint8_t)((n >> 16) & 0xFFu);
    out[3] = (uint8_t)(n >> 24);
    put_u16(out + 4, dev->shown_crc);
    put_u16(out + 6, dev->rx_errors);
    put_u16(out + 8, dev->duplicates);
    return RING_STATUS_SIZE;
}

/* Execute one command; its reply frame goes to dev->reply.  data[0] is the echoed command,
 * then the ACK data or the NAK code. */
static void execute(ring_device_t *dev, const ring_frame_t *f)
{
    uint8_t data[3u + RING_FIRMWARE_ID_MAX];
    uint8_t n = 1, code = RING_REPLY_ACK, leds = dev->cfg.led_count;
    data[0] = f->cmd;
    switch (f->cmd) {
    case RING_CMD_HELLO: {
        /* Answered whatever the payload says: any host must learn this device's version. */
        const char *id = dev->cfg.firmware_id;
        data[n++] = dev->cfg.version;
        data[n++] = leds;
        while (*id && n < sizeof data) {
            data[n++] = (uint8_t)*id++;
        }
        break;
    }
    case RING_CMD_SET_ALL:
        if (f->len != 3u * leds + 1u) {
            code = RING_REPLY_NAK;
            data[n++] = RING_NAK_BAD_LENGTH;
        } else {
            memcpy(dev->pending, f->payload, 3u * leds);
            dev->pending_brightness = f->payload[3u * leds];
        }
        break;
    case RING_CMD_SET_ONE:
        if (f->len != 4u) {
            code = RING_REPLY_NAK;
            data[n++] = RING_NAK_BAD_LENGTH;
        } else if (f->payload[0] >= leds) {
            code = RING_REPLY_NAK;
            data[n++] = RING_NAK_BAD_ARGUMENT;
        } else {
            memcpy(dev->pending + 3u * f->payload[0], f->payload + 1, 3u);
        }
        break;
    case RING_CMD_SHOW:
    case RING_CMD_OFF:
    case RING_CMD_STATUS:
        if (f->len != 0u) {
            code = RING_REPLY_NAK;
            data[n++] = RING_NAK_BAD_LENGTH;
            break;
        }
        if (f->cmd == RING_CMD_OFF) {
            memset(dev->pending, 0, sizeof dev->pending);
            dev->pending_brightness = 0;
        }
        if (f->cmd != RING_CMD_STATUS) {
            latch(dev);
            ++dev->latch_count;
        }
        n = (uint8_t)(n + put_status(dev, data + n));
        break;
    default:
        code = RING_REPLY_NAK;
        data[n++] = RING_NAK_UNKNOWN_COMMAND;
        break;
    }
    dev->reply_len = (uint8_t)ring_encode_frame(dev->reply, f->seq, code, data, n);
}

static void handle(ring_device_t *dev, const ring_frame_t *f)
{
    /* The cache key is LEN SEQ CMD PAYLOAD (the CRC follows from them). */
    uint16_t key = (uint16_t)(3u + f->len);
    ++dev->commands;
    if (dev->cached && dev->last_frame[0] == f->len && memcmp(dev->last_frame, f->raw + 1, key) == 0) {
        /* A retransmission of the command just executed: answer from the cache and do not
         * execute it again (a repeated SHOW must not add a latch). */
        ++dev->duplicates;
    } else {
        execute(dev, f);
        memcpy(dev->last_frame, f->raw + 1, key);
        dev->cached = 1;
    }
    ring_hal_uart_write(dev->reply, dev->reply_len);
}

/* Count frames the parser dropped since the last call; each makes a NAK due. */
static void count_drops(ring_device_t *dev)
{
    uint32_t e = dev->rx.crc_errors + dev->rx.length_errors;
    if (e != dev->parser_errors) {
        dev->rx_errors = (uint16_t)(dev->rx_errors + (uint16_t)(e - dev->parser_errors));
        dev->parser_errors = e;
        dev->nak_due = 1;
    }
}

static void drain(ring_device_t *dev)
{
    ring_frame_t f;
    while (ring_parser_next(&dev->rx, &f)) {
        count_drops(dev);
        handle(dev, &f);
    }
    count_drops(dev);
}

void ring_poll(ring_device_t *dev)
{
    uint8_t chunk[32];
    uint16_t n, i;
    uint32_t now;
    int got = 0;
    while ((n = ring_hal_uart_read(chunk, (uint16_t)sizeof chunk)) > 0) {
        got = 1;
        for (i = 0; i < n; ++i) {
            ring_parser_push(&dev->rx, chunk[i]);
            drain(dev);
        }
    }
    now = ring_hal_millis();
    if (got) {
        dev->last_rx_ms = now;
    } else if (ring_parser_pending(&dev->rx) &&
               (uint32_t)(now - dev->last_rx_ms) > dev->cfg.frame_gap_ms) {
        /* A partial frame and an idle line: it will never complete (a corrupted LEN).  Drop
         * it START by START, rescanning what it held: a real frame may be inside. */
        ++dev->resyncs;
        ++dev->rx_errors;
        dev->nak_due = 1;
        while (ring_parser_pending(&dev->rx)) {
            ring_parser_drop(&dev->rx);
            drain(dev);
        }
    }
    if (dev->nak_due) {
        /* The sender's SEQ is unknown when a frame is damaged: SEQ 0, command byte 0. */
        static const uint8_t nak[2] = {0u, RING_NAK_BAD_CRC};
        uint8_t frame[RING_OVERHEAD + 2u];
        dev->nak_due = 0;
        ring_hal_uart_write(frame, ring_encode_frame(frame, 0u, RING_REPLY_NAK, nak, 2u));
    }
}

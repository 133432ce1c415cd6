/* IrisTac ring protocol: CRC-16, frame encoder, resynchronising parser (see ring_protocol.h). */
#include "ring_protocol.h"

#include <string.h>

/* CRC-16/CCITT-FALSE, one table lookup per byte: table[i] is the CRC register after shifting
 * byte i through it.  512 bytes of flash (const) instead of 8 shift steps per byte. */
static const uint16_t crc_table[256] = {
    0x0000u, 0x1021u, 0x2042u, 0x3063u, 0x4084u, 0x50A5u, 0x60C6u, 0x70E7u,
    0x8108u, 0x9129u, 0xA14Au, 0xB16Bu, 0xC18Cu, 0xD1ADu, 0xE1CEu, 0xF1EFu,
    0x1231u, 0x0210u, 0x3273u, 0x2252u, 0x52B5u, 0x4294u, 0x72F7u, 0x62D6u,
    0x9339u, 0x8318u, 0xB37Bu, 0xA35Au, 0xD3BDu, 0xC39Cu, 0xF3FFu, 0xE3DEu,
    0x2462u, 0x3443u, 0x0420u, 0x1401u, 0x64E6u, 0x74C7u, 0x44A4u, 0x5485u,
    0xA56Au, 0xB54Bu, 0x8528u, 0x9509u, 0xE5EEu, 0xF5CFu, 0xC5ACu, 0xD58Du,
    0x3653u, 0x2672u, 0x1611u, 0x0630u, 0x76D7u, 0x66F6u, 0x5695u, 0x46B4u,
    0xB75Bu, 0xA77Au, 0x9719u, 0x8738u, 0xF7DFu, 0xE7FEu, 0xD79Du, 0xC7BCu,
    0x48C4u, 0x58E5u, 0x6886u, 0x78A7u, 0x0840u, 0x1861u, 0x2802u, 0x3823u,
    0xC9CCu, 0xD9EDu, 0xE98Eu, 0xF9AFu, 0x8948u, 0x9969u, 0xA90Au, 0xB92Bu,
    0x5AF5u, 0x4AD4u, 0x7AB7u, 0x6A96u, 0x1A71u, 0x0A50u, 0x3A33u, 0x2A12u,
    0xDBFDu, 0xCBDCu, 0xFBBFu, 0xEB9Eu, 0x9B79u, 0x8B58u, 0xBB3Bu, 0xAB1Au,
    0x6CA6u, 0x7C87u, 0x4CE4u, 0x5CC5u, 0x2C22u, 0x3C03u, 0x0C60u, 0x1C41u,
    0xEDAEu, 0xFD8Fu, 0xCDECu, 0xDDCDu, 0xAD2Au, 0xBD0Bu, 0x8D68u, 0x9D49u,
    0x7E97u, 0x6EB6u, 0x5ED5u, 0x4EF4u, 0x3E13u, 0x2E32u, 0x1E51u, 0x0E70u,
    0xFF9Fu, 0xEFBEu, 0xDFDDu, 0xCFFCu, 0xBF1Bu, 0xAF3Au, 0x9F59u, 0x8F78u,
    0x9188u, 0x81A9u, 0xB1CAu, 0xA1EBu, 0xD10Cu, 0xC12Du, 0xF14Eu, 0xE16Fu,
    0x1080u, 0x00A1u, 0x30C2u, 0x20E3u, 0x5004u, 0x4025u, 0x7046u, 0x6067u,
    0x83B9u, 0x9398u, 0xA3FBu, 0xB3DAu, 0xC33Du, 0xD31Cu, 0xE37Fu, 0xF35Eu,
    0x02B1u, 0x1290u, 0x22F3u, 0x32D2u, 0x4235u, 0x5214u, 0x6277u, 0x7256u,
    0xB5EAu, 0xA5CBu, 0x95A8u, 0x8589u, 0xF56Eu, 0xE54Fu, 0xD52Cu, 0xC50Du,
    0x34E2u, 0x24C3u, 0x14A0u, 0x0481u, 0x7466u, 0x6447u, 0x5424u, 0x4405u,
    0xA7DBu, 0xB7FAu, 0x8799u, 0x97B8u, 0xE75Fu, 0xF77Eu, 0xC71Du, 0xD73Cu,
    0x26D3u, 0x36F2u, 0x0691u, 0x16B0u, 0x6657u, 0x7676u, 0x4615u, 0x5634u,
    0xD94Cu, 0xC96Du, 0xF90Eu, 0xE92Fu, 0x99C8u, 0x89E9u, 0xB98Au, 0xA9ABu,
    0x5844u, 0x4865u, 0x7806u, 0x6827u, 0x18C0u, 0x08E1u, 0x3882u, 0x28A3u,
    0xCB7Du, 0xDB5Cu, 0xEB3Fu, 0xFB1Eu, 0x8BF9u, 0x9BD8u, 0xABBBu, 0xBB9Au,
    0x4A75u, 0x5A54u, 0x6A37u, 0x7A16u, 0x0AF1u, 0x1AD0u, 0x2AB3u, 0x3A92u,
    0xFD2Eu, 0xED0Fu, 0xDD6Cu, 0xCD4Du, 0xBDAAu, 0xAD8Bu, 0x9DE8u, 0x8DC9u,
    0x7C26u, 0x6C07u, 0x5C64u, 0x4C45u, 0x3CA2u, 0x2C83u, 0x1CE0u, 0x0CC1u,
    0xEF1Fu, 0xFF3Eu, 0xCF5Du, 0xDF7Cu, 0xAF9Bu, 0xBFBAu, 0x8FD9u, 0x9FF8u,
    0x6E17u, 0x7E36u, 0x4E55u, 0x5E74u, 0x2E93u, 0x3EB2u, 0x0ED1u, 0x1EF0u
};

uint16_t ring_crc16(const uint8_t *data, uint16_t len, uint16_t crc)
{
    uint16_t i;
    for (i = 0; i < len; ++i) {
        crc = (uint16_t)((uint16_t)(crc << 8) ^ crc_table[(uint8_t)((crc >> 8) ^ data[i])]);
    }
    return crc;
}

uint16_t ring_encode_frame(uint8_t *out, uint8_t seq, uint8_t cmd, const uint8_t *payload,
                           uint8_t len)
{
    uint16_t crc;
    out[0] = RING_START;
    out[1] = len;
    out[2] = seq;
    out[3] = cmd;
    if (len) {
        memmove(out + RING_HEADER_SIZE, payload, len); /* payload may live in out already */
    }
    crc = ring_crc16(out + 1, (uint16_t)(3u + len), RING_CRC_INIT);
    out[RING_HEADER_SIZE + len] = (uint8_t)(crc & 0xFFu);
    out[RING_HEADER_SIZE + len + 1u] = (uint8_t)(crc >> 8);
    return (uint16_t)(len + RING_OVERHEAD);
}

void ring_parser_reset(ring_parser_t *p)
{
    memset(p, 0, sizeof *p);
}

static void discard(ring_parser_t *p, uint16_t n)
{
    if (n >= p->fill) {
        p->fill = 0;
    } else {
        memmove(p->buf, p->buf + n, (size_t)(p->fill - n));
        p->fill = (uint16_t)(p->fill - n);
    }
}

static void release(ring_parser_t *p)
{
    if (p->consumed) {
        discard(p, p->consumed);
        p->consumed = 0;
    }
}

int ring_parser_push(ring_parser_t *p, uint8_t byte)
{
    release(p);
    if (p->fill >= sizeof p->buf) {
        return 0;
    }
    p->buf[p->fill++] = byte;
    return 1;
}

int ring_parser_next(ring_parser_t *p, ring_frame_t *frame)
{
    release(p);
    for (;;) {
        uint16_t start = 0, total, crc;
        uint8_t len;
        while (start < p->fill && p->buf[start] != RING_START) {
            ++start;
        }
        if (start) {
            p->skipped_bytes += start;
            discard(p, start);
        }
        if (p->fill < RING_HEADER_SIZE) {
            return 0;
        }
        len = p->buf[1];
        if (len > RING_MAX_PAYLOAD) {
            ++p->length_errors;
            ++p->skipped_bytes;
            discard(p, 1);
            continue;
        }
        total = (uint16_t)(len + RING_OVERHEAD);
        if (p->fill < total) {
            return 0;
        }
        crc = (uint16_t)(p->buf[RING_HEADER_SIZE + len] |
                         (uint16_t)(p->buf[RING_HEADER_SIZE + len + 1u] << 8));
        if (ring_crc16(p->buf + 1, (uint16_t)(3u + len), RING_CRC_INIT) != crc) {
            /* Drop only the START: a real frame may begin inside this false one. */
            ++p->crc_errors;
            ++p->skipped_bytes;
            discard(p, 1);
            continue;
        }
        frame->len = len;
        frame->seq = p->buf[2];
        frame->cmd = p->buf[3];
        frame->payload = p->buf + RING_HEADER_SIZE;
        frame->raw = p->buf;
        p->consumed = total;
        return 1;
    }
}

uint16_t ring_parser_pending(const ring_parser_t *p)
{
    return (uint16_t)(p->fill - p->consumed);
}

void ring_parser_drop(ring_parser_t *p)
{
    release(p);
    if (p->fill) {
        ++p->skipped_bytes;
        discard(p, 1);
    }
}

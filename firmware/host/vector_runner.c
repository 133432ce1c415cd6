/*
 * Conformance test of the C firmware core: runs every case of a protocol vector file
 * (firmware/vectors/protocol.vec, format in its header) against ring_device.c with a
 * simulated UART, LED strip and clock.  Each case runs twice: with the clock starting at 0 and
 * just before millis() wraps around 2^32, so frame-gap timing survives the wrap.
 *
 *   vector_runner protocol.vec      -> one line per failure, then "N passed, M failed"
 */
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "ring_device.h"

#define LINE_MAX_CHARS 8192
#define BUF_MAX 4096

/* ---- the simulated board ---------------------------------------------------------------- */
static uint8_t rx[BUF_MAX];
static size_t rx_len, rx_pos;
static uint8_t tx[BUF_MAX];
static size_t tx_len;
static int tx_overflow;
static uint8_t shown[3 * RING_MAX_LEDS + 1];
static size_t shown_len;
static uint32_t clock_ms;

uint16_t ring_hal_uart_read(uint8_t *buf, uint16_t max)
{
    size_t n = rx_len - rx_pos;
    if (n > max) {
        n = max;
    }
    memcpy(buf, rx + rx_pos, n);
    rx_pos += n;
    return (uint16_t)n;
}

void ring_hal_uart_write(const uint8_t *buf, uint16_t len)
{
    if (tx_len + len > sizeof tx) {
        tx_overflow = 1;
        return;
    }
    memcpy(tx + tx_len, buf, len);
    tx_len += len;
}

void ring_hal_leds_show(const uint8_t *rgb, uint8_t count, uint8_t brightness)
{
    memcpy(shown, rgb, 3u * count);
    shown[3u * count] = brightness;
    shown_len = 3u * count + 1u;
}

uint32_t ring_hal_millis(void)
{
    return clock_ms;
}

/* ---- the vector file ------------------------------------------------------------------- */
static int hexval(int c)
{
    if (c >= '0' && c <= '9') return c - '0';
    if (c >= 'a' && c <= 'f') return c - 'a' + 10;
    if (c >= 'A' && c <= 'F') return c - 'A' + 10;
    return -1;
}

/* Parse hex bytes (spaces and '|' ignored) into out; -1 on a malformed string. */
static long parse_hex(const char *s, uint8_t *out, size_t max)
{
    size_t n = 0;
    while (*s) {
        int hi, lo;
        if (*s == ' ' || *s == '|' || *s == '\t') {
            ++s;
            continue;
        }
        hi = hexval((unsigned char)s[0]);
        lo = s[1] ? hexval((unsigned char)s[1]) : -1;
        if (hi < 0 || lo < 0 || n >= max) {
            return -1;
        }
        out[n++] = (uint8_t)(hi * 16 + lo);
        s += 2;
    }
    return (long)n;
}

static void print_hex(const char *label, const uint8_t *b, size_t n)
{
    size_t i;
    printf("    %s (%lu bytes):", label, (unsigned long)n);
    for (i = 0; i < n; ++i) {
        printf(" %02X", b[i]);
    }
    printf("\n");
}

typedef struct {
    char name[128];
    int line;
    int failed;
    ring_device_t dev;
    ring_config_t cfg;
    char firmware[64];
} case_t;

static int fail(case_t *c, int line, const char *what)
{
    if (!c->failed) {
        printf("FAIL %s (line %d): %s\n", c->name, line, what);
    }
    c->failed = 1;
    return 0;
}

static void start_case(case_t *c, const char *name, int line, uint32_t clock0)
{
    memset(c, 0, sizeof *c);
    strncpy(c->name, name, sizeof c->name - 1);
    c->line = line;
    strcpy(c->firmware, "vectors");
    c->cfg.led_count = 24;
    c->cfg.version = RING_PROTOCOL_VERSION;
    c->cfg.frame_gap_ms = RING_DEFAULT_FRAME_GAP_MS;
    c->cfg.firmware_id = c->firmware;
    rx_len = rx_pos = tx_len = shown_len = 0;
    tx_overflow = 0;
    clock_ms = clock0;
}

static void init_device(case_t *c, int line)
{
    if (ring_init(&c->dev, &c->cfg) != 0) {
        fail(c, line, "ring_init refused the configuration");
    }
}

static int device_option(case_t *c, char *arg, int line)
{
    char *tok = strtok(arg, " \t");
    for (; tok; tok = strtok(NULL, " \t")) {
        if (strncmp(tok, "leds=", 5) == 0) {
            c->cfg.led_count = (uint8_t)atoi(tok + 5);
        } else if (strncmp(tok, "version=", 8) == 0) {
            c->cfg.version = (uint8_t)atoi(tok + 8);
        } else if (strncmp(tok, "firmware=", 9) == 0) {
            strncpy(c->firmware, tok + 9, sizeof c->firmware - 1);
        } else {
            return fail(c, line, "unknown device option");
        }
    }
    init_device(c, line);
    return 1;
}

/* Run every case of the file with the given starting clock; count passes and failures. */
static int run_file(const char *path, uint32_t clock0, int *passed, int *failed)
{
    static char text[LINE_MAX_CHARS];
    static uint8_t bytes[BUF_MAX];
    static case_t c;
    FILE *f = fopen(path, "r");
    int lineno = 0, in_case = 0, initialised = 0;
    if (!f) {
        printf("cannot open %s\n", path);
        return -1;
    }
    for (;;) {
        char *line = fgets(text, sizeof text, f), *arg, *hash;
        long n;
        ++lineno;
        if (line) {
            hash = strchr(line, '#');
            if (hash) *hash = '\0';
            line[strcspn(line, "\r\n")] = '\0';
            while (*line == ' ') ++line;
            if (!*line) continue;
        }
        if (!line || strncmp(line, "case ", 5) == 0) {
            if (in_case) {
                if (!initialised) init_device(&c, lineno);
                if (tx_len) {
                    print_hex("unexpected output at the end", tx, tx_len);
                    fail(&c, lineno, "the device sent bytes no expect line accounts for");
                }
                if (c.failed) ++*failed; else ++*passed;
            }
            if (!line) break;
            start_case(&c, line + 5, lineno, clock0);
            in_case = 1;
            initialised = 0;
            continue;
        }
        if (!in_case) {
            printf("line %d: directive before the first case\n", lineno);
            fclose(f);
            return -1;
        }
        arg = strchr(line, ' ');
        arg = arg ? arg + 1 : line + strlen(line);
        if (strncmp(line, "device", 6) == 0) {
            if (initialised) fail(&c, lineno, "device must follow case directly");
            else device_option(&c, arg, lineno);
            initialised = 1;
            continue;
        }
        if (!initialised) {
            init_device(&c, lineno);
            initialised = 1;
        }
        if (strncmp(line, "send", 4) == 0) {
            n = parse_hex(arg, bytes, sizeof bytes);
            if (n < 0) { fail(&c, lineno, "malformed hex"); continue; }
            memcpy(rx, bytes, (size_t)n);
            rx_len = (size_t)n;
            rx_pos = 0;
            ring_poll(&c.dev);
            if (rx_pos != rx_len) fail(&c, lineno, "ring_poll left received bytes unread");
        } else if (strncmp(line, "wait", 4) == 0) {
            clock_ms += (uint32_t)strtoul(arg, NULL, 10);
            rx_len = rx_pos = 0;
            ring_poll(&c.dev);
        } else if (strncmp(line, "expect", 6) == 0) {
            n = parse_hex(arg, bytes, sizeof bytes);
            if (n < 0) { fail(&c, lineno, "malformed hex"); continue; }
            if (tx_overflow || (size_t)n != tx_len || memcmp(bytes, tx, tx_len) != 0) {
                if (!c.failed) {
                    fail(&c, lineno, "the device's output differs");
                    print_hex("expected", bytes, (size_t)n);
                    print_hex("got     ", tx, tx_len);
                }
            }
            tx_len = 0;
        } else if (strncmp(line, "shown", 5) == 0) {
            n = parse_hex(arg, bytes, sizeof bytes);
            if (n < 0 || (size_t)n != shown_len || memcmp(bytes, shown, shown_len) != 0) {
                if (!c.failed) {
                    fail(&c, lineno, "the LEDs show another state");
                    print_hex("expected", bytes, n < 0 ? 0 : (size_t)n);
                    print_hex("got     ", shown, shown_len);
                }
            }
        } else {
            fail(&c, lineno, "unknown directive");
        }
    }
    fclose(f);
    return 0;
}

int main(int argc, char **argv)
{
    int passed = 0, failed = 0, cases;
    if (argc != 2) {
        fprintf(stderr, "usage: %s VECTOR_FILE\n", argv[0]);
        return 2;
    }
    if (run_file(argv[1], 0u, &passed, &failed) != 0) return 2;
    cases = passed + failed;
    /* The same cases with millis() wrapping around 2^32 in the middle of each. */
    if (run_file(argv[1], 0xFFFFFFFEu, &passed, &failed) != 0) return 2;
    printf("%s: %d cases, each at clock 0 and across the millis() wrap\n", argv[1], cases);
    printf("%d passed, %d failed\n", passed, failed);
    return failed ? 1 : 0;
}

/*
 * iristac-ring-host: the C ring firmware core behind a pseudo-terminal, a drop-in for
 * `iristac emulate-ring` (pipeline/capture/emulator.py).  It prints the pty's device path on
 * its first line of output and serves the protocol there until SIGTERM/SIGINT, --duration or
 * an injected disconnect.  The protocol itself is ring_device.c, unchanged: this file is the
 * board (UART = the pty, LEDs = a log file, millis = CLOCK_MONOTONIC) plus the emulator's
 * fault injection on the wire.
 *
 *   --leds N                 LED count (default 24)
 *   --faults SPEC            drop=P,corrupt=P,delay=P,delay-s=S,disconnect-after=N, per frame
 *                            in each direction, as the Python emulator's --faults
 *   --baud B                 every frame costs 10 x bytes / B seconds on the wire
 *   --protocol-version V     version HELLO reports (to test a host's version check)
 *   --firmware-id ID         firmware id HELLO reports (default iristac-ring-c/1)
 *   --seed S                 seed of the fault injection
 *   --duration S             stop after S seconds
 *   --latch-log FILE         append every latched LED state: int64 CLOCK_MONOTONIC ns, u8 count,
 *                            u8 brightness, count x RGB (native byte order), written before
 *                            the reply that confirms it, so a reader that saw the ACK sees it
 *   --stats FILE             11 uint64 counters (native order), kept current through mmap:
 *                            commands dropped_in dropped_out corrupted_in corrupted_out delayed
 *                            duplicates crc_errors resyncs bytes_in bytes_out
 *
 * Exit status: 0 stopped, 1 after an injected disconnect, 2 bad arguments or a system error.
 */
#define _XOPEN_SOURCE 600

#include <errno.h>
#include <fcntl.h>
#include <math.h>
#include <poll.h>
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/mman.h>
#include <termios.h>
#include <time.h>
#include <unistd.h>

#include "ring_device.h"

enum { ST_COMMANDS, ST_DROPPED_IN, ST_DROPPED_OUT, ST_CORRUPTED_IN, ST_CORRUPTED_OUT, ST_DELAYED,
       ST_DUPLICATES, ST_CRC_ERRORS, ST_RESYNCS, ST_BYTES_IN, ST_BYTES_OUT, ST_COUNT };

static const char *prog = "iristac-ring-host";
static ring_device_t dev;
static int master_fd = -1, slave_fd = -1, log_fd = -1;
static volatile sig_atomic_t stop_requested;
static uint64_t local_stats[ST_COUNT];
static volatile uint64_t *stats = local_stats;

static struct {
    double drop, corrupt, delay, delay_s;
    long disconnect_after; /* -1: never */
    double baud;           /* 0: the wire is free */
    int split;             /* faults or a wire model: the host's bytes are split into frames */
} wire = {0.0, 0.0, 0.0, 0.05, -1L, 0.0, 0};

/* The device's receive FIFO: what has crossed the wire and ring_hal_uart_read hands out. */
static uint8_t fifo[8192];
static size_t fifo_len, fifo_pos;

/* ---- random numbers for the faults (splitmix64: small, seeded, reproducible) ------------- */
static uint64_t rng_state;

static uint64_t rng_next(void)
{
    uint64_t z = (rng_state += 0x9E3779B97F4A7C15ull);
    z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9ull;
    z = (z ^ (z >> 27)) * 0x94D049BB133111EBull;
    return z ^ (z >> 31);
}

static double rng_uniform(void)
{
    return (double)(rng_next() >> 11) * (1.0 / 9007199254740992.0);
}

/* ---- time ------------------------------------------------------------------------------- */
static int64_t now_ns(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (int64_t)ts.tv_sec * 1000000000 + ts.tv_nsec;
}

static void sleep_s(double s)
{
    struct timespec ts;
    if (s <= 0) return;
    ts.tv_sec = (time_t)s;
    ts.tv_nsec = (long)((s - (double)ts.tv_sec) * 1e9);
    while (nanosleep(&ts, &ts) != 0 && errno == EINTR && !stop_requested) {
    }
}

/* ---- the board: ring_hal.h --------------------------------------------------------------- */
uint32_t ring_hal_millis(void)
{
    return (uint32_t)(now_ns() / 1000000);
}

uint16_t ring_hal_uart_read(uint8_t *buf, uint16_t max)
{
    size_t n = fifo_len - fifo_pos;
    if (n > max) n = max;
    memcpy(buf, fifo + fifo_pos, n);
    fifo_pos += n;
    if (fifo_pos == fifo_len) fifo_pos = fifo_len = 0;
    return (uint16_t)n;
}

static void sync_stats(void)
{
    stats[ST_COMMANDS] = dev.commands;
    stats[ST_DUPLICATES] = dev.duplicates;
    stats[ST_CRC_ERRORS] = dev.rx_errors;
    stats[ST_RESYNCS] = dev.resyncs;
}

/* Lose it, flip one bit, or let it through (after its time on the wire): 0 when lost. */
static int cross_wire(uint8_t *frame, uint16_t len, int out)
{
    if (wire.drop > 0 && rng_uniform() < wire.drop) {
        ++stats[out ? ST_DROPPED_OUT : ST_DROPPED_IN];
        return 0;
    }
    if (wire.corrupt > 0 && rng_uniform() < wire.corrupt) {
        uint64_t r = rng_next();
        frame[(r >> 8) % len] ^= (uint8_t)(1u << (r & 7u));
        ++stats[out ? ST_CORRUPTED_OUT : ST_CORRUPTED_IN];
    }
    if (wire.baud > 0) sleep_s(10.0 * len / wire.baud);
    return 1;
}

void ring_hal_uart_write(const uint8_t *buf, uint16_t len)
{
    uint8_t frame[RING_MAX_FRAME];
    size_t done = 0;
    memcpy(frame, buf, len);
    if (wire.split && !cross_wire(frame, len, 1)) {
        sync_stats();
        return;
    }
    stats[ST_BYTES_OUT] += len;
    sync_stats(); /* before the reply leaves: a host that has the reply sees the counters */
    while (done < len) {
        ssize_t n = write(master_fd, frame + done, len - done);
        if (n < 0) {
            if (errno == EINTR) continue;
            return; /* the host is gone; nothing to tell it */
        }
        done += (size_t)n;
    }
}

void ring_hal_leds_show(const uint8_t *rgb, uint8_t count, uint8_t brightness)
{
    uint8_t record[10 + 3 * RING_MAX_LEDS];
    int64_t t = now_ns();
    size_t size = 10u + 3u * count;
    if (log_fd < 0) return;
    memcpy(record, &t, 8);
    record[8] = count;
    record[9] = brightness;
    memcpy(record + 10, rgb, 3u * count);
    /* One write per record, before the ACK is sent: whoever saw the ACK can read the state. */
    if (write(log_fd, record, size) != (ssize_t)size) {
        fprintf(stderr, "%s: cannot write the latch log: %s\n", prog, strerror(errno));
        stop_requested = 1;
    }
}

/* ---- the wire: host bytes -> (faults) -> device ------------------------------------------ */
static void deliver(const uint8_t *bytes, size_t n)
{
    if (fifo_len + n > sizeof fifo) n = sizeof fifo - fifo_len; /* cannot happen: polled at once */
    memcpy(fifo + fifo_len, bytes, n);
    fifo_len += n;
    ring_poll(&dev);
}

static void deliver_frame(const uint8_t *raw, uint16_t len)
{
    uint8_t frame[RING_MAX_FRAME];
    memcpy(frame, raw, len);
    if (!cross_wire(frame, len, 0)) return;
    if (wire.delay > 0 && rng_uniform() < wire.delay) {
        ++stats[ST_DELAYED];
        sleep_s(wire.delay_s); /* a busy MCU: the host times out and retransmits meanwhile */
    }
    deliver(frame, len);
}

/* ---- set-up ------------------------------------------------------------------------------ */
static void usage_error(const char *msg, const char *arg)
{
    fprintf(stderr, "%s: %s%s%s\n", prog, msg, arg ? " " : "", arg ? arg : "");
    exit(2);
}

static double number(const char *opt, const char *s)
{
    char *end;
    double v;
    /* No errno test: strtod reports ERANGE for a subnormal (a valid, tiny probability) too;
     * overflow gives an infinity, which isfinite rejects. */
    v = strtod(s, &end);
    if (end == s || *end || !isfinite(v)) {
        fprintf(stderr, "%s: %s %s is not a number\n", prog, opt, s);
        exit(2);
    }
    return v;
}

static void parse_faults(char *spec)
{
    char *item = strtok(spec, ",");
    for (; item; item = strtok(NULL, ",")) {
        char *eq = strchr(item, '='), *key = item, *val;
        double v;
        while (*key == ' ') ++key;
        if (!eq) {
            fprintf(stderr, "%s: --faults: cannot parse '%s'; expected key=value with key one of "
                    "corrupt, delay, delay-s, disconnect-after, drop\n", prog, item);
            exit(2);
        }
        *eq = '\0';
        val = eq + 1;
        v = number("--faults", val);
        if (strcmp(key, "drop") == 0 || strcmp(key, "corrupt") == 0 || strcmp(key, "delay") == 0) {
            if (v < 0 || v > 1) {
                fprintf(stderr, "%s: --faults: %s=%s must be a probability in [0, 1]\n", prog, key, val);
                exit(2);
            }
            *(strcmp(key, "drop") == 0 ? &wire.drop : strcmp(key, "corrupt") == 0 ? &wire.corrupt
                                                                                  : &wire.delay) = v;
        } else if (strcmp(key, "delay-s") == 0) {
            if (v < 0) usage_error("--faults: delay-s must be >= 0 seconds, got", val);
            wire.delay_s = v;
        } else if (strcmp(key, "disconnect-after") == 0) {
            if (v < 1 || v != floor(v)) usage_error("--faults: disconnect-after must be a positive count, got", val);
            wire.disconnect_after = (long)v;
        } else {
            fprintf(stderr, "%s: --faults: unknown key '%s'; expected one of corrupt, delay, "
                    "delay-s, disconnect-after, drop\n", prog, key);
            exit(2);
        }
    }
    wire.split = wire.drop > 0 || wire.corrupt > 0 || wire.delay > 0 || wire.disconnect_after > 0;
}

static void on_signal(int sig)
{
    (void)sig;
    stop_requested = 1;
}

static void open_pty(void)
{
    struct termios t;
    const char *name;
    master_fd = posix_openpt(O_RDWR | O_NOCTTY);
    if (master_fd < 0 || grantpt(master_fd) != 0 || unlockpt(master_fd) != 0 ||
        (name = ptsname(master_fd)) == NULL) {
        fprintf(stderr, "%s: cannot open a pseudo-terminal: %s\n", prog, strerror(errno));
        exit(2);
    }
    /* Keep the slave open ourselves: the host may close and reopen it without the master
     * seeing a hang-up. */
    slave_fd = open(name, O_RDWR | O_NOCTTY);
    if (slave_fd < 0 || tcgetattr(slave_fd, &t) != 0) {
        fprintf(stderr, "%s: cannot open %s: %s\n", prog, name, strerror(errno));
        exit(2);
    }
    /* Raw mode (what cfmakeraw does, in POSIX terms): binary, no echo, no translation. */
    t.c_iflag &= (tcflag_t) ~(IGNBRK | BRKINT | PARMRK | ISTRIP | INLCR | IGNCR | ICRNL | IXON);
    t.c_oflag &= (tcflag_t) ~OPOST;
    t.c_lflag &= (tcflag_t) ~(ECHO | ECHONL | ICANON | ISIG | IEXTEN);
    t.c_cflag &= (tcflag_t) ~(CSIZE | PARENB);
    t.c_cflag |= CS8;
    t.c_cc[VMIN] = 1;
    t.c_cc[VTIME] = 0;
    tcsetattr(slave_fd, TCSANOW, &t);
    printf("%s\n", name);
    fflush(stdout);
}

static void open_stats(const char *path)
{
    size_t size = sizeof(uint64_t) * ST_COUNT;
    void *map;
    int fd = open(path, O_RDWR | O_CREAT | O_TRUNC, 0644);
    if (fd < 0 || ftruncate(fd, (off_t)size) != 0) {
        fprintf(stderr, "%s: cannot create --stats %s: %s\n", prog, path, strerror(errno));
        exit(2);
    }
    map = mmap(NULL, size, PROT_READ | PROT_WRITE, MAP_SHARED, fd, 0);
    close(fd);
    if (map == MAP_FAILED) {
        fprintf(stderr, "%s: cannot map --stats %s: %s\n", prog, path, strerror(errno));
        exit(2);
    }
    stats = (volatile uint64_t *)map;
}

int main(int argc, char **argv)
{
    static char faults[512];
    static char firmware_id[64] = "iristac-ring-c/1";
    ring_config_t cfg;
    struct sigaction sa;
    struct pollfd pfd;
    ring_parser_t wire_rx;
    double duration = -1;
    long leds = 24, version = RING_PROTOCOL_VERSION;
    int64_t t0;
    int i;

    for (i = 1; i < argc; ++i) {
        const char *opt = argv[i], *val = i + 1 < argc ? argv[i + 1] : NULL;
        if (strcmp(opt, "-h") == 0 || strcmp(opt, "--help") == 0) {
            printf("usage: %s [--leds N] [--faults SPEC] [--baud B] [--protocol-version V]\n"
                   "       [--firmware-id ID] [--seed S] [--duration S] [--latch-log FILE]\n"
                   "       [--stats FILE]\n", prog);
            return 0;
        }
        if (!val) usage_error("missing value after", opt);
        ++i;
        if (strcmp(opt, "--leds") == 0) {
            leds = (long)number(opt, val);
            if (leds < 1 || leds > RING_MAX_LEDS) {
                fprintf(stderr, "%s: --leds must be in 1..%d, got %s\n", prog, RING_MAX_LEDS, val);
                return 2;
            }
        } else if (strcmp(opt, "--faults") == 0) {
            strncpy(faults, val, sizeof faults - 1);
            parse_faults(faults);
        } else if (strcmp(opt, "--baud") == 0) {
            wire.baud = number(opt, val);
            if (wire.baud <= 0) usage_error("--baud must be > 0, got", val);
        } else if (strcmp(opt, "--protocol-version") == 0) {
            version = (long)number(opt, val);
            if (version < 0 || version > 255) usage_error("--protocol-version must be in 0..255, got", val);
        } else if (strcmp(opt, "--firmware-id") == 0) {
            strncpy(firmware_id, val, sizeof firmware_id - 1);
        } else if (strcmp(opt, "--seed") == 0) {
            rng_state = (uint64_t)(long long)number(opt, val);
        } else if (strcmp(opt, "--duration") == 0) {
            duration = number(opt, val);
        } else if (strcmp(opt, "--latch-log") == 0) {
            log_fd = open(val, O_WRONLY | O_CREAT | O_TRUNC | O_APPEND, 0644);
            if (log_fd < 0) {
                fprintf(stderr, "%s: cannot create --latch-log %s: %s\n", prog, val, strerror(errno));
                return 2;
            }
        } else if (strcmp(opt, "--stats") == 0) {
            open_stats(val);
        } else {
            usage_error("unknown option", opt);
        }
    }
    if (wire.baud > 0) wire.split = 1;

    memset(&sa, 0, sizeof sa);
    sa.sa_handler = on_signal;
    sigaction(SIGTERM, &sa, NULL);
    sigaction(SIGINT, &sa, NULL);
    signal(SIGPIPE, SIG_IGN);

    cfg.led_count = (uint8_t)leds;
    cfg.version = (uint8_t)version;
    cfg.firmware_id = firmware_id;
    /* 2 ms, or 20 character times at the modelled baud rate if that is longer. */
    {
        double gap = wire.baud > 0 ? ceil(200.0 / wire.baud * 1000.0) : 2.0;
        cfg.frame_gap_ms = (uint8_t)(gap < 2.0 ? 2.0 : gap > 255.0 ? 255.0 : gap);
    }
    if (ring_init(&dev, &cfg) != 0) usage_error("invalid configuration", NULL);
    ring_parser_reset(&wire_rx);
    open_pty();

    pfd.fd = master_fd;
    pfd.events = POLLIN;
    t0 = now_ns();
    while (!stop_requested) {
        uint8_t buf[4096];
        ssize_t n;
        int r;
        if (duration >= 0 && (double)(now_ns() - t0) * 1e-9 >= duration) break;
        /* While a partial frame is buffered, wake within a millisecond for its frame gap. */
        r = poll(&pfd, 1, ring_parser_pending(&dev.rx) ? 1 : 50);
        if (r < 0) {
            if (errno == EINTR) continue;
            fprintf(stderr, "%s: poll: %s\n", prog, strerror(errno));
            return 2;
        }
        if (r == 0 || !(pfd.revents & POLLIN)) {
            ring_poll(&dev); /* the line is idle */
            sync_stats();
            if (r > 0 && (pfd.revents & (POLLERR | POLLNVAL))) return 2;
            continue;
        }
        n = read(master_fd, buf, sizeof buf);
        if (n <= 0) {
            if (n < 0 && errno != EINTR && errno != EAGAIN && errno != EIO) {
                fprintf(stderr, "%s: read: %s\n", prog, strerror(errno));
                return 2;
            }
            continue;
        }
        stats[ST_BYTES_IN] += (uint64_t)n;
        if (!wire.split) {
            deliver(buf, (size_t)n); /* no faults: the device sees the bytes as sent */
        } else {
            ssize_t k;
            for (k = 0; k < n; ++k) {
                ring_frame_t f;
                ring_parser_push(&wire_rx, buf[k]);
                while (ring_parser_next(&wire_rx, &f)) {
                    if (wire.disconnect_after > 0 && (long)dev.commands >= wire.disconnect_after) {
                        /* Unplugged: the frame after the N-th command finds the device gone. */
                        close(master_fd);
                        close(slave_fd);
                        fprintf(stderr, "emulated ring disconnected after %lu commands\n",
                                (unsigned long)dev.commands);
                        return 1;
                    }
                    deliver_frame(f.raw, (uint16_t)(f.len + RING_OVERHEAD));
                }
            }
        }
        sync_stats();
    }
    close(master_fd);
    close(slave_fd);
    return 0;
}

/*
 * fake_app.c -- a fake board around the rendered link module (tests only).
 *
 * Implements the app_* callbacks of link_fw.h with a toy drive (state machine IDLE/RUN/BRAKE/
 * FAULT, speed following the ramped setpoint with a first-order lag, an encoder position and a
 * hall code), a 256-byte EEPROM, a UART TX queue of configurable size, and a discrete-event
 * model of time: 1 kHz tick, link_sample() at sample_hz, and UART bytes in both directions at
 * the baud rate (10 bits per byte).  Python drives it through ctypes (fakeboard.py).
 */
#include <stdint.h>
#include <string.h>
#include "link_fw.h"
#include "fake_hooks.h"

/* ---------------- the toy drive ---------------- */
static uint8_t drv_state, drv_fault;
static int32_t spd_m;          /* speed, 1/1000 raw of the speed signal */
static int32_t ramp_m;         /* ramped setpoint, 1/1000 raw */
static int32_t pos_frac;       /* 1/1000 encoder counts */
static int16_t pos;
static int32_t integ;

static uint8_t eeprom[256];
static uint32_t n_param_changed, n_link_lost, n_commands, n_eeprom_writes;
static uint8_t last_param_changed;

/* UART TX queue of the "firmware" */
#define TXQ_MAX 4096u
static uint8_t txq[TXQ_MAX];
static uint16_t txq_head, txq_tail, txq_used, txq_cap = 64u;
static uint8_t tx_blocked;

/* host -> board bytes waiting to be "on the wire" */
#define RXQ_MAX 65536u
static uint8_t rxq[RXQ_MAX];
static uint32_t rxq_head, rxq_tail, rxq_used, rx_delivered;

/* time */
static uint64_t now_ns, t_tick, t_tx_free, t_rx_free, byte_ns;
static uint64_t sample_k;
static uint32_t sample_hz;

/* accepted-frame log (LINK_HOOK_FRAME) */
#define LOG_MAX 8192u
static struct { uint8_t type, seq, len; uint8_t payload[LINK_MAX_PAYLOAD]; uint32_t at; } flog[LOG_MAX];
static uint32_t flog_n;

void peer_hook_frame(uint8_t type, uint8_t seq, const uint8_t *payload, uint8_t len)
{
    if (flog_n < LOG_MAX) {
        flog[flog_n].type = type;
        flog[flog_n].seq = seq;
        flog[flog_n].len = len;
        memcpy(flog[flog_n].payload, payload, len);
        flog[flog_n].at = rx_delivered;
    }
    flog_n++;
}

static int16_t clamp16(int32_t v)
{
    if (v > 32767) return 32767;
    if (v < -32768) return -32768;
    return (int16_t)v;
}

uint8_t app_command(uint8_t cmd, const uint8_t *arg, uint8_t n)
{
    (void)arg;
    (void)n;
    n_commands++;
    switch (cmd) {
    case LINK_CMD_START:
        if (drv_state == LINK_STATE_FAULT) return LINK_NACK_FAULT_ACTIVE;
        drv_state = LINK_STATE_RUN;
        return 0u;
    case LINK_CMD_STOP:
        if (drv_state != LINK_STATE_FAULT) drv_state = LINK_STATE_IDLE;
        return 0u;
    case LINK_CMD_BRAKE:
        if (drv_state == LINK_STATE_FAULT) return LINK_NACK_FAULT_ACTIVE;
        drv_state = LINK_STATE_BRAKE;
        return 0u;
    case LINK_CMD_FAULT_CLEAR:
        if (drv_state == LINK_STATE_FAULT) {
            drv_state = LINK_STATE_IDLE;
            drv_fault = LINK_FAULT_NONE;
        }
        return 0u;
    default:
        return LINK_NACK_UNKNOWN_COMMAND;
    }
}

void app_param_changed(uint8_t id)
{
    n_param_changed++;
    last_param_changed = id;
}

/* every signal is computed from the toy drive's state: all through app_signal */
LINK_DATA int16_t * const app_signal_src[LINK_N_SIGNALS] = { 0 };

int16_t app_signal(uint8_t signal)
{
    static const uint8_t hall_seq[6] = {1u, 3u, 2u, 6u, 4u, 5u};
    int32_t s = spd_m / 1000, a, lo, hi;
    switch (signal) {
    case LINK_SIG_SPEED: return clamp16(s);
    case LINK_SIG_SETPOINT: return clamp16(ramp_m / 1000);
    case LINK_SIG_VOLTAGE: return clamp16(s / 4 + integ / 1000);
    case LINK_SIG_CURRENT: return clamp16((ramp_m - spd_m) / 4000);
    case LINK_SIG_INTEGRATOR: return clamp16(integ / 1000);
    case LINK_SIG_DUTY: return drv_state == LINK_STATE_RUN ? clamp16(s / 3) : 0;
    case LINK_SIG_HALL: return (int16_t)hall_seq[(uint16_t)pos / 50u % 6u];
    case LINK_SIG_STATE: return (int16_t)drv_state;
    case LINK_SIG_FAULT: return (int16_t)drv_fault;
    case LINK_SIG_MU1:
        a = s < 0 ? -s : s;
        lo = link_param_get(LINK_ID_PREMISE_LOW);
        hi = link_param_get(LINK_ID_PREMISE_HIGH);
        if (hi <= lo || a <= lo) return 16384;
        if (a >= hi) return 0;
        return clamp16((int32_t)(((int64_t)(hi - a) * 16384) / (hi - lo)));
    case LINK_SIG_POSITION: return pos;
    default: return 0;
    }
}

void app_link_lost(void)
{
    n_link_lost++;
    drv_state = LINK_STATE_FAULT;
    drv_fault = LINK_FAULT_LINK_LOST;
}

uint8_t app_tx_free(void)
{
    uint16_t f = (uint16_t)(txq_cap - txq_used);
    if (tx_blocked) return 0u;
    return (uint8_t)(f > 255u ? 255u : f);
}

void app_tx_byte(uint8_t b)
{
    if (txq_used >= txq_cap) return;          /* link_fw must never do this: checked by tests */
    txq[txq_head] = b;
    txq_head = (uint16_t)((txq_head + 1u) % TXQ_MAX);
    txq_used++;
}

uint8_t app_eeprom_read(uint8_t addr) { return eeprom[addr]; }

void app_eeprom_write(uint8_t addr, uint8_t value)
{
    n_eeprom_writes++;
    eeprom[addr] = value;
}

static void motor_ms(void)
{
    int32_t sp_m = link_param_get(LINK_ID_SPEED_SETPOINT) * 1000;
    int32_t acc = link_param_get(LINK_ID_ACCEL_LIMIT);      /* rpm/s = 1/1000 rpm per ms */
    int32_t target = 0, tau = 200;
    if (acc == 0) {
        ramp_m = sp_m;
    } else if (ramp_m < sp_m) {
        ramp_m = (sp_m - ramp_m > acc) ? ramp_m + acc : sp_m;
    } else if (ramp_m > sp_m) {
        ramp_m = (ramp_m - sp_m > acc) ? ramp_m - acc : sp_m;
    }
    if (drv_state == LINK_STATE_RUN) {
        target = ramp_m;
        tau = 20;
        integ += (target - spd_m) / 100;
    } else if (drv_state == LINK_STATE_BRAKE) {
        tau = 5;
    }
    if (drv_state != LINK_STATE_RUN) integ = 0;
    spd_m += (target - spd_m) / tau;
    pos_frac += spd_m / 30;                                  /* 2000 counts/rev */
    pos = (int16_t)(uint16_t)((uint16_t)pos + (uint16_t)(int16_t)(pos_frac / 1000));
    pos_frac %= 1000;
}

/* ---------------- the peer API (ctypes) ---------------- */
void peer_reset(uint32_t baud, uint32_t hz, uint16_t txq_bytes)
{
    drv_state = LINK_STATE_IDLE;
    drv_fault = LINK_FAULT_NONE;
    spd_m = ramp_m = pos_frac = integ = 0;
    pos = 0;
    n_param_changed = n_link_lost = n_commands = n_eeprom_writes = 0u;
    txq_head = txq_tail = txq_used = 0u;
    txq_cap = (txq_bytes == 0u || txq_bytes > TXQ_MAX) ? 64u : txq_bytes;
    tx_blocked = 0u;
    rxq_head = rxq_tail = rxq_used = rx_delivered = 0u;
    now_ns = 0u;
    t_tick = 1000000u;
    byte_ns = baud ? (10000000000ULL + baud / 2u) / baud : 0u;
    t_tx_free = t_rx_free = 0u;
    sample_hz = hz;
    sample_k = 1u;
    flog_n = 0u;
    link_init();
}

/* boot: reset + EEPROM load as the firmware does it; returns link_eeprom_load()'s result */
uint8_t peer_boot(uint32_t baud, uint32_t hz, uint16_t txq_bytes)
{
    uint8_t r;
    peer_reset(baud, hz, txq_bytes);
    r = link_eeprom_load();
    if (r == LINK_EE_CORRUPT) {
        drv_state = LINK_STATE_FAULT;
        drv_fault = LINK_FAULT_EEPROM_CRC;
        link_event(LINK_EVENT_FAULT, LINK_FAULT_EEPROM_CRC);
    }
    n_param_changed = 0u;
    link_poll();                      /* the main loop's first pass */
    return r;
}

void peer_erase_eeprom(void) { memset(eeprom, 0xFF, sizeof eeprom); }
uint8_t *peer_eeprom(void) { return eeprom; }

void peer_rx(const uint8_t *p, uint32_t n)
{
    uint32_t i;
    for (i = 0u; i < n && rxq_used < RXQ_MAX; i++) {
        rxq[rxq_head] = p[i];
        rxq_head = (rxq_head + 1u) % RXQ_MAX;
        rxq_used++;
    }
}

/* take everything queued for transmission (direct mode: no UART timing) */
uint32_t peer_take_tx(uint8_t *out, uint32_t cap)
{
    uint32_t n = 0u;
    while (txq_used != 0u && n < cap) {
        out[n++] = txq[txq_tail];
        txq_tail = (uint16_t)((txq_tail + 1u) % TXQ_MAX);
        txq_used--;
    }
    return n;
}

/* Run board time forward by ns.  UART bytes leave at the baud rate into out (at most cap). */
uint32_t peer_advance_ns(uint64_t ns, uint8_t *out, uint32_t cap)
{
    uint64_t end = now_ns + ns;
    uint32_t nout = 0u;
    for (;;) {
        uint64_t t = UINT64_MAX, ts;
        int ev = 0;
        if (t_tick <= end && t_tick < t) { t = t_tick; ev = 1; }
        if (sample_hz != 0u) {
            ts = sample_k * 1000000000ULL / sample_hz;
            if (ts <= end && ts < t) { t = ts; ev = 2; }
        }
        if (txq_used != 0u && nout < cap) {
            ts = t_tx_free > now_ns ? t_tx_free : now_ns;
            if (ts <= end && ts < t) { t = ts; ev = 3; }
        }
        if (rxq_used != 0u) {
            ts = t_rx_free > now_ns ? t_rx_free : now_ns;
            if (ts <= end && ts < t) { t = ts; ev = 4; }
        }
        if (ev == 0) break;
        now_ns = t;
        switch (ev) {
        case 1:
            link_tick_ms();
            motor_ms();
            t_tick += 1000000u;
            break;
        case 2:
            link_sample();
            sample_k++;
            break;
        case 3:
            out[nout++] = txq[txq_tail];
            txq_tail = (uint16_t)((txq_tail + 1u) % TXQ_MAX);
            txq_used--;
            t_tx_free = now_ns + byte_ns;
            break;
        default:
            link_rx_byte(rxq[rxq_tail]);
            rxq_tail = (rxq_tail + 1u) % RXQ_MAX;
            rxq_used--;
            rx_delivered++;
            t_rx_free = now_ns + byte_ns;
            break;
        }
        link_poll();
    }
    now_ns = end;
    return nout;
}

/* direct feeding (C-level tests, fuzzing): bytes straight into link_rx_byte, poll after each */
void peer_feed(const uint8_t *p, uint32_t n)
{
    uint32_t i;
    for (i = 0u; i < n; i++) {
        link_rx_byte(p[i]);
        rx_delivered++;
        link_poll();
    }
}

void peer_tick(uint32_t ms)
{
    while (ms--) {
        link_tick_ms();
        motor_ms();
        link_poll();
    }
}

void peer_sample(uint32_t n)
{
    while (n--) {
        link_sample();
        link_poll();
    }
}

void peer_inject_fault(uint8_t code)
{
    drv_state = LINK_STATE_FAULT;
    drv_fault = code;
    link_event(LINK_EVENT_FAULT, code);
}

void peer_set_tx_blocked(uint8_t b) { tx_blocked = b; }
uint64_t peer_now_ns(void) { return now_ns; }
uint32_t peer_txq_used(void) { return txq_used; }
uint32_t peer_rxq_used(void) { return rxq_used; }

uint32_t peer_stat(int which)
{
    switch (which) {
    case 0: return n_param_changed;
    case 1: return n_link_lost;
    case 2: return n_commands;
    case 3: return n_eeprom_writes;
    case 4: return last_param_changed;
    case 5: return drv_state;
    case 6: return drv_fault;
    case 7: return flog_n;
    case 8: return rx_delivered;
    default: return 0u;
    }
}

/* accepted frame i of the log: returns len, fills type/seq/payload/at */
int peer_log_get(uint32_t i, uint8_t *type, uint8_t *seq, uint8_t *payload, uint32_t *at)
{
    if (i >= flog_n || i >= LOG_MAX) return -1;
    *type = flog[i].type;
    *seq = flog[i].seq;
    *at = flog[i].at;
    memcpy(payload, flog[i].payload, flog[i].len);
    return flog[i].len;
}

void peer_log_clear(void) { flog_n = 0u; }

/*
 * link_fw.c -- picdrive serial link, C side: framing, CRC, resync, dispatcher with ACK/NACK
 * and duplicate-SEQ replay, parameter store with range checks, EEPROM image, telemetry,
 * triggered capture, link-loss watchdog.
 * Rendered by picdrive.protocol.render_c() from host/picdrive/protocol.py.  DO NOT EDIT.
 * protocol 1.0, table hash 0x02670AFBUL
 *
 * No heap, no floating point (scales are float32 bit patterns, only reported), explicit
 * widths, 32-bit casts before products that can exceed 16 bits.
 */
#include <stddef.h>
#include "link_fw.h"

#ifndef LINK_CRITICAL_BEGIN
#define LINK_CRITICAL_BEGIN() do { extern void fw_lock(void); fw_lock(); } while (0)
#endif
#ifndef LINK_CRITICAL_END
#define LINK_CRITICAL_END() do { extern void fw_unlock(void); fw_unlock(); } while (0)
#endif
#ifndef LINK_HOOK_FRAME      /* test hook: called with every frame that passed the CRC */
#define LINK_HOOK_FRAME(type, seq, payload, len) ((void)0)
#endif

#if (LINK_EE_BASE + LINK_EE_IMAGE_BYTES) > 256u
#error "EEPROM image does not fit 256 B at LINK_EE_BASE"
#endif

#define RX_MASK            ((uint8_t)(LINK_RX_RING - 1u))
#define SIGNAL_BASE_ID     LINK_SIGNAL_BASE_ID
#define SIG_ALL            0x07FFu
#define NONE               0xFFu
#define EE_MAGIC0          0x50u
#define EE_MAGIC1          0x44u
#define EE_VERSION         1u
#define EE_HEADER          8u
#define EE_DATA_BYTES      35u
#define TELEM_HEADER       2u
#define CAPREAD_HEADER     7u

link_params_t link_params;

/* ---- the table (flash) ---- */
typedef struct {
    uint8_t id;
    uint8_t type;
    uint8_t flags;
    uint8_t unit;
    uint32_t scale_bits;
    int32_t min;
    int32_t max;
    int32_t def;
    uint8_t offset;                    /* in link_params (parameters only) */
    const char *name;
} link_entry_t;

static const link_entry_t link_table[LINK_N_ENTRIES] = {
    { LINK_ID_SPEED_SETPOINT, LINK_T_INT16, 0x01u, 1u, 0x3E18C9EBUL, -17425L, 17425L, 0L, (uint8_t)offsetof(link_params_t, speed_setpoint), "speed_setpoint" },
    { LINK_ID_CONTROLLER, LINK_T_UINT8, 0x03u, 12u, 0x3F800000UL, 0L, 1L, 1L, (uint8_t)offsetof(link_params_t, controller), "controller" },
    { LINK_ID_PREMISE_LOW, LINK_T_INT16, 0x03u, 1u, 0x3E18C9EBUL, 0L, 32767L, 0L, (uint8_t)offsetof(link_params_t, premise_low), "premise_low" },
    { LINK_ID_PREMISE_HIGH, LINK_T_INT16, 0x03u, 1u, 0x3E18C9EBUL, 0L, 32767L, 17425L, (uint8_t)offsetof(link_params_t, premise_high), "premise_high" },
    { LINK_ID_SETPOINT_WEIGHT, LINK_T_INT16, 0x03u, 0u, 0x38800000UL, 0L, 32767L, 17078L, (uint8_t)offsetof(link_params_t, setpoint_weight), "setpoint_weight" },
    { LINK_ID_U_MIN, LINK_T_INT16, 0x03u, 3u, 0x3B800000UL, -11304L, 0L, -11304L, (uint8_t)offsetof(link_params_t, u_min), "u_min" },
    { LINK_ID_U_MAX, LINK_T_INT16, 0x03u, 3u, 0x3B800000UL, 0L, 11304L, 11304L, (uint8_t)offsetof(link_params_t, u_max), "u_max" },
    { LINK_ID_CURRENT_LIMIT, LINK_T_INT16, 0x03u, 4u, 0x3BA00000UL, 0L, 1023L, 307L, (uint8_t)offsetof(link_params_t, current_limit), "current_limit" },
    { LINK_ID_ACCEL_LIMIT, LINK_T_UINT16, 0x03u, 2u, 0x43153530UL, 0L, 65535L, 0L, (uint8_t)offsetof(link_params_t, accel_limit), "accel_limit" },
    { LINK_ID_LINK_TIMEOUT, LINK_T_UINT16, 0x03u, 9u, 0x3F800000UL, 20L, 60000L, 500L, (uint8_t)offsetof(link_params_t, link_timeout), "link_timeout" },
    { LINK_ID_STALL_TIMEOUT, LINK_T_UINT16, 0x03u, 9u, 0x3F800000UL, 10L, 60000L, 500L, (uint8_t)offsetof(link_params_t, stall_timeout), "stall_timeout" },
    { LINK_ID_SPEED, LINK_T_INT16, 0x04u, 1u, 0x3E18C9EBUL, -32768L, 32767L, 0L, 0u, "speed" },
    { LINK_ID_SETPOINT, LINK_T_INT16, 0x04u, 1u, 0x3E18C9EBUL, -32768L, 32767L, 0L, 0u, "setpoint" },
    { LINK_ID_VOLTAGE, LINK_T_INT16, 0x04u, 3u, 0x3B800000UL, -32768L, 32767L, 0L, 0u, "voltage" },
    { LINK_ID_CURRENT, LINK_T_INT16, 0x04u, 4u, 0x3BA00000UL, -1023L, 1023L, 0L, 0u, "current" },
    { LINK_ID_INTEGRATOR, LINK_T_INT16, 0x04u, 3u, 0x3B800000UL, -32768L, 32767L, 0L, 0u, "integrator" },
    { LINK_ID_DUTY, LINK_T_INT16, 0x04u, 10u, 0x3F800000UL, -2000L, 2000L, 0L, 0u, "duty" },
    { LINK_ID_HALL, LINK_T_INT16, 0x04u, 11u, 0x3F800000UL, -32768L, 32767L, 0L, 0u, "hall" },
    { LINK_ID_STATE, LINK_T_INT16, 0x04u, 12u, 0x3F800000UL, -32768L, 32767L, 0L, 0u, "state" },
    { LINK_ID_FAULT, LINK_T_INT16, 0x04u, 11u, 0x3F800000UL, -32768L, 32767L, 0L, 0u, "fault" },
    { LINK_ID_MU1, LINK_T_INT16, 0x04u, 0u, 0x39800000UL, 0L, 4096L, 4096L, 0u, "mu1" },
    { LINK_ID_POSITION, LINK_T_INT16, 0x04u, 10u, 0x3F800000UL, -32768L, 32767L, 0L, 0u, "position" },
    { LINK_ID_RULE1_KP, LINK_T_INT16, 0x03u, 5u, 0x39800000UL, -32768L, 32767L, 13859L, (uint8_t)offsetof(link_params_t, rule1_kp), "rule1_kp" },
    { LINK_ID_RULE1_KI, LINK_T_INT16, 0x03u, 6u, 0x3CFA0000UL, -32768L, 32767L, 9644L, (uint8_t)offsetof(link_params_t, rule1_ki), "rule1_ki" },
    { LINK_ID_RULE1_KD, LINK_T_INT16, 0x03u, 7u, 0x3283126FUL, -32768L, 32767L, 0L, (uint8_t)offsetof(link_params_t, rule1_kd), "rule1_kd" },
    { LINK_ID_RULE1_KC, LINK_T_INT16, 0x03u, 8u, 0x3B4CCCCDUL, -32768L, 32767L, 14101L, (uint8_t)offsetof(link_params_t, rule1_kc), "rule1_kc" },
    { LINK_ID_RULE2_KP, LINK_T_INT16, 0x03u, 5u, 0x39800000UL, -32768L, 32767L, 13859L, (uint8_t)offsetof(link_params_t, rule2_kp), "rule2_kp" },
    { LINK_ID_RULE2_KI, LINK_T_INT16, 0x03u, 6u, 0x3CFA0000UL, -32768L, 32767L, 9644L, (uint8_t)offsetof(link_params_t, rule2_ki), "rule2_ki" },
    { LINK_ID_RULE2_KD, LINK_T_INT16, 0x03u, 7u, 0x3283126FUL, -32768L, 32767L, 0L, (uint8_t)offsetof(link_params_t, rule2_kd), "rule2_kd" },
    { LINK_ID_RULE2_KC, LINK_T_INT16, 0x03u, 8u, 0x3B4CCCCDUL, -32768L, 32767L, 14101L, (uint8_t)offsetof(link_params_t, rule2_kc), "rule2_kc" },
};

static const uint8_t link_persisted[18] = {
    LINK_ID_CONTROLLER,
    LINK_ID_PREMISE_LOW,
    LINK_ID_PREMISE_HIGH,
    LINK_ID_SETPOINT_WEIGHT,
    LINK_ID_U_MIN,
    LINK_ID_U_MAX,
    LINK_ID_CURRENT_LIMIT,
    LINK_ID_ACCEL_LIMIT,
    LINK_ID_LINK_TIMEOUT,
    LINK_ID_STALL_TIMEOUT,
    LINK_ID_RULE1_KP,
    LINK_ID_RULE1_KI,
    LINK_ID_RULE1_KD,
    LINK_ID_RULE1_KC,
    LINK_ID_RULE2_KP,
    LINK_ID_RULE2_KI,
    LINK_ID_RULE2_KD,
    LINK_ID_RULE2_KC,
};

/* ---- buffers ---- */
static uint8_t rx_ring[LINK_RX_RING];          /* written by link_rx_byte, read by link_poll */
static uint8_t tx_buf[LINK_MAX_FRAME];         /* frame in flight; holds the command while it is dispatched */
static uint8_t tm_buf[LINK_MAX_PAYLOAD];       /* telemetry payload being filled by link_sample */
static uint8_t rp_data[LINK_REPLAY_BYTES];     /* last short reply, for duplicate-SEQ replay */
static int16_t cap_buf[LINK_CAPTURE_WORDS];    /* capture ring */

/* ---- scalar state ---- */
static struct {
    /* receive: ISR owns head/activity/overflows, main owns tail */
    volatile uint8_t rx_head;
    volatile uint8_t rx_tail;
    volatile uint8_t rx_activity;      /* a byte arrived (rx ISR sets, tick clears) */
    volatile uint8_t rx_stale;         /* tick: gap seen, bytes before rx_stale_head are old */
    volatile uint8_t rx_stale_head;
    volatile uint8_t rx_valid;         /* main: valid frame seen (tick clears: watchdog) */
    volatile uint16_t rx_overflows;
    uint8_t rx_gap_ms;
    uint16_t crc_errors;
    uint8_t nack_armed;                /* one BAD_CRC NACK per valid frame */
    uint8_t nack_pending;
    uint8_t nack_type;
    uint8_t nack_seq;
    /* transmit */
    uint8_t tx_len;                    /* bytes of tx_buf to send; 0 = free */
    uint8_t tx_pos;
    /* replay */
    uint8_t rp_valid;
    uint8_t rp_type;
    uint8_t rp_seq;
    uint8_t rp_rtype;
    uint8_t rp_len;                    /* NONE: reply too long to store (read-only command) */
    uint16_t rp_crc;
    /* watchdog, time */
    volatile uint8_t wd_armed;
    uint16_t wd_ms;
    volatile uint32_t uptime_ms;
    /* events (single-byte flags: safe from any context) */
    volatile uint8_t ev_boot;
    volatile uint8_t ev_boot_code;
    volatile uint8_t ev_fault;
    volatile uint8_t ev_watchdog;
    uint8_t ev_counter;
    /* telemetry */
    volatile uint8_t tm_ready;         /* sample fills tm_buf and sets it; poll sends and clears it */
    uint16_t tm_mask;
    uint16_t tm_dec;
    uint16_t tm_div;
    uint16_t tm_counter;
    volatile uint16_t tm_dropped;
    uint8_t tm_spf;
    uint8_t tm_nsamp;
    uint8_t tm_len;
    uint8_t tm_gen;
    /* capture */
    volatile uint8_t cap_state;
    volatile uint8_t cap_sp_changed;
    uint8_t cap_nsig;
    uint8_t cap_trig;
    uint8_t cap_prev_valid;
    uint16_t cap_mask;
    uint16_t cap_n;
    uint16_t cap_pre;
    uint16_t cap_dec;
    uint16_t cap_div;
    uint16_t cap_w;
    uint16_t cap_filled;
    uint16_t cap_post;
    uint16_t cap_total;
    uint16_t cap_start;
    uint16_t cap_tidx;
    int16_t cap_thr;
    int16_t cap_prev;
} S;

/* ---- little helpers ---- */
static void put16(uint8_t *p, uint16_t v)
{
    p[0] = (uint8_t)v;
    p[1] = (uint8_t)(v >> 8);
}

static void put32(uint8_t *p, uint32_t v)
{
    p[0] = (uint8_t)v;
    p[1] = (uint8_t)(v >> 8);
    p[2] = (uint8_t)(v >> 16);
    p[3] = (uint8_t)(v >> 24);
}

static uint16_t get16(const uint8_t *p)
{
    return (uint16_t)((uint16_t)p[0] | (uint16_t)((uint16_t)p[1] << 8));
}

static uint32_t get32(const uint8_t *p)
{
    return (uint32_t)p[0] | ((uint32_t)p[1] << 8) | ((uint32_t)p[2] << 16) | ((uint32_t)p[3] << 24);
}

static uint8_t popcount16(uint16_t m)
{
    uint8_t n = 0u;
    while (m != 0u) {
        n = (uint8_t)(n + (uint8_t)(m & 1u));
        m = (uint16_t)(m >> 1);
    }
    return n;
}

uint16_t link_crc16_update(uint16_t crc, uint8_t b)
{
    /* CRC-16/CCITT-FALSE, byte-wise without a table (poly 0x1021) */
    uint8_t x = (uint8_t)((uint8_t)(crc >> 8) ^ b);
    x = (uint8_t)(x ^ (uint8_t)(x >> 4));
    return (uint16_t)((uint16_t)(crc << 8) ^ (uint16_t)((uint16_t)x << 12) ^ (uint16_t)((uint16_t)x << 5)
                      ^ (uint16_t)x);
}

uint16_t link_crc16(const uint8_t *p, uint8_t n)
{
    uint16_t crc = 0xFFFFu;
    while (n != 0u) {
        crc = link_crc16_update(crc, *p);
        p++;
        n--;
    }
    return crc;
}

/* ---- parameter store ---- */
static uint8_t entry_index(uint8_t id)
{
    uint8_t i;
    for (i = 0u; i < LINK_N_ENTRIES; i++) {
        if (link_table[i].id == id) {
            return i;
        }
    }
    return NONE;
}

/* typed access to link_params through the entry's offset (no switch per parameter) */
static int32_t store_get_at(uint8_t idx)
{
    const uint8_t *p = (const uint8_t *)&link_params + link_table[idx].offset;
    switch (link_table[idx].type) {
    case LINK_T_UINT8: return (int32_t)*p;
    case LINK_T_INT8: return (int32_t)*(const int8_t *)(const void *)p;
    case LINK_T_UINT16: return (int32_t)*(const uint16_t *)(const void *)p;
    case LINK_T_INT16: return (int32_t)*(const int16_t *)(const void *)p;
    default: return *(const int32_t *)(const void *)p;
    }
}

static int32_t store_get(uint8_t id)
{
    uint8_t i = entry_index(id);
    return (i == NONE) ? 0 : store_get_at(i);
}

static void store_put_at(uint8_t idx, int32_t v)
{
    uint8_t *p = (uint8_t *)&link_params + link_table[idx].offset;
    LINK_CRITICAL_BEGIN();
    switch (link_table[idx].type) {
    case LINK_T_UINT8: *p = (uint8_t)v; break;
    case LINK_T_INT8: *(int8_t *)(void *)p = (int8_t)v; break;
    case LINK_T_UINT16: *(uint16_t *)(void *)p = (uint16_t)v; break;
    case LINK_T_INT16: *(int16_t *)(void *)p = (int16_t)v; break;
    default: *(int32_t *)(void *)p = v; break;
    }
    LINK_CRITICAL_END();
}

static int32_t signal_value(uint8_t idx)
{
    int16_t v = app_signal((uint8_t)(link_table[idx].id - SIGNAL_BASE_ID));
    if (link_table[idx].type == LINK_T_UINT16) {
        return (int32_t)(uint16_t)v;
    }
    return (int32_t)v;
}

int32_t link_param_get(uint8_t id)
{
    uint8_t i = entry_index(id);
    if (i == NONE) {
        return 0;
    }
    if ((link_table[i].flags & LINK_FLAG_SIGNAL) != 0u) {
        return signal_value(i);
    }
    return store_get_at(i);
}

int16_t link_param_i16(uint8_t id)
{
    int32_t v = link_param_get(id);
    if (v > (int32_t)INT16_MAX) {
        return INT16_MAX;
    }
    if (v < (int32_t)INT16_MIN) {
        return INT16_MIN;
    }
    return (int16_t)v;
}

uint8_t link_param_set(uint8_t id, int32_t raw)
{
    uint8_t i = entry_index(id);
    if (i == NONE) {
        return LINK_NACK_UNKNOWN_PARAM;
    }
    if ((link_table[i].flags & LINK_FLAG_WRITABLE) == 0u) {
        return LINK_NACK_READ_ONLY;
    }
    if (raw < link_table[i].min || raw > link_table[i].max) {
        return LINK_NACK_OUT_OF_RANGE;
    }
    store_put_at(i, raw);
    if (id == LINK_ID_SPEED_SETPOINT) {
        S.cap_sp_changed = 1u;
    }
    app_param_changed(id);
    return 0u;
}

static void store_defaults(void)
{
    uint8_t i;
    for (i = 0u; i < LINK_N_ENTRIES; i++) {
        if ((link_table[i].flags & LINK_FLAG_SIGNAL) == 0u) {
            store_put_at(i, link_table[i].def);
        }
    }
}

/* ---- EEPROM image ---- */
static uint8_t entry_size(uint8_t type)
{
    if (type == LINK_T_INT32) {
        return 4u;
    }
    if (type == LINK_T_INT16 || type == LINK_T_UINT16) {
        return 2u;
    }
    return 1u;
}

static uint8_t ee_addr(uint8_t off)
{
    return (uint8_t)(LINK_EE_BASE + off);
}

static int32_t ee_value(uint8_t off, uint8_t type)
{
    uint32_t u = 0u;
    uint8_t k, n = entry_size(type);
    for (k = 0u; k < n; k++) {
        u |= (uint32_t)app_eeprom_read(ee_addr((uint8_t)(off + k))) << (uint8_t)(8u * k);
    }
    switch (type) {
    case LINK_T_INT8: return (int32_t)(int8_t)(uint8_t)u;
    case LINK_T_INT16: return (int32_t)(int16_t)(uint16_t)u;
    case LINK_T_INT32: return (int32_t)u;
    default: return (int32_t)u;
    }
}

static uint16_t ee_crc(uint8_t n)
{
    uint16_t crc = 0xFFFFu;
    uint8_t a;
    for (a = 0u; a < n; a++) {
        crc = link_crc16_update(crc, app_eeprom_read(ee_addr(a)));
    }
    return crc;
}

uint8_t link_eeprom_save(void)
{
    uint8_t hdr[EE_HEADER];
    uint8_t off = 0u, i, k, n, idx;
    uint16_t crc = 0xFFFFu;
    uint32_t v;
    hdr[0] = EE_MAGIC0;
    hdr[1] = EE_MAGIC1;
    hdr[2] = EE_VERSION;
    put32(&hdr[3], LINK_TABLE_HASH);
    hdr[7] = EE_DATA_BYTES;
    for (k = 0u; k < EE_HEADER; k++) {
        app_eeprom_write(ee_addr(off), hdr[k]);
        crc = link_crc16_update(crc, hdr[k]);
        off++;
    }
    for (i = 0u; i < (uint8_t)sizeof link_persisted; i++) {
        idx = entry_index(link_persisted[i]);
        n = entry_size(link_table[idx].type);
        v = (uint32_t)store_get_at(idx);
        for (k = 0u; k < n; k++) {
            uint8_t b = (uint8_t)(v >> (uint8_t)(8u * k));
            app_eeprom_write(ee_addr(off), b);
            crc = link_crc16_update(crc, b);
            off++;
        }
    }
    app_eeprom_write(ee_addr(off), (uint8_t)(crc >> 8));
    app_eeprom_write(ee_addr((uint8_t)(off + 1u)), (uint8_t)crc);
    /* read-back verify */
    if (ee_crc(off) != crc || app_eeprom_read(ee_addr(off)) != (uint8_t)(crc >> 8)
        || app_eeprom_read(ee_addr((uint8_t)(off + 1u))) != (uint8_t)crc) {
        return LINK_NACK_EEPROM_ERROR;
    }
    return 0u;
}

uint8_t link_eeprom_load(void)
{
    uint8_t off, i, k, idx;
    uint16_t crc;
    int32_t v;
    if (app_eeprom_read(ee_addr(0u)) != EE_MAGIC0 || app_eeprom_read(ee_addr(1u)) != EE_MAGIC1) {
        return LINK_EE_BLANK;
    }
    if (app_eeprom_read(ee_addr(2u)) != EE_VERSION || app_eeprom_read(ee_addr(7u)) != EE_DATA_BYTES) {
        return LINK_EE_OTHER_BUILD;
    }
    for (k = 0u; k < 4u; k++) {
        if (app_eeprom_read(ee_addr((uint8_t)(3u + k))) != (uint8_t)(LINK_TABLE_HASH >> (uint8_t)(8u * k))) {
            return LINK_EE_OTHER_BUILD;
        }
    }
    off = (uint8_t)(EE_HEADER + EE_DATA_BYTES);
    crc = ee_crc(off);
    if (app_eeprom_read(ee_addr(off)) != (uint8_t)(crc >> 8)
        || app_eeprom_read(ee_addr((uint8_t)(off + 1u))) != (uint8_t)crc) {
        return LINK_EE_CORRUPT;
    }
    /* every value in range, or nothing is loaded */
    off = EE_HEADER;
    for (i = 0u; i < (uint8_t)sizeof link_persisted; i++) {
        idx = entry_index(link_persisted[i]);
        v = ee_value(off, link_table[idx].type);
        if (v < link_table[idx].min || v > link_table[idx].max) {
            return LINK_EE_CORRUPT;
        }
        off = (uint8_t)(off + entry_size(link_table[idx].type));
    }
    off = EE_HEADER;
    for (i = 0u; i < (uint8_t)sizeof link_persisted; i++) {
        idx = entry_index(link_persisted[i]);
        store_put_at(idx, ee_value(off, link_table[idx].type));
        off = (uint8_t)(off + entry_size(link_table[idx].type));
    }
    for (i = 0u; i < (uint8_t)sizeof link_persisted; i++) {
        app_param_changed(link_persisted[i]);
    }
    return LINK_EE_OK;
}

/* ---- init, events ---- */
void link_init(void)
{
    volatile uint8_t *p = (volatile uint8_t *)&S;
    uint16_t k;
    for (k = 0u; k < (uint16_t)sizeof S; k++) {
        p[k] = 0u;
    }
    store_defaults();
    S.rp_len = NONE;
    S.nack_armed = 1u;
    S.ev_boot = 1u;
    S.cap_state = LINK_CAP_IDLE;
}

void link_event(uint8_t event, uint8_t code)
{
    if (event == LINK_EVENT_BOOT) {
        S.ev_boot_code = code;
        S.ev_boot = 1u;
    } else if (event == LINK_EVENT_FAULT) {
        S.ev_fault = code;
    } else if (event == LINK_EVENT_WATCHDOG) {
        S.ev_watchdog = 1u;
    }
}

/* ---- receive ---- */
void link_rx_byte(uint8_t b)
{
    uint8_t next = (uint8_t)((uint8_t)(S.rx_head + 1u) & RX_MASK);
    if (next == S.rx_tail) {
        if (S.rx_overflows != 0xFFFFu) {
            S.rx_overflows++;
        }
    } else {
        rx_ring[S.rx_head] = b;
        S.rx_head = next;
    }
    S.rx_activity = 1u;
}

static uint8_t rx_at(uint8_t i)
{
    return rx_ring[(uint8_t)((uint8_t)(S.rx_tail + i) & RX_MASK)];
}

static void rx_drop(uint8_t n)
{
    S.rx_tail = (uint8_t)((uint8_t)(S.rx_tail + n) & RX_MASK);
}

/* Find the next valid frame in the ring.  On success its LEN, TYPE, SEQ and payload are copied
 * to tx_buf[1..] (tx_buf is free while a command is dispatched) and its CRC is returned in *crc. */
static uint8_t rx_parse(uint16_t *crc_out)
{
    for (;;) {
        uint8_t avail = (uint8_t)((uint8_t)(S.rx_head - S.rx_tail) & RX_MASK);
        uint8_t old = 0xFFu;           /* bytes from the tail that arrived before a gap */
        uint8_t len, need, i;
        uint16_t crc, got;
        if (S.rx_stale != 0u) {
            old = (uint8_t)((uint8_t)(S.rx_stale_head - S.rx_tail) & RX_MASK);
            if (old == 0u) {
                S.rx_stale = 0u;
                old = 0xFFu;
            }
        }
        if (avail == 0u) {
            return 0u;
        }
        if (rx_ring[S.rx_tail] != LINK_SOF) {
            rx_drop(1u);
            continue;
        }
        if (avail < 2u) {
            if (old < 2u) {            /* SOF alone before a gap: abandon */
                rx_drop(1u);
                continue;
            }
            return 0u;
        }
        len = rx_at(1u);
        if (len > LINK_MAX_PAYLOAD) {  /* impossible LEN: drop the SOF, rescan */
            rx_drop(1u);
            continue;
        }
        need = (uint8_t)(len + 6u);
        if (old != 0xFFu && need > old) {   /* frame spans a gap: abandon */
            rx_drop(1u);
            continue;
        }
        if (avail < need) {
            return 0u;
        }
        crc = 0xFFFFu;
        for (i = 1u; i < (uint8_t)(len + 4u); i++) {
            crc = link_crc16_update(crc, rx_at(i));
        }
        got = (uint16_t)((uint16_t)((uint16_t)rx_at((uint8_t)(len + 4u)) << 8) | (uint16_t)rx_at((uint8_t)(len + 5u)));
        if (crc != got) {
            if (S.crc_errors != 0xFFFFu) {
                S.crc_errors++;
            }
            if (S.nack_armed != 0u) {
                S.nack_armed = 0u;
                S.nack_pending = 1u;
                S.nack_type = rx_at(2u);
                S.nack_seq = rx_at(3u);
            }
            rx_drop(1u);
            continue;
        }
        for (i = 1u; i < (uint8_t)(len + 4u); i++) {
            tx_buf[i] = rx_at(i);
        }
        rx_drop(need);
        *crc_out = crc;
        return 1u;
    }
}

/* ---- transmit ---- */
static void tx_seal(uint8_t type, uint8_t seq, uint8_t len)
{
    uint16_t crc;
    tx_buf[0] = LINK_SOF;
    tx_buf[1] = len;
    tx_buf[2] = type;
    tx_buf[3] = seq;
    crc = link_crc16(&tx_buf[1], (uint8_t)(len + 3u));
    tx_buf[(uint8_t)(len + 4u)] = (uint8_t)(crc >> 8);
    tx_buf[(uint8_t)(len + 5u)] = (uint8_t)crc;
    S.tx_len = (uint8_t)(len + 6u);
    S.tx_pos = 0u;
}

static void tx_drain(void)
{
    uint8_t room;
    if (S.tx_len == 0u) {
        return;
    }
    room = app_tx_free();
    while (room != 0u && S.tx_pos < S.tx_len) {
        app_tx_byte(tx_buf[S.tx_pos]);
        S.tx_pos++;
        room--;
    }
    if (S.tx_pos >= S.tx_len) {
        S.tx_len = 0u;
        S.tx_pos = 0u;
    }
}

/* ---- command handlers: arguments in a[0..n-1], reply written over them ---- */
static uint8_t drive_busy(void)
{
    int16_t st = app_signal(LINK_SIG_STATE);
    return (uint8_t)(st == (int16_t)LINK_STATE_RUN || st == (int16_t)LINK_STATE_BRAKE);
}

static uint8_t mask_ok(uint16_t mask)
{
    return (uint8_t)(mask != 0u && (mask & (uint16_t)~SIG_ALL) == 0u);
}

static uint8_t cmd_param_info(uint8_t *a, uint8_t *r)
{
    const link_entry_t *e;
    uint8_t k;
    if (a[0] >= LINK_N_ENTRIES) {
        return LINK_NACK_UNKNOWN_PARAM;
    }
    e = &link_table[a[0]];
    a[0] = e->id;
    a[1] = e->type;
    a[2] = e->flags;
    a[3] = e->unit;
    put32(&a[4], e->scale_bits);
    put32(&a[8], (uint32_t)e->min);
    put32(&a[12], (uint32_t)e->max);
    put32(&a[16], (uint32_t)e->def);
    for (k = 0u; k < LINK_NAME_MAX && e->name[k] != '\0'; k++) {
        a[20u + k] = (uint8_t)e->name[k];
    }
    *r = (uint8_t)(20u + k);
    return 0u;
}

static uint8_t cmd_param_get(uint8_t *a, uint8_t n, uint8_t *r)
{
    uint8_t i, idx;
    int32_t v;
    if (n == 0u || n > LINK_PARAM_GET_MAX) {
        return LINK_NACK_MALFORMED;
    }
    for (i = 0u; i < n; i++) {
        if (entry_index(a[i]) == NONE) {
            return LINK_NACK_UNKNOWN_PARAM;
        }
    }
    /* last id first: value i goes to a[4i..4i+3], which holds only ids already answered */
    i = n;
    while (i != 0u) {
        i--;
        idx = entry_index(a[i]);
        if ((link_table[idx].flags & LINK_FLAG_SIGNAL) != 0u) {
            v = signal_value(idx);
        } else {
            v = store_get_at(idx);
        }
        put32(&a[(uint8_t)(4u * i)], (uint32_t)v);
    }
    *r = (uint8_t)(4u * n);
    return 0u;
}

static uint8_t cmd_telem_config(uint8_t *a, uint8_t *r)
{
    uint16_t mask = get16(&a[0]);
    uint16_t dec = get16(&a[2]);
    uint8_t spf = a[4];
    uint8_t nsig = popcount16(mask);
    uint16_t len = (uint16_t)(TELEM_HEADER + (uint16_t)((uint16_t)((uint16_t)nsig * spf) * 2u));
    if (dec != 0u && (!mask_ok(mask) || spf == 0u || len > LINK_MAX_PAYLOAD)) {
        return LINK_NACK_OUT_OF_RANGE;
    }
    LINK_CRITICAL_BEGIN();
    S.tm_dec = 0u;
    S.tm_mask = mask;
    S.tm_spf = spf;
    S.tm_div = 0u;
    S.tm_nsamp = 0u;
    S.tm_len = 0u;
    S.tm_counter = 0u;
    S.tm_ready = 0u;
    S.tm_gen++;
    S.tm_dec = dec;
    LINK_CRITICAL_END();
    a[0] = S.tm_gen;
    a[1] = (uint8_t)(dec != 0u ? len : 0u);
    *r = 2u;
    return 0u;
}

static uint8_t cmd_capture_arm(const uint8_t *a)
{
    uint16_t mask = get16(&a[0]);
    uint16_t n = get16(&a[2]);
    uint16_t pre = get16(&a[4]);
    uint16_t dec = get16(&a[6]);
    uint8_t trig = a[8];
    int16_t thr = (int16_t)get16(&a[9]);
    uint8_t nsig = popcount16(mask);
    if (!mask_ok(mask) || n == 0u || dec == 0u || trig > LINK_TRIG_SPEED_FALLING || pre >= n
        || (trig == LINK_TRIG_IMMEDIATE && pre != 0u) || (uint32_t)n * (uint32_t)nsig > (uint32_t)LINK_CAPTURE_WORDS) {
        return LINK_NACK_OUT_OF_RANGE;
    }
    LINK_CRITICAL_BEGIN();
    S.cap_state = LINK_CAP_IDLE;
    S.cap_mask = mask;
    S.cap_nsig = nsig;
    S.cap_n = n;
    S.cap_pre = pre;
    S.cap_dec = dec;
    S.cap_div = 0u;
    S.cap_trig = trig;
    S.cap_thr = thr;
    S.cap_prev_valid = 0u;
    S.cap_w = 0u;
    S.cap_filled = 0u;
    S.cap_post = 0u;
    S.cap_total = 0u;
    S.cap_start = 0u;
    S.cap_tidx = 0u;
    S.cap_sp_changed = 0u;
    S.cap_state = LINK_CAP_ARMED;
    LINK_CRITICAL_END();
    return 0u;
}

static uint8_t cmd_capture_read(uint8_t *a, uint8_t *r)
{
    uint16_t start = get16(&a[0]);
    uint8_t want = a[2];
    uint16_t k, s, slot, fit;
    uint8_t j, o;
    if (S.cap_state == LINK_CAP_ARMED || S.cap_state == LINK_CAP_TRIGGERED) {
        return LINK_NACK_BUSY;
    }
    if (S.cap_state != LINK_CAP_DONE) {
        return LINK_NACK_WRONG_STATE;
    }
    if (start > S.cap_total) {
        return LINK_NACK_OUT_OF_RANGE;
    }
    fit = (uint16_t)((LINK_MAX_PAYLOAD - CAPREAD_HEADER) / (uint16_t)(2u * S.cap_nsig));
    k = (uint16_t)(S.cap_total - start);
    if (k > want) {
        k = want;
    }
    if (k > fit) {
        k = fit;
    }
    a[0] = S.cap_state;
    put16(&a[1], S.cap_total);
    put16(&a[3], S.cap_tidx);
    put16(&a[5], start);
    o = CAPREAD_HEADER;
    for (s = 0u; s < k; s++) {
        slot = (uint16_t)((uint16_t)(S.cap_start + start + s) % S.cap_n);
        for (j = 0u; j < S.cap_nsig; j++) {
            put16(&a[o], (uint16_t)cap_buf[(uint16_t)((uint16_t)(slot * S.cap_nsig) + j)]);
            o = (uint8_t)(o + 2u);
        }
    }
    *r = o;
    return 0u;
}

static uint8_t cmd_status(uint8_t *a, uint8_t *r)
{
    uint16_t ovf, drop;
    uint32_t up;
    a[0] = (uint8_t)app_signal(LINK_SIG_STATE);
    a[1] = (uint8_t)app_signal(LINK_SIG_FAULT);
    a[2] = S.cap_state;
    a[3] = S.tm_gen;
    put16(&a[4], S.crc_errors);
    LINK_CRITICAL_BEGIN();
    ovf = S.rx_overflows;
    drop = S.tm_dropped;
    up = S.uptime_ms;
    LINK_CRITICAL_END();
    put16(&a[6], ovf);
    put16(&a[8], drop);
    put32(&a[10], up);
    *r = 14u;
    return 0u;
}

static void dispatch(uint16_t fcrc)
{
    uint8_t n = tx_buf[1];
    uint8_t type = tx_buf[2];
    uint8_t seq = tx_buf[3];
    uint8_t *a = &tx_buf[4];
    uint8_t code = 0u, r = 0u, rtype, i;
    S.rx_valid = 1u;
    S.nack_armed = 1u;
    LINK_HOOK_FRAME(type, seq, a, n);
    if (S.rp_valid != 0u && type == S.rp_type && seq == S.rp_seq && fcrc == S.rp_crc && S.rp_len != NONE) {
        for (i = 0u; i < S.rp_len; i++) {
            a[i] = rp_data[i];
        }
        tx_seal(S.rp_rtype, seq, S.rp_len);
        return;
    }
    switch (type) {
    case LINK_CMD_HELLO:
        if (n != 0u) {
            code = LINK_NACK_MALFORMED;
            break;
        }
        a[0] = LINK_PROTO_MAJOR;
        a[1] = LINK_PROTO_MINOR;
        put32(&a[2], LINK_BUILD_ID);
        put32(&a[6], LINK_PROFILE_HASH);
        put32(&a[10], LINK_TABLE_HASH);
        a[14] = LINK_N_ENTRIES;
        a[15] = LINK_MAX_PAYLOAD;
        put16(&a[16], LINK_CAPTURE_WORDS);
        put16(&a[18], LINK_SAMPLE_HZ);
        r = 20u;
        break;
    case LINK_CMD_PARAM_INFO:
        code = (n != 1u) ? LINK_NACK_MALFORMED : cmd_param_info(a, &r);
        break;
    case LINK_CMD_PARAM_GET:
        code = cmd_param_get(a, n, &r);
        break;
    case LINK_CMD_PARAM_SET:
        if (n != 5u) {
            code = LINK_NACK_MALFORMED;
            break;
        }
        code = link_param_set(a[0], (int32_t)get32(&a[1]));
        if (code == 0u) {
            put32(&a[1], (uint32_t)store_get(a[0]));
            r = 5u;
        }
        break;
    case LINK_CMD_SET_SPEED:
        if (n != 4u) {
            code = LINK_NACK_MALFORMED;
            break;
        }
        code = link_param_set(LINK_ID_SPEED_SETPOINT, (int32_t)get32(&a[0]));
        if (code == 0u) {
            put32(&a[0], (uint32_t)store_get(LINK_ID_SPEED_SETPOINT));
            r = 4u;
        }
        break;
    case LINK_CMD_START:
    case LINK_CMD_STOP:
    case LINK_CMD_BRAKE:
    case LINK_CMD_FAULT_CLEAR:
        code = (n != 0u) ? LINK_NACK_MALFORMED : app_command(type, a, n);
        break;
    case LINK_CMD_SELECT_CONTROLLER:
        if (n != 1u) {
            code = LINK_NACK_MALFORMED;
            break;
        }
        code = link_param_set(LINK_ID_CONTROLLER, (int32_t)a[0]);
        if (code == 0u) {
            a[0] = (uint8_t)store_get(LINK_ID_CONTROLLER);
            r = 1u;
        }
        break;
    case LINK_CMD_TELEM_CONFIG:
        code = (n != 5u) ? LINK_NACK_MALFORMED : cmd_telem_config(a, &r);
        break;
    case LINK_CMD_CAPTURE_ARM:
        code = (n != 11u) ? LINK_NACK_MALFORMED : cmd_capture_arm(a);
        break;
    case LINK_CMD_CAPTURE_READ:
        code = (n != 3u) ? LINK_NACK_MALFORMED : cmd_capture_read(a, &r);
        break;
    case LINK_CMD_EEPROM_SAVE:
        if (n != 0u) {
            code = LINK_NACK_MALFORMED;
        } else if (drive_busy()) {
            code = LINK_NACK_WRONG_STATE;
        } else {
            code = link_eeprom_save();
        }
        break;
    case LINK_CMD_EEPROM_LOAD:
        if (n != 0u) {
            code = LINK_NACK_MALFORMED;
        } else if (drive_busy()) {
            code = LINK_NACK_WRONG_STATE;
        } else if (link_eeprom_load() != LINK_EE_OK) {
            code = LINK_NACK_EEPROM_ERROR;
        }
        break;
    case LINK_CMD_STATUS:
        code = (n != 0u) ? LINK_NACK_MALFORMED : cmd_status(a, &r);
        break;
    case LINK_CMD_HEARTBEAT:
        code = (n != 0u) ? LINK_NACK_MALFORMED : 0u;
        break;
    default:
        code = LINK_NACK_UNKNOWN_COMMAND;
        break;
    }
    if (code != 0u) {
        a[0] = type;
        a[1] = code;
        r = 2u;
        rtype = LINK_MSG_NACK;
    } else {
        rtype = (uint8_t)(type | LINK_ACK_BIT);
    }
    tx_seal(rtype, seq, r);
    S.rp_valid = 1u;
    S.rp_type = type;
    S.rp_seq = seq;
    S.rp_crc = fcrc;
    S.rp_rtype = rtype;
    if (r <= LINK_REPLAY_BYTES) {
        for (i = 0u; i < r; i++) {
            rp_data[i] = a[i];
        }
        S.rp_len = r;
    } else {
        S.rp_len = NONE;
    }
}

/* ---- board-initiated frames ---- */
static uint8_t send_event(void)
{
    uint8_t ev, code;
    if (S.ev_boot != 0u) {
        S.ev_boot = 0u;
        ev = LINK_EVENT_BOOT;
        code = S.ev_boot_code;
    } else if (S.ev_watchdog != 0u) {
        S.ev_watchdog = 0u;
        ev = LINK_EVENT_WATCHDOG;
        code = LINK_FAULT_LINK_LOST;
    } else if (S.ev_fault != 0u) {
        code = S.ev_fault;
        S.ev_fault = 0u;
        ev = LINK_EVENT_FAULT;
    } else {
        return 0u;
    }
    tx_buf[4] = ev;
    tx_buf[5] = code;
    tx_seal(LINK_MSG_EVENT, S.ev_counter, 2u);
    S.ev_counter++;
    return 1u;
}

void link_poll(void)
{
    uint8_t k, i;
    uint16_t fcrc = 0u;
    S.wd_armed = (uint8_t)(app_signal(LINK_SIG_STATE) == (int16_t)LINK_STATE_RUN);
    for (k = 0u; k < 8u; k++) {
        tx_drain();
        if (S.tx_len != 0u) {
            break;
        }
        if (S.nack_pending != 0u) {
            S.nack_pending = 0u;
            tx_buf[4] = S.nack_type;
            tx_buf[5] = LINK_NACK_BAD_CRC;
            tx_seal(LINK_MSG_NACK, S.nack_seq, 2u);
            continue;
        }
        if (rx_parse(&fcrc) != 0u) {
            dispatch(fcrc);
            continue;
        }
        if (S.nack_pending != 0u) {
            continue;
        }
        if (send_event() != 0u) {
            continue;
        }
        if (S.tm_ready != 0u) {
            for (i = 0u; i < S.tm_len; i++) {
                tx_buf[(uint8_t)(4u + i)] = tm_buf[i];
            }
            tx_seal(LINK_MSG_TELEMETRY, S.tm_gen, S.tm_len);
            S.tm_nsamp = 0u;
            S.tm_len = 0u;
            S.tm_ready = 0u;
            continue;
        }
        break;
    }
    /* again after dispatching: a start just executed arms the watchdog at once */
    S.wd_armed = (uint8_t)(app_signal(LINK_SIG_STATE) == (int16_t)LINK_STATE_RUN);
}

/* ---- time base: frame gap, watchdog ---- */
void link_tick_ms(void)
{
    S.uptime_ms++;
    if (S.rx_activity != 0u) {
        S.rx_activity = 0u;
        S.rx_gap_ms = 0u;
    } else if (S.rx_gap_ms < 255u) {
        S.rx_gap_ms++;
        if (S.rx_gap_ms == LINK_FRAME_GAP_MS) {
            S.rx_stale_head = S.rx_head;
            if (S.rx_activity == 0u) {   /* no byte slipped in since the check above */
                S.rx_stale = 1u;
            }
        }
    }
    if (S.wd_armed == 0u) {
        S.wd_ms = 0u;
    } else if (S.rx_valid != 0u) {
        S.rx_valid = 0u;
        S.wd_ms = 0u;
    } else {
        if (S.wd_ms != 0xFFFFu) {
            S.wd_ms++;
        }
        if ((int32_t)S.wd_ms >= (int32_t)link_params.link_timeout) {
            S.wd_armed = 0u;
            S.wd_ms = 0u;
            app_link_lost();
            S.ev_watchdog = 1u;
        }
    }
}

/* ---- per speed-loop sample: telemetry and capture ---- */
static void capture_sample(void)
{
    uint8_t fire = 0u, j, k;
    uint16_t base;
    int16_t sp;
    S.cap_div++;
    if (S.cap_div < S.cap_dec) {
        return;
    }
    S.cap_div = 0u;
    if (S.cap_state == LINK_CAP_ARMED) {
        switch (S.cap_trig) {
        case LINK_TRIG_IMMEDIATE:
            fire = 1u;
            break;
        case LINK_TRIG_SETPOINT_CHANGE:
            fire = S.cap_sp_changed;
            break;
        default:
            sp = app_signal(LINK_SIG_SPEED);
            if (S.cap_prev_valid != 0u) {
                if (S.cap_trig == LINK_TRIG_SPEED_RISING) {
                    fire = (uint8_t)(S.cap_prev < S.cap_thr && sp >= S.cap_thr);
                } else {
                    fire = (uint8_t)(S.cap_prev > S.cap_thr && sp <= S.cap_thr);
                }
            }
            S.cap_prev = sp;
            S.cap_prev_valid = 1u;
            break;
        }
        if (fire != 0u) {
            S.cap_tidx = (S.cap_filled < S.cap_pre) ? S.cap_filled : S.cap_pre;
            S.cap_post = 0u;
            S.cap_state = LINK_CAP_TRIGGERED;
        }
    }
    base = (uint16_t)(S.cap_w * (uint16_t)S.cap_nsig);
    k = 0u;
    for (j = 0u; j < LINK_N_SIGNALS; j++) {
        if ((S.cap_mask & (uint16_t)(1u << j)) != 0u) {
            cap_buf[(uint16_t)(base + k)] = app_signal(j);
            k++;
        }
    }
    S.cap_w++;
    if (S.cap_w >= S.cap_n) {
        S.cap_w = 0u;
    }
    if (S.cap_filled < S.cap_n) {
        S.cap_filled++;
    }
    if (S.cap_state == LINK_CAP_TRIGGERED) {
        S.cap_post++;
        if (S.cap_post >= (uint16_t)(S.cap_n - S.cap_pre)) {
            S.cap_total = (uint16_t)(S.cap_tidx + S.cap_post);
            S.cap_start = (uint16_t)((uint16_t)(S.cap_w + S.cap_n - S.cap_total) % S.cap_n);
            S.cap_state = LINK_CAP_DONE;
        }
    }
}

void link_sample(void)
{
    uint8_t j;
    if (S.tm_dec != 0u) {
        S.tm_div++;
        if (S.tm_div >= S.tm_dec) {
            S.tm_div = 0u;
            if (S.tm_ready != 0u) {
                if (S.tm_dropped != 0xFFFFu) {
                    S.tm_dropped++;
                }
            } else {
                if (S.tm_nsamp == 0u) {
                    put16(&tm_buf[0], S.tm_counter);
                    S.tm_len = TELEM_HEADER;
                }
                for (j = 0u; j < LINK_N_SIGNALS; j++) {
                    if ((S.tm_mask & (uint16_t)(1u << j)) != 0u) {
                        put16(&tm_buf[S.tm_len], (uint16_t)app_signal(j));
                        S.tm_len = (uint8_t)(S.tm_len + 2u);
                    }
                }
                S.tm_nsamp++;
                if (S.tm_nsamp >= S.tm_spf) {
                    S.tm_ready = 1u;
                }
            }
            S.tm_counter++;
        }
    }
    if (S.cap_state == LINK_CAP_ARMED || S.cap_state == LINK_CAP_TRIGGERED) {
        capture_sample();
    }
}

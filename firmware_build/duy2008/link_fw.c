/*
 * link_fw.c -- picdrive serial link, C side: COBS framing, CRC, dispatcher with ACK/NACK and
 * duplicate-SEQ replay, parameter store with range checks, EEPROM image, telemetry, triggered
 * capture, link-loss watchdog.
 * Rendered by picdrive.protocol.render_c() from host/picdrive/protocol.py.  DO NOT EDIT.
 * protocol 2.0, table hash 0x9E641D7AUL
 *
 * Written for an 8-bit core (PIC18, SDCC or XC8): no heap, no floating point (scales are
 * float32 bit patterns, only reported), no run-time multiplication or division (sizes are
 * built by additions; the compilers' multiply/divide helpers keep their operands in static RAM
 * and are not reentrant), data-space pointers, tables in flash indexed by byte offsets, and
 * no 32-bit arithmetic outside the parameter range checks.
 *
 * Contexts: link_rx_byte() (UART RX interrupt) only stores the byte in the ring and counts an
 * overflow; link_tick_ms() and link_sample() (speed-loop interrupt) touch no flash table; all
 * framing, CRC and dispatch run in link_poll() (main loop).
 */
#include <stddef.h>
#include "link_fw.h"


#ifndef LINK_CRITICAL_BEGIN
#define LINK_CRITICAL_BEGIN() do { extern void fw_lock(void); fw_lock(); } while (0)
#endif
#ifndef LINK_CRITICAL_END
#define LINK_CRITICAL_END() do { extern void fw_unlock(void); fw_unlock(); } while (0)
#endif
#ifndef LINK_HOOK_FRAME      /* test hook: called with every host command that passed the checks */
#define LINK_HOOK_FRAME(type, seq, payload, len) ((void)0)
#endif

#if (LINK_EE_BASE + LINK_EE_IMAGE_BYTES) > 256u
#error "EEPROM image does not fit 256 B at LINK_EE_BASE"
#endif

#define RX_MASK            ((uint8_t)(LINK_RX_RING - 1u))
#define SIG_ALL            0x07FFu
#define NONE               0xFFu
#define ROW                20u          /* bytes of a table row (= param_info reply head) */
#define EE_HEADER          8u
#define EE_DATA_BYTES      35u
#define TELEM_HEADER       2u
#define CAPREAD_HEADER     7u
#if 20 != 20
#error "row_of() multiplies by 20 with shifts"
#endif
#define PL                 3u                        /* payload offset in the frame body */
#define BODY_OVERHEAD      5u                        /* LEN, TYPE, SEQ, CRC high, CRC low */
#define A(i)               tx_buf[PL + (i)]
#define N_CMDS             17u

#if LINK_MAX_BODY > 253u
#error "one COBS block per frame: the body must stay below 254 bytes"
#endif

link_params_t link_params;

/* ---- the table (flash): rows of id, ctype, flags, unit, scale bits, min, max, default
 *      (little-endian: the param_info reply), then per entry the store offset, the size
 *      (bit 7: signed) and the name's offset in link_names ---- */
static const uint8_t link_rows[LINK_N_ENTRIES * ROW] = {
    0x00u, 0x04u, 0x01u, 0x01u, 0xEBu, 0xC9u, 0x18u, 0x3Eu, 0xEFu, 0xBBu, 0xFFu, 0xFFu, 0x11u, 0x44u, 0x00u, 0x00u, 0x00u, 0x00u, 0x00u, 0x00u,   /* speed_setpoint */
    0x01u, 0x01u, 0x03u, 0x0Cu, 0x00u, 0x00u, 0x80u, 0x3Fu, 0x00u, 0x00u, 0x00u, 0x00u, 0x01u, 0x00u, 0x00u, 0x00u, 0x01u, 0x00u, 0x00u, 0x00u,   /* controller */
    0x02u, 0x04u, 0x03u, 0x01u, 0xEBu, 0xC9u, 0x18u, 0x3Eu, 0x00u, 0x00u, 0x00u, 0x00u, 0xFFu, 0x7Fu, 0x00u, 0x00u, 0x00u, 0x00u, 0x00u, 0x00u,   /* premise_low */
    0x03u, 0x04u, 0x03u, 0x01u, 0xEBu, 0xC9u, 0x18u, 0x3Eu, 0x00u, 0x00u, 0x00u, 0x00u, 0xFFu, 0x7Fu, 0x00u, 0x00u, 0x11u, 0x44u, 0x00u, 0x00u,   /* premise_high */
    0x04u, 0x04u, 0x03u, 0x00u, 0x00u, 0x00u, 0x80u, 0x38u, 0x00u, 0x00u, 0x00u, 0x00u, 0xFFu, 0x7Fu, 0x00u, 0x00u, 0x94u, 0x51u, 0x00u, 0x00u,   /* setpoint_weight */
    0x05u, 0x04u, 0x03u, 0x03u, 0x00u, 0x00u, 0x80u, 0x3Bu, 0xD8u, 0xD3u, 0xFFu, 0xFFu, 0x00u, 0x00u, 0x00u, 0x00u, 0xD8u, 0xD3u, 0xFFu, 0xFFu,   /* u_min */
    0x06u, 0x04u, 0x03u, 0x03u, 0x00u, 0x00u, 0x80u, 0x3Bu, 0x00u, 0x00u, 0x00u, 0x00u, 0x28u, 0x2Cu, 0x00u, 0x00u, 0x28u, 0x2Cu, 0x00u, 0x00u,   /* u_max */
    0x07u, 0x04u, 0x03u, 0x04u, 0x00u, 0x00u, 0xA0u, 0x3Bu, 0x00u, 0x00u, 0x00u, 0x00u, 0xFFu, 0x03u, 0x00u, 0x00u, 0x33u, 0x01u, 0x00u, 0x00u,   /* current_limit */
    0x08u, 0x03u, 0x03u, 0x02u, 0x30u, 0x35u, 0x15u, 0x43u, 0x00u, 0x00u, 0x00u, 0x00u, 0xFFu, 0xFFu, 0x00u, 0x00u, 0x00u, 0x00u, 0x00u, 0x00u,   /* accel_limit */
    0x09u, 0x03u, 0x03u, 0x09u, 0x00u, 0x00u, 0x80u, 0x3Fu, 0x14u, 0x00u, 0x00u, 0x00u, 0x60u, 0xEAu, 0x00u, 0x00u, 0xF4u, 0x01u, 0x00u, 0x00u,   /* link_timeout */
    0x0Au, 0x03u, 0x03u, 0x09u, 0x00u, 0x00u, 0x80u, 0x3Fu, 0x0Au, 0x00u, 0x00u, 0x00u, 0x60u, 0xEAu, 0x00u, 0x00u, 0xF4u, 0x01u, 0x00u, 0x00u,   /* stall_timeout */
    0x20u, 0x04u, 0x04u, 0x01u, 0xEBu, 0xC9u, 0x18u, 0x3Eu, 0x00u, 0x80u, 0xFFu, 0xFFu, 0xFFu, 0x7Fu, 0x00u, 0x00u, 0x00u, 0x00u, 0x00u, 0x00u,   /* speed */
    0x21u, 0x04u, 0x04u, 0x01u, 0xEBu, 0xC9u, 0x18u, 0x3Eu, 0x00u, 0x80u, 0xFFu, 0xFFu, 0xFFu, 0x7Fu, 0x00u, 0x00u, 0x00u, 0x00u, 0x00u, 0x00u,   /* setpoint */
    0x22u, 0x04u, 0x04u, 0x03u, 0x00u, 0x00u, 0x80u, 0x3Bu, 0x00u, 0x80u, 0xFFu, 0xFFu, 0xFFu, 0x7Fu, 0x00u, 0x00u, 0x00u, 0x00u, 0x00u, 0x00u,   /* voltage */
    0x23u, 0x04u, 0x04u, 0x04u, 0x00u, 0x00u, 0xA0u, 0x3Bu, 0x01u, 0xFCu, 0xFFu, 0xFFu, 0xFFu, 0x03u, 0x00u, 0x00u, 0x00u, 0x00u, 0x00u, 0x00u,   /* current */
    0x24u, 0x04u, 0x04u, 0x03u, 0x00u, 0x00u, 0x80u, 0x3Bu, 0x00u, 0x80u, 0xFFu, 0xFFu, 0xFFu, 0x7Fu, 0x00u, 0x00u, 0x00u, 0x00u, 0x00u, 0x00u,   /* integrator */
    0x25u, 0x04u, 0x04u, 0x0Au, 0x00u, 0x00u, 0x80u, 0x3Fu, 0x30u, 0xF8u, 0xFFu, 0xFFu, 0xD0u, 0x07u, 0x00u, 0x00u, 0x00u, 0x00u, 0x00u, 0x00u,   /* duty */
    0x26u, 0x04u, 0x04u, 0x0Bu, 0x00u, 0x00u, 0x80u, 0x3Fu, 0x00u, 0x80u, 0xFFu, 0xFFu, 0xFFu, 0x7Fu, 0x00u, 0x00u, 0x00u, 0x00u, 0x00u, 0x00u,   /* hall */
    0x27u, 0x04u, 0x04u, 0x0Cu, 0x00u, 0x00u, 0x80u, 0x3Fu, 0x00u, 0x80u, 0xFFu, 0xFFu, 0xFFu, 0x7Fu, 0x00u, 0x00u, 0x00u, 0x00u, 0x00u, 0x00u,   /* state */
    0x28u, 0x04u, 0x04u, 0x0Bu, 0x00u, 0x00u, 0x80u, 0x3Fu, 0x00u, 0x80u, 0xFFu, 0xFFu, 0xFFu, 0x7Fu, 0x00u, 0x00u, 0x00u, 0x00u, 0x00u, 0x00u,   /* fault */
    0x29u, 0x04u, 0x04u, 0x00u, 0x00u, 0x00u, 0x80u, 0x39u, 0x00u, 0x00u, 0x00u, 0x00u, 0x00u, 0x10u, 0x00u, 0x00u, 0x00u, 0x10u, 0x00u, 0x00u,   /* mu1 */
    0x2Au, 0x04u, 0x04u, 0x0Au, 0x00u, 0x00u, 0x80u, 0x3Fu, 0x00u, 0x80u, 0xFFu, 0xFFu, 0xFFu, 0x7Fu, 0x00u, 0x00u, 0x00u, 0x00u, 0x00u, 0x00u,   /* position */
    0x40u, 0x04u, 0x03u, 0x05u, 0x00u, 0x00u, 0x80u, 0x38u, 0x00u, 0x80u, 0xFFu, 0xFFu, 0xFFu, 0x7Fu, 0x00u, 0x00u, 0x64u, 0x21u, 0x00u, 0x00u,   /* rule1_kp */
    0x41u, 0x04u, 0x03u, 0x06u, 0x00u, 0x00u, 0x7Au, 0x3Bu, 0x00u, 0x80u, 0xFFu, 0xFFu, 0xFFu, 0x7Fu, 0x00u, 0x00u, 0x67u, 0x29u, 0x00u, 0x00u,   /* rule1_ki */
    0x42u, 0x04u, 0x03u, 0x07u, 0x6Fu, 0x12u, 0x83u, 0x32u, 0x00u, 0x80u, 0xFFu, 0xFFu, 0xFFu, 0x7Fu, 0x00u, 0x00u, 0x00u, 0x00u, 0x00u, 0x00u,   /* rule1_kd */
    0x43u, 0x04u, 0x03u, 0x08u, 0xCDu, 0xCCu, 0xCCu, 0x39u, 0x00u, 0x80u, 0xFFu, 0xFFu, 0xFFu, 0x7Fu, 0x00u, 0x00u, 0x89u, 0x34u, 0x00u, 0x00u,   /* rule1_kc */
    0x44u, 0x04u, 0x03u, 0x05u, 0x00u, 0x00u, 0x80u, 0x38u, 0x00u, 0x80u, 0xFFu, 0xFFu, 0xFFu, 0x7Fu, 0x00u, 0x00u, 0x64u, 0x21u, 0x00u, 0x00u,   /* rule2_kp */
    0x45u, 0x04u, 0x03u, 0x06u, 0x00u, 0x00u, 0x7Au, 0x3Bu, 0x00u, 0x80u, 0xFFu, 0xFFu, 0xFFu, 0x7Fu, 0x00u, 0x00u, 0x67u, 0x29u, 0x00u, 0x00u,   /* rule2_ki */
    0x46u, 0x04u, 0x03u, 0x07u, 0x6Fu, 0x12u, 0x83u, 0x32u, 0x00u, 0x80u, 0xFFu, 0xFFu, 0xFFu, 0x7Fu, 0x00u, 0x00u, 0x00u, 0x00u, 0x00u, 0x00u,   /* rule2_kd */
    0x47u, 0x04u, 0x03u, 0x08u, 0xCDu, 0xCCu, 0xCCu, 0x39u, 0x00u, 0x80u, 0xFFu, 0xFFu, 0xFFu, 0x7Fu, 0x00u, 0x00u, 0x89u, 0x34u, 0x00u, 0x00u,   /* rule2_kc */
};
static const uint8_t link_ids[LINK_N_ENTRIES] = { LINK_ID_SPEED_SETPOINT, LINK_ID_CONTROLLER, LINK_ID_PREMISE_LOW, LINK_ID_PREMISE_HIGH, LINK_ID_SETPOINT_WEIGHT, LINK_ID_U_MIN, LINK_ID_U_MAX, LINK_ID_CURRENT_LIMIT, LINK_ID_ACCEL_LIMIT, LINK_ID_LINK_TIMEOUT, LINK_ID_STALL_TIMEOUT, LINK_ID_SPEED, LINK_ID_SETPOINT, LINK_ID_VOLTAGE, LINK_ID_CURRENT, LINK_ID_INTEGRATOR, LINK_ID_DUTY, LINK_ID_HALL, LINK_ID_STATE, LINK_ID_FAULT, LINK_ID_MU1, LINK_ID_POSITION, LINK_ID_RULE1_KP, LINK_ID_RULE1_KI, LINK_ID_RULE1_KD, LINK_ID_RULE1_KC, LINK_ID_RULE2_KP, LINK_ID_RULE2_KI, LINK_ID_RULE2_KD, LINK_ID_RULE2_KC };
static const uint8_t link_index_of[72] = { 0u, 1u, 2u, 3u, 4u, 5u, 6u, 7u, 8u, 9u, 10u, NONE, NONE, NONE, NONE, NONE, NONE, NONE, NONE, NONE, NONE, NONE, NONE, NONE, NONE, NONE, NONE, NONE, NONE, NONE, NONE, NONE, 11u, 12u, 13u, 14u, 15u, 16u, 17u, 18u, 19u, 20u, 21u, NONE, NONE, NONE, NONE, NONE, NONE, NONE, NONE, NONE, NONE, NONE, NONE, NONE, NONE, NONE, NONE, NONE, NONE, NONE, NONE, NONE, 22u, 23u, 24u, 25u, 26u, 27u, 28u, 29u };   /* by id */
static const uint8_t link_off[LINK_N_ENTRIES] = { (uint8_t)offsetof(link_params_t, speed_setpoint), (uint8_t)offsetof(link_params_t, controller), (uint8_t)offsetof(link_params_t, premise_low), (uint8_t)offsetof(link_params_t, premise_high), (uint8_t)offsetof(link_params_t, setpoint_weight), (uint8_t)offsetof(link_params_t, u_min), (uint8_t)offsetof(link_params_t, u_max), (uint8_t)offsetof(link_params_t, current_limit), (uint8_t)offsetof(link_params_t, accel_limit), (uint8_t)offsetof(link_params_t, link_timeout), (uint8_t)offsetof(link_params_t, stall_timeout), NONE, NONE, NONE, NONE, NONE, NONE, NONE, NONE, NONE, NONE, NONE, (uint8_t)offsetof(link_params_t, rule1_kp), (uint8_t)offsetof(link_params_t, rule1_ki), (uint8_t)offsetof(link_params_t, rule1_kd), (uint8_t)offsetof(link_params_t, rule1_kc), (uint8_t)offsetof(link_params_t, rule2_kp), (uint8_t)offsetof(link_params_t, rule2_ki), (uint8_t)offsetof(link_params_t, rule2_kd), (uint8_t)offsetof(link_params_t, rule2_kc) };
static const uint8_t link_size[LINK_N_ENTRIES] = { 0x82u, 0x01u, 0x82u, 0x82u, 0x82u, 0x82u, 0x82u, 0x82u, 0x02u, 0x02u, 0x02u, 0x82u, 0x82u, 0x82u, 0x82u, 0x82u, 0x82u, 0x82u, 0x82u, 0x82u, 0x82u, 0x82u, 0x82u, 0x82u, 0x82u, 0x82u, 0x82u, 0x82u, 0x82u, 0x82u };
static const uint8_t link_name_at[LINK_N_ENTRIES + 1u] = { 0u, 14u, 24u, 35u, 47u, 62u, 67u, 72u, 85u, 96u, 108u, 121u, 126u, 134u, 141u, 148u, 158u, 162u, 166u, 171u, 176u, 179u, 187u, 195u, 203u, 211u, 219u, 227u, 235u, 243u, 251u };
static const char link_names[] = "speed_setpointcontrollerpremise_lowpremise_highsetpoint_weightu_minu_maxcurrent_limitaccel_limitlink_timeoutstall_timeoutspeedsetpointvoltagecurrentintegratordutyhallstatefaultmu1positionrule1_kprule1_kirule1_kdrule1_kcrule2_kprule2_kirule2_kdrule2_kc";
static const uint8_t link_hello[20] = { LINK_PROTO_MAJOR, LINK_PROTO_MINOR, (uint8_t)LINK_BUILD_ID, (uint8_t)(LINK_BUILD_ID >> 8u), (uint8_t)(LINK_BUILD_ID >> 16u), (uint8_t)(LINK_BUILD_ID >> 24u), (uint8_t)LINK_PROFILE_HASH, (uint8_t)(LINK_PROFILE_HASH >> 8u), (uint8_t)(LINK_PROFILE_HASH >> 16u), (uint8_t)(LINK_PROFILE_HASH >> 24u), (uint8_t)LINK_TABLE_HASH, (uint8_t)(LINK_TABLE_HASH >> 8u), (uint8_t)(LINK_TABLE_HASH >> 16u), (uint8_t)(LINK_TABLE_HASH >> 24u), LINK_N_ENTRIES, LINK_MAX_PAYLOAD, (uint8_t)LINK_HELLO_CAPTURE_WORDS, (uint8_t)(LINK_HELLO_CAPTURE_WORDS >> 8u), (uint8_t)LINK_SAMPLE_HZ, (uint8_t)(LINK_SAMPLE_HZ >> 8u) };
#if LINK_WITH_EEPROM
static const uint8_t link_persisted[18] = { 1u, 2u, 3u, 4u, 5u, 6u, 7u, 8u, 9u, 10u, 22u, 23u, 24u, 25u, 26u, 27u, 28u, 29u };   /* entry indices */
static const uint8_t link_ee_head[EE_HEADER] = { 0x50u, 0x44u, 0x01u, (uint8_t)LINK_TABLE_HASH, (uint8_t)(LINK_TABLE_HASH >> 8u), (uint8_t)(LINK_TABLE_HASH >> 16u), (uint8_t)(LINK_TABLE_HASH >> 24u), EE_DATA_BYTES };
#endif

/* ---- buffers ---- */
static uint8_t rx_ring[LINK_RX_RING];          /* written by link_rx_byte only */
static uint8_t tx_buf[LINK_MAX_BODY];          /* frame body: decoded command, then the reply being sent */
static uint8_t tm_buf[LINK_MAX_PAYLOAD];       /* telemetry payload being filled by link_sample */
static uint8_t rp_data[LINK_REPLAY_BYTES];     /* last short reply, for duplicate-SEQ replay */
#if LINK_WITH_CAPTURE
static uint8_t cap_buf[2u * LINK_CAPTURE_WORDS]; /* capture ring, sample-major, int16 little-endian: byte
                                                  * indices, so no index is scaled by a multiply helper */
#endif
static union { int32_t l; uint8_t b[4]; } V;   /* the value being moved (main loop only) */

/* ---- scalar state ---- */
static struct {
    /* receive: the RX interrupt owns rx_head and rx_ovf_isr (single bytes), the main loop the rest */
    volatile uint8_t rx_head;
    volatile uint8_t rx_tail;
    volatile uint8_t rx_ovf_isr;       /* bytes dropped, wraps; the main loop accumulates */
    uint8_t rx_ovf_seen;
    uint8_t rx_scan;                   /* first ring byte not yet searched for a delimiter */
    uint8_t rx_skip;                   /* discard up to the next delimiter */
    volatile uint8_t rx_valid;         /* a host command arrived (main sets, tick clears: watchdog) */
    uint16_t rx_overflows;
    uint16_t crc_errors;
    uint8_t nack_armed;                /* one BAD_CRC NACK per valid frame */
    uint8_t nack_pending;
    uint8_t nack_type;
    uint8_t nack_seq;
    uint8_t n;                         /* argument bytes of the command, then reply bytes */
    uint8_t crc_hi;                    /* CRC state (main loop): in S, so in one bank with the rest */
    uint8_t crc_lo;
    uint8_t crc_x;
    uint8_t ee_off;                    /* next EEPROM image byte */
    /* transmit: COBS-encoded on the fly from tx_buf */
    uint8_t tx_len;                    /* body bytes; 0 = free */
    uint8_t tx_pos;
    uint8_t tx_run;
    uint8_t tx_state;
    /* replay */
    uint8_t rp_valid;
    uint8_t rp_type;
    uint8_t rp_seq;
    uint8_t rp_rtype;
    uint8_t rp_len;                    /* NONE: reply too long to store (read-only command) */
    uint8_t rp_crc0;
    uint8_t rp_crc1;
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
    volatile uint16_t tm_dropped;
    uint8_t tm_spf;
    uint8_t tm_gen;
    struct {                           /* restarted by telem_config */
        uint16_t div;
        uint16_t counter;
        uint8_t nsamp;
        uint8_t len;
    } tr;
    /* capture */
    volatile uint8_t cap_state;
    volatile uint8_t cap_sp_changed;
    uint8_t cap_nsig;
    uint8_t cap_trig;
    uint16_t cap_mask;
    uint16_t cap_n;
    uint16_t cap_bytes;                /* 2 cap_n cap_nsig, built by additions at arm time */
    uint16_t cap_pre;
    uint16_t cap_dec;
    int16_t cap_thr;
    struct {                           /* restarted by capture_arm */
        uint16_t div;
        uint16_t w;                    /* next sample slot */
        uint16_t wi;                   /* its byte index in cap_buf */
        uint16_t filled;
        uint16_t post;
        uint16_t total;
        uint16_t start;
        uint16_t tidx;
        int16_t prev;
        uint8_t prev_valid;
    } cr;
} S;

/* ---- little helpers (offsets into tx_buf) ---- */
/* o: constant offsets, so the compiler addresses tx_buf directly */
#define put16(o, v) do { uint16_t v_ = (v); tx_buf[(o)] = (uint8_t)v_; tx_buf[(o) + 1u] = (uint8_t)(v_ >> 8); } while (0)
#define get16(o) ((uint16_t)((uint16_t)tx_buf[(o)] | (uint16_t)((uint16_t)tx_buf[(o) + 1u] << 8)))

static void mcopy(LINK_DATA uint8_t *d, const LINK_DATA uint8_t *src, uint8_t n)   /* RAM to RAM */
{
    while (n != 0u) {
        *d = *src;
        d++;
        src++;
        n--;
    }
}

static void mzero(LINK_DATA uint8_t *d, uint8_t n)
{
    while (n != 0u) {
        *d = 0u;
        d++;
        n--;
    }
}

static void put_v(uint8_t o) LINK_WPARAM           /* V, 4 bytes little-endian */
{
    mcopy(&tx_buf[o], V.b, 4u);
}

static void get_v(uint8_t o) LINK_WPARAM
{
    mcopy(V.b, &tx_buf[o], 4u);
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

/* CRC-16/CCITT-FALSE (poly 0x1021) byte-wise without a table, on two bytes of state: 8-bit
 * shifts and XORs only (a shift form needs no 512 B table and no 16-bit arithmetic) */
#define crc_hi S.crc_hi
#define crc_lo S.crc_lo
#define crc_x S.crc_x
#define CRC_INIT() do { crc_hi = 0xFFu; crc_lo = 0xFFu; } while (0)

static void crc_byte(uint8_t b) LINK_WPARAM
{
    crc_x = (uint8_t)(crc_hi ^ b);
    crc_x = (uint8_t)(crc_x ^ (uint8_t)(crc_x >> 4));
    crc_hi = (uint8_t)(crc_lo ^ (uint8_t)(crc_x >> 3) ^ (uint8_t)(crc_x << 4));
    crc_lo = (uint8_t)(crc_x ^ (uint8_t)(crc_x << 5));
}
#define CRC_STEP(b) crc_byte(b)

uint16_t link_crc16(const uint8_t *p, uint8_t n)
{
    CRC_INIT();
    while (n != 0u) {
        CRC_STEP(*p);
        p++;
        n--;
    }
    return (uint16_t)((uint16_t)((uint16_t)crc_hi << 8) | crc_lo);
}

/* CRC of tx_buf[0..n-1] into crc_hi, crc_lo */
static void body_crc(uint8_t n) LINK_WPARAM
{
    uint8_t i;
    CRC_INIT();
    for (i = 0u; i < n; i++) {
        CRC_STEP(tx_buf[i]);
    }
}

/* ---- parameter store: table-driven, no switch per parameter or type ---- */
static uint8_t entry_index(uint8_t id) LINK_WPARAM   /* one flash read, no search */
{
    return (id < (uint8_t)sizeof link_index_of) ? link_index_of[id] : NONE;
}

static uint16_t row_of(uint8_t idx) LINK_WPARAM    /* idx * 20, by shifts */
{
    uint16_t o = (uint16_t)((uint16_t)idx << 2);
    return (uint16_t)(o + (uint16_t)(o << 2));
}

static void row_v(uint16_t o)          /* V = the int32 at link_rows[o] */
{
    uint8_t k;
    for (k = 0u; k < 4u; k++) {
        V.b[k] = link_rows[(uint16_t)(o + k)];
    }
}

static void sign_extend(uint8_t sz) LINK_WPARAM    /* V.b[0..n-1] hold a value of size code sz */
{
    uint8_t n = (uint8_t)(sz & 0x7Fu), fill = 0u, k;
    if ((sz & 0x80u) != 0u && (V.b[n - 1u] & 0x80u) != 0u) {
        fill = 0xFFu;
    }
    for (k = n; k < 4u; k++) {
        V.b[k] = fill;
    }
}

static void store_get_at(uint8_t idx) LINK_WPARAM  /* V = the parameter's value */
{
    LINK_DATA uint8_t *p = (LINK_DATA uint8_t *)&link_params;
    uint8_t off = link_off[idx], sz = link_size[idx], k;
    for (k = 0u; k < (uint8_t)(sz & 0x7Fu); k++) {
        V.b[k] = p[(uint8_t)(off + k)];
    }
    sign_extend(sz);
}

static void store_put_at(uint8_t idx) LINK_WPARAM  /* the parameter = V (already range-checked) */
{
    LINK_DATA uint8_t *p = (LINK_DATA uint8_t *)&link_params;
    uint8_t off = link_off[idx], sz = (uint8_t)(link_size[idx] & 0x7Fu), k;
    LINK_CRITICAL_BEGIN();
    for (k = 0u; k < sz; k++) {
        p[(uint8_t)(off + k)] = V.b[k];
    }
    LINK_CRITICAL_END();
}

static void value_at(uint8_t idx) LINK_WPARAM      /* V = parameter or signal */
{
    if (link_off[idx] == NONE) {
        int16_t v = app_signal((uint8_t)(link_ids[idx] - LINK_SIGNAL_BASE_ID));
        V.b[0] = (uint8_t)v;
        V.b[1] = (uint8_t)((uint16_t)v >> 8);
        sign_extend(link_size[idx]);
    } else {
        store_get_at(idx);
    }
}

static uint8_t in_range(uint8_t idx) LINK_WPARAM   /* V within the entry's [min, max] */
{
    int32_t v = V.l, lo, hi;
    uint16_t o = row_of(idx);
    row_v((uint16_t)(o + 8u));
    lo = V.l;
    row_v((uint16_t)(o + 12u));
    hi = V.l;
    V.l = v;
    return (uint8_t)(v >= lo && v <= hi);
}

int32_t link_param_get(uint8_t id)
{
    uint8_t i = entry_index(id);
    if (i == NONE) {
        return 0;
    }
    value_at(i);
    return V.l;
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

static uint8_t set_v(uint8_t id) LINK_WPARAM       /* write V to entry id: 0 or a NACK code */
{
    uint8_t i = entry_index(id);
    if (i == NONE) {
        return LINK_NACK_UNKNOWN_PARAM;
    }
    if ((link_rows[(uint16_t)(row_of(i) + 2u)] & LINK_FLAG_WRITABLE) == 0u) {
        return LINK_NACK_READ_ONLY;
    }
    if (!in_range(i)) {
        return LINK_NACK_OUT_OF_RANGE;
    }
    store_put_at(i);
    if (id == LINK_ID_SPEED_SETPOINT) {
        S.cap_sp_changed = 1u;
    }
    app_param_changed(id);
    return 0u;
}

uint8_t link_param_set(uint8_t id, int32_t raw)
{
    V.l = raw;
    return set_v(id);
}

/* ---- EEPROM image ---- */
#if LINK_WITH_EEPROM
static uint8_t ee_rd(uint8_t a) LINK_WPARAM
{
    return app_eeprom_read((uint8_t)(LINK_EE_BASE + a));
}

static void ee_crc(uint8_t n) LINK_WPARAM           /* into crc_hi, crc_lo */
{
    uint8_t a;
    CRC_INIT();
    for (a = 0u; a < n; a++) {
        CRC_STEP(ee_rd(a));
    }
}

#define ee_off S.ee_off

static void ee_put(uint8_t b) LINK_WPARAM          /* write the next image byte, CRC it */
{
    app_eeprom_write((uint8_t)(LINK_EE_BASE + ee_off), b);
    ee_off++;
    CRC_STEP(b);
}

uint8_t link_eeprom_save(void)
{
    uint8_t i, k, n, idx, hi, lo;
    ee_off = 0u;
    CRC_INIT();
    for (k = 0u; k < EE_HEADER; k++) {
        ee_put(link_ee_head[k]);
    }
    for (i = 0u; i < (uint8_t)sizeof link_persisted; i++) {
        idx = link_persisted[i];
        n = (uint8_t)(link_size[idx] & 0x7Fu);
        store_get_at(idx);
        for (k = 0u; k < n; k++) {
            ee_put(V.b[k]);
        }
    }
    hi = crc_hi;
    lo = crc_lo;
    ee_put(hi);
    ee_put(lo);
    /* read-back verify: the image with its CRC leaves 0 (CRC-16 catches any 1-3 bad bits), and
     * the CRC bytes are the ones computed from the store */
    ee_crc(ee_off);
    if ((crc_hi | crc_lo) != 0u || ee_rd((uint8_t)(ee_off - 2u)) != hi || ee_rd((uint8_t)(ee_off - 1u)) != lo) {
        return LINK_NACK_EEPROM_ERROR;
    }
    return 0u;
}

/* V = the persisted value at image offset off of entry idx */
static void ee_value(uint8_t off, uint8_t idx)
{
    uint8_t sz = link_size[idx], k;
    for (k = 0u; k < (uint8_t)(sz & 0x7Fu); k++) {
        V.b[k] = ee_rd((uint8_t)(off + k));
    }
    sign_extend(sz);
}

uint8_t link_eeprom_load(void)
{
    uint8_t off, i, k, idx, pass;
    if (ee_rd(0u) != link_ee_head[0] || ee_rd(1u) != link_ee_head[1]) {
        return LINK_EE_BLANK;
    }
    for (k = 2u; k < EE_HEADER; k++) {
        if (ee_rd(k) != link_ee_head[k]) {
            return LINK_EE_OTHER_BUILD;
        }
    }
    off = (uint8_t)(EE_HEADER + EE_DATA_BYTES);
    ee_crc(off);
    if (ee_rd(off) != crc_hi || ee_rd((uint8_t)(off + 1u)) != crc_lo) {
        return LINK_EE_CORRUPT;
    }
    /* pass 0: every value in range, or nothing is loaded; pass 1: store */
    for (pass = 0u; pass < 2u; pass++) {
        off = EE_HEADER;
        for (i = 0u; i < (uint8_t)sizeof link_persisted; i++) {
            idx = link_persisted[i];
            ee_value(off, idx);
            if (pass == 0u) {
                if (!in_range(idx)) {
                    return LINK_EE_CORRUPT;
                }
            } else {
                store_put_at(idx);
            }
            off = (uint8_t)(off + (uint8_t)(link_size[idx] & 0x7Fu));
        }
    }
    for (i = 0u; i < (uint8_t)sizeof link_persisted; i++) {
        app_param_changed(link_ids[link_persisted[i]]);
    }
    return LINK_EE_OK;
}
#else  /* generated without EEPROM persistence: nothing to load, saving is refused */
uint8_t link_eeprom_save(void)
{
    return LINK_NACK_EEPROM_ERROR;
}

uint8_t link_eeprom_load(void)
{
    return LINK_EE_BLANK;
}
#endif

/* ---- init, events ---- */
void link_init(void)
{
    uint8_t i;
    mzero((LINK_DATA uint8_t *)&S, (uint8_t)sizeof S);
    for (i = 0u; i < LINK_N_ENTRIES; i++) {
        if (link_off[i] != NONE) {
            row_v((uint16_t)(row_of(i) + 16u));
            store_put_at(i);
        }
    }
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

/* ---- receive: the interrupt only stores the byte ---- */
void link_rx_byte(uint8_t b) LINK_WPARAM
{
    uint8_t h = S.rx_head;
    uint8_t next = (uint8_t)((uint8_t)(h + 1u) & RX_MASK);
    if (next == S.rx_tail) {
        S.rx_ovf_isr++;
    } else {
        rx_ring[h] = b;
        S.rx_head = next;
    }
}

/* COBS-decode ring bytes [rx_tail, end) into tx_buf; the frame length, or 0 if malformed */
static uint8_t rx_decode(uint8_t end) LINK_WPARAM
{
    uint8_t t = S.rx_tail, o = 0u, run = 0u, zero = 0u, b;
    while (t != end) {
        b = rx_ring[t];
        t = (uint8_t)((uint8_t)(t + 1u) & RX_MASK);
        if (run == 0u) {               /* a code byte: the implied zero of the block before */
            if (zero != 0u) {
                if (o >= LINK_MAX_BODY) {
                    return 0u;
                }
                tx_buf[o] = 0u;
                o++;
            }
            run = (uint8_t)(b - 1u);
            zero = 1u;
        } else {
            if (o >= LINK_MAX_BODY) {
                return 0u;
            }
            tx_buf[o] = b;
            o++;
            run--;
        }
    }
    return (run == 0u) ? o : 0u;       /* a block cut short: malformed */
}

/* Next complete frame that passes the checks: its body is in tx_buf (tx_buf is free while a
 * command is dispatched), its length is returned; 0 when none. */
static uint8_t rx_frame(void)
{
    uint8_t h, n, end;
    for (;;) {
        h = S.rx_head;
        if (S.rx_ovf_isr != S.rx_ovf_seen) {   /* bytes were lost: drop what is here */
            n = (uint8_t)(S.rx_ovf_isr - S.rx_ovf_seen);
            S.rx_ovf_seen = (uint8_t)(S.rx_ovf_seen + n);
            S.rx_overflows = (uint16_t)(S.rx_overflows + n);
            if (S.rx_overflows < n) {  /* saturate */
                S.rx_overflows = 0xFFFFu;
            }
            S.rx_tail = h;
            S.rx_scan = h;
            S.rx_skip = 1u;
            return 0u;
        }
        end = S.rx_scan;
        while (end != h && rx_ring[end] != 0u) {
            end = (uint8_t)((uint8_t)(end + 1u) & RX_MASK);
        }
        if (end == h) {                /* no delimiter yet */
            S.rx_scan = end;
            if ((uint8_t)((uint8_t)(h - S.rx_tail) & RX_MASK) == RX_MASK) {
                S.rx_tail = h;         /* a full ring without a delimiter: garbage */
                S.rx_skip = 1u;
            }
            return 0u;
        }
        n = 0u;
        if (S.rx_skip == 0u && end != S.rx_tail) {
            n = rx_decode(end);
            if (n >= BODY_OVERHEAD) {
                body_crc(n);           /* over the CRC too: a good frame leaves 0 */
            }
            if (n < BODY_OVERHEAD || (uint8_t)(tx_buf[0] + BODY_OVERHEAD) != n || (crc_hi | crc_lo) != 0u) {
                if (S.crc_errors != 0xFFFFu) {
                    S.crc_errors++;
                }
                if (S.nack_armed != 0u && n >= PL) {
                    S.nack_armed = 0u;
                    S.nack_pending = 1u;
                    S.nack_type = tx_buf[1];
                    S.nack_seq = tx_buf[2];
                }
                n = 0u;
            }
        }
        S.rx_skip = 0u;
        end = (uint8_t)((uint8_t)(end + 1u) & RX_MASK);
        S.rx_tail = end;
        S.rx_scan = end;
        if (n != 0u) {
            return n;
        }
    }
}

/* ---- transmit: body in tx_buf, COBS-encoded byte by byte as the UART queue has room ---- */
static void tx_seal(uint8_t type, uint8_t seq, uint8_t len)
{
    tx_buf[0] = len;
    tx_buf[1] = type;
    tx_buf[2] = seq;
    len = (uint8_t)(len + PL);
    body_crc(len);
    tx_buf[len] = crc_hi;
    tx_buf[(uint8_t)(len + 1u)] = crc_lo;
    S.tx_len = (uint8_t)(len + 2u);
    S.tx_pos = 0u;
    S.tx_state = 1u;
}

static void tx_drain(void)
{
    uint8_t room, k;
    if (S.tx_len == 0u) {
        return;
    }
    room = app_tx_free();
    while (room != 0u) {
        if (S.tx_state == 1u) {        /* a block: its code is 1 + the non-zero bytes up to the next zero */
            k = S.tx_pos;
            while (k < S.tx_len && tx_buf[k] != 0u) {
                k++;
            }
            S.tx_run = (uint8_t)(k - S.tx_pos);
            app_tx_byte((uint8_t)(S.tx_run + 1u));
            S.tx_state = 2u;
        } else if (S.tx_state == 2u) {
            if (S.tx_run != 0u) {
                app_tx_byte(tx_buf[S.tx_pos]);
                S.tx_pos++;
                S.tx_run--;
                room--;
                continue;
            }
            if (S.tx_pos >= S.tx_len) {
                S.tx_state = 3u;
            } else {
                S.tx_pos++;            /* the zero the next code implies */
                S.tx_state = 1u;
            }
            continue;
        } else {
            app_tx_byte(0u);           /* delimiter */
            S.tx_len = 0u;
            S.tx_state = 0u;
            return;
        }
        room--;
    }
}

/* ---- command handlers: arguments in A(0..S.n-1), reply written over them, length in S.n ---- */
static uint8_t drive_busy(void)
{
    int16_t st = app_signal(LINK_SIG_STATE);
    return (uint8_t)(st == (int16_t)LINK_STATE_RUN || st == (int16_t)LINK_STATE_BRAKE);
}

static uint8_t mask_ok(uint16_t mask)
{
    return (uint8_t)(mask != 0u && (mask & (uint16_t)~SIG_ALL) == 0u);
}

static uint8_t h_hello(void)
{
    uint8_t k;
    for (k = 0u; k < 20u; k++) {
        A(k) = link_hello[k];
    }
    S.n = 20u;
    return 0u;
}

static uint8_t h_param_info(void)
{
    uint8_t idx = A(0), k;
    uint8_t a, e;
    uint16_t o;
    if (idx >= LINK_N_ENTRIES) {
        return LINK_NACK_UNKNOWN_PARAM;
    }
    o = row_of(idx);
    for (k = 0u; k < ROW; k++) {
        A(k) = link_rows[(uint16_t)(o + k)];
    }
    a = link_name_at[idx];
    e = link_name_at[(uint8_t)(idx + 1u)];
    while (a != e) {
        A(k) = (uint8_t)link_names[a];
        k++;
        a++;
    }
    S.n = k;
    return 0u;
}

static uint8_t h_param_get(void)
{
    uint8_t n = S.n, i, idx;
    if (n == 0u || n > LINK_PARAM_GET_MAX) {
        return LINK_NACK_MALFORMED;
    }
    for (i = 0u; i < n; i++) {
        if (entry_index(A(i)) == NONE) {
            return LINK_NACK_UNKNOWN_PARAM;
        }
    }
    /* last id first: value i goes to A(4i..4i+3), which holds only ids already answered */
    i = n;
    while (i != 0u) {
        i--;
        idx = entry_index(A(i));
        value_at(idx);
        put_v((uint8_t)(PL + (uint8_t)(i << 2)));
    }
    S.n = (uint8_t)(n << 2);
    return 0u;
}

static uint8_t set_reply(uint8_t id, uint8_t at)   /* set id from A(at..at+3), reply the stored value there */
{
    uint8_t code;
    get_v((uint8_t)(PL + at));
    code = set_v(id);
    if (code == 0u) {
        store_get_at(entry_index(id));
        put_v((uint8_t)(PL + at));
    }
    return code;
}

static uint8_t h_param_set(void)
{
    S.n = 5u;
    return set_reply(A(0), 1u);
}

static uint8_t h_set_speed(void)
{
    S.n = 4u;
    return set_reply(LINK_ID_SPEED_SETPOINT, 0u);
}

static uint8_t h_select_controller(void)
{
    uint8_t code;
    V.l = (int32_t)A(0);
    code = set_v(LINK_ID_CONTROLLER);
    A(0) = (uint8_t)link_params.controller;
    S.n = 1u;
    return code;
}

static uint8_t h_app(void)
{
    uint8_t code = app_command(tx_buf[1], &A(0), 0u);
    S.n = 0u;
    return code;
}

static uint8_t h_telem_config(void)
{
    uint16_t mask = get16(PL), dec = get16(PL + 2u);
    uint8_t spf = A(4), nsig = popcount16(mask), len = TELEM_HEADER, k;
    if (dec != 0u) {
        if (!mask_ok(mask) || spf == 0u) {
            return LINK_NACK_OUT_OF_RANGE;
        }
        for (k = 0u; k < spf; k++) {   /* TELEM_HEADER + 2 nsig spf, by additions */
            len = (uint8_t)(len + (uint8_t)(nsig << 1));
            if (len > LINK_MAX_PAYLOAD) {
                return LINK_NACK_OUT_OF_RANGE;
            }
        }
    }
    LINK_CRITICAL_BEGIN();
    S.tm_dec = 0u;
    S.tm_mask = mask;
    S.tm_spf = spf;
    mzero((LINK_DATA uint8_t *)&S.tr, (uint8_t)sizeof S.tr);
    S.tm_ready = 0u;
    S.tm_gen++;
    S.tm_dec = dec;
    LINK_CRITICAL_END();
    A(0) = S.tm_gen;
    A(1) = (uint8_t)(dec != 0u ? len : 0u);
    S.n = 2u;
    return 0u;
}

#if LINK_WITH_CAPTURE
static uint8_t h_capture_arm(void)
{
    uint16_t mask = get16(PL), n = get16(PL + 2u), pre = get16(PL + 4u), dec = get16(PL + 6u), words = 0u;
    uint8_t trig = A(8), nsig = popcount16(mask), k;
    S.n = 0u;
    if (!mask_ok(mask) || n == 0u || n > LINK_CAPTURE_WORDS || dec == 0u || trig > LINK_TRIG_SPEED_FALLING
        || pre >= n || (trig == LINK_TRIG_IMMEDIATE && pre != 0u)) {
        return LINK_NACK_OUT_OF_RANGE;
    }
    for (k = 0u; k < nsig; k++) {      /* n * nsig, by additions (n <= LINK_CAPTURE_WORDS) */
        words = (uint16_t)(words + n);
        if (words > LINK_CAPTURE_WORDS) {
            return LINK_NACK_OUT_OF_RANGE;
        }
    }
    words = (uint16_t)(words << 1);
    LINK_CRITICAL_BEGIN();
    S.cap_state = LINK_CAP_IDLE;
    S.cap_mask = mask;
    S.cap_nsig = nsig;
    S.cap_n = n;
    S.cap_bytes = words;
    S.cap_pre = pre;
    S.cap_dec = dec;
    S.cap_trig = trig;
    S.cap_thr = (int16_t)get16(PL + 9u);
    mzero((LINK_DATA uint8_t *)&S.cr, (uint8_t)sizeof S.cr);
    S.cap_sp_changed = 0u;
    S.cap_state = LINK_CAP_ARMED;
    LINK_CRITICAL_END();
    return 0u;
}

static uint8_t h_capture_read(void)
{
    uint16_t start = get16(PL), p, wi = 0u;
    uint8_t want = A(2), j, o, st = S.cap_state, nb = (uint8_t)(S.cap_nsig << 1);
    if (st == LINK_CAP_ARMED || st == LINK_CAP_TRIGGERED) {
        return LINK_NACK_BUSY;
    }
    if (st != LINK_CAP_DONE) {
        return LINK_NACK_WRONG_STATE;
    }
    if (start > S.cr.total) {
        return LINK_NACK_OUT_OF_RANGE;
    }
    A(0) = st;
    put16(PL + 1u, S.cr.total);
    put16(PL + 3u, S.cr.tidx);
    put16(PL + 5u, start);
    p = (uint16_t)(S.cr.start + start);   /* < 2 cap_n */
    if (p >= S.cap_n) {
        p = (uint16_t)(p - S.cap_n);
    }
    for (j = 0u; j < S.cap_nsig; j++) {    /* byte index 2 p nsig, by additions */
        wi = (uint16_t)(wi + p);
    }
    wi = (uint16_t)(wi << 1);
    o = (uint8_t)(PL + CAPREAD_HEADER);
    p = (uint16_t)(S.cr.total - start);   /* samples left */
    while (want != 0u && p != 0u && (uint8_t)(o + nb) <= (uint8_t)(PL + LINK_MAX_PAYLOAD)) {
        mcopy(&tx_buf[o], &cap_buf[wi], nb);
        o = (uint8_t)(o + nb);
        wi = (uint16_t)(wi + nb);
        if (wi >= S.cap_bytes) {
            wi = 0u;
        }
        want--;
        p--;
    }
    S.n = (uint8_t)(o - PL);
    return 0u;
}
#endif

static uint8_t h_eeprom_save(void)
{
    S.n = 0u;
    return link_eeprom_save();
}

static uint8_t h_eeprom_load(void)
{
    S.n = 0u;
    return (link_eeprom_load() != LINK_EE_OK) ? LINK_NACK_EEPROM_ERROR : 0u;
}

static uint8_t h_status(void)
{
    uint16_t drop;
    A(0) = (uint8_t)app_signal(LINK_SIG_STATE);
    A(1) = (uint8_t)app_signal(LINK_SIG_FAULT);
    A(2) = S.cap_state;
    A(3) = S.tm_gen;
    put16(PL + 4u, S.crc_errors);
    put16(PL + 6u, S.rx_overflows);
    LINK_CRITICAL_BEGIN();
    drop = S.tm_dropped;
    V.l = (int32_t)S.uptime_ms;
    LINK_CRITICAL_END();
    put16(PL + 8u, drop);
    put_v(PL + 10u);
    S.n = 14u;
    return 0u;
}

static uint8_t h_none(void)
{
    S.n = 0u;
    return 0u;
}

#if !LINK_WITH_CAPTURE
#define h_capture_arm h_unknown
#define h_capture_read h_unknown
static uint8_t h_unknown(void)          /* a command this build was generated without */
{
    return LINK_NACK_UNKNOWN_COMMAND;
}
#endif

/* dispatch table, by command code - 1: handler, argument bytes (0xFF: checked by the handler),
 * bit 0 of the flags: refused while the motor runs or brakes */
typedef uint8_t (*link_handler_t)(void);
static const link_handler_t cmd_fn[N_CMDS] = {
    h_hello,
    h_param_info,
    h_param_get,
    h_param_set,
    h_set_speed,
    h_app,
    h_app,
    h_app,
    h_select_controller,
    h_telem_config,
    h_capture_arm,
    h_capture_read,
    h_eeprom_save,
    h_eeprom_load,
    h_app,
    h_status,
    h_none,
};
static const uint8_t cmd_args[N_CMDS] = { 0u, 1u, 255u, 5u, 4u, 0u, 0u, 0u, 1u, 5u, 11u, 3u, 0u, 0u, 0u, 0u, 0u };
static const uint8_t cmd_idle[N_CMDS] = { 0u, 0u, 0u, 0u, 0u, 0u, 0u, 0u, 0u, 0u, 0u, 0u, 1u, 1u, 0u, 0u, 0u };

static void dispatch(uint8_t blen) LINK_WPARAM
{
    uint8_t type = tx_buf[1], seq = tx_buf[2], c, code, rtype;
    if ((type & LINK_ACK_BIT) != 0u || type == LINK_MSG_NACK || type == LINK_MSG_EVENT
        || type == LINK_MSG_TELEMETRY) {
        return;                        /* a board frame (an echo, a loop-back): not for us, no reply */
    }
    S.n = tx_buf[0];
    c = (uint8_t)(type - 1u);
    if (c < N_CMDS) {
        S.rx_valid = 1u;               /* only a host command feeds the watchdog */
    }
    S.nack_armed = 1u;
    LINK_HOOK_FRAME(type, seq, &A(0), S.n);
    if (S.rp_valid != 0u && type == S.rp_type && seq == S.rp_seq && tx_buf[(uint8_t)(blen - 2u)] == S.rp_crc0
        && tx_buf[(uint8_t)(blen - 1u)] == S.rp_crc1 && S.rp_len != NONE) {
        mcopy(&A(0), rp_data, S.rp_len);
        tx_seal(S.rp_rtype, seq, S.rp_len);
        return;
    }
    S.rp_crc0 = tx_buf[(uint8_t)(blen - 2u)];
    S.rp_crc1 = tx_buf[(uint8_t)(blen - 1u)];
    if (c >= N_CMDS) {
        code = LINK_NACK_UNKNOWN_COMMAND;
    } else if (cmd_args[c] != 0xFFu && cmd_args[c] != S.n) {
        code = LINK_NACK_MALFORMED;
    } else if (cmd_idle[c] != 0u && drive_busy()) {
        code = LINK_NACK_WRONG_STATE;
    } else {
        code = cmd_fn[c]();
    }
    if (code != 0u) {
        A(0) = type;
        A(1) = code;
        S.n = 2u;
        rtype = LINK_MSG_NACK;
    } else {
        rtype = (uint8_t)(type | LINK_ACK_BIT);
    }
    tx_seal(rtype, seq, S.n);
    S.rp_valid = 1u;
    S.rp_type = type;
    S.rp_seq = seq;
    S.rp_rtype = rtype;
    S.rp_len = NONE;
    if (S.n <= LINK_REPLAY_BYTES) {
        mcopy(rp_data, &A(0), S.n);
        S.rp_len = S.n;
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
    A(0) = ev;
    A(1) = code;
    tx_seal(LINK_MSG_EVENT, S.ev_counter, 2u);
    S.ev_counter++;
    return 1u;
}

void link_poll(void)
{
    uint8_t k, n;
    for (k = 0u; k < 8u; k++) {
        S.wd_armed = (uint8_t)(app_signal(LINK_SIG_STATE) == (int16_t)LINK_STATE_RUN);
        tx_drain();
        if (S.tx_len != 0u) {
            break;
        }
        if (S.nack_pending != 0u) {
            S.nack_pending = 0u;
            A(0) = S.nack_type;
            A(1) = LINK_NACK_BAD_CRC;
            tx_seal(LINK_MSG_NACK, S.nack_seq, 2u);
            continue;
        }
        n = rx_frame();
        if (n != 0u) {
            dispatch(n);
            continue;
        }
        if (S.nack_pending != 0u) {
            continue;
        }
        if (send_event() != 0u) {
            continue;
        }
        if (S.tm_ready != 0u) {
            mcopy(&A(0), tm_buf, S.tr.len);
            tx_seal(LINK_MSG_TELEMETRY, S.tm_gen, S.tr.len);
            S.tr.nsamp = 0u;
            S.tr.len = 0u;
            S.tm_ready = 0u;
            continue;
        }
        break;
    }
    /* again after dispatching: a start just executed arms the watchdog at once */
    S.wd_armed = (uint8_t)(app_signal(LINK_SIG_STATE) == (int16_t)LINK_STATE_RUN);
}

/* ---- time base: watchdog, uptime ---- */
void link_tick_ms(void)
{
    S.uptime_ms++;
    if (S.wd_armed == 0u) {
        S.wd_ms = 0u;
    } else if (S.rx_valid != 0u) {
        S.rx_valid = 0u;
        S.wd_ms = 0u;
    } else {
        if (S.wd_ms != 0xFFFFu) {
            S.wd_ms++;
        }
        if (S.wd_ms >= link_params.link_timeout) {
            S.wd_armed = 0u;
            S.wd_ms = 0u;
            app_link_lost();
            S.ev_watchdog = 1u;
        }
    }
}

/* ---- per speed-loop sample: telemetry and capture ---- */
/* the masked signals' values, int16 little-endian, from p on; returns the bytes written */
static uint8_t put_signals(LINK_DATA uint8_t *p, uint16_t m)
{
    uint8_t j, n = 0u;
    uint16_t v;
    for (j = 0u; m != 0u; j++) {
        if ((m & 1u) != 0u) {
            v = (uint16_t)app_signal(j);
            p[n] = (uint8_t)v;
            p[(uint8_t)(n + 1u)] = (uint8_t)(v >> 8);
            n = (uint8_t)(n + 2u);
        }
        m = (uint16_t)(m >> 1);
    }
    return n;
}

#if LINK_WITH_CAPTURE
static void capture_sample(void)
{
    uint8_t fire = 0u, trig = S.cap_trig;
    uint16_t wi;
    int16_t sp, thr = S.cap_thr;
    S.cr.div++;
    if (S.cr.div < S.cap_dec) {
        return;
    }
    S.cr.div = 0u;
    if (S.cap_state == LINK_CAP_ARMED) {
        if (trig == LINK_TRIG_IMMEDIATE) {
            fire = 1u;
        } else if (trig == LINK_TRIG_SETPOINT_CHANGE) {
            fire = S.cap_sp_changed;
        } else {
            sp = app_signal(LINK_SIG_SPEED);
            if (trig == LINK_TRIG_SPEED_FALLING) {   /* falling through thr = rising through ~thr */
                sp = (int16_t)(-1 - sp);
                thr = (int16_t)(-1 - thr);
            }
            fire = (uint8_t)(S.cr.prev_valid != 0u && S.cr.prev < thr && sp >= thr);
            S.cr.prev = sp;
            S.cr.prev_valid = 1u;
        }
        if (fire != 0u) {
            S.cr.tidx = (S.cr.filled < S.cap_pre) ? S.cr.filled : S.cap_pre;
            S.cr.post = 0u;
            S.cap_state = LINK_CAP_TRIGGERED;
        }
    }
    wi = (uint16_t)(S.cr.wi + put_signals(&cap_buf[S.cr.wi], S.cap_mask));
    S.cr.w++;
    if (S.cr.w >= S.cap_n) {
        S.cr.w = 0u;
        wi = 0u;
    }
    S.cr.wi = wi;
    if (S.cr.filled < S.cap_n) {
        S.cr.filled++;
    }
    if (S.cap_state == LINK_CAP_TRIGGERED) {
        S.cr.post++;
        if (S.cr.post >= (uint16_t)(S.cap_n - S.cap_pre)) {
            S.cr.total = (uint16_t)(S.cr.tidx + S.cr.post);
            wi = (uint16_t)(S.cr.w + (uint16_t)(S.cap_n - S.cr.total));   /* < 2 cap_n */
            if (wi >= S.cap_n) {
                wi = (uint16_t)(wi - S.cap_n);
            }
            S.cr.start = wi;
            S.cap_state = LINK_CAP_DONE;
        }
    }
}
#endif

void link_sample(void)
{
    uint8_t len;
    if (S.tm_dec != 0u) {
        S.tr.div++;
        if (S.tr.div >= S.tm_dec) {
            S.tr.div = 0u;
            if (S.tm_ready != 0u) {
                if (S.tm_dropped != 0xFFFFu) {
                    S.tm_dropped++;
                }
            } else {
                len = S.tr.len;
                if (S.tr.nsamp == 0u) {
                    tm_buf[0] = (uint8_t)S.tr.counter;
                    tm_buf[1] = (uint8_t)(S.tr.counter >> 8);
                    len = TELEM_HEADER;
                }
                S.tr.len = (uint8_t)(len + put_signals(&tm_buf[len], S.tm_mask));
                S.tr.nsamp++;
                if (S.tr.nsamp >= S.tm_spf) {
                    S.tm_ready = 1u;
                }
            }
            S.tr.counter++;
        }
    }
#if LINK_WITH_CAPTURE
    if (S.cap_state == LINK_CAP_ARMED || S.cap_state == LINK_CAP_TRIGGERED) {
        capture_sample();
    }
#endif
}

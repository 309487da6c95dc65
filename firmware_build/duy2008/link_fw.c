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
 * and are not reentrant), data-space pointers, one flash table read through one function, byte
 * indices (every buffer is shorter than 256 B), and no 32-bit arithmetic: values move and are
 * range-checked byte by byte.
 *
 * Contexts: link_rx_byte() (UART RX interrupt) only stores the byte in the frame buffer and
 * marks the frame complete at the delimiter; link_tick_ms() and link_sample() (speed-loop
 * interrupt) touch no flash table but app_signal_src (put_signals saves the table pointer); COBS decoding, CRC and dispatch run in link_poll() (main loop).
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

#define SIG_ALL            0x07FFu
#define NONE               0xFFu
#define ROW                20u          /* bytes of a table row (= param_info reply head) */
#define EE_HEADER          8u
#define EE_DATA_BYTES      35u
#define TELEM_HEADER       2u
#define CAPREAD_HEADER     7u
#define RX_SKIP            0xFFu                     /* rx_n: discard up to the next delimiter */
#define PL                 3u                        /* payload offset in the frame body */
#define BODY_OVERHEAD      5u                        /* LEN, TYPE, SEQ, CRC high, CRC low */
#define R(i)               rx_buf[PL + (i)]          /* command arguments (decoded body in rx_buf) */
#define A(i)               tx_buf[1u + PL + (i)]     /* reply payload (body in tx_buf[1..], COBS code at 0) */
#define N_CMDS             17u
#define SIG_INDEX          11u          /* table index of the first signal */
#define CMD_IDLE           0x80u                     /* cmd spec: refused while the motor runs or brakes */
#define CMD_ANY_LEN        0x7Fu                     /* cmd spec: argument length checked by the handler */

#if LINK_MAX_BODY > 253u
#error "one COBS block per frame: the body must stay below 254 bytes"
#endif
#if LINK_CAPTURE_WORDS > 128u
#error "capture indices are bytes: at most 256 B of capture buffer"
#endif

link_params_t link_params;

/* ---- flash: one byte table, read through rom_next() only ---- */
#define ROM_ROWS           0u   /* 600 B */
#define ROM_OFF            600u   /* 30 B */
#define ROM_SIZE           630u   /* 30 B */
#define ROM_NAME_LEN       660u   /* 30 B */
#define ROM_HELLO          690u   /* 20 B */
#define ROM_CMD            710u   /* 17 B */
#define ROM_NAMES          727u   /* 251 B */
#define ROM_EE_HEAD        978u   /* 8 B */
#define ROM_PERSIST        986u   /* 18 B */
static const uint8_t link_rom[1004] = {
    /* ROM_ROWS */
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
    /* ROM_OFF */
    (uint8_t)offsetof(link_params_t, speed_setpoint), (uint8_t)offsetof(link_params_t, controller), (uint8_t)offsetof(link_params_t, premise_low), (uint8_t)offsetof(link_params_t, premise_high),
    (uint8_t)offsetof(link_params_t, setpoint_weight), (uint8_t)offsetof(link_params_t, u_min), (uint8_t)offsetof(link_params_t, u_max), (uint8_t)offsetof(link_params_t, current_limit),
    (uint8_t)offsetof(link_params_t, accel_limit), (uint8_t)offsetof(link_params_t, link_timeout), (uint8_t)offsetof(link_params_t, stall_timeout), NONE,
    NONE, NONE, NONE, NONE,
    NONE, NONE, NONE, NONE,
    NONE, NONE, (uint8_t)offsetof(link_params_t, rule1_kp), (uint8_t)offsetof(link_params_t, rule1_ki),
    (uint8_t)offsetof(link_params_t, rule1_kd), (uint8_t)offsetof(link_params_t, rule1_kc), (uint8_t)offsetof(link_params_t, rule2_kp), (uint8_t)offsetof(link_params_t, rule2_ki),
    (uint8_t)offsetof(link_params_t, rule2_kd), (uint8_t)offsetof(link_params_t, rule2_kc),
    /* ROM_SIZE */
    0x82u, 0x01u, 0x82u, 0x82u, 0x82u, 0x82u, 0x82u, 0x82u, 0x02u, 0x02u, 0x02u, 0x82u,
    0x82u, 0x82u, 0x82u, 0x82u, 0x82u, 0x82u, 0x82u, 0x82u, 0x82u, 0x82u, 0x82u, 0x82u,
    0x82u, 0x82u, 0x82u, 0x82u, 0x82u, 0x82u,
    /* ROM_NAME_LEN */
    14u, 10u, 11u, 12u, 15u, 5u, 5u, 13u, 11u, 12u, 13u, 5u,
    8u, 7u, 7u, 10u, 4u, 4u, 5u, 5u, 3u, 8u, 8u, 8u,
    8u, 8u, 8u, 8u, 8u, 8u,
    /* ROM_HELLO */
    LINK_PROTO_MAJOR, LINK_PROTO_MINOR, (uint8_t)LINK_BUILD_ID, (uint8_t)(LINK_BUILD_ID >> 8u),
    (uint8_t)(LINK_BUILD_ID >> 16u), (uint8_t)(LINK_BUILD_ID >> 24u), (uint8_t)LINK_PROFILE_HASH, (uint8_t)(LINK_PROFILE_HASH >> 8u),
    (uint8_t)(LINK_PROFILE_HASH >> 16u), (uint8_t)(LINK_PROFILE_HASH >> 24u), (uint8_t)LINK_TABLE_HASH, (uint8_t)(LINK_TABLE_HASH >> 8u),
    (uint8_t)(LINK_TABLE_HASH >> 16u), (uint8_t)(LINK_TABLE_HASH >> 24u), LINK_N_ENTRIES, LINK_MAX_PAYLOAD,
    (uint8_t)LINK_HELLO_CAPTURE_WORDS, (uint8_t)(LINK_HELLO_CAPTURE_WORDS >> 8u), (uint8_t)LINK_SAMPLE_HZ, (uint8_t)(LINK_SAMPLE_HZ >> 8u),
    /* ROM_CMD */
    0x00u, 0x01u, 0x7Fu, 0x05u, 0x04u, 0x00u, 0x00u, 0x00u, 0x01u, 0x05u, 0x0Bu, 0x03u,
    0x80u, 0x80u, 0x00u, 0x00u, 0x00u,
    /* ROM_NAMES */
    0x73u, 0x70u, 0x65u, 0x65u, 0x64u, 0x5Fu, 0x73u, 0x65u, 0x74u, 0x70u, 0x6Fu, 0x69u, 0x6Eu, 0x74u, 0x63u, 0x6Fu,
    0x6Eu, 0x74u, 0x72u, 0x6Fu, 0x6Cu, 0x6Cu, 0x65u, 0x72u, 0x70u, 0x72u, 0x65u, 0x6Du, 0x69u, 0x73u, 0x65u, 0x5Fu,
    0x6Cu, 0x6Fu, 0x77u, 0x70u, 0x72u, 0x65u, 0x6Du, 0x69u, 0x73u, 0x65u, 0x5Fu, 0x68u, 0x69u, 0x67u, 0x68u, 0x73u,
    0x65u, 0x74u, 0x70u, 0x6Fu, 0x69u, 0x6Eu, 0x74u, 0x5Fu, 0x77u, 0x65u, 0x69u, 0x67u, 0x68u, 0x74u, 0x75u, 0x5Fu,
    0x6Du, 0x69u, 0x6Eu, 0x75u, 0x5Fu, 0x6Du, 0x61u, 0x78u, 0x63u, 0x75u, 0x72u, 0x72u, 0x65u, 0x6Eu, 0x74u, 0x5Fu,
    0x6Cu, 0x69u, 0x6Du, 0x69u, 0x74u, 0x61u, 0x63u, 0x63u, 0x65u, 0x6Cu, 0x5Fu, 0x6Cu, 0x69u, 0x6Du, 0x69u, 0x74u,
    0x6Cu, 0x69u, 0x6Eu, 0x6Bu, 0x5Fu, 0x74u, 0x69u, 0x6Du, 0x65u, 0x6Fu, 0x75u, 0x74u, 0x73u, 0x74u, 0x61u, 0x6Cu,
    0x6Cu, 0x5Fu, 0x74u, 0x69u, 0x6Du, 0x65u, 0x6Fu, 0x75u, 0x74u, 0x73u, 0x70u, 0x65u, 0x65u, 0x64u, 0x73u, 0x65u,
    0x74u, 0x70u, 0x6Fu, 0x69u, 0x6Eu, 0x74u, 0x76u, 0x6Fu, 0x6Cu, 0x74u, 0x61u, 0x67u, 0x65u, 0x63u, 0x75u, 0x72u,
    0x72u, 0x65u, 0x6Eu, 0x74u, 0x69u, 0x6Eu, 0x74u, 0x65u, 0x67u, 0x72u, 0x61u, 0x74u, 0x6Fu, 0x72u, 0x64u, 0x75u,
    0x74u, 0x79u, 0x68u, 0x61u, 0x6Cu, 0x6Cu, 0x73u, 0x74u, 0x61u, 0x74u, 0x65u, 0x66u, 0x61u, 0x75u, 0x6Cu, 0x74u,
    0x6Du, 0x75u, 0x31u, 0x70u, 0x6Fu, 0x73u, 0x69u, 0x74u, 0x69u, 0x6Fu, 0x6Eu, 0x72u, 0x75u, 0x6Cu, 0x65u, 0x31u,
    0x5Fu, 0x6Bu, 0x70u, 0x72u, 0x75u, 0x6Cu, 0x65u, 0x31u, 0x5Fu, 0x6Bu, 0x69u, 0x72u, 0x75u, 0x6Cu, 0x65u, 0x31u,
    0x5Fu, 0x6Bu, 0x64u, 0x72u, 0x75u, 0x6Cu, 0x65u, 0x31u, 0x5Fu, 0x6Bu, 0x63u, 0x72u, 0x75u, 0x6Cu, 0x65u, 0x32u,
    0x5Fu, 0x6Bu, 0x70u, 0x72u, 0x75u, 0x6Cu, 0x65u, 0x32u, 0x5Fu, 0x6Bu, 0x69u, 0x72u, 0x75u, 0x6Cu, 0x65u, 0x32u,
    0x5Fu, 0x6Bu, 0x64u, 0x72u, 0x75u, 0x6Cu, 0x65u, 0x32u, 0x5Fu, 0x6Bu, 0x63u,
    /* ROM_EE_HEAD */
    0x50u, 0x44u, 0x01u, (uint8_t)LINK_TABLE_HASH, (uint8_t)(LINK_TABLE_HASH >> 8u), (uint8_t)(LINK_TABLE_HASH >> 16u), (uint8_t)(LINK_TABLE_HASH >> 24u), EE_DATA_BYTES,
    /* ROM_PERSIST */
    1u, 2u, 3u, 4u, 5u, 6u, 7u, 8u, 9u, 10u, 22u, 23u,
    24u, 25u, 26u, 27u, 28u, 29u,
};

/* ---- buffers ---- */
static uint8_t rx_buf[LINK_RX_BYTES];          /* raw frame (COBS code + body), decoded in place */
static uint8_t tx_buf[1u + LINK_MAX_BODY];     /* COBS code, then the body being sent, encoded in place */
static uint8_t tm_buf[LINK_MAX_PAYLOAD];       /* telemetry payload being filled by link_sample */
static uint8_t rp_data[LINK_REPLAY_BYTES];     /* last short reply, for duplicate-SEQ replay */
#if LINK_WITH_CAPTURE
static uint8_t cap_buf[2u * LINK_CAPTURE_WORDS]; /* capture ring, sample-major, int16 little-endian */
#endif
static union { int32_t l; uint8_t b[4]; } V;   /* the value being moved (main loop only) */

/* The most used scalars, in the access bank under SDCC (LINK_ACCESS_AT up to 0x3F: no bank
 * select per access; the chip's access RAM is 0x00-0x5F, but picdrive.firmware.gpsim's timing
 * build keeps 0x40-0x5F for the registers it moves, so the firmware's access RAM ends at 0x3F;
 * SDCC's own registers r0x.. and drive_core's accumulator sit below this block, and gplink
 * refuses a build whose registers reach it).  rx_n, rx_ready, rx_ovf and
 * the CRC come first: the assembly below addresses them by offset. */
#if defined(__SDCC_pic16)
#define LINK_FAST_RAM __at(LINK_ACCESS_AT)  /* external linkage: SDCC 4.2 emits a static __at twice */
#else
#define LINK_FAST_RAM static
#endif
LINK_FAST_RAM struct link_fast {
    /* receive: the RX interrupt owns rx_n and rx_ovf while rx_ready is 0, the main loop rx_buf and
     * rx_n while it is 1; all single bytes */
    volatile uint8_t rx_n;
    volatile uint8_t rx_ready;
    volatile uint8_t rx_ovf;
    uint8_t crc_hi;                    /* CRC state (main loop) */
    uint8_t crc_lo;
    uint8_t n;                         /* argument bytes of the command, then reply bytes */
    uint16_t ro;                       /* next link_rom byte */
    uint8_t e_off;                     /* entry_load(): store offset (NONE: a signal), size code */
    uint8_t e_sz;
    uint8_t tx_len;                    /* bytes to send from tx_buf (COBS-encoded in place); 0 = free */
    /* telemetry (speed-loop interrupt) */
    volatile uint8_t tm_ready;         /* sample fills tm_buf and sets it; poll sends and clears it */
    uint8_t tm_nb;                     /* bytes per sample: 2 x signals */
    uint16_t tm_dec;
    struct {                           /* restarted by telem_config */
        uint16_t div;
        uint16_t counter;
        uint8_t nsamp;
        uint8_t len;
    } tr;
#if LINK_WITH_CAPTURE
    uint8_t cap_n;
    uint8_t cap_nb;                    /* bytes per sample: 2 x signals */
    uint16_t cap_dec;
    uint16_t cr_div;                   /* capture decimation counter, restarted by capture_arm */
#endif
} link_hot;

/* the sample being written (speed-loop interrupt only): telemetry and capture destinations and
 * the masks still to write */
static struct link_sg {               /* put_signals' assembly addresses the fields by offset */
    LINK_DATA uint8_t *p;
    LINK_DATA uint8_t *q;              /* 0: no capture sample */
    uint16_t tm;
    uint16_t cm;
    uint8_t j;
} sg;
#if defined(__SDCC_pic16)
typedef char link_sg_layout[(offsetof(struct link_sg, tm) == 4u && offsetof(struct link_sg, j) == 8u) ? 1 : -1];
typedef char link_fast_layout[(offsetof(struct link_fast, crc_lo) == 4u
                               && LINK_ACCESS_AT + sizeof(struct link_fast) <= 0x40u) ? 1 : -1];
#else
typedef char link_fast_layout[(offsetof(struct link_fast, crc_lo) == 4u) ? 1 : -1];
#endif
#define rx_n link_hot.rx_n
#define rx_ready link_hot.rx_ready
#define rx_ovf link_hot.rx_ovf
#define crc_hi link_hot.crc_hi
#define crc_lo link_hot.crc_lo

/* ---- scalar state ---- */
static struct link_state {
    /* the status reply from its third byte on, in reply order (one copy) */
    volatile uint8_t cap_state;
    uint8_t tm_gen;
    uint16_t crc_errors;
    uint16_t rx_overflows;
    volatile uint16_t tm_dropped;
    volatile uint32_t uptime_ms;
    /* receive */
    uint8_t rx_ovf_seen;
    volatile uint8_t rx_valid;         /* a host command arrived (main sets, tick clears: watchdog) */
    uint8_t nack_armed;                /* one BAD_CRC NACK per valid frame */
    uint8_t nack_pending;
    uint8_t nack_type;
    uint8_t nack_seq;
    /* replay */
    uint8_t c;                         /* command code - 1 */
    uint8_t tseq;                      /* SEQ of the frame being sealed */
    uint8_t ee_off;                    /* next EEPROM image byte */
    uint8_t tx_pos;
    uint8_t tm_spf;
    uint8_t rp_type;                   /* 0: nothing stored */
    uint8_t rp_seq;
    uint8_t rp_rtype;
    uint8_t rp_len;                    /* NONE: reply too long to store (read-only command) */
    uint8_t rp_crc0;
    uint8_t rp_crc1;
    uint8_t fc0;                       /* CRC bytes of the frame being dispatched */
    uint8_t fc1;
    /* watchdog */
    volatile uint8_t wd_armed;
    uint16_t wd_ms;
    /* events (single-byte flags: safe from any context) */
    volatile uint8_t ev_boot;
    volatile uint8_t ev_boot_code;
    volatile uint8_t ev_fault;
    volatile uint8_t ev_watchdog;
    uint8_t ev_counter;
    /* telemetry */
    uint16_t tm_mask;
#if LINK_WITH_CAPTURE
    /* capture: sample counts and byte indices are bytes (at most 128 samples, 256 B) */
    volatile uint8_t cap_sp_changed;
    uint8_t cap_trig;
    uint8_t cap_bytes;                 /* cap_n cap_nb - 1: the last byte index */
    uint8_t cap_pre;
    uint16_t cap_mask;
    int16_t cap_thr;
    struct {                           /* restarted by capture_arm (and link_hot.cr_div) */
        uint8_t w;                     /* next sample slot */
        uint8_t wi;                    /* its byte index in cap_buf */
        uint8_t filled;
        uint8_t post;
        uint8_t total;
        uint8_t start;
        uint8_t tidx;
        uint8_t prev_valid;
        int16_t prev;
    } cr;
#endif
} S;

typedef char link_status_layout[(offsetof(struct link_state, uptime_ms) == 8u) ? 1 : -1];

/* ---- little helpers ---- */
#define put16(o, v) do { uint16_t v_ = (v); A(o) = (uint8_t)v_; A((o) + 1u) = (uint8_t)(v_ >> 8); } while (0)
#define arg16(o) ((uint16_t)((uint16_t)R(o) | (uint16_t)((uint16_t)R((o) + 1u) << 8)))

/* copies and loops walk static data-space pointers: no arguments on the software stack */
static LINK_DATA uint8_t *cp_d;
static LINK_DATA uint8_t *cp_s;

static void mcopy_n(uint8_t n) LINK_WPARAM         /* cp_d[0..n-1] = cp_s[0..n-1] (RAM to RAM) */
{
    while (n != 0u) {
        *cp_d = *cp_s;
        cp_d++;
        cp_s++;
        n--;
    }
}
#define mcopy(d, src, n) do { cp_d = (d); cp_s = (src); mcopy_n(n); } while (0)

static void mzero_n(uint8_t n) LINK_WPARAM
{
    while (n != 0u) {
        *cp_d = 0u;
        cp_d++;
        n--;
    }
}
#define mzero(d, n) do { cp_d = (d); mzero_n(n); } while (0)

static uint8_t rom_next(void)          /* link_rom[link_hot.ro++]: the module's only flash read */
{
    uint8_t b = link_rom[link_hot.ro];
    link_hot.ro++;
    return b;
}

#define rom_at(o) (link_hot.ro = (uint16_t)(o))

static uint8_t popcount16(uint16_t m)
{
    uint8_t n = 0u;
    while (m != 0u) {
        if (((uint8_t)m & 1u) != 0u) {
            n++;
        }
        m = (uint16_t)(m >> 1);
    }
    return n;
}

/* CRC-16/CCITT-FALSE (poly 0x1021) byte-wise without a table, on two bytes of state: 8-bit
 * shifts and XORs only (a shift form needs no 512 B table and no 16-bit arithmetic) */
#define CRC_INIT() do { crc_hi = 0xFFu; crc_lo = 0xFFu; } while (0)

#if defined(__SDCC_pic16)
/* the same steps in PIC18 assembly (20 cycles instead of 70; x in PRODL (0xFF3), a rotation in PRODH (0xFF4):
 * scratch registers the compiler does not keep values in across a call) */
static void crc_byte(uint8_t b) LINK_WPARAM __naked
{
    (void)b;
    __asm
    XORWF   (_link_hot + 3), W, A      ; x = hi ^ b
    MOVWF   0xFF3, A
    SWAPF   0xFF3, W, A
    ANDLW   0x0F
    XORWF   0xFF3, F, A         ; x ^= x >> 4
    SWAPF   0xFF3, W, A
    ANDLW   0xF0                ; x << 4
    XORWF   (_link_hot + 4), W, A
    MOVWF   (_link_hot + 3), A         ; hi = lo ^ (x << 4)
    SWAPF   0xFF3, W, A
    RLNCF   0xFE8, W, A         ; x rotated right by 3
    MOVWF   0xFF4, A
    ANDLW   0x1F                ; x >> 3
    XORWF   (_link_hot + 3), F, A      ; hi ^= x >> 3
    MOVF    0xFF4, W, A
    ANDLW   0xE0                ; x << 5
    XORWF   0xFF3, W, A
    MOVWF   (_link_hot + 4), A         ; lo = x ^ (x << 5)
    RETURN
    __endasm;
}
#else
static void crc_byte(uint8_t b) LINK_WPARAM
{
    uint8_t x = (uint8_t)(crc_hi ^ b);
    x = (uint8_t)(x ^ (uint8_t)(x >> 4));
    crc_hi = (uint8_t)(crc_lo ^ (uint8_t)(x >> 3) ^ (uint8_t)(x << 4));
    crc_lo = (uint8_t)(x ^ (uint8_t)(x << 5));
}
#endif

/* CRC of cp_s[0..n-1] into crc_hi, crc_lo */
static void crc_n(uint8_t n) LINK_WPARAM
{
    CRC_INIT();
    while (n != 0u) {
        crc_byte(*cp_s);
        cp_s++;
        n--;
    }
}
#define crc_buf(p, n) do { cp_s = (p); crc_n(n); } while (0)

uint16_t link_crc16(const uint8_t *p, uint8_t n)
{
    CRC_INIT();
    while (n != 0u) {
        crc_byte(*p);
        p++;
        n--;
    }
    return (uint16_t)((uint16_t)((uint16_t)crc_hi << 8) | crc_lo);
}

/* ---- the table: ids in contiguous runs, so the index is a subtraction ---- */
static uint8_t entry_index(uint8_t id) LINK_WPARAM
{
    if ((uint8_t)(id - 0x00u) < 11u) {
        return (uint8_t)(id - 0u);
    }
    if ((uint8_t)(id - 0x20u) < 11u) {
        return (uint8_t)(id - 21u);
    }
    if ((uint8_t)(id - 0x40u) < 8u) {
        return (uint8_t)(id - 42u);
    }
    return NONE;
}

static void row_of(uint8_t idx) LINK_WPARAM        /* link_hot.ro = the entry's row (idx * 20, by shifts) */
{
    uint16_t o = (uint16_t)((uint16_t)idx << 2);
    link_hot.ro = (uint16_t)(o + (uint16_t)(o << 2));
}
#define row_at(idx, k) do { row_of(idx); link_hot.ro = (uint16_t)(link_hot.ro + (k)); } while (0)

static void entry_load(uint8_t idx) LINK_WPARAM   /* link_hot.e_off, link_hot.e_sz */
{
    rom_at((uint16_t)(ROM_OFF + idx));
    link_hot.e_off = rom_next();
    rom_at((uint16_t)(ROM_SIZE + idx));
    link_hot.e_sz = rom_next();
}

static void sign_extend(void)          /* V.b[0..n-1] hold a value of size code link_hot.e_sz */
{
    uint8_t k = (uint8_t)(link_hot.e_sz & 0x7Fu), fill = 0u;
    if ((link_hot.e_sz & 0x80u) != 0u && (V.b[k - 1u] & 0x80u) != 0u) {
        fill = 0xFFu;
    }
    while (k < 4u) {
        V.b[k] = fill;
        k++;
    }
}

static void store_get(void)            /* V = the parameter at link_hot.e_off */
{
    mcopy(V.b, (LINK_DATA uint8_t *)&link_params + link_hot.e_off, (uint8_t)(link_hot.e_sz & 0x7Fu));
    sign_extend();
}

static void store_put(void)            /* the parameter at link_hot.e_off = V (already range-checked) */
{
    LINK_CRITICAL_BEGIN();
    mcopy((LINK_DATA uint8_t *)&link_params + link_hot.e_off, V.b, (uint8_t)(link_hot.e_sz & 0x7Fu));
    LINK_CRITICAL_END();
}

static void value_at(uint8_t idx) LINK_WPARAM      /* V = parameter or signal */
{
    entry_load(idx);
    if (link_hot.e_off == NONE) {
        int16_t v = app_signal((uint8_t)(idx - SIG_INDEX));
        V.b[0] = (uint8_t)v;
        V.b[1] = (uint8_t)((uint16_t)v >> 8);
        sign_extend();
    } else {
        store_get();
    }
}

static union { int32_t l; uint8_t b[4]; } X;   /* a limit read from the table */

static void rom_x(void)                /* X = the next 4 table bytes (little-endian int32) */
{
    X.b[0] = rom_next();
    X.b[1] = rom_next();
    X.b[2] = rom_next();
    X.b[3] = rom_next();
}

static uint8_t in_range(uint8_t idx) LINK_WPARAM   /* V within the entry's [min, max] */
{
    row_at(idx, 8u);
    rom_x();
    if (V.l < X.l) {
        return 0u;
    }
    rom_x();
    return (uint8_t)(V.l <= X.l);
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
    row_at(i, 2u);
    if ((rom_next() & LINK_FLAG_WRITABLE) == 0u) {
        return LINK_NACK_READ_ONLY;
    }
    if (!in_range(i)) {
        return LINK_NACK_OUT_OF_RANGE;
    }
    entry_load(i);
    store_put();
#if LINK_WITH_CAPTURE
    if (id == LINK_ID_SPEED_SETPOINT) {
        S.cap_sp_changed = 1u;
    }
#endif
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
#define ee_off S.ee_off

static uint8_t id_of(uint8_t idx) LINK_WPARAM
{
    if (idx < 11u) {
        return (uint8_t)(idx + 0u);
    }
    if (idx < 22u) {
        return (uint8_t)(idx + 21u);
    }
    return (uint8_t)(idx + 42u);
}

static uint8_t ee_next(void)           /* the next image byte, CRC'd */
{
    uint8_t b = app_eeprom_read((uint8_t)(LINK_EE_BASE + ee_off));
    ee_off++;
    crc_byte(b);
    return b;
}

static void ee_put(uint8_t b) LINK_WPARAM          /* write the next image byte, CRC it */
{
    app_eeprom_write((uint8_t)(LINK_EE_BASE + ee_off), b);
    ee_off++;
    crc_byte(b);
}

static uint8_t persisted(uint8_t i) LINK_WPARAM    /* entry index of persisted parameter i, loaded */
{
    uint8_t idx;
    rom_at((uint16_t)(ROM_PERSIST + i));
    idx = rom_next();
    entry_load(idx);
    return idx;
}

uint8_t link_eeprom_save(void)
{
    uint8_t i, k;
    ee_off = 0u;
    CRC_INIT();
    for (k = 0u; k < EE_HEADER; k++) {
        rom_at((uint16_t)(ROM_EE_HEAD + k));
        ee_put(rom_next());
    }
    for (i = 0u; i < LINK_N_PERSISTED; i++) {
        (void)persisted(i);
        store_get();
        for (k = 0u; k < (uint8_t)(link_hot.e_sz & 0x7Fu); k++) {
            ee_put(V.b[k]);
        }
    }
    V.b[0] = crc_hi;
    V.b[1] = crc_lo;
    ee_put(V.b[0]);
    ee_put(V.b[1]);
    /* read-back verify: the image with its CRC leaves 0 (CRC-16 catches any 1-3 bad bits), and
     * the CRC bytes are the ones computed from the store */
    k = ee_off;
    ee_off = 0u;
    CRC_INIT();
    while (ee_off < (uint8_t)(k - 2u)) {
        (void)ee_next();
    }
    if (ee_next() != V.b[0] || ee_next() != V.b[1] || (crc_hi | crc_lo) != 0u) {
        return LINK_NACK_EEPROM_ERROR;
    }
    return 0u;
}

uint8_t link_eeprom_load(void)
{
    uint8_t i, k, pass, r = LINK_EE_BLANK;
    ee_off = 0u;
    CRC_INIT();
    for (k = 0u; k < EE_HEADER; k++) {   /* magic (BLANK), then version, hash, length (OTHER_BUILD) */
        rom_at((uint16_t)(ROM_EE_HEAD + k));
        if (ee_next() != rom_next()) {
            return r;
        }
        if (k == 1u) {
            r = LINK_EE_OTHER_BUILD;
        }
    }
    while (ee_off < (uint8_t)(EE_HEADER + EE_DATA_BYTES + 2u)) {
        (void)ee_next();
    }
    if ((crc_hi | crc_lo) != 0u) {
        return LINK_EE_CORRUPT;
    }
    /* pass 0: every value in range, or nothing is loaded; pass 1: store */
    for (pass = 0u; pass < 2u; pass++) {
        ee_off = EE_HEADER;
        for (i = 0u; i < LINK_N_PERSISTED; i++) {
            uint8_t idx = persisted(i);
            for (k = 0u; k < (uint8_t)(link_hot.e_sz & 0x7Fu); k++) {
                V.b[k] = ee_next();
            }
            sign_extend();
            if (pass == 0u) {
                if (!in_range(idx)) {
                    return LINK_EE_CORRUPT;
                }
            } else {
                store_put();
            }
        }
    }
    for (i = 0u; i < LINK_N_PERSISTED; i++) {
        app_param_changed(id_of(persisted(i)));
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
    mzero((LINK_DATA uint8_t *)&link_hot, (uint8_t)sizeof link_hot);
    for (i = 0u; i < LINK_N_ENTRIES; i++) {   /* the parameters' defaults */
        entry_load(i);
        if (link_hot.e_off != NONE) {
            uint8_t k;
            row_at(i, 16u);
            for (k = 0u; k < 4u; k++) {
                V.b[k] = rom_next();
            }
            store_put();
        }
    }
    S.rp_len = NONE;
    S.nack_armed = 1u;
    S.ev_boot = 1u;
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

/* ---- receive: the interrupt only stores the byte and marks the frame complete ---- */
#if defined(__SDCC_pic16)
/* the C below in PIC18 assembly: about 20 cycles a byte, no register saved (b in W, kept in PRODL
 * (0xFF3), stored through FSR0 + W (PLUSW0, 0xFEB);
 * FSR0 and PROD are saved by the interrupt's prologue) */
void link_rx_byte(uint8_t b) LINK_WPARAM __naked
{
    (void)b;
    __asm
    MOVWF   0xFF3, A
    MOVF    (_link_hot + 1), W, A      ; rx_ready
    BNZ     _lrx_lost           ; a frame waits: the byte is lost
    MOVF    0xFF3, F, A
    BZ      _lrx_delim
    MOVLW   46          ; LINK_RX_BYTES
    CPFSLT  (_link_hot + 0), A         ; rx_n
    BRA     _lrx_long
    MOVF    (_link_hot + 0), W, A
    LFSR    0, _rx_buf
    MOVFF   0xFF3, 0xFEB
    INCF    (_link_hot + 0), F, A      ; rx_buf[rx_n++] = b
    RETURN
_lrx_long:
    SETF    (_link_hot + 0), A         ; longer than any frame: RX_SKIP
    RETURN
_lrx_delim:
    INCF    (_link_hot + 0), W, A
    BZ      _lrx_clear          ; RX_SKIP: the garbage ends here
    MOVF    (_link_hot + 0), F, A
    BZ      _lrx_done           ; nothing since the last delimiter
    INCF    (_link_hot + 1), F, A      ; 0 -> 1: the frame is complete
_lrx_done:
    RETURN
_lrx_clear:
    CLRF    (_link_hot + 0), A
    RETURN
_lrx_lost:
    INCF    (_link_hot + 2), F, A      ; rx_ovf
    RETURN
    __endasm;
}
#else
void link_rx_byte(uint8_t b) LINK_WPARAM
{
    if (rx_ready != 0u) {              /* a frame waits for the main loop: this byte is lost */
        rx_ovf++;
    } else if (b == 0u) {              /* delimiter */
        if (rx_n == RX_SKIP) {
            rx_n = 0u;
        } else if (rx_n != 0u) {
            rx_ready = 1u;
        }
    } else if (rx_n < LINK_RX_BYTES) {
        rx_buf[rx_n] = b;
        rx_n++;
    } else {
        rx_n = RX_SKIP;                /* longer than any frame: garbage */
    }
}
#endif

/* The complete frame in rx_buf, COBS-decoded in place (each byte moves one place down, the code
 * bytes become the zeros they stand for): its body length if it passes the length and CRC checks,
 * else 0.  The frame's CRC bytes are kept in S.fc0, S.fc1 (duplicate detection). */
static uint8_t rx_frame(void)
{
    uint8_t n = (uint8_t)(rx_n - 1u), run = rx_buf[0], b;
    cp_s = &rx_buf[1];
    cp_d = rx_buf;
    while (n != 0u) {
        b = *cp_s;
        cp_s++;
        run--;
        if (run == 0u) {               /* a code byte: the zero it stands for */
            run = b;
            b = 0u;
        }
        *cp_d = b;
        cp_d++;
        n--;
    }
    n = (uint8_t)(rx_n - 1u);          /* the body length */
    if (run == 1u && n >= BODY_OVERHEAD) {
        crc_buf(rx_buf, n);            /* over the CRC too: a good frame leaves 0 */
        if ((uint8_t)(rx_buf[0] + BODY_OVERHEAD) == n && (crc_hi | crc_lo) == 0u) {
            cp_s--;
            S.fc1 = *cp_s;
            cp_s--;
            S.fc0 = *cp_s;
            return n;
        }
    }
    if (S.crc_errors != 0xFFFFu) {
        S.crc_errors++;
    }
    if (S.nack_armed != 0u && n >= PL) {
        S.nack_armed = 0u;
        S.nack_pending = 1u;
        S.nack_type = rx_buf[1];
        S.nack_seq = rx_buf[2];
    }
    return 0u;
}

static void rx_release(void)           /* rx_buf back to the interrupt */
{
    uint8_t d;
    LINK_CRITICAL_BEGIN();
    d = (uint8_t)(rx_ovf - S.rx_ovf_seen);
    S.rx_ovf_seen = rx_ovf;
    rx_n = (d != 0u) ? RX_SKIP : 0u;   /* bytes were lost: the frame they belonged to is dropped */
    rx_ready = 0u;
    LINK_CRITICAL_END();
    S.rx_overflows = (uint16_t)(S.rx_overflows + d);
    if (S.rx_overflows < d) {          /* saturate */
        S.rx_overflows = 0xFFFFu;
    }
}

/* ---- transmit: body in tx_buf[1..], COBS-encoded in place, sent as the UART queue has room ---- */
static void tx_seal(uint8_t type) LINK_WPARAM   /* payload A(0..link_hot.n-1), SEQ S.tseq */
{
    uint8_t run = 1u, len;
    tx_buf[2] = type;
    tx_buf[1] = link_hot.n;
    tx_buf[3] = S.tseq;
    len = (uint8_t)(link_hot.n + PL);
    crc_buf(&tx_buf[1], len);          /* cp_s ends on the CRC's place */
    *cp_s = crc_hi;
    cp_s++;
    *cp_s = crc_lo;
    len = (uint8_t)(len + 2u);         /* body bytes */
    link_hot.tx_len = (uint8_t)(len + 2u);    /* with the COBS code and the delimiter */
    S.tx_pos = 0u;
    cp_d = tx_buf;                     /* each zero becomes the distance to the next one */
    cp_s = &tx_buf[1];
    while (len != 0u) {
        if (*cp_s == 0u) {
            *cp_d = run;
            cp_d = cp_s;
            run = 0u;
        }
        run++;
        cp_s++;
        len--;
    }
    *cp_d = run;
}

static void tx_drain(void)
{
    uint8_t room;
    if (link_hot.tx_len == 0u) {
        return;
    }
    room = app_tx_free();
    while (room != 0u) {
        if (S.tx_pos == (uint8_t)(link_hot.tx_len - 1u)) {
            app_tx_byte(0u);           /* delimiter */
            link_hot.tx_len = 0u;
            return;
        }
        app_tx_byte(tx_buf[S.tx_pos]);
        S.tx_pos++;
        room--;
    }
}

/* ---- command handlers: arguments in R(0..link_hot.n-1), reply in A(..), its length in link_hot.n ---- */
static uint8_t drive_busy(void)
{
    int16_t st = app_signal(LINK_SIG_STATE);
    return (uint8_t)(st == (int16_t)LINK_STATE_RUN || st == (int16_t)LINK_STATE_BRAKE);
}

static uint8_t mask_ok(uint16_t mask)
{
    return (uint8_t)(mask != 0u && (mask & (uint16_t)~SIG_ALL) == 0u);
}

static void rom_copy(uint8_t n) LINK_WPARAM        /* A(link_hot.n..) = n flash bytes from link_hot.ro on */
{
    while (n != 0u) {
        A(link_hot.n) = rom_next();
        link_hot.n++;
        n--;
    }
}

static uint8_t h_hello(void)
{
    link_hot.n = 0u;
    rom_at(ROM_HELLO);
    rom_copy(20u);
    return 0u;
}

static uint8_t h_param_info(void)
{
    uint8_t idx = R(0), i;
    uint16_t a = ROM_NAMES;
    if (idx >= LINK_N_ENTRIES) {
        return LINK_NACK_UNKNOWN_PARAM;
    }
    rom_at(ROM_NAME_LEN);
    for (i = 0u; i < idx; i++) {       /* the name's offset: the lengths before it */
        a = (uint16_t)(a + rom_next());
    }
    i = rom_next();
    link_hot.n = 0u;
    row_at(idx, 0u);
    rom_copy(ROW);
    rom_at(a);
    rom_copy(i);
    return 0u;
}

static uint8_t h_param_get(void)
{
    uint8_t n = link_hot.n, i, o = 0u;
    if (n == 0u || n > LINK_PARAM_GET_MAX) {
        return LINK_NACK_MALFORMED;
    }
    for (i = 0u; i < n; i++) {
        if (entry_index(R(i)) == NONE) {
            return LINK_NACK_UNKNOWN_PARAM;
        }
    }
    for (i = 0u; i < n; i++) {
        value_at(entry_index(R(i)));
        mcopy(&A(o), V.b, 4u);
        o = (uint8_t)(o + 4u);
    }
    link_hot.n = o;
    return 0u;
}

/* set id to the value in V; reply the stored value (4 bytes) at A(at) */
static uint8_t set_reply(uint8_t id, uint8_t at)
{
    uint8_t code = set_v(id);
    if (code == 0u) {
        store_get();
        mcopy(&A(at), V.b, 4u);
    }
    return code;
}

static uint8_t h_param_set(void)
{
    mcopy(V.b, &R(1), 4u);
    A(0) = R(0);
    link_hot.n = 5u;
    return set_reply(R(0), 1u);
}

static uint8_t h_set_speed(void)
{
    mcopy(V.b, &R(0), 4u);
    link_hot.n = 4u;
    return set_reply(LINK_ID_SPEED_SETPOINT, 0u);
}

static uint8_t h_select_controller(void)
{
    uint8_t code;
    V.l = 0;
    V.b[0] = R(0);
    code = set_v(LINK_ID_CONTROLLER);
    A(0) = (uint8_t)link_params.controller;
    link_hot.n = 1u;
    return code;
}

static uint8_t h_app(void)
{
    uint8_t code = app_command(rx_buf[1], &R(0), 0u);
    link_hot.n = 0u;
    return code;
}

static uint8_t h_telem_config(void)
{
    uint16_t mask = arg16(0), dec = arg16(2u);
    uint8_t spf = R(4), nb = (uint8_t)(popcount16(mask) << 1), len = TELEM_HEADER, k;
    if (dec != 0u) {
        if (!mask_ok(mask) || spf == 0u) {
            return LINK_NACK_OUT_OF_RANGE;
        }
        for (k = 0u; k < spf; k++) {   /* TELEM_HEADER + 2 nsig spf, by additions */
            len = (uint8_t)(len + nb);
            if (len > LINK_MAX_PAYLOAD) {
                return LINK_NACK_OUT_OF_RANGE;
            }
        }
    }
    LINK_CRITICAL_BEGIN();
    link_hot.tm_dec = 0u;
    S.tm_mask = mask;
    S.tm_spf = spf;
    link_hot.tm_nb = nb;
    mzero((LINK_DATA uint8_t *)&link_hot.tr, (uint8_t)sizeof link_hot.tr);
    link_hot.tm_ready = 0u;
    S.tm_gen++;
    link_hot.tm_dec = dec;
    LINK_CRITICAL_END();
    A(0) = S.tm_gen;
    A(1) = (uint8_t)(dec != 0u ? len : 0u);
    link_hot.n = 2u;
    return 0u;
}

#if LINK_WITH_CAPTURE
static uint8_t h_capture_arm(void)
{
    uint16_t mask = arg16(0), dec = arg16(6u);
    uint8_t n = R(2), pre = R(4), trig = R(8), nsig = popcount16(mask), k, bytes = 0u, words = 0u;
    link_hot.n = 0u;
    if (!mask_ok(mask) || R(3) != 0u || R(5) != 0u || n == 0u || n > LINK_CAPTURE_WORDS || dec == 0u
        || trig > LINK_TRIG_SPEED_FALLING || pre >= n || (trig == LINK_TRIG_IMMEDIATE && pre != 0u)) {
        return LINK_NACK_OUT_OF_RANGE;
    }
    for (k = 0u; k < nsig; k++) {      /* n * nsig, by additions (n <= LINK_CAPTURE_WORDS) */
        words = (uint8_t)(words + n);
        if (words > LINK_CAPTURE_WORDS || words < n) {
            return LINK_NACK_OUT_OF_RANGE;
        }
    }
    bytes = (uint8_t)((uint8_t)(words << 1) - 1u);
    LINK_CRITICAL_BEGIN();
    S.cap_state = LINK_CAP_IDLE;
    S.cap_mask = mask;
    link_hot.cap_nb = (uint8_t)(nsig << 1);
    link_hot.cap_n = n;
    S.cap_bytes = bytes;
    S.cap_pre = pre;
    link_hot.cap_dec = dec;
    S.cap_trig = trig;
    S.cap_thr = (int16_t)arg16(9u);
    mzero((LINK_DATA uint8_t *)&S.cr, (uint8_t)sizeof S.cr);
    link_hot.cr_div = 0u;
    S.cap_sp_changed = 0u;
    S.cap_state = LINK_CAP_ARMED;
    LINK_CRITICAL_END();
    return 0u;
}

static uint8_t h_capture_read(void)
{
    uint8_t start = R(0), want = R(2), nb = link_hot.cap_nb, st = S.cap_state, p, wi = 0u, j, o;
    if (st == LINK_CAP_ARMED || st == LINK_CAP_TRIGGERED) {
        return LINK_NACK_BUSY;
    }
    if (st != LINK_CAP_DONE) {
        return LINK_NACK_WRONG_STATE;
    }
    if (R(1) != 0u || start > S.cr.total) {
        return LINK_NACK_OUT_OF_RANGE;
    }
    A(0) = st;
    A(1) = S.cr.total;
    A(2) = 0u;
    A(3) = S.cr.tidx;
    A(4) = 0u;
    A(5) = start;
    A(6) = 0u;
    p = (uint8_t)(S.cr.start + start);  /* < 2 cap_n <= 256 */
    if (p >= link_hot.cap_n) {
        p = (uint8_t)(p - link_hot.cap_n);
    }
    for (j = 0u; j < nb; j++) {        /* byte index p nb, by additions */
        wi = (uint8_t)(wi + p);
    }
    o = CAPREAD_HEADER;
    p = (uint8_t)(S.cr.total - start);  /* samples left */
    while (want != 0u && p != 0u && (uint8_t)(o + nb) <= LINK_MAX_PAYLOAD) {
        mcopy(&A(o), &cap_buf[wi], nb);
        o = (uint8_t)(o + nb);
        wi = (uint8_t)(wi + nb);
        if ((uint8_t)(wi - 1u) == S.cap_bytes) {
            wi = 0u;
        }
        want--;
        p--;
    }
    link_hot.n = o;
    return 0u;
}
#endif

static uint8_t h_eeprom_save(void)
{
    link_hot.n = 0u;
    return link_eeprom_save();
}

static uint8_t h_eeprom_load(void)
{
    link_hot.n = 0u;
    return (link_eeprom_load() != LINK_EE_OK) ? LINK_NACK_EEPROM_ERROR : 0u;
}

static uint8_t h_status(void)
{
    A(0) = (uint8_t)app_signal(LINK_SIG_STATE);
    A(1) = (uint8_t)app_signal(LINK_SIG_FAULT);
    LINK_CRITICAL_BEGIN();
    mcopy(&A(2), (LINK_DATA uint8_t *)&S, 12u);   /* capture state .. uptime, in reply order */
    LINK_CRITICAL_END();
    link_hot.n = 14u;
    return 0u;
}

static uint8_t h_none(void)
{
    link_hot.n = 0u;
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

/* dispatch table, by command code - 1; the argument length and the idle flag are in ROM_CMD */
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

static uint8_t run_command(void)       /* the handler of command S.c: 0 or a NACK code */
{
    uint8_t spec;
    if (S.c >= N_CMDS) {
        return LINK_NACK_UNKNOWN_COMMAND;
    }
    rom_at((uint16_t)(ROM_CMD + S.c));
    spec = rom_next();
    if ((uint8_t)(spec & CMD_ANY_LEN) != CMD_ANY_LEN && (uint8_t)(spec & CMD_ANY_LEN) != link_hot.n) {
        return LINK_NACK_MALFORMED;
    }
    if ((spec & CMD_IDLE) != 0u && drive_busy()) {
        return LINK_NACK_WRONG_STATE;
    }
    return cmd_fn[S.c]();
}

static void dispatch(void)
{
    uint8_t type = rx_buf[1], code;
    if ((type & LINK_ACK_BIT) != 0u || type == LINK_MSG_NACK || type == LINK_MSG_EVENT
        || type == LINK_MSG_TELEMETRY) {
        return;                        /* a board frame (an echo, a loop-back): not for us, no reply */
    }
    S.tseq = rx_buf[2];
    link_hot.n = rx_buf[0];
    S.c = (uint8_t)(type - 1u);
    if (S.c < N_CMDS) {
        S.rx_valid = 1u;               /* only a host command feeds the watchdog */
    }
    S.nack_armed = 1u;
    LINK_HOOK_FRAME(type, S.tseq, &R(0), link_hot.n);
    if (type == S.rp_type && S.tseq == S.rp_seq && S.fc0 == S.rp_crc0 && S.fc1 == S.rp_crc1
        && S.rp_len != NONE) {
        link_hot.n = S.rp_len;
        mcopy(&A(0), rp_data, link_hot.n);
        tx_seal(S.rp_rtype);
        return;
    }
    S.rp_crc0 = S.fc0;
    S.rp_crc1 = S.fc1;
    S.rp_type = type;
    S.rp_seq = S.tseq;
    code = run_command();
    type = (uint8_t)(type | LINK_ACK_BIT);
    if (code != 0u) {
        A(0) = S.rp_type;
        A(1) = code;
        link_hot.n = 2u;
        type = LINK_MSG_NACK;
    }
    S.rp_rtype = type;
    S.rp_len = NONE;
    if (link_hot.n <= LINK_REPLAY_BYTES) {
        mcopy(rp_data, &A(0), link_hot.n);
        S.rp_len = link_hot.n;
    }
    tx_seal(type);
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
    link_hot.n = 2u;
    S.tseq = S.ev_counter;
    tx_seal(LINK_MSG_EVENT);
    S.ev_counter++;
    return 1u;
}

static void wd_arm(void)
{
    S.wd_armed = (uint8_t)(app_signal(LINK_SIG_STATE) == (int16_t)LINK_STATE_RUN);
}

void link_poll(void)
{
    uint8_t k;
    for (k = 0u; k < 8u; k++) {
        wd_arm();
        tx_drain();
        if (link_hot.tx_len != 0u) {
            break;
        }
        if (S.nack_pending != 0u) {
            S.nack_pending = 0u;
            A(0) = S.nack_type;
            A(1) = LINK_NACK_BAD_CRC;
            link_hot.n = 2u;
            S.tseq = S.nack_seq;
            tx_seal(LINK_MSG_NACK);
            continue;
        }
        if (rx_ready != 0u) {
            if (rx_frame() != 0u) {
                dispatch();
            }
            rx_release();
            continue;
        }
        if (send_event() != 0u) {
            continue;
        }
        if (link_hot.tm_ready != 0u) {
            link_hot.n = link_hot.tr.len;
            mcopy(&A(0), tm_buf, link_hot.n);
            S.tseq = S.tm_gen;
            tx_seal(LINK_MSG_TELEMETRY);
            link_hot.tr.nsamp = 0u;
            link_hot.tr.len = 0u;
            link_hot.tm_ready = 0u;
            continue;
        }
        break;
    }
    /* again after dispatching: a start just executed arms the watchdog at once */
    wd_arm();
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
/* One sample's signals, read once each: those of sg.tm (telemetry) to sg.p, those of sg.cm (capture)
 * to sg.q, int16 little-endian (speed-loop interrupt only).  Each value comes straight from
 * app_signal_src[j] (no call, no lock: the interrupt owns the values), or through app_signal(j) for
 * a NULL entry.  The masks are consumed (shifted out); they are within SIG_ALL (mask_ok). */
#if defined(__SDCC_pic16)
/* PIC18 assembly: about 60 cycles a selected signal, no software-stack frame.  The flash table is
 * read with TBLRD: TBLPTR and TABLAT are saved on entry and restored on exit (hazard a: this runs
 * in an interrupt, whatever the application's prologue saves).  FSR0 and PROD are saved by the
 * interrupt's prologue; sg (one bank) holds the pointers, the masks and the index j. */
static void put_signals(void) __naked
{
    __asm
    MOVFF   0xFF8, 0xFE5            ; save TBLPTRU, TBLPTRH, TBLPTRL, TABLAT (POSTDEC1)
    MOVFF   0xFF7, 0xFE5
    MOVFF   0xFF6, 0xFE5
    MOVFF   0xFF5, 0xFE5
    MOVLW   UPPER(_app_signal_src)
    MOVWF   0xFF8, A
    MOVLW   HIGH(_app_signal_src)
    MOVWF   0xFF7, A
    MOVLW   LOW(_app_signal_src)
    MOVWF   0xFF6, A
    BANKSEL _sg
    CLRF    (_sg + 8), B            ; j = 0
lps_loop:
    TBLRD*+
    MOVFF   0xFF5, 0xFE9            ; FSR0 = app_signal_src[j]
    TBLRD*+
    MOVFF   0xFF5, 0xFEA
    MOVF    (_sg + 4), W, B
    IORWF   (_sg + 6), W, B
    BTFSS   0xFE8, 0, A             ; signal j in neither mask: next
    BRA     lps_next
    MOVF    0xFE9, W, A
    IORWF   0xFEA, W, A
    BZ      lps_call
    MOVFF   0xFEE, 0xFF3            ; PRODL, PRODH = *src (POSTINC0)
    MOVFF   0xFEE, 0xFF4
    BRA     lps_have
lps_call:                          ; NULL: app_signal(j), the table pointer kept across the call
    MOVFF   0xFF8, 0xFE5
    MOVFF   0xFF7, 0xFE5
    MOVFF   0xFF6, 0xFE5
    MOVF    (_sg + 8), W, B
    CALL    _app_signal             ; low byte in W, high byte in PRODL
    MOVFF   0xFF3, 0xFF4
    MOVWF   0xFF3, A
    MOVFF   0xFE4, 0xFF6            ; PREINC1
    MOVFF   0xFE4, 0xFF7
    MOVFF   0xFE4, 0xFF8
    BANKSEL _sg
lps_have:
    BTFSS   (_sg + 4), 0, B
    BRA     lps_cap
    MOVFF   _sg, 0xFE9              ; *sg.p++ = value
    MOVFF   (_sg + 1), 0xFEA
    MOVFF   0xFF3, 0xFEE
    MOVFF   0xFF4, 0xFEE
    MOVFF   0xFE9, _sg
    MOVFF   0xFEA, (_sg + 1)
lps_cap:
    BTFSS   (_sg + 6), 0, B
    BRA     lps_next
    MOVFF   (_sg + 2), 0xFE9        ; *sg.q++ = value
    MOVFF   (_sg + 3), 0xFEA
    MOVFF   0xFF3, 0xFEE
    MOVFF   0xFF4, 0xFEE
    MOVFF   0xFE9, (_sg + 2)
    MOVFF   0xFEA, (_sg + 3)
lps_next:
    INCF    (_sg + 8), F, B
    BCF     0xFD8, 0, A             ; tm >>= 1, cm >>= 1
    RRCF    (_sg + 5), F, B
    RRCF    (_sg + 4), F, B
    BCF     0xFD8, 0, A
    RRCF    (_sg + 7), F, B
    RRCF    (_sg + 6), F, B
    MOVF    (_sg + 4), W, B
    IORWF   (_sg + 5), W, B
    IORWF   (_sg + 6), W, B
    IORWF   (_sg + 7), W, B
    BNZ     lps_loop
    MOVFF   0xFE4, 0xFF5            ; restore TABLAT, TBLPTRL, TBLPTRH, TBLPTRU (PREINC1)
    MOVFF   0xFE4, 0xFF6
    MOVFF   0xFE4, 0xFF7
    MOVFF   0xFE4, 0xFF8
    RETURN
    __endasm;
}
#else
static void put_signals(void)
{
    uint8_t j = 0u;
    uint16_t v;
    LINK_DATA int16_t *src;
    while ((sg.tm | sg.cm) != 0u) {
        if ((uint8_t)((uint8_t)(sg.tm | sg.cm) & 1u) != 0u) {
            src = app_signal_src[j];
            v = (uint16_t)((src != 0) ? *src : app_signal(j));
            if (((uint8_t)sg.tm & 1u) != 0u) {
                *sg.p = (uint8_t)v;
                sg.p++;
                *sg.p = (uint8_t)(v >> 8);
                sg.p++;
            }
            if (((uint8_t)sg.cm & 1u) != 0u) {
                *sg.q = (uint8_t)v;
                sg.q++;
                *sg.q = (uint8_t)(v >> 8);
                sg.q++;
            }
        }
        sg.tm = (uint16_t)(sg.tm >> 1);
        sg.cm = (uint16_t)(sg.cm >> 1);
        j++;
    }
}
#endif

#if LINK_WITH_CAPTURE
static void capture_due(void)          /* decimation and trigger; a sample due: sg.q, sg.cm set */
{
    uint8_t fire = 0u, trig = S.cap_trig;
    int16_t sp, thr = S.cap_thr;
    link_hot.cr_div++;
    if (link_hot.cr_div < link_hot.cap_dec) {
        return;
    }
    link_hot.cr_div = 0u;
    if (S.cap_state == LINK_CAP_ARMED) {
        if (trig == LINK_TRIG_IMMEDIATE) {
            fire = 1u;
        } else if (trig == LINK_TRIG_SETPOINT_CHANGE) {
            fire = S.cap_sp_changed;
        } else {
            sp = app_signal(LINK_SIG_SPEED);
            if (trig == LINK_TRIG_SPEED_FALLING) {   /* falling through thr = rising through ~thr */
                sp = (int16_t)~sp;
                thr = (int16_t)~thr;
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
    sg.q = &cap_buf[S.cr.wi];
    sg.cm = S.cap_mask;
}

static void capture_done(void)         /* after a sample was written: the ring and the record */
{
    uint8_t wi = (uint8_t)(S.cr.wi + link_hot.cap_nb);
    S.cr.w++;
    if (S.cr.w == link_hot.cap_n) {
        S.cr.w = 0u;
        wi = 0u;
    }
    S.cr.wi = wi;
    if (S.cr.filled != link_hot.cap_n) {
        S.cr.filled++;
    }
    if (S.cap_state == LINK_CAP_TRIGGERED) {
        S.cr.post++;
        if (S.cr.post == (uint8_t)(link_hot.cap_n - S.cap_pre)) {
            S.cr.total = (uint8_t)(S.cr.tidx + S.cr.post);
            wi = (uint8_t)(S.cr.w - S.cr.total);   /* (w - total) mod n */
            if (S.cr.w < S.cr.total) {
                wi = (uint8_t)(wi + link_hot.cap_n);
            }
            S.cr.start = wi;
            S.cap_state = LINK_CAP_DONE;
        }
    }
}
#endif

void link_sample(void)
{
    uint8_t tel = 0u;
    sg.tm = 0u;
    sg.cm = 0u;
    if (link_hot.tm_dec != 0u) {
        link_hot.tr.div++;
        if (link_hot.tr.div >= link_hot.tm_dec) {
            link_hot.tr.div = 0u;
            if (link_hot.tm_ready != 0u) {
                if (S.tm_dropped != 0xFFFFu) {
                    S.tm_dropped++;
                }
            } else {
                if (link_hot.tr.nsamp == 0u) {
                    tm_buf[0] = (uint8_t)link_hot.tr.counter;
                    tm_buf[1] = (uint8_t)(link_hot.tr.counter >> 8);
                    link_hot.tr.len = TELEM_HEADER;
                }
                sg.p = &tm_buf[link_hot.tr.len];
                sg.tm = S.tm_mask;
                tel = 1u;
            }
            link_hot.tr.counter++;
        }
    }
#if LINK_WITH_CAPTURE
    if (S.cap_state == LINK_CAP_ARMED || S.cap_state == LINK_CAP_TRIGGERED) {
        capture_due();
    }
#endif
    if ((sg.tm | sg.cm) != 0u) {
        put_signals();
    }
    if (tel != 0u) {
        link_hot.tr.len = (uint8_t)(link_hot.tr.len + link_hot.tm_nb);
        link_hot.tr.nsamp++;
        if (link_hot.tr.nsamp >= S.tm_spf) {
            link_hot.tm_ready = 1u;
        }
    }
#if LINK_WITH_CAPTURE
    if (sg.q != 0) {
        sg.q = 0;
        capture_done();
    }
#endif
}

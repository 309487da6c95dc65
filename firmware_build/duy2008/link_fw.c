/*
 * link_fw.c -- picdrive serial link, C side: COBS framing, CRC, dispatcher with ACK/NACK and
 * duplicate-SEQ replay, parameter store with range checks, EEPROM image, telemetry, triggered
 * capture, link-loss watchdog.
 * Rendered by picdrive.link.protocol_c.render_c() from host/picdrive/link/protocol.py.  DO NOT EDIT.
 * protocol 2.1, table hash 0xA892BE6EUL
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
#if defined(__SDCC_pic16)
/* the registers the assembly names (p18f4431.inc's names): SDCC declares every SFR of the device
 * header to the assembler */
#include <xc.h>
#endif


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

#define SIG_ALL            0x0FFFu
#define NONE               0xFFu
#define NACK_ARMED         1u                        /* S.nack: a bad frame may be NACKed */
#define NACK_PENDING       2u                        /* S.nack: a BAD_CRC NACK to send */
#define EE_ALL             0xFEu                     /* S.changed: every persisted parameter (not an id) */
#define ROW                14u          /* bytes of a table row (the param_info reply head with min, max, default as 16 bits) */
#define ROW16              1u           /* 1: a row's min, max, default are 16 bits, widened by the size code */
#define ROW_DEFAULT        12u          /* the default's offset in a row */
#define EE_HEADER          8u
#define EE_DATA_BYTES      35u
#define TELEM_HEADER       2u
#define CAPREAD_HEADER     7u
#define RX_SKIP            0xFFu                     /* rx_n: discard up to the next delimiter */
#define PL                 3u                        /* payload offset in the frame body */
#define BODY_OVERHEAD      5u                        /* LEN, TYPE, SEQ, CRC high, CRC low */
#define R(i)               rx_buf[PL + (i)]          /* command arguments (decoded body in rx_buf) */
#define A(i)               tx_buf[1u + PL + (i)]     /* reply payload (body in tx_buf[1..], COBS code at 0) */
#define N_CMDS             18u
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
#define ROM_ROWS           0u   /* 434 B */
#define ROM_OFF            434u   /* 31 B */
#define ROM_SIZE           465u   /* 31 B */
#define ROM_NAME_LEN       496u   /* 31 B */
#define ROM_HELLO          527u   /* 21 B */
#define ROM_CMD            548u   /* 18 B */
#define ROM_NAMES          566u   /* 262 B */
#define ROM_EE_HEAD        828u   /* 8 B */
#define ROM_PERSIST        836u   /* 18 B */
static const uint8_t link_rom[854] = {
    /* ROM_ROWS */
    0x00u, 0x04u, 0x01u, 0x01u, 0xEBu, 0xC9u, 0x18u, 0x3Eu, 0xEFu, 0xBBu, 0x11u, 0x44u, 0x00u, 0x00u,   /* speed_setpoint */
    0x01u, 0x01u, 0x03u, 0x0Cu, 0x00u, 0x00u, 0x80u, 0x3Fu, 0x00u, 0x00u, 0x01u, 0x00u, 0x01u, 0x00u,   /* controller */
    0x02u, 0x04u, 0x03u, 0x01u, 0xEBu, 0xC9u, 0x18u, 0x3Eu, 0x00u, 0x00u, 0xFFu, 0x7Fu, 0x00u, 0x00u,   /* premise_low */
    0x03u, 0x04u, 0x03u, 0x01u, 0xEBu, 0xC9u, 0x18u, 0x3Eu, 0x00u, 0x00u, 0xFFu, 0x7Fu, 0x11u, 0x44u,   /* premise_high */
    0x04u, 0x04u, 0x03u, 0x00u, 0x00u, 0x00u, 0x80u, 0x38u, 0x00u, 0x00u, 0xFFu, 0x7Fu, 0xB5u, 0x44u,   /* setpoint_weight */
    0x05u, 0x04u, 0x03u, 0x03u, 0x00u, 0x00u, 0x80u, 0x3Bu, 0xD8u, 0xD3u, 0x00u, 0x00u, 0xD8u, 0xD3u,   /* u_min */
    0x06u, 0x04u, 0x03u, 0x03u, 0x00u, 0x00u, 0x80u, 0x3Bu, 0x00u, 0x00u, 0x28u, 0x2Cu, 0x28u, 0x2Cu,   /* u_max */
    0x07u, 0x04u, 0x03u, 0x04u, 0x00u, 0x00u, 0xA0u, 0x3Bu, 0x00u, 0x00u, 0xFFu, 0x03u, 0x33u, 0x01u,   /* current_limit */
    0x08u, 0x03u, 0x03u, 0x02u, 0x30u, 0x35u, 0x15u, 0x43u, 0x00u, 0x00u, 0xFFu, 0xFFu, 0x00u, 0x00u,   /* accel_limit */
    0x09u, 0x03u, 0x03u, 0x09u, 0x00u, 0x00u, 0x80u, 0x3Fu, 0x14u, 0x00u, 0x60u, 0xEAu, 0xF4u, 0x01u,   /* link_timeout */
    0x0Au, 0x03u, 0x03u, 0x09u, 0x00u, 0x00u, 0x80u, 0x3Fu, 0x0Au, 0x00u, 0x60u, 0xEAu, 0xF4u, 0x01u,   /* stall_timeout */
    0x20u, 0x04u, 0x04u, 0x01u, 0xEBu, 0xC9u, 0x18u, 0x3Eu, 0x00u, 0x80u, 0xFFu, 0x7Fu, 0x00u, 0x00u,   /* speed */
    0x21u, 0x04u, 0x04u, 0x01u, 0xEBu, 0xC9u, 0x18u, 0x3Eu, 0x00u, 0x80u, 0xFFu, 0x7Fu, 0x00u, 0x00u,   /* setpoint */
    0x22u, 0x04u, 0x04u, 0x03u, 0x00u, 0x00u, 0x80u, 0x3Bu, 0x00u, 0x80u, 0xFFu, 0x7Fu, 0x00u, 0x00u,   /* voltage */
    0x23u, 0x04u, 0x04u, 0x04u, 0x00u, 0x00u, 0xA0u, 0x3Bu, 0x01u, 0xFCu, 0xFFu, 0x03u, 0x00u, 0x00u,   /* current */
    0x24u, 0x04u, 0x04u, 0x03u, 0x00u, 0x00u, 0x80u, 0x3Bu, 0x00u, 0x80u, 0xFFu, 0x7Fu, 0x00u, 0x00u,   /* integrator */
    0x25u, 0x04u, 0x04u, 0x0Au, 0x00u, 0x00u, 0x80u, 0x3Fu, 0x30u, 0xF8u, 0xD0u, 0x07u, 0x00u, 0x00u,   /* duty */
    0x26u, 0x04u, 0x04u, 0x0Bu, 0x00u, 0x00u, 0x80u, 0x3Fu, 0x00u, 0x80u, 0xFFu, 0x7Fu, 0x00u, 0x00u,   /* hall */
    0x27u, 0x04u, 0x04u, 0x0Cu, 0x00u, 0x00u, 0x80u, 0x3Fu, 0x00u, 0x80u, 0xFFu, 0x7Fu, 0x00u, 0x00u,   /* state */
    0x28u, 0x04u, 0x04u, 0x0Bu, 0x00u, 0x00u, 0x80u, 0x3Fu, 0x00u, 0x80u, 0xFFu, 0x7Fu, 0x00u, 0x00u,   /* fault */
    0x29u, 0x04u, 0x04u, 0x00u, 0x00u, 0x00u, 0x80u, 0x39u, 0x00u, 0x00u, 0x00u, 0x10u, 0x00u, 0x10u,   /* mu1 */
    0x2Au, 0x04u, 0x04u, 0x0Au, 0x00u, 0x00u, 0x80u, 0x3Fu, 0x00u, 0x80u, 0xFFu, 0x7Fu, 0x00u, 0x00u,   /* position */
    0x2Bu, 0x04u, 0x04u, 0x03u, 0x00u, 0x00u, 0xC0u, 0x3Du, 0x00u, 0x00u, 0xFFu, 0x03u, 0x00u, 0x00u,   /* bus_voltage */
    0x40u, 0x04u, 0x03u, 0x05u, 0x00u, 0x00u, 0x80u, 0x39u, 0x00u, 0x80u, 0xFFu, 0x7Fu, 0x49u, 0x23u,   /* rule1_kp */
    0x41u, 0x04u, 0x03u, 0x06u, 0x00u, 0x00u, 0x7Au, 0x3Cu, 0x00u, 0x80u, 0xFFu, 0x7Fu, 0xD9u, 0x2Fu,   /* rule1_ki */
    0x42u, 0x04u, 0x03u, 0x07u, 0x6Fu, 0x12u, 0x83u, 0x32u, 0x00u, 0x80u, 0xFFu, 0x7Fu, 0x00u, 0x00u,   /* rule1_kd */
    0x43u, 0x04u, 0x03u, 0x08u, 0xCDu, 0xCCu, 0x4Cu, 0x3Bu, 0x00u, 0x80u, 0xFFu, 0x7Fu, 0x79u, 0x21u,   /* rule1_kc */
    0x44u, 0x04u, 0x03u, 0x05u, 0x00u, 0x00u, 0x80u, 0x39u, 0x00u, 0x80u, 0xFFu, 0x7Fu, 0xD7u, 0x1Eu,   /* rule2_kp */
    0x45u, 0x04u, 0x03u, 0x06u, 0x00u, 0x00u, 0x7Au, 0x3Cu, 0x00u, 0x80u, 0xFFu, 0x7Fu, 0xD4u, 0x28u,   /* rule2_ki */
    0x46u, 0x04u, 0x03u, 0x07u, 0x6Fu, 0x12u, 0x83u, 0x32u, 0x00u, 0x80u, 0xFFu, 0x7Fu, 0x00u, 0x00u,   /* rule2_kd */
    0x47u, 0x04u, 0x03u, 0x08u, 0xCDu, 0xCCu, 0x4Cu, 0x3Bu, 0x00u, 0x80u, 0xFFu, 0x7Fu, 0x66u, 0x15u,   /* rule2_kc */
    /* ROM_OFF */
    (uint8_t)offsetof(link_params_t, speed_setpoint), (uint8_t)offsetof(link_params_t, controller), (uint8_t)offsetof(link_params_t, premise_low), (uint8_t)offsetof(link_params_t, premise_high),
    (uint8_t)offsetof(link_params_t, setpoint_weight), (uint8_t)offsetof(link_params_t, u_min), (uint8_t)offsetof(link_params_t, u_max), (uint8_t)offsetof(link_params_t, current_limit),
    (uint8_t)offsetof(link_params_t, accel_limit), (uint8_t)offsetof(link_params_t, link_timeout), (uint8_t)offsetof(link_params_t, stall_timeout), NONE,
    NONE, NONE, NONE, NONE,
    NONE, NONE, NONE, NONE,
    NONE, NONE, NONE, (uint8_t)offsetof(link_params_t, rule1_kp),
    (uint8_t)offsetof(link_params_t, rule1_ki), (uint8_t)offsetof(link_params_t, rule1_kd), (uint8_t)offsetof(link_params_t, rule1_kc), (uint8_t)offsetof(link_params_t, rule2_kp),
    (uint8_t)offsetof(link_params_t, rule2_ki), (uint8_t)offsetof(link_params_t, rule2_kd), (uint8_t)offsetof(link_params_t, rule2_kc),
    /* ROM_SIZE */
    0x82u, 0x01u, 0x82u, 0x82u, 0x82u, 0x82u, 0x82u, 0x82u, 0x02u, 0x02u, 0x02u, 0x82u,
    0x82u, 0x82u, 0x82u, 0x82u, 0x82u, 0x82u, 0x82u, 0x82u, 0x82u, 0x82u, 0x82u, 0x82u,
    0x82u, 0x82u, 0x82u, 0x82u, 0x82u, 0x82u, 0x82u,
    /* ROM_NAME_LEN */
    14u, 10u, 11u, 12u, 15u, 5u, 5u, 13u, 11u, 12u, 13u, 5u,
    8u, 7u, 7u, 10u, 4u, 4u, 5u, 5u, 3u, 8u, 11u, 8u,
    8u, 8u, 8u, 8u, 8u, 8u, 8u,
    /* ROM_HELLO */
    LINK_PROTO_MAJOR, LINK_PROTO_MINOR, (uint8_t)LINK_BUILD_ID, (uint8_t)(LINK_BUILD_ID >> 8u),
    (uint8_t)(LINK_BUILD_ID >> 16u), (uint8_t)(LINK_BUILD_ID >> 24u), (uint8_t)LINK_PROFILE_HASH, (uint8_t)(LINK_PROFILE_HASH >> 8u),
    (uint8_t)(LINK_PROFILE_HASH >> 16u), (uint8_t)(LINK_PROFILE_HASH >> 24u), (uint8_t)LINK_TABLE_HASH, (uint8_t)(LINK_TABLE_HASH >> 8u),
    (uint8_t)(LINK_TABLE_HASH >> 16u), (uint8_t)(LINK_TABLE_HASH >> 24u), LINK_N_ENTRIES, LINK_MAX_PAYLOAD,
    (uint8_t)LINK_HELLO_CAPTURE_WORDS, (uint8_t)(LINK_HELLO_CAPTURE_WORDS >> 8u), (uint8_t)LINK_SAMPLE_HZ, (uint8_t)(LINK_SAMPLE_HZ >> 8u),
    LINK_FEATURES,
    /* ROM_CMD */
    0x00u, 0x01u, 0x7Fu, 0x05u, 0x04u, 0x00u, 0x00u, 0x00u, 0x01u, 0x05u, 0x0Bu, 0x03u,
    0x80u, 0x80u, 0x00u, 0x00u, 0x00u, 0x04u,
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
    0x6Du, 0x75u, 0x31u, 0x70u, 0x6Fu, 0x73u, 0x69u, 0x74u, 0x69u, 0x6Fu, 0x6Eu, 0x62u, 0x75u, 0x73u, 0x5Fu, 0x76u,
    0x6Fu, 0x6Cu, 0x74u, 0x61u, 0x67u, 0x65u, 0x72u, 0x75u, 0x6Cu, 0x65u, 0x31u, 0x5Fu, 0x6Bu, 0x70u, 0x72u, 0x75u,
    0x6Cu, 0x65u, 0x31u, 0x5Fu, 0x6Bu, 0x69u, 0x72u, 0x75u, 0x6Cu, 0x65u, 0x31u, 0x5Fu, 0x6Bu, 0x64u, 0x72u, 0x75u,
    0x6Cu, 0x65u, 0x31u, 0x5Fu, 0x6Bu, 0x63u, 0x72u, 0x75u, 0x6Cu, 0x65u, 0x32u, 0x5Fu, 0x6Bu, 0x70u, 0x72u, 0x75u,
    0x6Cu, 0x65u, 0x32u, 0x5Fu, 0x6Bu, 0x69u, 0x72u, 0x75u, 0x6Cu, 0x65u, 0x32u, 0x5Fu, 0x6Bu, 0x64u, 0x72u, 0x75u,
    0x6Cu, 0x65u, 0x32u, 0x5Fu, 0x6Bu, 0x63u,
    /* ROM_EE_HEAD */
    0x50u, 0x44u, 0x01u, (uint8_t)LINK_TABLE_HASH, (uint8_t)(LINK_TABLE_HASH >> 8u), (uint8_t)(LINK_TABLE_HASH >> 16u), (uint8_t)(LINK_TABLE_HASH >> 24u), EE_DATA_BYTES,
    /* ROM_PERSIST */
    1u, 2u, 3u, 4u, 5u, 6u, 7u, 8u, 9u, 10u, 23u, 24u,
    25u, 26u, 27u, 28u, 29u, 30u,
};

/* ---- buffers ---- */
static uint8_t rx_buf[LINK_RX_BYTES];          /* raw frame (COBS code + body), decoded in place */
/* the bytes that arrive while the main loop holds rx_buf (rx_ready != 0): a ring the interrupt
 * fills at rx_sp_w and the main loop empties at rx_sp_r (one slot stays free), single bytes */
static uint8_t rx_spill[LINK_RX_SPILL];
static volatile uint8_t rx_sp_w;
static volatile uint8_t rx_sp_r;
static uint8_t tx_buf[1u + LINK_MAX_BODY];     /* COBS code, then the body being sent, encoded in place */
static uint8_t tm_buf[LINK_MAX_PAYLOAD];       /* telemetry payload being filled by link_sample */
static uint8_t rp_data[LINK_REPLAY_BYTES];     /* last short reply, for duplicate-SEQ replay */
#if LINK_WITH_CAPTURE
static uint8_t cap_buf[2u * LINK_CAPTURE_WORDS]; /* capture ring, sample-major, int16 little-endian */
#endif

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
#if defined(__SDCC_pic16)
/* struct link_fast's fields the assembly addresses, by byte offset (SDCC packs the struct: no
 * padding), each checked against offsetof */
#define LH_RX_N 0
#define LH_RX_READY 1
#define LH_RX_OVF 2
#define LH_CRC_HI 3
#define LH_CRC_LO 4
#define LH_N 5
#define LH_RO 6
#define LH_E_OFF 8
#define LH_E_SZ 9
#define LH_TX_LEN 10
#define LH_TM_READY 11
#define LH_TM_NB 12
#define LH_TM_DEC 13
#define LH_TR_DIV 15
#define LH_TR_COUNTER 17
#define LH_TR_NSAMP 19
#define LH_TR_LEN 20
typedef char link_fast_offsets[(offsetof(struct link_fast, rx_n) == LH_RX_N
    && offsetof(struct link_fast, rx_ready) == LH_RX_READY
    && offsetof(struct link_fast, rx_ovf) == LH_RX_OVF
    && offsetof(struct link_fast, crc_hi) == LH_CRC_HI
    && offsetof(struct link_fast, crc_lo) == LH_CRC_LO
    && offsetof(struct link_fast, n) == LH_N
    && offsetof(struct link_fast, ro) == LH_RO
    && offsetof(struct link_fast, e_off) == LH_E_OFF
    && offsetof(struct link_fast, e_sz) == LH_E_SZ
    && offsetof(struct link_fast, tx_len) == LH_TX_LEN
    && offsetof(struct link_fast, tm_ready) == LH_TM_READY
    && offsetof(struct link_fast, tm_nb) == LH_TM_NB
    && offsetof(struct link_fast, tm_dec) == LH_TM_DEC
    && offsetof(struct link_fast, tr.div) == LH_TR_DIV
    && offsetof(struct link_fast, tr.counter) == LH_TR_COUNTER
    && offsetof(struct link_fast, tr.nsamp) == LH_TR_NSAMP
    && offsetof(struct link_fast, tr.len) == LH_TR_LEN) ? 1 : -1];
#if LINK_WITH_CAPTURE
#define LH_CAP_N 21
#define LH_CAP_NB 22
#define LH_CAP_DEC 23
#define LH_CR_DIV 25
typedef char link_fast_capture_offsets[(offsetof(struct link_fast, cap_n) == LH_CAP_N
    && offsetof(struct link_fast, cap_nb) == LH_CAP_NB
    && offsetof(struct link_fast, cap_dec) == LH_CAP_DEC
    && offsetof(struct link_fast, cr_div) == LH_CR_DIV) ? 1 : -1];
#endif
#endif

#if defined(__SDCC_pic16)
typedef char link_fast_layout[(LINK_ACCESS_AT + sizeof(struct link_fast) <= 0x40u) ? 1 : -1];
#else
typedef char link_fast_layout[(offsetof(struct link_fast, crc_lo) == 4u) ? 1 : -1];
#endif
#define rx_n link_hot.rx_n
#define rx_ready link_hot.rx_ready
#define rx_ovf link_hot.rx_ovf
#define crc_hi link_hot.crc_hi
#define crc_lo link_hot.crc_lo

/* the sample being written (speed-loop interrupt only): telemetry and capture destinations,
 * the masks still to write (put_signals' assembly addresses the fields by offset) */
static struct link_sg {
    LINK_DATA uint8_t *p;
    LINK_DATA uint8_t *q;              /* 0: no capture sample */
    uint16_t tm;
    uint16_t cm;
} sg;
#if defined(__SDCC_pic16)
/* struct link_sg's fields the assembly addresses, by byte offset (SDCC packs the struct: no
 * padding), each checked against offsetof */
#define SG_P 0
#define SG_Q 2
#define SG_TM 4
#define SG_CM 6
typedef char link_sg_offsets[(offsetof(struct link_sg, p) == SG_P
    && offsetof(struct link_sg, q) == SG_Q
    && offsetof(struct link_sg, tm) == SG_TM
    && offsetof(struct link_sg, cm) == SG_CM) ? 1 : -1];
#endif
static union { int32_t l; uint8_t b[4]; } V;   /* the value being moved (main loop only) */
/* copies and loops walk static data-space pointers: no arguments on the software stack */
static LINK_DATA uint8_t *cp_d;
static LINK_DATA uint8_t *cp_s;

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
    uint8_t nack;                      /* one BAD_CRC NACK per valid frame: NACK_ARMED, then NACK_PENDING */
    uint8_t nack_type;
    uint8_t nack_seq;
    /* replay */
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
    uint8_t changed;                   /* parameter to announce (app_param_changed) after the command:
                                        * NONE, an id, or EE_ALL (every persisted one) */
    uint8_t fc0;                       /* CRC bytes of the frame being dispatched */
    uint8_t fc1;
    uint8_t rx_lost_at;                /* bytes were lost to a full spill ring after its byte at
                                        * this index (NONE: no loss pending) */
} S;
#if defined(__SDCC_pic16)
/* struct link_state's fields the assembly addresses, by byte offset (SDCC packs the struct: no
 * padding), each checked against offsetof */
#define LS_TM_GEN 1
#define LS_TM_DROPPED 6
#define LS_UPTIME_MS 8
#define LS_RX_VALID 13
#define LS_NACK 14
#define LS_NACK_TYPE 15
#define LS_NACK_SEQ 16
#define LS_TSEQ 17
#define LS_TX_POS 19
#define LS_TM_SPF 20
#define LS_WD_ARMED 27
#define LS_WD_MS 28
#define LS_EV_WATCHDOG 33
#define LS_TM_MASK 35
#if LINK_WITH_CAPTURE
#define LS_CHANGED 55
#else
#define LS_CHANGED 37
#endif
typedef char link_state_offsets[(offsetof(struct link_state, tm_gen) == LS_TM_GEN
    && offsetof(struct link_state, tm_dropped) == LS_TM_DROPPED
    && offsetof(struct link_state, uptime_ms) == LS_UPTIME_MS
    && offsetof(struct link_state, rx_valid) == LS_RX_VALID
    && offsetof(struct link_state, nack) == LS_NACK
    && offsetof(struct link_state, nack_type) == LS_NACK_TYPE
    && offsetof(struct link_state, nack_seq) == LS_NACK_SEQ
    && offsetof(struct link_state, tseq) == LS_TSEQ
    && offsetof(struct link_state, tx_pos) == LS_TX_POS
    && offsetof(struct link_state, tm_spf) == LS_TM_SPF
    && offsetof(struct link_state, wd_armed) == LS_WD_ARMED
    && offsetof(struct link_state, wd_ms) == LS_WD_MS
    && offsetof(struct link_state, ev_watchdog) == LS_EV_WATCHDOG
    && offsetof(struct link_state, tm_mask) == LS_TM_MASK
    && offsetof(struct link_state, changed) == LS_CHANGED) ? 1 : -1];
#if LINK_WITH_CAPTURE
#define LS_CAP_SP_CHANGED 37
#define LS_CAP_TRIG 38
#define LS_CAP_BYTES 39
#define LS_CAP_PRE 40
#define LS_CAP_MASK 41
#define LS_CAP_THR 43
#define LS_CR_W 45
#define LS_CR_WI 46
#define LS_CR_FILLED 47
#define LS_CR_POST 48
#define LS_CR_TOTAL 49
#define LS_CR_START 50
#define LS_CR_TIDX 51
#define LS_CR_PREV_VALID 52
#define LS_CR_PREV 53
typedef char link_state_capture_offsets[(offsetof(struct link_state, cap_sp_changed) == LS_CAP_SP_CHANGED
    && offsetof(struct link_state, cap_trig) == LS_CAP_TRIG
    && offsetof(struct link_state, cap_bytes) == LS_CAP_BYTES
    && offsetof(struct link_state, cap_pre) == LS_CAP_PRE
    && offsetof(struct link_state, cap_mask) == LS_CAP_MASK
    && offsetof(struct link_state, cap_thr) == LS_CAP_THR
    && offsetof(struct link_state, cr.w) == LS_CR_W
    && offsetof(struct link_state, cr.wi) == LS_CR_WI
    && offsetof(struct link_state, cr.filled) == LS_CR_FILLED
    && offsetof(struct link_state, cr.post) == LS_CR_POST
    && offsetof(struct link_state, cr.total) == LS_CR_TOTAL
    && offsetof(struct link_state, cr.start) == LS_CR_START
    && offsetof(struct link_state, cr.tidx) == LS_CR_TIDX
    && offsetof(struct link_state, cr.prev_valid) == LS_CR_PREV_VALID
    && offsetof(struct link_state, cr.prev) == LS_CR_PREV) ? 1 : -1];
#endif
#endif

typedef char link_status_layout[(offsetof(struct link_state, uptime_ms) == 8u) ? 1 : -1];

/* ---- little helpers ---- */
#define put16(o, v) do { uint16_t v_ = (v); A(o) = (uint8_t)v_; A((o) + 1u) = (uint8_t)(v_ >> 8); } while (0)
#define arg16(o) ((uint16_t)((uint16_t)R(o) | (uint16_t)((uint16_t)R((o) + 1u) << 8)))


#if defined(__SDCC_pic16)
/* PIC18 assembly (main loop only): FSR0, PROD and the table pointer are the compiler's scratch
 * registers.  FSR2 is not used: it is the compiler's frame pointer, and a function of an
 * interrupt that sets it saves only its low byte (the stack's bank is fixed). */
/* Contract: in n (W, 0: nothing), cp_s, cp_d; out the n bytes copied, cp_s and cp_d past them;
 * clobbers W, STATUS, PROD, FSR0; n <= 255, the pointers stay in the data space. */
static void mcopy_n(uint8_t n) LINK_WPARAM __naked  /* cp_d[0..n-1] = cp_s[0..n-1] (RAM to RAM) */
{
    (void)n;
    __asm
    MOVWF   _PRODL, A               ; PRODL = n
    MOVF    _PRODL, F, A
    BZ      lmc_end
lmc_loop:
    MOVFF   _cp_s, _FSR0L           ; PRODH = *cp_s++ (FSR0 only: FSR2 is the frame pointer of an
    MOVFF   (_cp_s + 1), _FSR0H     ; interrupt function, which saves only its low byte)
    MOVFF   _POSTINC0, _PRODH
    MOVFF   _FSR0L, _cp_s
    MOVFF   _FSR0H, (_cp_s + 1)
    MOVFF   _cp_d, _FSR0L           ; *cp_d++ = PRODH
    MOVFF   (_cp_d + 1), _FSR0H
    MOVFF   _PRODH, _POSTINC0
    MOVFF   _FSR0L, _cp_d
    MOVFF   _FSR0H, (_cp_d + 1)
    DECFSZ  _PRODL, F, A
    BRA     lmc_loop
lmc_end:
    RETURN
    __endasm;
}

/* Contract: in n (W, 0: nothing), cp_d; out n zero bytes, cp_d past them; clobbers W, STATUS,
 * PROD, FSR0. */
static void mzero_n(uint8_t n) LINK_WPARAM __naked  /* cp_d[0..n-1] = 0 */
{
    (void)n;
    __asm
    MOVWF   _PRODL, A
    MOVF    _PRODL, F, A
    BZ      lmz_end
    MOVFF   _cp_d, _FSR0L
    MOVFF   (_cp_d + 1), _FSR0H
lmz_loop:
    CLRF    _POSTINC0, A
    DECFSZ  _PRODL, F, A
    BRA     lmz_loop
    MOVFF   _FSR0L, _cp_d
    MOVFF   _FSR0H, (_cp_d + 1)
lmz_end:
    RETURN
    __endasm;
}

/* Contract: in link_hot.ro; out W = link_rom[ro], ro + 1 (wraps modulo 2^16, beyond the table's
 * size); clobbers STATUS, TBLPTR, TABLAT (main loop only: an interrupt that reads tables saves
 * them itself). */
static uint8_t rom_next(void) __naked  /* link_rom[link_hot.ro++]: the module's only flash read */
{
    __asm
    MOVLW   LOW(_link_rom)
    ADDWF   (_link_hot + LH_RO), W, A   ; TBLPTR = link_rom + ro
    MOVWF   _TBLPTRL, A
    MOVLW   HIGH(_link_rom)
    ADDWFC  (_link_hot + LH_RO + 1), W, A
    MOVWF   _TBLPTRH, A
    CLRF    _TBLPTRU, A             ; (CLRF and MOVLW keep the carry)
    MOVLW   UPPER(_link_rom)
    ADDWFC  _TBLPTRU, F, A
    TBLRD*
    INFSNZ  (_link_hot + LH_RO), F, A   ; ro++
    INCF    (_link_hot + LH_RO + 1), F, A
    MOVF    _TABLAT, W, A
    RETURN
    __endasm;
}
#else
static void mcopy_n(uint8_t n) LINK_WPARAM         /* cp_d[0..n-1] = cp_s[0..n-1] (RAM to RAM) */
{
    while (n != 0u) {
        *cp_d = *cp_s;
        cp_d++;
        cp_s++;
        n--;
    }
}

static void mzero_n(uint8_t n) LINK_WPARAM
{
    while (n != 0u) {
        *cp_d = 0u;
        cp_d++;
        n--;
    }
}

static uint8_t rom_next(void)          /* link_rom[link_hot.ro++]: the module's only flash read */
{
    uint8_t b = link_rom[link_hot.ro];
    link_hot.ro++;
    return b;
}
#endif
#define mcopy(d, src, n) do { cp_d = (d); cp_s = (src); mcopy_n(n); } while (0)
#define mzero(d, n) do { cp_d = (d); mzero_n(n); } while (0)

#define rom_at(o) (link_hot.ro = (uint16_t)(o))

/* The signals of the mask in the command's first two argument bytes (telem_config, capture_arm):
 * their number, or 0 for an empty mask or one with bits beyond the table's signals. */
#if defined(__SDCC_pic16)
/* Contract: in R(0..1), the command's signal mask; out W = the number of signals in it, 0 for an
 * empty mask or a bit beyond the table; clobbers W, STATUS, PROD, TABLAT. */
static uint8_t mask_nsig(void) __naked     /* PROD shifts, TABLAT counts */
{
    __asm
    MOVFF   (_rx_buf + 3), _PRODL   ; PRODL, PRODH = R(0), R(1)
    MOVFF   (_rx_buf + 4), _PRODH
    MOVLW   0xF0
    ANDWF   _PRODH, W, A
    BNZ     lmn_bad
    MOVLW   0x00
    ANDWF   _PRODL, W, A
    BNZ     lmn_bad
    CLRF    _TABLAT, A
lmn_loop:
    MOVF    _PRODL, W, A
    IORWF   _PRODH, W, A
    BZ      lmn_end
    BCF     _STATUS, 0, A
    RRCF    _PRODH, F, A
    RRCF    _PRODL, F, A
    BTFSC   _STATUS, 0, A
    INCF    _TABLAT, F, A
    BRA     lmn_loop
lmn_end:
    MOVF    _TABLAT, W, A
    RETURN
lmn_bad:
    RETLW   0
    __endasm;
}
#else
static uint8_t mask_nsig(void)
{
    uint16_t m = (uint16_t)((uint16_t)rx_buf[PL] | (uint16_t)((uint16_t)rx_buf[PL + 1u] << 8));
    uint8_t n = 0u;
    if ((m & (uint16_t)~SIG_ALL) != 0u) {
        return 0u;
    }
    while (m != 0u) {
        n = (uint8_t)(n + ((uint8_t)m & 1u));
        m = (uint16_t)(m >> 1);
    }
    return n;
}
#endif

/* CRC-16/CCITT-FALSE (poly 0x1021) byte-wise without a table, on two bytes of state: 8-bit
 * shifts and XORs only (a shift form needs no 512 B table and no 16-bit arithmetic) */
#define CRC_INIT() do { crc_hi = 0xFFu; crc_lo = 0xFFu; } while (0)

#if defined(__SDCC_pic16)
/* the same steps in PIC18 assembly (20 cycles instead of 70; x in PRODL, a rotation in PRODH:
 * scratch registers the compiler does not keep values in across a call) */
/* Contract: in b (W), crc_hi:crc_lo; out the CRC-16/CCITT state after b; clobbers W, STATUS,
 * PROD (FSR0 and TABLAT kept: crc_n counts in them); 8-bit register arithmetic, no overflow. */
static void crc_byte(uint8_t b) LINK_WPARAM __naked
{
    (void)b;
    __asm
    XORWF   (_link_hot + LH_CRC_HI), W, A      ; x = hi ^ b
    MOVWF   _PRODL, A
    SWAPF   _PRODL, W, A
    ANDLW   0x0F
    XORWF   _PRODL, F, A        ; x ^= x >> 4
    SWAPF   _PRODL, W, A
    ANDLW   0xF0                ; x << 4
    XORWF   (_link_hot + LH_CRC_LO), W, A
    MOVWF   (_link_hot + LH_CRC_HI), A         ; hi = lo ^ (x << 4)
    SWAPF   _PRODL, W, A
    RLNCF   _WREG, W, A         ; x rotated right by 3
    MOVWF   _PRODH, A
    ANDLW   0x1F                ; x >> 3
    XORWF   (_link_hot + LH_CRC_HI), F, A      ; hi ^= x >> 3
    MOVF    _PRODH, W, A
    ANDLW   0xE0                ; x << 5
    XORWF   _PRODL, W, A
    MOVWF   (_link_hot + LH_CRC_LO), A         ; lo = x ^ (x << 5)
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

/* CRC of cp_s[0..n-1] into crc_hi, crc_lo; cp_s ends after them */
#if defined(__SDCC_pic16)
/* Contract: in n (W), cp_s; out crc_hi:crc_lo after the n bytes, cp_s past them; clobbers W,
 * STATUS, PROD, FSR0, TABLAT. */
static void crc_n(uint8_t n) LINK_WPARAM __naked   /* TABLAT counts (crc_byte keeps it and FSR0) */
{
    (void)n;
    __asm
    MOVWF   _TABLAT, A
    SETF    (_link_hot + LH_CRC_HI), A      ; CRC_INIT
    SETF    (_link_hot + LH_CRC_LO), A
    MOVF    _TABLAT, F, A
    BZ      lcrc_end
    MOVFF   _cp_s, _FSR0L
    MOVFF   (_cp_s + 1), _FSR0H
lcrc_loop:
    MOVF    _POSTINC0, W, A
    CALL    _crc_byte
    DECFSZ  _TABLAT, F, A
    BRA     lcrc_loop
    MOVFF   _FSR0L, _cp_s
    MOVFF   _FSR0H, (_cp_s + 1)
lcrc_end:
    RETURN
    __endasm;
}
#else
static void crc_n(uint8_t n) LINK_WPARAM
{
    CRC_INIT();
    while (n != 0u) {
        crc_byte(*cp_s);
        cp_s++;
        n--;
    }
}
#endif
#define crc_buf(p, n) do { cp_s = (p); crc_n(n); } while (0)

#if LINK_WITH_HOST_API
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
#endif

/* ---- the table: ids in contiguous runs, so the index is a subtraction ---- */
static uint8_t entry_index(uint8_t id) LINK_WPARAM
{
    if ((uint8_t)(id - 0x00u) < 11u) {
        return (uint8_t)(id - 0u);
    }
    if ((uint8_t)(id - 0x20u) < 12u) {
        return (uint8_t)(id - 21u);
    }
    if ((uint8_t)(id - 0x40u) < 8u) {
        return (uint8_t)(id - 41u);
    }
    return NONE;
}

#if defined(__SDCC_pic16)
/* Contract: in idx (W); out link_hot.ro = idx ROW (one 8x8 product: 255 ROW < 2^16); clobbers W,
 * PROD. */
static void row_of(uint8_t idx) LINK_WPARAM __naked   /* link_hot.ro = the entry's row: idx ROW (MULLW) */
{
    (void)idx;
    __asm
    MULLW   14
    MOVFF   _PRODL, (_link_hot + LH_RO)
    MOVFF   _PRODH, (_link_hot + LH_RO + 1)
    RETURN
    __endasm;
}
#else
static void row_of(uint8_t idx) LINK_WPARAM        /* link_hot.ro = the entry's row */
{
    link_hot.ro = (uint16_t)((uint16_t)idx * ROW);
}
#endif
#define row_at(idx, k) do { row_of(idx); link_hot.ro = (uint16_t)(link_hot.ro + (k)); } while (0)

#if defined(__SDCC_pic16)
typedef char link_entry_layout[(ROM_SIZE == ROM_OFF + LINK_N_ENTRIES
                                && ROM_OFF == 434u) ? 1 : -1];
/* PIC18 assembly (the C below, step for step): ROM_SIZE + idx is one table further on */
/* Contract: in idx (W) < LINK_N_ENTRIES; out link_hot.e_off, .e_sz (.ro just past e_sz's byte);
 * clobbers W, STATUS, TBLPTR, TABLAT (PROD kept). */
static void entry_load(uint8_t idx) LINK_WPARAM __naked   /* link_hot.e_off, link_hot.e_sz */
{
    (void)idx;
    __asm
    ADDLW   178                 ; rom_at(ROM_OFF + idx)
    MOVWF   (_link_hot + LH_RO), A
    MOVLW   1
    BTFSC   _STATUS, 0, A
    ADDLW   1
    MOVWF   (_link_hot + LH_RO + 1), A
    CALL    _rom_next
    MOVWF   (_link_hot + LH_E_OFF), A
    MOVLW   30                  ; rom_at(ROM_SIZE + idx): LINK_N_ENTRIES - 1 past the byte read
    ADDWF   (_link_hot + LH_RO), F, A
    MOVLW   0
    ADDWFC  (_link_hot + LH_RO + 1), F, A
    CALL    _rom_next
    MOVWF   (_link_hot + LH_E_SZ), A
    RETURN
    __endasm;
}
#else
static void entry_load(uint8_t idx) LINK_WPARAM   /* link_hot.e_off, link_hot.e_sz */
{
    rom_at((uint16_t)(ROM_OFF + idx));
    link_hot.e_off = rom_next();
    rom_at((uint16_t)(ROM_SIZE + idx));
    link_hot.e_sz = rom_next();
}
#endif

/* V.b[0..n-1] hold a value of size code link_hot.e_sz (n bytes, bit 7: signed): extend it to 32 bits */
#if defined(__SDCC_pic16)
/* Contract: in V.b[0..n-1] of size code link_hot.e_sz (bit 7: signed); out V extended to 32 bits
 * (sign or zero fill); clobbers W, STATUS, PROD, FSR0. */
static void sign_extend(void) __naked      /* PRODL the fill byte, PRODH the index, FSR0 at V */
{
    __asm
    CLRF    _PRODL, A
    MOVLW   0x7F
    ANDWF   (_link_hot + LH_E_SZ), W, A
    MOVWF   _PRODH, A
    LFSR    0, (_V - 1)
    BTFSS   (_link_hot + LH_E_SZ), 7, A
    BRA     lse_fill
    BTFSC   _PLUSW0, 7, A           ; V.b[n - 1] (PLUSW0) negative: fill with 0xFF
    SETF    _PRODL, A
lse_fill:
    LFSR    0, _V
lse_loop:
    MOVLW   0x04
    CPFSLT  _PRODH, A               ; index < 4: store the fill
    RETURN
    MOVF    _PRODH, W, A
    MOVFF   _PRODL, _PLUSW0         ; V.b[index] = fill
    INCF    _PRODH, F, A
    BRA     lse_loop
    __endasm;
}
#else
static void sign_extend(void)
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
#endif

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

#if defined(__SDCC_pic16)
/* PIC18 assembly (the C below, step for step): idx in PRODL across entry_load (which keeps PROD) */
/* Contract: in idx (W), a parameter or signal index; out V = its value, extended to 32 bits;
 * clobbers W, STATUS, BSR, FSR0, PROD, TBLPTR, TABLAT and what the compiled C it calls may
 * change (W, STATUS, BSR, PROD, FSR0, TBLPTR, TABLAT). */
static void value_at(uint8_t idx) LINK_WPARAM __naked      /* V = parameter or signal */
{
    (void)idx;
    __asm
    MOVWF   _PRODL, A               ; PRODL = idx
    CALL    _entry_load
    INCF    (_link_hot + LH_E_OFF), W, A   ; e_off == NONE: a signal
    BNZ     lva_store
    MOVLW   11
    SUBWF   _PRODL, W, A            ; app_signal(idx - SIG_INDEX): low byte in W, high in PRODL
    CALL    _app_signal
    BANKSEL _V
    MOVWF   _V, B
    MOVFF   _PRODL, (_V + 1)
    GOTO    _sign_extend
lva_store:
    GOTO    _store_get
    __endasm;
}
#else
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
#endif

#if defined(__SDCC_pic16)
/* The next 4 table bytes (an int32 limit X, little-endian) against V, signed: 1 if V < X
 * (above = 0) or if X < V (above != 0), else 0.  X is held in PRODL, PRODH, FSR0L, TABLAT, the
 * mode on the software stack; the subtraction runs low byte first through the borrow (MOVF keeps
 * the carry); signed less-than is N xor OV. */
#if ROW16
/* (16-bit rows: X's upper half is the fill of the entry loaded last, entry_load) */
#endif
/* Contract: in above (W), V, the next 4 table bytes X; out W = 1 if V < X (above = 0) or X < V
 * (above != 0), else 0; link_hot.ro past X; clobbers W, STATUS, BSR, PROD, FSR0, TBLPTR, TABLAT;
 * the 32-bit signed compare reads N xor OV, so it cannot overflow. */
static uint8_t rom_cmp(uint8_t above) LINK_WPARAM __naked
{
    (void)above;
    __asm
    MOVWF   _POSTDEC1, A
    CALL    _rom_next
    MOVWF   _PRODL, A
    CALL    _rom_next
    MOVWF   _PRODH, A
    CLRF    _FSR0L, A               ; the upper half: the fill of the entry size code (link_hot.e_sz)
    BTFSS   (_link_hot + LH_E_SZ), 7, A
    BRA     lrc_fill
    BTFSC   _PRODH, 7, A
    SETF    _FSR0L, A
lrc_fill:
    MOVFF   _FSR0L, _TABLAT         ; the top byte in TABLAT too (FSR0H holds 4 bits only)
    MOVF    _PREINC1, F, A          ; PREINC1: Z = below
    BANKSEL _V
    BNZ     lrc_above
    MOVF    _PRODL, W, A            ; V - X
    SUBWF   _V, W, B
    MOVF    _PRODH, W, A
    SUBWFB  (_V + 1), W, B
    MOVF    _FSR0L, W, A
    SUBWFB  (_V + 2), W, B
    MOVF    _TABLAT, W, A
    SUBWFB  (_V + 3), W, B
    BRA     lrc_sign
lrc_above:
    MOVF    _V, W, B                ; X - V
    SUBWF   _PRODL, W, A
    MOVF    (_V + 1), W, B
    SUBWFB  _PRODH, W, A
    MOVF    (_V + 2), W, B
    SUBWFB  _FSR0L, W, A
    MOVF    (_V + 3), W, B
    SUBWFB  _TABLAT, W, A
lrc_sign:
    BOV     lrc_ov
    BN      lrc_lt
    RETLW   0
lrc_ov:
    BN      lrc_ge
lrc_lt:
    RETLW   1
lrc_ge:
    RETLW   0
    __endasm;
}

/* (the C below, step for step: row_at(idx, 8), V < min: 0, else not max < V) */
/* Contract: in idx (W, its entry loaded), V; out W = 1 if min <= V <= max, else 0; clobbers as
 * rom_cmp. */
static uint8_t in_range(uint8_t idx) LINK_WPARAM __naked   /* V within the entry's [min, max] (entry idx loaded) */
{
    (void)idx;
    __asm
    CALL    _row_of
    MOVLW   8                       ; the row min
    ADDWF   (_link_hot + LH_RO), F, A
    MOVLW   0
    ADDWFC  (_link_hot + LH_RO + 1), F, A
    MOVLW   0
    CALL    _rom_cmp                ; V < min
    IORLW   0
    BZ      lir_max
    RETLW   0
lir_max:
    MOVLW   1
    CALL    _rom_cmp                ; max < V
    XORLW   1
    RETURN
    __endasm;
}
#else
static union { int32_t l; uint8_t b[4]; } X;   /* a limit read from the table */

static void rom_x(void)                /* X = the next limit (little-endian int32; 16-bit rows: widened) */
{
    X.b[0] = rom_next();
    X.b[1] = rom_next();
#if ROW16
    X.b[2] = ((link_hot.e_sz & 0x80u) != 0u && (X.b[1] & 0x80u) != 0u) ? 0xFFu : 0u;
    X.b[3] = X.b[2];
#else
    X.b[2] = rom_next();
    X.b[3] = rom_next();
#endif
}

static uint8_t in_range(uint8_t idx) LINK_WPARAM   /* V within the entry's [min, max] (entry idx loaded) */
{
    row_at(idx, 8u);
    rom_x();
    if (V.l < X.l) {
        return 0u;
    }
    rom_x();
    return (uint8_t)(V.l <= X.l);
}
#endif

int32_t link_param_get(uint8_t id)
{
    uint8_t i = entry_index(id);
    if (i == NONE) {
        return 0;
    }
    value_at(i);
    return V.l;
}

#if defined(__SDCC_pic16)
/* PIC18 assembly: V's upper half must be the sign extension of its lower half, else the nearer
 * limit; the result in PRODL (high byte) and W (low byte) */
/* Contract: in id (W); out the parameter's value in PRODL:W, clamped to int16 when the stored
 * value does not fit (the nearer limit), 0 for an unknown id; clobbers W, STATUS, BSR, FSR0,
 * PROD, TBLPTR, TABLAT and what the compiled C it calls may change (W, STATUS, BSR, PROD, FSR0,
 * TBLPTR, TABLAT). */
int16_t link_param_i16(uint8_t id) LINK_WPARAM __naked
{
    (void)id;
    __asm
    CALL    _entry_index
    MOVWF   _PRODL, A
    INCF    _PRODL, W, A            ; NONE: unknown id, 0
    BZ      lpi_zero
    MOVF    _PRODL, W, A
    CALL    _value_at
    BANKSEL _V
    MOVLW   0x00                    ; the sign extension of the low half
    BTFSC   (_V + 1), 7, B
    MOVLW   0xFF
    CPFSEQ  (_V + 2), B
    BRA     lpi_sat
    CPFSEQ  (_V + 3), B
    BRA     lpi_sat
    MOVFF   (_V + 1), _PRODL
    MOVF    _V, W, B
    RETURN
lpi_sat:
    BTFSC   (_V + 3), 7, B
    BRA     lpi_min
    MOVLW   0x7F                    ; INT16_MAX
    MOVWF   _PRODL, A
    RETLW   0xFF
lpi_min:
    MOVLW   0x80                    ; INT16_MIN
    MOVWF   _PRODL, A
    RETLW   0x00
lpi_zero:
    CLRF    _PRODL, A
    RETLW   0x00
    __endasm;
}
#else
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
#endif

static uint8_t set_v(uint8_t id) LINK_WPARAM       /* write V to entry id: 0 or a NACK code */
{
    uint8_t i = entry_index(id);
    if (i == NONE) {
        return LINK_NACK_UNKNOWN_PARAM;
    }
    entry_load(i);                     /* in_range widens the limits by its size code */
    row_at(i, 2u);
    if ((rom_next() & LINK_FLAG_WRITABLE) == 0u) {
        return LINK_NACK_READ_ONLY;
    }
    if (!in_range(i)) {
        return LINK_NACK_OUT_OF_RANGE;
    }
    store_put();
#if LINK_WITH_CAPTURE
    if (id == LINK_ID_SPEED_SETPOINT) {
        S.cap_sp_changed = 1u;
    }
#endif
    S.changed = id;                    /* announced by link_notify, after the reply (shallow stack) */
    return 0u;
}

/* ---- EEPROM image ---- */
#if LINK_WITH_EEPROM
#define ee_off S.ee_off

static uint8_t id_of(uint8_t idx) LINK_WPARAM
{
    if (idx < 11u) {
        return (uint8_t)(idx + 0u);
    }
    if (idx < 23u) {
        return (uint8_t)(idx + 21u);
    }
    return (uint8_t)(idx + 41u);
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
    rom_at(ROM_EE_HEAD);               /* (ee_put reads no table: link_hot.ro runs on) */
    for (k = 0u; k < EE_HEADER; k++) {
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

static uint8_t ee_load(void)           /* link_eeprom_load without the announcement */
{
    uint8_t i, k, pass, r = LINK_EE_BLANK;
    ee_off = 0u;
    CRC_INIT();
    rom_at(ROM_EE_HEAD);               /* (ee_next reads no table: link_hot.ro runs on) */
    for (k = 0u; k < EE_HEADER; k++) {   /* magic (BLANK), then version, hash, length (OTHER_BUILD) */
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
    S.changed = EE_ALL;
    return LINK_EE_OK;
}
#else  /* generated without EEPROM persistence: nothing to load, saving is refused */
uint8_t link_eeprom_save(void)
{
    return LINK_NACK_EEPROM_ERROR;
}

static uint8_t ee_load(void)
{
    return LINK_EE_BLANK;
}
#endif

#if defined(__SDCC_pic16)
/* PIC18 assembly: no register held across the calls (S.changed counts), no frame */
/* Contract: in S.changed (NONE, an id or EE_ALL); out app_param_changed called for it (for
 * EE_ALL, every persisted parameter), S.changed = NONE; clobbers W, STATUS, BSR and what the
 * compiled C it calls may change (W, STATUS, BSR, PROD, FSR0, TBLPTR, TABLAT). */
static void link_notify(void) __naked  /* app_param_changed for what the last command or load changed */
{
    __asm
    extern  _app_param_changed
    BANKSEL _S
    MOVF    (_S + LS_CHANGED), W, B
    XORLW   0xFE          ; EE_ALL: every persisted parameter
    BNZ     lnt_one
#if LINK_WITH_EEPROM
    CLRF    (_S + LS_CHANGED), B
lnt_loop:
    MOVF    (_S + LS_CHANGED), W, B
    CALL    _persisted
    CALL    _id_of
    CALL    _app_param_changed
    BANKSEL _S
    INCF    (_S + LS_CHANGED), F, B
    MOVLW   18
    CPFSEQ  (_S + LS_CHANGED), B
    BRA     lnt_loop
#endif
    BRA     lnt_end
lnt_one:
    INCF    (_S + LS_CHANGED), W, B  ; NONE (0xFF): nothing
    BZ      lnt_end
    MOVF    (_S + LS_CHANGED), W, B
    CALL    _app_param_changed
lnt_end:
    BANKSEL _S
    SETF    (_S + LS_CHANGED), B    ; NONE
    RETURN
    __endasm;
}
#else
static void link_notify(void)          /* app_param_changed for what the last command or load changed */
{
#if LINK_WITH_EEPROM
    if (S.changed == EE_ALL) {
        for (S.changed = 0u; S.changed < LINK_N_PERSISTED; S.changed++) {
            app_param_changed(id_of(persisted(S.changed)));
        }
    } else
#endif
    if (S.changed != NONE) {
        app_param_changed(S.changed);
    }
    S.changed = NONE;
}
#endif

#if LINK_WITH_HOST_API
uint8_t link_param_set(uint8_t id, int32_t raw)
{
    uint8_t code;
    V.l = raw;
    code = set_v(id);
    link_notify();
    return code;
}
#endif

uint8_t link_eeprom_load(void)
{
    uint8_t r = ee_load();
    link_notify();
    return r;
}

/* ---- init, events ---- */
void link_init(void)
{
    uint8_t i;
    mzero((LINK_DATA uint8_t *)&S, (uint8_t)sizeof S);
    mzero((LINK_DATA uint8_t *)&link_hot, (uint8_t)sizeof link_hot);
    rx_sp_w = 0u;
    rx_sp_r = 0u;
    for (i = 0u; i < LINK_N_ENTRIES; i++) {   /* the parameters' defaults */
        entry_load(i);
        if (link_hot.e_off != NONE) {
            row_at(i, ROW_DEFAULT);
            V.b[0] = rom_next();       /* the store takes at most the low e_sz bytes */
            V.b[1] = rom_next();
#if !ROW16
            V.b[2] = rom_next();
            V.b[3] = rom_next();
#endif
            store_put();
        }
    }
    S.rp_len = NONE;
    S.changed = NONE;
    S.rx_lost_at = NONE;
    S.nack = NACK_ARMED;
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
/* the C below in PIC18 assembly: at most 20 cycles a byte, no register saved (b in W, kept in PRODL,
 * stored through FSR0 + W (PLUSW0); the spill ring's read index copied to PRODH;
 * FSR0, PROD and BSR are saved by the interrupt's prologue) */
/* Contract: in b (W), the receive state; out b stored in rx_buf or the spill ring, rx_n,
 * rx_ready, rx_ovf and rx_sp_w updated (one-byte writes only); clobbers W, STATUS, BSR, PROD,
 * FSR0 (the high-priority interrupt saves them); rx_n stops at the buffer's size (rx_ovf set),
 * the ring's indices wrap at its size. */
void link_rx_byte(uint8_t b) LINK_WPARAM __naked
{
    (void)b;
    __asm
    MOVWF   _PRODL, A
    MOVF    (_link_hot + LH_RX_READY), W, A
    BNZ     _lrx_spill          ; the main loop holds rx_buf: the byte waits in the spill ring
    MOVF    _PRODL, F, A
    BZ      _lrx_delim
    MOVLW   46          ; LINK_RX_BYTES
    CPFSLT  (_link_hot + LH_RX_N), A
    BRA     _lrx_long
    MOVF    (_link_hot + LH_RX_N), W, A
    LFSR    0, _rx_buf
    MOVFF   _PRODL, _PLUSW0
    INCF    (_link_hot + LH_RX_N), F, A      ; rx_buf[rx_n++] = b
    RETURN
_lrx_long:
    SETF    (_link_hot + LH_RX_N), A         ; longer than any frame: RX_SKIP
    RETURN
_lrx_delim:
    INCF    (_link_hot + LH_RX_N), W, A
    BZ      _lrx_clear          ; RX_SKIP: the garbage ends here
    MOVF    (_link_hot + LH_RX_N), F, A
    BZ      _lrx_done           ; nothing since the last delimiter
    INCF    (_link_hot + LH_RX_READY), F, A      ; 0 -> 1: the frame is complete
_lrx_done:
    RETURN
_lrx_clear:
    CLRF    (_link_hot + LH_RX_N), A
    RETURN
_lrx_spill:
    BANKSEL _rx_sp_w
    MOVF    _rx_sp_w, W, B
    LFSR    0, _rx_spill
    MOVFF   _PRODL, _PLUSW0     ; rx_spill[rx_sp_w] = b (the slot kept empty, even when the ring is full)
    INCF    _rx_sp_w, W, B
    ANDLW   15          ; LINK_RX_SPILL - 1: the next index
    MOVFF   _rx_sp_r, _PRODH
    CPFSEQ  _PRODH, A           ; full (next == rx_sp_r): skip the store
    MOVWF   _rx_sp_w, B         ; the byte is in
    CPFSEQ  _rx_sp_w, B         ; stored: skip the count
    INCF    (_link_hot + LH_RX_OVF), F, A      ; rx_ovf: the byte is lost
    RETURN
    __endasm;
}
#else
void link_rx_byte(uint8_t b) LINK_WPARAM
{
    if (rx_ready != 0u) {              /* rx_buf is the main loop's: the byte waits in the spill ring */
        uint8_t w = (uint8_t)((uint8_t)(rx_sp_w + 1u) & (LINK_RX_SPILL - 1u));
        if (w == rx_sp_r) {
            rx_ovf++;                  /* full: the byte is lost */
        } else {
            rx_spill[rx_sp_w] = b;
            rx_sp_w = w;
        }
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
#if defined(__SDCC_pic16)
/* PIC18 assembly: FSR0 walks the frame, each byte goes one place down (PLUSW0 with W = -1);
 * TABLAT the run, PRODH the count */
/* Contract: in rx_buf[0..rx_n-1], a COBS frame; out the frame decoded in place, W = the body
 * length if the length and CRC check, else 0, S.fc0/fc1 its CRC bytes; clobbers W, STATUS, PROD,
 * FSR0, TABLAT. */
static uint8_t cobs_decode(void) __naked   /* rx_buf decoded in place; the last run (1: well formed) */
{
    __asm
    DECF    (_link_hot + LH_RX_N), W, A   ; rx_n - 1 bytes after the code byte
    MOVWF   _PRODH, A
    MOVFF   _rx_buf, _TABLAT        ; run = the code byte
    LFSR    0, (_rx_buf + 1)
    MOVF    _PRODH, F, A
    BZ      lcd3_end
lcd3_loop:
    MOVF    _INDF0, W, A
    DECFSZ  _TABLAT, F, A           ; the run ends here: a code byte, the zero it stands for
    BRA     lcd3_put
    MOVWF   _TABLAT, A
    MOVLW   0
lcd3_put:
    MOVWF   _PRODL, A
    MOVLW   0xFF
    MOVFF   _PRODL, _PLUSW0         ; FSR0[-1]
    MOVF    _POSTINC0, F, A         ; FSR0++
    DECFSZ  _PRODH, F, A
    BRA     lcd3_loop
lcd3_end:
    MOVF    _TABLAT, W, A
    RETURN
    __endasm;
}
#else
static uint8_t cobs_decode(void)       /* rx_buf decoded in place; the last run (1: well formed) */
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
    return run;
}
#endif

static uint8_t rx_frame(void)
{
    uint8_t n = (uint8_t)(rx_n - 1u);  /* the body length */
    if (cobs_decode() == 1u && n >= BODY_OVERHEAD) {
        crc_buf(rx_buf, n);            /* over the CRC too: a good frame leaves 0 */
        if ((uint8_t)(rx_buf[0] + BODY_OVERHEAD) == n && (crc_hi | crc_lo) == 0u) {
            cp_s--;                    /* crc_n left cp_s after the frame */
            S.fc1 = *cp_s;
            cp_s--;
            S.fc0 = *cp_s;
            return n;
        }
    }
    if (S.crc_errors != 0xFFFFu) {
        S.crc_errors++;
    }
    if (S.nack == NACK_ARMED && n >= PL) {
        S.nack = NACK_PENDING;
        S.nack_type = rx_buf[1];
        S.nack_seq = rx_buf[2];
    }
    return 0u;
}

/* The frame in rx_buf is done with: the bytes that arrived meanwhile (the spill ring) go through
 * the interrupt's framing here, until a frame is complete (rx_ready stays 1: link_poll takes it
 * next) or the ring is empty (rx_buf back to the interrupt, with the frame begun in it).  Bytes
 * lost to a full ring (rx_ovf moved) came after the ring's content (it stays full until this
 * loop takes from it): the frame being assembled when the loop reaches that place is dropped
 * (discarded up to the next delimiter). */
static void rx_release(void)
{
    uint8_t b, d;
    rx_n = 0u;
    for (;;) {
        d = (uint8_t)(rx_ovf - S.rx_ovf_seen);   /* one byte, written by the interrupt */
        if (d != 0u) {
            S.rx_ovf_seen = (uint8_t)(S.rx_ovf_seen + d);
            S.rx_lost_at = rx_sp_w;
            S.rx_overflows = (uint16_t)(S.rx_overflows + d);
            if (S.rx_overflows < d) {  /* saturate */
                S.rx_overflows = 0xFFFFu;
            }
        }
        if (rx_sp_r == S.rx_lost_at) {
            S.rx_lost_at = NONE;
            rx_n = RX_SKIP;            /* the frame the lost bytes belonged to */
        }
        if (rx_sp_r == rx_sp_w) {
            LINK_CRITICAL_BEGIN();     /* the receive interrupt masked: no byte between the test and the hand-back */
            if (rx_sp_r == rx_sp_w) {
                rx_ready = 0u;
            }
            LINK_CRITICAL_END();
            if (rx_ready == 0u) {
                return;
            }
            continue;
        }
        b = rx_spill[rx_sp_r];
        rx_sp_r = (uint8_t)((uint8_t)(rx_sp_r + 1u) & (LINK_RX_SPILL - 1u));
        if (b == 0u) {                 /* delimiter */
            if (rx_n == RX_SKIP) {
                rx_n = 0u;
            } else if (rx_n != 0u) {
                return;                /* a frame complete: rx_ready stays 1 */
            }
        } else if (rx_n < LINK_RX_BYTES) {
            rx_buf[rx_n] = b;
            rx_n++;
        } else {
            rx_n = RX_SKIP;            /* longer than any frame: garbage */
        }
    }
}

/* ---- transmit: body in tx_buf[1..], COBS-encoded in place, sent as the UART queue has room ---- */
#if defined(__SDCC_pic16)
/* PIC18 assembly: the CRC through crc_n (FSR0 ends on the CRC's place), then COBS in place with
 * FSR0 scanning: the last code byte is run bytes back (PLUSW0); TABLAT the run, PRODH the count. */
/* Contract: in type (W), the payload A(0..link_hot.n-1), S.tseq; out the sealed frame in tx_buf
 * (header, CRC, COBS in place), link_hot.tx_len; clobbers W, STATUS, BSR, PROD, FSR0, TABLAT. */
static void tx_seal(uint8_t type) LINK_WPARAM __naked   /* payload A(0..link_hot.n-1), SEQ S.tseq */
{
    (void)type;
    __asm
    MOVFF   _WREG, (_tx_buf + 2)    ; TYPE, LEN, SEQ
    MOVFF   (_link_hot + LH_N), (_tx_buf + 1)
    MOVFF   (_S + LS_TSEQ), (_tx_buf + 3)
    MOVLW   LOW(_tx_buf + 1)        ; CRC over LEN .. payload
    MOVFF   _WREG, _cp_s
    MOVLW   HIGH(_tx_buf + 1)
    MOVFF   _WREG, (_cp_s + 1)
    MOVF    (_link_hot + LH_N), W, A
    ADDLW   3
    CALL    _crc_n
    MOVFF   (_link_hot + LH_CRC_HI), _POSTINC0 ; CRC high, low
    MOVFF   (_link_hot + LH_CRC_LO), _POSTINC0
    MOVF    (_link_hot + LH_N), W, A   ; tx_len = body + COBS code + delimiter
    ADDLW   7
    MOVWF   (_link_hot + LH_TX_LEN), A
    BANKSEL _S
    CLRF    (_S + LS_TX_POS), B            ; tx_pos = 0
    MOVF    (_link_hot + LH_N), W, A   ; count = body bytes
    ADDLW   5
    MOVWF   _PRODH, A
    LFSR    0, (_tx_buf + 1)
    MOVLW   1
    MOVWF   _TABLAT, A              ; run = 1: the code byte is run bytes back
lts_loop:
    MOVF    _POSTINC0, W, A         ; POSTINC0: a zero becomes the distance to the next one
    BNZ     lts_next
    MOVF    _TABLAT, W, A           ; *(this byte - run) = run: W = -run - 1 from FSR0 (one past it)
    SUBLW   0xFF
    MOVFF   _TABLAT, _PLUSW0
    CLRF    _TABLAT, A
lts_next:
    INCF    _TABLAT, F, A
    DECFSZ  _PRODH, F, A
    BRA     lts_loop
    MOVF    _TABLAT, W, A           ; the last code byte: run back from one past the end
    SUBLW   0
    MOVFF   _TABLAT, _PLUSW0
    RETURN
    __endasm;
}
#else
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
#endif

#if defined(__SDCC_pic16)
/* PIC18 assembly (the C below, step for step): the room on the software stack (PLUSW1, W = 1) */
/* Contract: in tx_buf[S.tx_pos..tx_len-1]; out as many bytes queued as app_tx_free allows,
 * S.tx_pos on, tx_len = 0 when all are out; clobbers W, STATUS, BSR, FSR0 and what the compiled
 * C it calls may change (W, STATUS, BSR, PROD, FSR0, TBLPTR, TABLAT). */
static void tx_drain(void) __naked
{
    __asm
    extern  _app_tx_free
    extern  _app_tx_byte
    MOVF    (_link_hot + LH_TX_LEN), W, A  ; tx_len: nothing to send
    BZ      ltd_ret
    CALL    _app_tx_free
    IORLW   0
    BZ      ltd_ret
    MOVWF   _POSTDEC1, A            ; room
ltd_loop:
    BANKSEL _S
    DECF    (_link_hot + LH_TX_LEN), W, A  ; tx_pos == tx_len - 1: only the delimiter is left
    XORWF   (_S + LS_TX_POS), W, B
    BZ      ltd_end
    LFSR    0, _tx_buf
    MOVF    (_S + LS_TX_POS), W, B
    MOVF    _PLUSW0, W, A           ; tx_buf[tx_pos]
    CALL    _app_tx_byte
    BANKSEL _S
    INCF    (_S + LS_TX_POS), F, B
    MOVLW   1
    DECFSZ  _PLUSW1, F, A           ; room--
    BRA     ltd_loop
    BRA     ltd_pop
ltd_end:
    MOVLW   0
    CALL    _app_tx_byte            ; the delimiter
    CLRF    (_link_hot + LH_TX_LEN), A
ltd_pop:
    MOVF    _PREINC1, F, A          ; drop room
ltd_ret:
    RETURN
    __endasm;
}
#else
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
#endif

/* ---- command handlers: arguments in R(0..link_hot.n-1), reply in A(..), its length in link_hot.n ---- */
static uint8_t drive_busy(void)
{
    int16_t st = app_signal(LINK_SIG_STATE);
    return (uint8_t)(st == (int16_t)LINK_STATE_RUN || st == (int16_t)LINK_STATE_BRAKE);
}

#if defined(__SDCC_pic16)
#if LINK_MAX_PAYLOAD > 127u
#error "rom_copy indexes the reply with PLUSW0 (a signed offset): at most 127 payload bytes"
#endif
/* PIC18 assembly (the C below, step for step): no frame, no register saved; PROD counts and
 * carries (rom_next keeps it) */
/* Contract: in n (W, <= 127), link_hot.ro, link_hot.n; out A(n..n+n-1) = the next n table bytes,
 * ro and n past them; clobbers W, STATUS, PROD, FSR0, TBLPTR, TABLAT. */
static void rom_copy(uint8_t n) LINK_WPARAM __naked /* A(link_hot.n..) = n flash bytes from link_hot.ro on */
{
    (void)n;
    __asm
    MOVWF   _PRODL, A               ; PRODL = n
    MOVF    _PRODL, F, A
    BZ      lrc_end
lrc_loop:
    CALL    _rom_next
    MOVWF   _PRODH, A               ; PRODH = the byte
    LFSR    0, (_tx_buf + 4)        ; A(0)
    MOVF    (_link_hot + LH_N), W, A   ; link_hot.n
    MOVFF   _PRODH, _PLUSW0         ; A(link_hot.n)
    INCF    (_link_hot + LH_N), F, A
    DECFSZ  _PRODL, F, A
    BRA     lrc_loop
lrc_end:
    RETURN
    __endasm;
}

/* Contract: in nothing (the hello command has no arguments); out the hello reply in A(0..),
 * link_hot.n, W = 0 (answered); clobbers W, STATUS, PROD, FSR0, TBLPTR, TABLAT. */
static uint8_t h_hello(void) __naked
{
    __asm
    CLRF    (_link_hot + LH_N), A      ; link_hot.n = 0
    MOVLW   15              ; rom_at(ROM_HELLO)
    MOVWF   (_link_hot + LH_RO), A
    MOVLW   2
    MOVWF   (_link_hot + LH_RO + 1), A
    MOVLW   21
    CALL    _rom_copy
    RETLW   0
    __endasm;
}

#if ROW16
/* A(link_hot.n..) = the next two table bytes widened to 4 by the loaded entry's size code */
/* Contract: in the next two table bytes, the loaded entry's size code; out A(link_hot.n..+3) =
 * them widened to 32 bits, n + 4; clobbers W, STATUS, PROD, FSR0, TBLPTR, TABLAT. */
static void rom_val16(void) __naked
{
    __asm
    MOVLW   2
    CALL    _rom_copy
    CLRF    _PRODL, A               ; PRODL = the fill
    BTFSS   (_link_hot + LH_E_SZ), 7, A   ; e_sz: signed
    BRA     lrv_fill
    LFSR    0, (_tx_buf + 3)        ; A(n - 1): the high byte (PLUSW0)
    MOVF    (_link_hot + LH_N), W, A
    BTFSC   _PLUSW0, 7, A
    SETF    _PRODL, A
lrv_fill:
    LFSR    0, (_tx_buf + 4)
    MOVF    (_link_hot + LH_N), W, A
    MOVFF   _PRODL, _PLUSW0         ; A(n)
    INCF    (_link_hot + LH_N), F, A
    MOVF    (_link_hot + LH_N), W, A
    MOVFF   _PRODL, _PLUSW0
    INCF    (_link_hot + LH_N), F, A
    RETURN
    __endasm;
}
#endif

/* the index and then the name's offset and length on the software stack across the calls (read
 * above FSR1 or popped by one instruction: an interrupt pushes at FSR1) */
/* Contract: in R(0), an entry index; out the entry's description in A(0..), link_hot.n, W = 0
 * (answered) or a NACK code; clobbers W, STATUS, PROD, FSR0, TBLPTR, TABLAT (software stack balanced). */
static uint8_t h_param_info(void) __naked
{
    __asm
    MOVFF   (_rx_buf + 3), _FSR0L   ; FSR0L = idx = R(0): the lengths to add
    MOVF    _FSR0L, W, A
    SUBLW   30
    BNC     lpi_bad                 ; idx >= LINK_N_ENTRIES
    MOVFF   _FSR0L, _POSTDEC1       ; push idx
    MOVLW   240              ; rom_at(ROM_NAME_LEN)
    MOVWF   (_link_hot + LH_RO), A
    MOVLW   1
    MOVWF   (_link_hot + LH_RO + 1), A
    MOVLW   54             ; PROD = ROM_NAMES
    MOVWF   _PRODL, A
    MOVLW   2
    MOVWF   _PRODH, A
    MOVF    _FSR0L, F, A
    BZ      lpi_len
lpi_sum:                            ; the name offset: the lengths before it
    CALL    _rom_next
    ADDWF   _PRODL, F, A
    MOVLW   0
    ADDWFC  _PRODH, F, A
    DECFSZ  _FSR0L, F, A
    BRA     lpi_sum
lpi_len:
    CALL    _rom_next               ; the name length
    MOVWF   _POSTDEC1, A            ; push the length, the offset (idx stays below them)
    MOVFF   _PRODH, _POSTDEC1
    MOVFF   _PRODL, _POSTDEC1
    CLRF    (_link_hot + LH_N), A      ; link_hot.n = 0
    MOVLW   4
    MOVF    _PLUSW1, W, A           ; idx
    CALL    _entry_load             ; its size code widens min, max, default
    MOVLW   4
    MOVF    _PLUSW1, W, A           ; idx
    CALL    _row_of
    MOVLW   8                       ; id, ctype, flags, unit, scale
    CALL    _rom_copy
    CALL    _rom_val16              ; min, max, default
    CALL    _rom_val16
    CALL    _rom_val16
    MOVFF   _PREINC1, (_link_hot + LH_RO) ; rom_at(offset)
    MOVFF   _PREINC1, (_link_hot + LH_RO + 1)
    MOVF    _PREINC1, W, A          ; the length
    MOVF    _PREINC1, F, A          ; drop idx (each pop one instruction: an interrupt pushes at FSR1)
    CALL    _rom_copy
    RETLW   0
lpi_bad:
    RETLW   8
    __endasm;
}
#else
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
    rom_copy(21u);
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
#if ROW16
    entry_load(idx);                   /* its size code widens min, max, default */
    row_at(idx, 0u);
    rom_copy(8u);
    {
        uint8_t k;
        for (k = 0u; k < 3u; k++) {
            uint8_t fill;
            rom_copy(2u);
            fill = ((link_hot.e_sz & 0x80u) != 0u && (A(link_hot.n - 1u) & 0x80u) != 0u) ? 0xFFu : 0u;
            A(link_hot.n) = fill;
            A(link_hot.n + 1u) = fill;
            link_hot.n = (uint8_t)(link_hot.n + 2u);
        }
    }
#else
    row_at(idx, 0u);
    rom_copy(ROW);
#endif
    rom_at(a);
    rom_copy(i);
    return 0u;
}
#endif

#if defined(__SDCC_pic16)
/* PIC18 assembly (the C below, step for step): the index on the software stack (PLUSW1 with
 * W = 1 reaches it across the calls), every id checked before any value is read */
/* Contract: in R(0..), the ids asked for; out their values in A(0..), link_hot.n, W = 0 (answered) or a
 * NACK code (every id checked before a value is read); clobbers W, STATUS, BSR, PROD, FSR0,
 * TBLPTR, TABLAT and what the compiled C it calls may change (W, STATUS, BSR, PROD, FSR0,
 * TBLPTR, TABLAT). */
static uint8_t h_param_get(void) __naked
{
    __asm
    MOVF    (_link_hot + LH_N), W, A   ; 1 .. LINK_PARAM_GET_MAX ids
    BZ      lpg_bad
    SUBLW   10
    BNC     lpg_bad
    CLRF    _POSTDEC1, A            ; i = 0
lpg_check:
    MOVLW   1
    MOVF    _PLUSW1, W, A           ; i
    LFSR    0, (_rx_buf + 3)
    MOVF    _PLUSW0, W, A           ; R(i)
    CALL    _entry_index
    XORLW   0xFF
    BZ      lpg_unknown
    MOVLW   1
    INCF    _PLUSW1, F, A
    MOVLW   1
    MOVF    _PLUSW1, W, A
    XORWF   (_link_hot + LH_N), W, A
    BNZ     lpg_check
    MOVLW   1
    CLRF    _PLUSW1, A
lpg_value:
    MOVLW   1
    MOVF    _PLUSW1, W, A
    LFSR    0, (_rx_buf + 3)
    MOVF    _PLUSW0, W, A
    CALL    _entry_index
    CALL    _value_at
    MOVLW   1                       ; A(4 i ..) = V
    MOVF    _PLUSW1, W, A
    MULLW   4
    LFSR    0, (_tx_buf + 4)
    MOVF    _PRODL, W, A
    ADDWF   _FSR0L, F, A
    BTFSC   _STATUS, 0, A
    INCF    _FSR0H, F, A
    MOVFF   _V, _POSTINC0
    MOVFF   (_V + 1), _POSTINC0
    MOVFF   (_V + 2), _POSTINC0
    MOVFF   (_V + 3), _POSTINC0
    MOVLW   1
    INCF    _PLUSW1, F, A
    MOVLW   1
    MOVF    _PLUSW1, W, A
    XORWF   (_link_hot + LH_N), W, A
    BNZ     lpg_value
    MOVF    (_link_hot + LH_N), W, A   ; 4 bytes an id
    MULLW   4
    MOVFF   _PRODL, (_link_hot + LH_N)
    MOVF    _PREINC1, F, A          ; drop i
    RETLW   0
lpg_unknown:
    MOVF    _PREINC1, F, A
    RETLW   8
lpg_bad:
    RETLW   3
    __endasm;
}
#else
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
#endif

/* set id to the value in V; reply the stored value: the last 4 of the link_hot.n reply bytes */
static uint8_t set_reply(uint8_t id) LINK_WPARAM
{
    uint8_t code = set_v(id);
    if (code == 0u) {
        store_get();
        mcopy(&A((uint8_t)(link_hot.n - 4u)), V.b, 4u);
    }
    return code;
}

static uint8_t h_param_set(void)
{
    mcopy(V.b, &R(1), 4u);
    A(0) = R(0);
    link_hot.n = 5u;
    return set_reply(R(0));
}

static uint8_t h_set_speed(void)
{
    mcopy(V.b, &R(0), 4u);
    link_hot.n = 4u;
    return set_reply(LINK_ID_SPEED_SETPOINT);
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

#if defined(__SDCC_pic16)
static void crit_begin(void)           /* LINK_CRITICAL_BEGIN/END as functions, for the assembly */
{
    LINK_CRITICAL_BEGIN();
}

static void crit_end(void)
{
    LINK_CRITICAL_END();
}

/* PIC18 assembly (the C below, step for step).  R(0..1) mask, R(2..3) decimation, R(4) samples
 * per frame (R(i) = rx_buf[3 + i]); PRODH the bytes per sample, PRODL the frame length, TABLAT
 * counts; the length and the bytes per sample wait on the software stack across the critical
 * section. */
/* Contract: in R(0..4) (mask, decimation, samples per frame); out the telemetry setting (under
 * the critical section), W = 0 (answered) or a NACK code; clobbers W, STATUS, BSR, PROD, TABLAT and what
 * the compiled C it calls may change (W, STATUS, BSR, PROD, FSR0, TBLPTR, TABLAT); the frame
 * length is checked against the payload before it is stored. */
static uint8_t h_telem_config(void) __naked
{
    __asm
    CALL    _mask_nsig
    MOVWF   _PRODH, A
    RLNCF   _PRODH, F, A            ; PRODH = 2 signals
    MOVLW   2
    MOVWF   _PRODL, A               ; PRODL = the frame length
    BANKSEL _rx_buf
    MOVF    (_rx_buf + 5), W, B     ; decimation 0: telemetry off, nothing to check
    IORWF   (_rx_buf + 6), W, B
    BZ      ltc_set
    MOVF    _PRODH, W, A            ; a bad mask
    BZ      ltc_bad
    MOVF    (_rx_buf + 7), W, B     ; samples per frame >= 1
    BZ      ltc_bad
    MOVWF   _TABLAT, A
ltc_len:
    MOVF    _PRODH, W, A            ; header + samples x bytes, by additions, <= LINK_MAX_PAYLOAD
    ADDWF   _PRODL, F, A
    MOVF    _PRODL, W, A
    SUBLW   40
    BNC     ltc_bad
    DECFSZ  _TABLAT, F, A
    BRA     ltc_len
ltc_set:
    MOVFF   _PRODL, _POSTDEC1       ; the length, the bytes per sample
    MOVFF   _PRODH, _POSTDEC1
    CALL    _crit_begin
    CLRF    (_link_hot + LH_TM_DEC), A     ; tm_dec = 0 while the settings change
    CLRF    (_link_hot + LH_TM_DEC + 1), A
    MOVFF   (_rx_buf + 3), (_S + LS_TM_MASK)
    MOVFF   (_rx_buf + 4), (_S + LS_TM_MASK + 1)
    MOVFF   (_rx_buf + 7), (_S + LS_TM_SPF)
    MOVFF   _PREINC1, (_link_hot + LH_TM_NB) ; tm_nb
    CLRF    (_link_hot + LH_TR_DIV), A     ; tr: div, counter, nsamp, len
    CLRF    (_link_hot + LH_TR_DIV + 1), A
    CLRF    (_link_hot + LH_TR_COUNTER), A
    CLRF    (_link_hot + LH_TR_COUNTER + 1), A
    CLRF    (_link_hot + LH_TR_NSAMP), A
    CLRF    (_link_hot + LH_TR_LEN), A
    CLRF    (_link_hot + LH_TM_READY), A
    BANKSEL _S
    INCF    (_S + LS_TM_GEN), F, B
    MOVFF   (_rx_buf + 5), (_link_hot + LH_TM_DEC)   ; tm_dec last
    MOVFF   (_rx_buf + 6), (_link_hot + LH_TM_DEC + 1)
    CALL    _crit_end
    MOVFF   (_S + LS_TM_GEN), (_tx_buf + 4) ; A(0) = tm_gen, A(1) = the frame length (0: off)
    MOVFF   _PREINC1, _PRODL
    BANKSEL _rx_buf
    MOVF    (_rx_buf + 5), W, B
    IORWF   (_rx_buf + 6), W, B
    BTFSS   _STATUS, 2, A
    MOVF    _PRODL, W, A
    MOVFF   _WREG, (_tx_buf + 5)
    MOVLW   2
    MOVWF   (_link_hot + LH_N), A
    RETLW   0
ltc_bad:
    RETLW   4
    __endasm;
}
#else
static uint8_t h_telem_config(void)
{
    uint16_t mask = arg16(0), dec = arg16(2u);
    uint8_t spf = R(4), nsig = mask_nsig(), nb = (uint8_t)(nsig << 1), len = TELEM_HEADER, k;
    if (dec != 0u) {
        if (nsig == 0u || spf == 0u) {
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
#endif

#if LINK_WITH_CAPTURE
#if defined(__SDCC_pic16)
/* PIC18 assembly (the C below, step for step).  R(0..1) mask, R(2..3) samples, R(4..5)
 * pre-trigger, R(6..7) decimation, R(8) trigger, R(9..10) threshold (R(i) = rx_buf[3 + i]);
 * PRODL counts the words, PRODH the signals; the byte count and the bytes per sample wait on the
 * software stack across the critical section. */
/* Contract: in R(0..10) (mask, samples, pre-trigger, decimation, trigger, threshold); out the
 * capture armed (under the critical section), W = 0 (answered) or a NACK code; clobbers W, STATUS, BSR,
 * PROD, FSR0, TABLAT and what the compiled C it calls may change (W, STATUS, BSR, PROD, FSR0,
 * TBLPTR, TABLAT); the byte count is an 8x8 product checked against the buffer (<= 256). */
static uint8_t h_capture_arm(void) __naked
{
    __asm
    CLRF    (_link_hot + LH_N), A      ; no reply payload
    CALL    _mask_nsig
    MOVWF   _PRODH, A               ; PRODH = signals (0: a bad mask)
    BZ      lca_bad
    BANKSEL _rx_buf
    MOVF    (_rx_buf + 6), W, B     ; samples, pre-trigger: high bytes 0
    IORWF   (_rx_buf + 8), W, B
    BNZ     lca_bad
    MOVF    (_rx_buf + 5), W, B     ; 1 <= samples <= LINK_CAPTURE_WORDS
    BZ      lca_bad
    SUBLW   64
    BNC     lca_bad
    MOVF    (_rx_buf + 9), W, B     ; decimation != 0
    IORWF   (_rx_buf + 10), W, B
    BZ      lca_bad
    MOVF    (_rx_buf + 11), W, B    ; trigger <= SPEED_FALLING
    SUBLW   3
    BNC     lca_bad
    MOVF    (_rx_buf + 5), W, B     ; pre-trigger < samples
    CPFSLT  (_rx_buf + 7), B
    BRA     lca_bad
    MOVF    (_rx_buf + 11), W, B    ; IMMEDIATE: no pre-trigger
    BNZ     lca_words
    MOVF    (_rx_buf + 7), W, B
    BNZ     lca_bad
lca_words:
    RLNCF   _PRODH, W, A            ; bytes per sample = 2 signals (at most 2 x 16)
    MOVWF   _POSTDEC1, A
    CLRF    _PRODL, A               ; PRODL = words
lca_loop:
    MOVF    _PRODL, W, A            ; samples > LINK_CAPTURE_WORDS - words: too many
    SUBLW   64
    CPFSGT  (_rx_buf + 5), B
    BRA     lca_add
    MOVF    _PREINC1, F, A          ; drop the pushed byte
    BRA     lca_bad
lca_add:
    MOVF    (_rx_buf + 5), W, B
    ADDWF   _PRODL, F, A
    DECFSZ  _PRODH, F, A
    BRA     lca_loop
    DECF    _PRODL, W, A            ; the last byte index: 2 words - 1
    ADDWF   _PRODL, W, A
    MOVWF   _POSTDEC1, A
    CALL    _crit_begin
    BANKSEL _S
    CLRF    _S, B                   ; IDLE while the settings change
    MOVFF   (_rx_buf + 3), (_S + LS_CAP_MASK)
    MOVFF   (_rx_buf + 4), (_S + LS_CAP_MASK + 1)
    MOVFF   _PREINC1, (_S + LS_CAP_BYTES)     ; cap_bytes
    MOVFF   _PREINC1, (_link_hot + LH_CAP_NB)
    MOVFF   (_rx_buf + 5), (_link_hot + LH_CAP_N)
    MOVFF   (_rx_buf + 7), (_S + LS_CAP_PRE)
    MOVFF   (_rx_buf + 9), (_link_hot + LH_CAP_DEC)
    MOVFF   (_rx_buf + 10), (_link_hot + LH_CAP_DEC + 1)
    MOVFF   (_rx_buf + 11), (_S + LS_CAP_TRIG)
    MOVFF   (_rx_buf + 12), (_S + LS_CAP_THR)   ; cap_thr (SPEED_FALLING: complemented)
    MOVFF   (_rx_buf + 13), (_S + LS_CAP_THR + 1)
    MOVF    (_S + LS_CAP_TRIG), W, B
    XORLW   3
    BNZ     lca_clear
    COMF    (_S + LS_CAP_THR), F, B
    COMF    (_S + LS_CAP_THR + 1), F, B
lca_clear:
    LFSR    0, (_S + LS_CR_W)            ; the record (S.cr, 10 bytes)
    MOVLW   10
lca_zero:
    CLRF    _POSTINC0, A
    DECFSZ  _WREG, F, A
    BRA     lca_zero
    CLRF    (_link_hot + LH_CR_DIV), A
    CLRF    (_link_hot + LH_CR_DIV + 1), A
    CLRF    (_S + LS_CAP_SP_CHANGED), B
    MOVLW   1
    MOVWF   _S, B
    CALL    _crit_end
    RETLW   0
lca_bad:
    RETLW   4
    __endasm;
}
#else
static uint8_t h_capture_arm(void)
{
    /* R(0..1) mask, R(2..3) samples, R(4..5) pre-trigger, R(6..7) decimation, R(8) trigger,
     * R(9..10) threshold; read in place (no copies in registers) */
    uint8_t nsig = mask_nsig(), words = 0u, k;
    link_hot.n = 0u;
    if (nsig == 0u || R(3) != 0u || R(5) != 0u || R(2) == 0u || R(2) > LINK_CAPTURE_WORDS
        || (uint8_t)(R(6) | R(7)) == 0u || R(8) > LINK_TRIG_SPEED_FALLING || R(4) >= R(2)
        || (R(8) == LINK_TRIG_IMMEDIATE && R(4) != 0u)) {
        return LINK_NACK_OUT_OF_RANGE;
    }
    for (k = 0u; k < nsig; k++) {      /* samples x signals, by additions, within the buffer */
        if (R(2) > (uint8_t)(LINK_CAPTURE_WORDS - words)) {
            return LINK_NACK_OUT_OF_RANGE;
        }
        words = (uint8_t)(words + R(2));
    }
    LINK_CRITICAL_BEGIN();
    S.cap_state = LINK_CAP_IDLE;
    S.cap_mask = arg16(0u);
    link_hot.cap_nb = (uint8_t)(nsig << 1);
    link_hot.cap_n = R(2);
    S.cap_bytes = (uint8_t)((uint8_t)(words << 1) - 1u);
    S.cap_pre = R(4);
    link_hot.cap_dec = arg16(6u);
    S.cap_trig = R(8);
    S.cap_thr = (int16_t)arg16(9u);
    if (R(8) == LINK_TRIG_SPEED_FALLING) {
        S.cap_thr = (int16_t)~S.cap_thr;      /* capture_due compares ~speed with ~threshold */
    }
    mzero((LINK_DATA uint8_t *)&S.cr, (uint8_t)sizeof S.cr);
    link_hot.cr_div = 0u;
    S.cap_sp_changed = 0u;
    S.cap_state = LINK_CAP_ARMED;
    LINK_CRITICAL_END();
    return 0u;
}
#endif

#if defined(__SDCC_pic16)
/* PIC18 assembly (the C below, step for step).  R(0..1) start, R(2) count (R(i) = rx_buf[3 + i]).
 * The samples sent: min(count, total - start, what fits), their bytes by the 8x8 multiplier
 * (at most 256: the buffer's size); FSR0 walks the ring (wrapping after cap_bytes) and the reply
 * (cp_d) in turn; PRODH the byte index, TABLAT the bytes left. */
/* Contract: in R(0..2) (start, count); out the samples in A(0..), link_hot.n, W = 0 (answered) or a NACK
 * code; clobbers W, STATUS, BSR, PROD, FSR0, TABLAT; byte counts by the 8x8 multiplier (at most
 * 256), the ring's index wraps after cap_bytes. */
static uint8_t h_capture_read(void) __naked
{
    __asm
    BANKSEL _S
    MOVF    _S, W, B                ; cap_state
    XORLW   3
    BZ      lcr_done
    DECF    _S, W, B                ; ARMED or TRIGGERED: busy
    SUBLW   1
    BNC     lcr_wrong
    RETLW   7
lcr_wrong:
    RETLW   6
lcr_done:
    MOVFF   (_S + LS_CR_TOTAL), _PRODL       ; PRODL = total
    BANKSEL _rx_buf
    MOVF    (_rx_buf + 4), W, B     ; start < 256
    BNZ     lcr_range
    MOVF    (_rx_buf + 3), W, B     ; PRODH = total - start (start <= total)
    SUBWF   _PRODL, W, A
    BNC     lcr_range
    MOVWF   _PRODH, A
    MOVLW   3          ; A(0..6): state, total, trigger index, start (u16 each but the state)
    MOVFF   _WREG, (_tx_buf + 4)
    MOVFF   (_S + LS_CR_TOTAL), (_tx_buf + 5)
    MOVFF   (_S + LS_CR_TIDX), (_tx_buf + 7)
    MOVFF   (_rx_buf + 3), (_tx_buf + 9)
    MOVLW   0
    MOVFF   _WREG, (_tx_buf + 6)
    MOVFF   _WREG, (_tx_buf + 8)
    MOVFF   _WREG, (_tx_buf + 10)
    MOVF    (_rx_buf + 5), W, B     ; samples = min(count, total - start)
    CPFSLT  _PRODH, A
    MOVWF   _PRODH, A
    MOVLW   33   ; and what fits after the header
    MOVWF   _PRODL, A
    CLRF    _TABLAT, A
lcr_fit:
    MOVF    (_link_hot + LH_CAP_NB), W, A
    SUBWF   _PRODL, F, A
    BNC     lcr_fitted
    INCF    _TABLAT, F, A
    BRA     lcr_fit
lcr_fitted:
    MOVF    _TABLAT, W, A
    CPFSLT  _PRODH, A
    MOVWF   _PRODH, A
    MOVF    _PRODH, W, A            ; bytes = samples x cap_nb (PRODL)
    MULWF   (_link_hot + LH_CAP_NB), A
    MOVF    _PRODL, W, A            ; reply length = header + bytes
    ADDLW   7
    MOVWF   (_link_hot + LH_N), A
    MOVFF   _PRODL, _TABLAT         ; TABLAT = bytes
    BANKSEL _S
    MOVFF   (_rx_buf + 3), _WREG    ; the first sample: (record start + start) mod cap_n
    ADDWF   (_S + LS_CR_START), W, B
    MOVWF   _PRODL, A
    MOVF    (_link_hot + LH_CAP_N), W, A
    CPFSLT  _PRODL, A
    SUBWF   _PRODL, F, A
    MOVF    _PRODL, W, A            ; its byte index (< 256)
    MULWF   (_link_hot + LH_CAP_NB), A
    MOVFF   _PRODL, _PRODH          ; PRODH = the byte index
    MOVLW   LOW(_tx_buf + 11)   ; cp_d: the reply after its header
    MOVFF   _WREG, _cp_d
    MOVLW   HIGH(_tx_buf + 11)
    MOVFF   _WREG, (_cp_d + 1)
    LFSR    0, _cap_buf
    MOVF    _PRODH, W, A
    ADDWF   _FSR0L, F, A
    BTFSC   _STATUS, 0, A
    INCF    _FSR0H, F, A
    MOVF    _TABLAT, F, A
    BZ      lcr_end
lcr_loop:
    MOVFF   _POSTINC0, _PRODL       ; PRODL = the ring byte (POSTINC0), then *cp_d++ = PRODL
    MOVFF   _FSR0L, _cp_s           ; (FSR0 only: the ring position waits in cp_s)
    MOVFF   _FSR0H, (_cp_s + 1)
    MOVFF   _cp_d, _FSR0L
    MOVFF   (_cp_d + 1), _FSR0H
    MOVFF   _PRODL, _POSTINC0
    MOVFF   _FSR0L, _cp_d
    MOVFF   _FSR0H, (_cp_d + 1)
    MOVFF   _cp_s, _FSR0L
    MOVFF   (_cp_s + 1), _FSR0H
    INCF    _PRODH, F, A
    DECF    _PRODH, W, A            ; past the last byte: back to the start
    XORWF   (_S + LS_CAP_BYTES), W, B
    BNZ     lcr_next
    CLRF    _PRODH, A
    LFSR    0, _cap_buf
lcr_next:
    DECFSZ  _TABLAT, F, A
    BRA     lcr_loop
lcr_end:
    RETLW   0
lcr_range:
    RETLW   4
    __endasm;
}
#else
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
#endif

static uint8_t h_eeprom_save(void)
{
    link_hot.n = 0u;
    return link_eeprom_save();
}

static uint8_t h_eeprom_load(void)
{
    link_hot.n = 0u;
    return (ee_load() != LINK_EE_OK) ? LINK_NACK_EEPROM_ERROR : 0u;   /* announced by link_poll */
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
    h_app,
};

static uint8_t run_command(uint8_t c) LINK_WPARAM  /* the handler of command code c + 1: 0 or a NACK code */
{
    uint8_t spec;
    if (c >= N_CMDS) {
        return LINK_NACK_UNKNOWN_COMMAND;
    }
    rom_at((uint16_t)(ROM_CMD + c));
    spec = rom_next();
    if ((uint8_t)(spec & CMD_ANY_LEN) != CMD_ANY_LEN && (uint8_t)(spec & CMD_ANY_LEN) != link_hot.n) {
        return LINK_NACK_MALFORMED;
    }
    if ((spec & CMD_IDLE) != 0u && drive_busy()) {
        return LINK_NACK_WRONG_STATE;
    }
    return cmd_fn[c]();
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
    S.nack = NACK_ARMED;
    LINK_HOOK_FRAME(type, S.tseq, &R(0), link_hot.n);
    if (type == S.rp_type && S.tseq == S.rp_seq && S.fc0 == S.rp_crc0 && S.fc1 == S.rp_crc1) {
        /* the last frame again (a retry, or a replayed frame): answered, but it does not feed the
         * watchdog; a stored reply is sent again, a read-only command runs again */
        if (S.rp_len != NONE) {
            link_hot.n = S.rp_len;
            mcopy(&A(0), rp_data, link_hot.n);
            tx_seal(S.rp_rtype);
            return;
        }
    } else if ((uint8_t)(type - 1u) < N_CMDS) {
        S.rx_valid = 1u;               /* only a new host command feeds the watchdog */
    }
    S.rp_crc0 = S.fc0;
    S.rp_crc1 = S.fc1;
    S.rp_type = type;
    S.rp_seq = S.tseq;
    code = run_command((uint8_t)(type - 1u));
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
    int16_t st = app_signal(LINK_SIG_STATE);
    S.wd_armed = (uint8_t)(st == (int16_t)LINK_STATE_RUN);
}

#if defined(__SDCC_pic16)
/* PIC18 assembly (the C below, step for step): the pass count on the software stack, no register
 * held across the calls */
/* Contract: in a received frame (rx_ready), the pending events and telemetry; out at most the
 * frames one pass allows answered, events and telemetry queued; clobbers W, STATUS, BSR, PROD,
 * FSR0, TABLAT and what the compiled C it calls may change (W, STATUS, BSR, PROD, FSR0, TBLPTR,
 * TABLAT) (software stack balanced). */
void link_poll(void) __naked
{
    __asm
    MOVLW   8                       ; at most 8 frames a call
    MOVWF   _POSTDEC1, A
lpl_loop:
    CALL    _wd_arm
    CALL    _tx_drain
    MOVF    (_link_hot + LH_TX_LEN), W, A  ; tx_len: a frame still leaving
    BNZ     lpl_end
    BANKSEL _S
    MOVF    (_S + LS_NACK), W, B         ; nack == NACK_PENDING: one BAD_CRC NACK
    XORLW   2
    BNZ     lpl_rx
    CLRF    (_S + LS_NACK), B
    MOVFF   (_S + LS_NACK_TYPE), (_tx_buf + 4)   ; A(0) = the frame type, A(1) = BAD_CRC
    MOVLW   2
    MOVFF   _WREG, (_tx_buf + 5)
    MOVLW   2
    MOVWF   (_link_hot + LH_N), A
    MOVFF   (_S + LS_NACK_SEQ), (_S + LS_TSEQ)    ; SEQ of the bad frame
    MOVLW   127
    CALL    _tx_seal
    BRA     lpl_next
lpl_rx:
    MOVF    (_link_hot + LH_RX_READY), W, A
    BZ      lpl_ev
    CALL    _rx_frame
    IORLW   0
    BZ      lpl_release
    CALL    _dispatch
    CALL    _link_notify
lpl_release:
    CALL    _rx_release
    BRA     lpl_next
lpl_ev:
    CALL    _send_event
    IORLW   0
    BNZ     lpl_next
    MOVF    (_link_hot + LH_TM_READY), W, A  ; tm_ready: the telemetry frame
    BZ      lpl_end
    MOVF    (_link_hot + LH_TR_LEN), W, A  ; n = tr.len; A(0..) = tm_buf
    MOVWF   (_link_hot + LH_N), A
    MOVLW   LOW(_tx_buf + 4)
    MOVFF   _WREG, _cp_d
    MOVLW   HIGH(_tx_buf + 4)
    MOVFF   _WREG, (_cp_d + 1)
    MOVLW   LOW(_tm_buf)
    MOVFF   _WREG, _cp_s
    MOVLW   HIGH(_tm_buf)
    MOVFF   _WREG, (_cp_s + 1)
    MOVF    (_link_hot + LH_N), W, A
    CALL    _mcopy_n
    MOVFF   (_S + LS_TM_GEN), (_S + LS_TSEQ)     ; SEQ = tm_gen
    MOVLW   96
    CALL    _tx_seal
    CLRF    (_link_hot + LH_TR_NSAMP), A     ; tr.nsamp = tr.len = 0, tm_ready = 0
    CLRF    (_link_hot + LH_TR_LEN), A
    CLRF    (_link_hot + LH_TM_READY), A
lpl_next:
    MOVF    _PREINC1, W, A          ; the pass count
    DECF    _WREG, F, A
    BZ      lpl_last
    MOVWF   _POSTDEC1, A
    BRA     lpl_loop
lpl_end:
    MOVF    _PREINC1, F, A          ; drop the pass count
lpl_last:
    CALL    _wd_arm                 ; again: a start just executed arms the watchdog at once
    RETURN
    __endasm;
}
#else
void link_poll(void)
{
    uint8_t k;
    for (k = 0u; k < 8u; k++) {
        wd_arm();
        tx_drain();
        if (link_hot.tx_len != 0u) {
            break;
        }
        if (S.nack == NACK_PENDING) {
            S.nack = 0u;
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
                link_notify();
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
#endif

/* ---- per speed-loop sample: telemetry and capture ---- */
/* One sample's signals, read once each: those of sg.tm (telemetry) to sg.p, those of sg.cm (capture)
 * to sg.q, int16 little-endian (speed-loop interrupt only).  Each value comes straight from
 * app_signal_src[j] (no call, no lock: the interrupt owns the values), or through app_signal(j) for
 * a NULL entry.  The masks are consumed (shifted out); they are within SIG_ALL (mask_nsig). */
#if defined(__SDCC_pic16)
/* PIC18 assembly: about 60 cycles a selected signal, no software-stack frame.  The flash table is
 * read with TBLRD: TBLPTR and TABLAT are saved on entry and restored on exit (hazard a: this runs
 * in an interrupt, whatever the application's prologue saves).  FSR0 and PROD are saved by the
 * interrupt's prologue; sg (one bank) holds the pointers and the masks. */
/* Contract: in sg.p, sg.q, sg.tm, sg.cm; out the selected signals written to the telemetry and
 * capture samples; saves and restores TBLPTR and TABLAT itself (interrupt context), clobbers W,
 * STATUS, BSR, PROD, FSR0 (saved by the interrupt's prologue). */
static void put_signals(void) __naked
{
    __asm
    MOVFF   _TBLPTRU, _POSTDEC1     ; save TBLPTRU, TBLPTRH, TBLPTRL, TABLAT
    MOVFF   _TBLPTRH, _POSTDEC1
    MOVFF   _TBLPTRL, _POSTDEC1
    MOVFF   _TABLAT, _POSTDEC1
    MOVLW   UPPER(_app_signal_src)
    MOVWF   _TBLPTRU, A
    MOVLW   HIGH(_app_signal_src)
    MOVWF   _TBLPTRH, A
    MOVLW   LOW(_app_signal_src)
    MOVWF   _TBLPTRL, A
    BANKSEL _sg
lps_loop:
    TBLRD*+
    MOVFF   _TABLAT, _FSR0L         ; FSR0 = app_signal_src[j]
    TBLRD*+
    MOVFF   _TABLAT, _FSR0H
    MOVF    (_sg + SG_TM), W, B
    IORWF   (_sg + SG_CM), W, B
    BTFSS   _WREG, 0, A             ; signal j in neither mask: next
    BRA     lps_next
    MOVF    _FSR0L, W, A
    IORWF   _FSR0H, W, A
    BZ      lps_call
    MOVFF   _POSTINC0, _PRODL       ; PRODL, PRODH = *src
    MOVFF   _POSTINC0, _PRODH
    BRA     lps_have
lps_call:                          ; NULL: app_signal(j), the table pointer kept across the call
    MOVFF   _TBLPTRU, _POSTDEC1
    MOVFF   _TBLPTRH, _POSTDEC1
    MOVFF   _TBLPTRL, _POSTDEC1
    MOVLW   LOW(_app_signal_src + 2)    ; j = (TBLPTR - (app_signal_src + 2)) / 2, the low bytes suffice
    SUBWF   _TBLPTRL, W, A
    RRNCF   _WREG, W, A
    CALL    _app_signal             ; low byte in W, high byte in PRODL
    MOVFF   _PRODL, _PRODH
    MOVWF   _PRODL, A
    MOVFF   _PREINC1, _TBLPTRL
    MOVFF   _PREINC1, _TBLPTRH
    MOVFF   _PREINC1, _TBLPTRU
    BANKSEL _sg
lps_have:
    BTFSS   (_sg + SG_TM), 0, B
    BRA     lps_cap
    MOVFF   _sg, _FSR0L             ; *sg.p++ = value
    MOVFF   (_sg + SG_P + 1), _FSR0H
    MOVFF   _PRODL, _POSTINC0
    MOVFF   _PRODH, _POSTINC0
    MOVFF   _FSR0L, _sg
    MOVFF   _FSR0H, (_sg + SG_P + 1)
lps_cap:
    BTFSS   (_sg + SG_CM), 0, B
    BRA     lps_next
    MOVFF   (_sg + SG_Q), _FSR0L       ; *sg.q++ = value
    MOVFF   (_sg + SG_Q + 1), _FSR0H
    MOVFF   _PRODL, _POSTINC0
    MOVFF   _PRODH, _POSTINC0
    MOVFF   _FSR0L, (_sg + SG_Q)
    MOVFF   _FSR0H, (_sg + SG_Q + 1)
lps_next:
    BCF     _STATUS, 0, A ; tm >>= 1, cm >>= 1
    RRCF    (_sg + SG_TM + 1), F, B
    RRCF    (_sg + SG_TM), F, B
    BCF     _STATUS, 0, A
    RRCF    (_sg + SG_CM + 1), F, B
    RRCF    (_sg + SG_CM), F, B
    MOVF    (_sg + SG_TM), W, B
    IORWF   (_sg + SG_TM + 1), W, B
    IORWF   (_sg + SG_CM), W, B
    IORWF   (_sg + SG_CM + 1), W, B
    BNZ     lps_loop
    MOVFF   _PREINC1, _TABLAT       ; restore TABLAT, TBLPTRL, TBLPTRH, TBLPTRU
    MOVFF   _PREINC1, _TBLPTRL
    MOVFF   _PREINC1, _TBLPTRH
    MOVFF   _PREINC1, _TBLPTRU
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

/* The speed-loop interrupt's part in PIC18 assembly: no software-stack frame, no register saved
 * (W, STATUS, BSR, PROD are the interrupt's; app_signal and app_link_lost are called like the C
 * did).  Offsets into link_hot (access bank) and S are pinned by the layout checks below. */
#if defined(__SDCC_pic16)
#define LP_LINK_TIMEOUT 17                /* offsetof(link_params_t, link_timeout), checked below */
typedef char link_isr_layout[(offsetof(link_params_t, link_timeout) == LP_LINK_TIMEOUT) ? 1 : -1];
#if LINK_WITH_CAPTURE
typedef char link_cap_layout[(sizeof S.cr == 10u) ? 1 : -1];

/* decimation and trigger; a sample due: sg.q, sg.cm set */
/* Contract: in the capture state S.cr and the decimation counter; out sg.q, sg.cm set when a
 * sample is due (the trigger tested on its signal); clobbers W, STATUS, BSR, PROD, FSR0, TBLPTR,
 * TABLAT. */
static void capture_due(void) __naked
{
    __asm
    INFSNZ  (_link_hot + LH_CR_DIV), F, A  ; cr_div++
    INCF    (_link_hot + LH_CR_DIV + 1), F, A
    MOVF    (_link_hot + LH_CAP_DEC), W, A  ; cr_div - cap_dec: borrow = not due yet
    SUBWF   (_link_hot + LH_CR_DIV), W, A
    MOVF    (_link_hot + LH_CAP_DEC + 1), W, A
    SUBWFB  (_link_hot + LH_CR_DIV + 1), W, A
    BC      lcd_due
    RETURN
lcd_due:
    CLRF    (_link_hot + LH_CR_DIV), A
    CLRF    (_link_hot + LH_CR_DIV + 1), A
    BANKSEL _S
    MOVF    _S, W, B                ; cap_state
    XORLW   1
    BNZ     lcd_slot
    MOVF    (_S + LS_CAP_TRIG), W, B
    BZ      lcd_fire                ; IMMEDIATE
    XORLW   1
    BNZ     lcd_speed
    MOVF    (_S + LS_CAP_SP_CHANGED), W, B         ; SETPOINT_CHANGE: the setpoint was written
    BZ      lcd_slot
    BRA     lcd_fire
lcd_speed:                          ; a crossing: sp in PRODH:PRODL
    MOVLW   0
    CALL    _app_signal             ; low byte in W, high byte in PRODL
    MOVFF   _PRODL, _PRODH
    MOVWF   _PRODL, A
    BANKSEL _S
    MOVF    (_S + LS_CAP_TRIG), W, B
    XORLW   3
    BNZ     lcd_cmp
    COMF    _PRODL, F, A            ; falling through thr = ~speed rising through ~thr (stored so)
    COMF    _PRODH, F, A
lcd_cmp:
    MOVF    (_S + LS_CR_PREV_VALID), W, B         ; no previous sample: no crossing
    BZ      lcd_keep
    MOVF    (_S + LS_CAP_THR), W, B         ; prev - thr: signed less-than is N xor OV
    SUBWF   (_S + LS_CR_PREV), W, B
    MOVF    (_S + LS_CAP_THR + 1), W, B
    SUBWFB  (_S + LS_CR_PREV + 1), W, B
    BOV     lcd_ov1
    BNN     lcd_keep
    BRA     lcd_now
lcd_ov1:
    BN      lcd_keep
lcd_now:
    MOVF    (_S + LS_CAP_THR), W, B         ; sp - thr: greater or equal is N == OV
    SUBWF   _PRODL, W, A
    MOVF    (_S + LS_CAP_THR + 1), W, B
    SUBWFB  _PRODH, W, A
    BOV     lcd_ov2
    BN      lcd_keep
    BRA     lcd_yes
lcd_ov2:
    BNN     lcd_keep
lcd_yes:
    MOVFF   _PRODL, (_S + LS_CR_PREV)       ; prev = sp
    MOVFF   _PRODH, (_S + LS_CR_PREV + 1)
    BRA     lcd_fire
lcd_keep:
    MOVFF   _PRODL, (_S + LS_CR_PREV)       ; prev = sp, prev_valid = 1
    MOVFF   _PRODH, (_S + LS_CR_PREV + 1)
    MOVLW   1
    MOVWF   (_S + LS_CR_PREV_VALID), B
    BRA     lcd_slot
lcd_fire:
    MOVF    (_S + LS_CR_FILLED), W, B         ; tidx = min(filled, pre)
    CPFSGT  (_S + LS_CAP_PRE), B
    MOVF    (_S + LS_CAP_PRE), W, B
    MOVWF   (_S + LS_CR_TIDX), B
    CLRF    (_S + LS_CR_POST), B            ; post = 0
    MOVLW   2
    MOVWF   _S, B
lcd_slot:
    MOVF    (_S + LS_CR_WI), W, B         ; sg.q = &cap_buf[wi], sg.cm = cap_mask
    ADDLW   LOW(_cap_buf)
    MOVFF   _WREG, (_sg + SG_Q)
    MOVLW   HIGH(_cap_buf)
    BTFSC   _STATUS, 0, A
    ADDLW   1
    MOVFF   _WREG, (_sg + SG_Q + 1)
    MOVFF   (_S + LS_CAP_MASK), (_sg + SG_CM)
    MOVFF   (_S + LS_CAP_MASK + 1), (_sg + SG_CM + 1)
    RETURN
    __endasm;
}

/* Contract: in the sample just written; out the ring's write index and the record's counts on
 * (S.cr), the capture state at its end; clobbers W, STATUS, BSR; counts are bytes (at most 128
 * samples, 256 B). */
static void capture_done(void) __naked  /* after a sample was written: the ring and the record */
{
    __asm
    BANKSEL _S
    MOVF    (_link_hot + LH_CAP_NB), W, A  ; wi += cap_nb
    ADDWF   (_S + LS_CR_WI), F, B
    INCF    (_S + LS_CR_W), F, B         ; w++
    MOVF    (_link_hot + LH_CAP_N), W, A  ; W = cap_n
    CPFSEQ  (_S + LS_CR_W), B
    BRA     lcd2_fill
    CLRF    (_S + LS_CR_W), B            ; the ring wraps
    CLRF    (_S + LS_CR_WI), B
lcd2_fill:
    CPFSEQ  (_S + LS_CR_FILLED), B            ; filled < cap_n: one more
    INCF    (_S + LS_CR_FILLED), F, B
    MOVF    _S, W, B
    XORLW   2
    BNZ     lcd2_end
    INCF    (_S + LS_CR_POST), F, B         ; post++
    MOVF    (_S + LS_CAP_PRE), W, B         ; post + pre == cap_n: the record is complete
    ADDWF   (_S + LS_CR_POST), W, B
    XORWF   (_link_hot + LH_CAP_N), W, A
    BNZ     lcd2_end
    MOVF    (_S + LS_CR_TIDX), W, B         ; total = tidx + post
    ADDWF   (_S + LS_CR_POST), W, B
    MOVWF   (_S + LS_CR_TOTAL), B
    SUBWF   (_S + LS_CR_W), W, B         ; start = (w - total) mod cap_n
    BC      lcd2_start
    ADDWF   (_link_hot + LH_CAP_N), W, A
lcd2_start:
    MOVWF   (_S + LS_CR_START), B
    MOVLW   3
    MOVWF   _S, B
lcd2_end:
    RETURN
    __endasm;
}
#endif

/* Contract: in the speed-loop sample (the signals through app_signal); out the telemetry and
 * capture samples written when due (tm_ready set, drops counted); clobbers W, STATUS, BSR, PROD,
 * FSR0, TBLPTR, TABLAT (interrupt context: the prologue saves them); counters wrap modulo 2^16
 * as the C's. */
void link_sample(void) __naked
{
    __asm
    BANKSEL _sg
    CLRF    (_sg + SG_TM), B            ; sg.tm = sg.cm = 0
    CLRF    (_sg + SG_TM + 1), B
    CLRF    (_sg + SG_CM), B
    CLRF    (_sg + SG_CM + 1), B
    MOVF    (_link_hot + LH_TM_DEC), W, A  ; telemetry on (tm_dec != 0)?
    IORWF   (_link_hot + LH_TM_DEC + 1), W, A
    BZ      lsm_cap
    INFSNZ  (_link_hot + LH_TR_DIV), F, A  ; tr.div++
    INCF    (_link_hot + LH_TR_DIV + 1), F, A
    MOVF    (_link_hot + LH_TM_DEC), W, A  ; tr.div - tm_dec: borrow = not due yet
    SUBWF   (_link_hot + LH_TR_DIV), W, A
    MOVF    (_link_hot + LH_TM_DEC + 1), W, A
    SUBWFB  (_link_hot + LH_TR_DIV + 1), W, A
    BNC     lsm_cap
    CLRF    (_link_hot + LH_TR_DIV), A
    CLRF    (_link_hot + LH_TR_DIV + 1), A
    BANKSEL _S
    MOVF    (_link_hot + LH_TM_READY), W, A  ; tm_ready: the last frame is not sent yet: a drop
    BZ      lsm_fill
    MOVF    (_S + LS_TM_DROPPED), W, B          ; tm_dropped++, saturating: not at 0xFFFF
    ANDWF   (_S + LS_TM_DROPPED + 1), W, B
    INCF    _WREG, W, A
    BZ      lsm_count
    INFSNZ  (_S + LS_TM_DROPPED), F, B
    INCF    (_S + LS_TM_DROPPED + 1), F, B
    BRA     lsm_count
lsm_fill:
    MOVF    (_link_hot + LH_TR_NSAMP), W, A  ; the first sample of a frame: its counter, the header
    BNZ     lsm_ptr
    MOVFF   (_link_hot + LH_TR_COUNTER), _tm_buf
    MOVFF   (_link_hot + LH_TR_COUNTER + 1), (_tm_buf + 1)
    MOVLW   2
    MOVWF   (_link_hot + LH_TR_LEN), A
lsm_ptr:
    MOVF    (_link_hot + LH_TR_LEN), W, A  ; sg.p = &tm_buf[tr.len], sg.tm = tm_mask
    ADDLW   LOW(_tm_buf)
    MOVFF   _WREG, _sg
    MOVLW   HIGH(_tm_buf)
    BTFSC   _STATUS, 0, A
    ADDLW   1
    MOVFF   _WREG, (_sg + SG_P + 1)
    MOVFF   (_S + LS_TM_MASK), (_sg + SG_TM)
    MOVFF   (_S + LS_TM_MASK + 1), (_sg + SG_TM + 1)
    MOVF    (_link_hot + LH_TM_NB), W, A  ; tr.len += tm_nb, tr.nsamp++
    ADDWF   (_link_hot + LH_TR_LEN), F, A
    INCF    (_link_hot + LH_TR_NSAMP), F, A
    MOVF    (_S + LS_TM_SPF), W, B         ; tr.nsamp >= tm_spf: the frame is ready (filled before return)
    CPFSLT  (_link_hot + LH_TR_NSAMP), A
    BSF     (_link_hot + LH_TM_READY), 0, A
lsm_count:
    INFSNZ  (_link_hot + LH_TR_COUNTER), F, A  ; tr.counter++
    INCF    (_link_hot + LH_TR_COUNTER + 1), F, A
lsm_cap:
#if LINK_WITH_CAPTURE
    BANKSEL _S
    DECF    _S, W, B                ; cap_state ARMED or TRIGGERED: a capture sample may be due
    SUBLW   1
    BTFSC   _STATUS, 0, A
    CALL    _capture_due
#endif
    BANKSEL _sg
    MOVF    (_sg + SG_TM), W, B
    IORWF   (_sg + SG_TM + 1), W, B
    IORWF   (_sg + SG_CM), W, B
    IORWF   (_sg + SG_CM + 1), W, B
    BTFSS   _STATUS, 2, A ; a signal to write (Z clear)
    CALL    _put_signals
#if LINK_WITH_CAPTURE
    BANKSEL _sg
    MOVF    (_sg + SG_Q), W, B         ; a capture sample was written: sg.q = 0, capture_done
    IORWF   (_sg + SG_Q + 1), W, B
    BZ      lsm_end
    CLRF    (_sg + SG_Q), B
    CLRF    (_sg + SG_Q + 1), B
    CALL    _capture_done
lsm_end:
#endif
    RETURN
    __endasm;
}

/* ---- time base: watchdog, uptime ---- */
/* Contract: in nothing (a 1 ms tick); out S.uptime_ms + 1 (wraps modulo 2^32), the link watchdog
 * counted and app_link_lost called once it expires; clobbers W, STATUS, BSR, PROD and what the
 * compiled C it calls may change (W, STATUS, BSR, PROD, FSR0, TBLPTR, TABLAT); wd_ms saturates
 * at 0xFFFF. */
void link_tick_ms(void) __naked
{
    __asm
    extern  _app_link_lost
    BANKSEL _S
    INCF    (_S + LS_UPTIME_MS), F, B          ; uptime_ms++ (32 bits)
    BNZ     ltk_wd
    INCF    (_S + LS_UPTIME_MS + 1), F, B
    BNZ     ltk_wd
    INCF    (_S + LS_UPTIME_MS + 2), F, B
    BNZ     ltk_wd
    INCF    (_S + LS_UPTIME_MS + 3), F, B
ltk_wd:
    MOVF    (_S + LS_WD_ARMED), W, B
    BZ      ltk_clear
    MOVF    (_S + LS_RX_VALID), W, B         ; rx_valid: a host command arrived
    BZ      ltk_count
    CLRF    (_S + LS_RX_VALID), B
ltk_clear:
    CLRF    (_S + LS_WD_MS), B            ; wd_ms = 0
    CLRF    (_S + LS_WD_MS + 1), B
    RETURN
ltk_count:
    MOVF    (_S + LS_WD_MS), W, B         ; wd_ms++, saturating: not at 0xFFFF
    ANDWF   (_S + LS_WD_MS + 1), W, B
    INCF    _WREG, W, A
    BZ      ltk_cmp
    INFSNZ  (_S + LS_WD_MS), F, B
    INCF    (_S + LS_WD_MS + 1), F, B
ltk_cmp:
    MOVFF   (_link_params + LP_LINK_TIMEOUT), _PRODL  ; wd_ms - link_timeout: no borrow = expired
    MOVFF   (_link_params + LP_LINK_TIMEOUT + 1), _PRODH
    MOVF    _PRODL, W, A
    SUBWF   (_S + LS_WD_MS), W, B
    MOVF    _PRODH, W, A
    SUBWFB  (_S + LS_WD_MS + 1), W, B
    BNC     ltk_end
    CLRF    (_S + LS_WD_ARMED), B            ; disarm, outputs off (the application), the event
    CLRF    (_S + LS_WD_MS), B
    CLRF    (_S + LS_WD_MS + 1), B
    CALL    _app_link_lost
    BANKSEL _S
    MOVLW   1
    MOVWF   (_S + LS_EV_WATCHDOG), B
ltk_end:
    RETURN
    __endasm;
}
#else  /* the same in C */
#if LINK_WITH_CAPTURE
static void capture_due(void)          /* decimation and trigger; a sample due: sg.q, sg.cm set */
{
    uint8_t fire = 0u;
    int16_t sp;
    link_hot.cr_div++;
    if (link_hot.cr_div < link_hot.cap_dec) {
        return;
    }
    link_hot.cr_div = 0u;
    if (S.cap_state == LINK_CAP_ARMED) {
        if (S.cap_trig == LINK_TRIG_IMMEDIATE) {
            fire = 1u;
        } else if (S.cap_trig == LINK_TRIG_SETPOINT_CHANGE) {
            fire = S.cap_sp_changed;
        } else {
            /* falling through thr = ~speed rising through ~thr (capture_arm stored ~thr) */
            sp = app_signal(LINK_SIG_SPEED);
            if (S.cap_trig == LINK_TRIG_SPEED_FALLING) {
                sp = (int16_t)~sp;
            }
            fire = (uint8_t)(S.cr.prev_valid != 0u && S.cr.prev < S.cap_thr && sp >= S.cap_thr);
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
    S.cr.wi = (uint8_t)(S.cr.wi + link_hot.cap_nb);
    S.cr.w++;
    if (S.cr.w == link_hot.cap_n) {
        S.cr.w = 0u;
        S.cr.wi = 0u;
    }
    if (S.cr.filled != link_hot.cap_n) {
        S.cr.filled++;
    }
    if (S.cap_state == LINK_CAP_TRIGGERED) {
        S.cr.post++;
        if ((uint8_t)(S.cr.post + S.cap_pre) == link_hot.cap_n) {
            S.cr.total = (uint8_t)(S.cr.tidx + S.cr.post);
            S.cr.start = (uint8_t)(S.cr.w - S.cr.total);   /* (w - total) mod n */
            if (S.cr.w < S.cr.total) {
                S.cr.start = (uint8_t)(S.cr.start + link_hot.cap_n);
            }
            S.cap_state = LINK_CAP_DONE;
        }
    }
}
#endif

void link_sample(void)
{
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
                link_hot.tr.len = (uint8_t)(link_hot.tr.len + link_hot.tm_nb);
                link_hot.tr.nsamp++;
                if (link_hot.tr.nsamp >= S.tm_spf) {
                    link_hot.tm_ready = 1u;    /* the interrupt fills tm_buf before it returns */
                }
            }
            link_hot.tr.counter++;
        }
    }
#if LINK_WITH_CAPTURE
    if ((uint8_t)(S.cap_state - LINK_CAP_ARMED) <= (uint8_t)(LINK_CAP_TRIGGERED - LINK_CAP_ARMED)) {
        capture_due();
    }
#endif
    if ((sg.tm | sg.cm) != 0u) {
        put_signals();
    }
#if LINK_WITH_CAPTURE
    if (sg.q != 0) {
        sg.q = 0;
        capture_done();
    }
#endif
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
#endif

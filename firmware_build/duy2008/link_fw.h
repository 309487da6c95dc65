/*
 * link_fw.h -- picdrive serial link, C side.
 * Rendered by picdrive.link.protocol_c.render_c() from host/picdrive/link/protocol.py.  DO NOT EDIT.
 *
 * protocol 2.1, 31 table entries (2 rules),
 * table hash 0xA892BE6EUL, build id 0xBA71C15AUL, profile hash 0x4B0E5FBAUL
 *
 * Frame on the wire: COBS(body) then the delimiter 0x00, which never occurs inside a frame; the
 * host also sends a 0x00 before each command.  Body: LEN (0..40), TYPE, SEQ, payload,
 * CRC-16/CCITT-FALSE over LEN..payload, high byte first.  A frame whose decoded length is not
 * LEN + 5 or whose CRC fails is dropped whole; the receiver resynchronises at the next 0x00.
 *
 * RAM (bytes) of this module: buffers and scalar state (the total is what avr-gcc allocates):
 *   rx_frame           46
 *   rx_spill           16
 *   tx_frame           46
 *   telemetry_frame    40
 *   replay              8
 *   param_store        37
 *   capture           128
 *   state             108
 *   total             429
 *
 * Contexts: link_rx_byte(), link_tick_ms() and link_sample() may be called from interrupts,
 * link_poll() from the main loop.  link_rx_byte() stores the byte in the frame buffer and marks
 * the frame complete at its delimiter, or in the spill ring while the main loop holds the frame
 * buffer; it shares only single bytes (the fill count, the ready flag, the ring's indices and
 * bytes, an 8-bit count of bytes lost to a full ring) with the main loop; link_tick_ms() and link_sample() share 16/32-bit
 * counters read by link_poll() inside LINK_CRITICAL_BEGIN()/END(), which must therefore mask
 * the interrupt that calls them.  None of them calls a compiler helper (multiply, divide,
 * generic pointer), so none is shared with the main loop; link_sample() reads the flash table
 * app_signal_src and saves/restores the table pointer (TBLPTR, TABLAT) around that itself.
 * Parameter-store writes happen in link_poll() between LINK_CRITICAL_BEGIN() and
 * LINK_CRITICAL_END() (define them, e.g. to clear/set GIEH, if the speed-loop interrupt
 * reads link_params).
 */
#ifndef LINK_FW_H
#define LINK_FW_H

#include <stdint.h>

#if defined(__SDCC_pic16) || defined(__SDCC_PIC16)
#define LINK_DATA __data                 /* 2-byte data-space pointers, not 3-byte generic ones */
#define LINK_WPARAM __wparam             /* a single byte argument travels in W, not on the stack */
#else
#define LINK_DATA
#define LINK_WPARAM
#endif

#define LINK_PROTO_MAJOR        2u
#define LINK_PROTO_MINOR        1u
#define LINK_BUILD_ID           0xBA71C15AUL
#define LINK_PROFILE_HASH       0x4B0E5FBAUL
#define LINK_TABLE_HASH         0xA892BE6EUL
#define LINK_SAMPLE_HZ          1000u
#define LINK_N_RULES            2u
#define LINK_N_ENTRIES          31u
#define LINK_N_SIGNALS          12u

#define LINK_DELIMITER          0x00u
#define LINK_MAX_PAYLOAD        40u
#define LINK_MAX_BODY           45u   /* LEN, TYPE, SEQ, payload, CRC */
#define LINK_MAX_FRAME          47u   /* on the wire: COBS code + body + delimiter */
#define LINK_RX_BYTES           46u   /* receive buffer: one frame without its delimiter */
#define LINK_RX_SPILL           16u   /* spill ring: bytes arriving while link_poll holds the frame buffer */
#define LINK_N_PERSISTED        18u
#define LINK_REPLAY_BYTES       8u
#define LINK_CAPTURE_WORDS      64u
#define LINK_PARAM_GET_MAX      10u
#define LINK_NAME_MAX           15u
#define LINK_SIGNAL_BASE_ID     0x20u
#define LINK_EE_IMAGE_BYTES     45u
/* features (generation options; -DLINK_WITH_...=0 drops one): capture commands and buffer,
 * EEPROM persistence.  bench/link_pic18.py measures what each costs. */
#ifndef LINK_WITH_CAPTURE
#define LINK_WITH_CAPTURE       1
#endif
#ifndef LINK_WITH_EEPROM
#define LINK_WITH_EEPROM        1
#endif
#if LINK_WITH_CAPTURE
#define LINK_HELLO_CAPTURE_WORDS LINK_CAPTURE_WORDS
#else
#define LINK_HELLO_CAPTURE_WORDS 0u        /* hello: no capture in this build */
#endif
/* hello's features (bit 0: the application implements ident, the identification mode) */
#define LINK_FEATURES           0u
#ifndef LINK_ACCESS_AT            /* SDCC: access-bank address of the link's hot scalars (27 B at most), */
#define LINK_ACCESS_AT          0x25  /* ending at 0x3F: SDCC's registers and drive_core's access RAM below */
#endif
/* link_crc16() and link_param_set(): for tests and host tools (nothing on the chip calls them);
 * left out of a PIC18 build unless -DLINK_WITH_HOST_API=1 */
#ifndef LINK_WITH_HOST_API
#if defined(__SDCC_pic16) || defined(__SDCC_PIC16) || defined(__XC8)
#define LINK_WITH_HOST_API      0
#else
#define LINK_WITH_HOST_API      1
#endif
#endif
#ifndef LINK_EE_BASE
#define LINK_EE_BASE            0u
#endif

/* ---- message types ---- */
#define LINK_CMD_HELLO               0x01u   /* hello */
#define LINK_CMD_PARAM_INFO          0x02u   /* param_info */
#define LINK_CMD_PARAM_GET           0x03u   /* param_get */
#define LINK_CMD_PARAM_SET           0x04u   /* param_set */
#define LINK_CMD_SET_SPEED           0x05u   /* set_speed */
#define LINK_CMD_START               0x06u   /* start */
#define LINK_CMD_STOP                0x07u   /* stop */
#define LINK_CMD_BRAKE               0x08u   /* brake */
#define LINK_CMD_SELECT_CONTROLLER   0x09u   /* select_controller */
#define LINK_CMD_TELEM_CONFIG        0x0Au   /* telem_config */
#define LINK_CMD_CAPTURE_ARM         0x0Bu   /* capture_arm */
#define LINK_CMD_CAPTURE_READ        0x0Cu   /* capture_read */
#define LINK_CMD_EEPROM_SAVE         0x0Du   /* eeprom_save */
#define LINK_CMD_EEPROM_LOAD         0x0Eu   /* eeprom_load */
#define LINK_CMD_FAULT_CLEAR         0x0Fu   /* fault_clear */
#define LINK_CMD_STATUS              0x10u   /* status */
#define LINK_CMD_HEARTBEAT           0x11u   /* heartbeat */
#define LINK_CMD_IDENT               0x12u   /* ident */
#define LINK_MSG_TELEMETRY           0x60u
#define LINK_MSG_EVENT               0x61u
#define LINK_MSG_NACK                0x7Fu
#define LINK_ACK_BIT                 0x80u

/* ---- NACK codes ---- */
#define LINK_NACK_UNKNOWN_COMMAND      1u
#define LINK_NACK_BAD_CRC              2u
#define LINK_NACK_MALFORMED            3u
#define LINK_NACK_OUT_OF_RANGE         4u
#define LINK_NACK_READ_ONLY            5u
#define LINK_NACK_WRONG_STATE          6u
#define LINK_NACK_BUSY                 7u
#define LINK_NACK_UNKNOWN_PARAM        8u
#define LINK_NACK_FAULT_ACTIVE         9u
#define LINK_NACK_EEPROM_ERROR         10u

/* ---- fault codes (latched by the firmware) ---- */
#define LINK_FAULT_NONE                0u
#define LINK_FAULT_HALL_INVALID        1u
#define LINK_FAULT_OVERCURRENT         2u
#define LINK_FAULT_STALL               3u
#define LINK_FAULT_LINK_LOST           4u
#define LINK_FAULT_UNDERVOLTAGE        5u
#define LINK_FAULT_OVERVOLTAGE         6u
#define LINK_FAULT_EEPROM_CRC          7u
#define LINK_FAULT_OVERSPEED           8u

/* ---- drive states (signal "state"; the watchdog is armed in RUN) ---- */
#define LINK_STATE_IDLE                0u
#define LINK_STATE_RUN                 1u
#define LINK_STATE_BRAKE               2u
#define LINK_STATE_FAULT               3u
#define LINK_STATE_IDENT               4u

/* ---- events ---- */
#define LINK_EVENT_BOOT                1u
#define LINK_EVENT_FAULT               2u
#define LINK_EVENT_WATCHDOG            3u

/* ---- capture triggers and states ---- */
#define LINK_TRIG_IMMEDIATE            0u
#define LINK_TRIG_SETPOINT_CHANGE      1u
#define LINK_TRIG_SPEED_RISING         2u
#define LINK_TRIG_SPEED_FALLING        3u
#define LINK_CAP_IDLE                  0u
#define LINK_CAP_ARMED                 1u
#define LINK_CAP_TRIGGERED             2u
#define LINK_CAP_DONE                  3u

/* ---- controllers (parameter "controller") ---- */
#define LINK_CONTROLLER_PID            0u
#define LINK_CONTROLLER_FUZZY          1u

/* ---- link_eeprom_load() results ---- */
#define LINK_EE_OK                     0u
#define LINK_EE_BLANK                  1u
#define LINK_EE_OTHER_BUILD            2u
#define LINK_EE_CORRUPT                3u

/* ---- entry flags and C type codes (param_info) ---- */
#define LINK_FLAG_WRITABLE      0x01u
#define LINK_FLAG_PERSISTED     0x02u
#define LINK_FLAG_SIGNAL        0x04u
#define LINK_T_UINT8                   1u
#define LINK_T_INT8                    2u
#define LINK_T_UINT16                  3u
#define LINK_T_INT16                   4u
#define LINK_T_INT32                   5u

/* ---- table entry ids (param_get / param_set) ---- */
#define LINK_ID_SPEED_SETPOINT       0x00u   /* rpm, scale 0.149207756 */
#define LINK_ID_CONTROLLER           0x01u   /* enum, scale 1 */
#define LINK_ID_PREMISE_LOW          0x02u   /* rpm, scale 0.149207756 */
#define LINK_ID_PREMISE_HIGH         0x03u   /* rpm, scale 0.149207756 */
#define LINK_ID_SETPOINT_WEIGHT      0x04u   /* 1, scale 6.10351562e-05 */
#define LINK_ID_U_MIN                0x05u   /* V, scale 0.00390625 */
#define LINK_ID_U_MAX                0x06u   /* V, scale 0.00390625 */
#define LINK_ID_CURRENT_LIMIT        0x07u   /* A, scale 0.0048828125 */
#define LINK_ID_ACCEL_LIMIT          0x08u   /* rpm/s, scale 149.207764 */
#define LINK_ID_LINK_TIMEOUT         0x09u   /* ms, scale 1 */
#define LINK_ID_STALL_TIMEOUT        0x0Au   /* ms, scale 1 */
#define LINK_ID_SPEED                0x20u   /* rpm, scale 0.149207756, read-only signal */
#define LINK_ID_SETPOINT             0x21u   /* rpm, scale 0.149207756, read-only signal */
#define LINK_ID_VOLTAGE              0x22u   /* V, scale 0.00390625, read-only signal */
#define LINK_ID_CURRENT              0x23u   /* A, scale 0.0048828125, read-only signal */
#define LINK_ID_INTEGRATOR           0x24u   /* V, scale 0.00390625, read-only signal */
#define LINK_ID_DUTY                 0x25u   /* counts, scale 1, read-only signal */
#define LINK_ID_HALL                 0x26u   /* code, scale 1, read-only signal */
#define LINK_ID_STATE                0x27u   /* enum, scale 1, read-only signal */
#define LINK_ID_FAULT                0x28u   /* code, scale 1, read-only signal */
#define LINK_ID_MU1                  0x29u   /* 1, scale 0.000244140625, read-only signal */
#define LINK_ID_POSITION             0x2Au   /* counts, scale 1, read-only signal */
#define LINK_ID_BUS_VOLTAGE          0x2Bu   /* V, scale 0.09375, read-only signal */
#define LINK_ID_RULE1_KP             0x40u   /* V/(rad/s), scale 0.000244140625 */
#define LINK_ID_RULE1_KI             0x41u   /* V/rad, scale 0.0152587891 */
#define LINK_ID_RULE1_KD             0x42u   /* V s^2/rad, scale 1.52587898e-08 */
#define LINK_ID_RULE1_KC             0x43u   /* V/A, scale 0.00312500005 */
#define LINK_ID_RULE2_KP             0x44u   /* V/(rad/s), scale 0.000244140625 */
#define LINK_ID_RULE2_KI             0x45u   /* V/rad, scale 0.0152587891 */
#define LINK_ID_RULE2_KD             0x46u   /* V s^2/rad, scale 1.52587898e-08 */
#define LINK_ID_RULE2_KC             0x47u   /* V/A, scale 0.00312500005 */

/* ---- signal indices: app_signal() argument, bit of telemetry/capture masks ---- */
#define LINK_SIG_SPEED                 0u
#define LINK_SIG_SETPOINT              1u
#define LINK_SIG_VOLTAGE               2u
#define LINK_SIG_CURRENT               3u
#define LINK_SIG_INTEGRATOR            4u
#define LINK_SIG_DUTY                  5u
#define LINK_SIG_HALL                  6u
#define LINK_SIG_STATE                 7u
#define LINK_SIG_FAULT                 8u
#define LINK_SIG_MU1                   9u
#define LINK_SIG_POSITION              10u
#define LINK_SIG_BUS_VOLTAGE           11u

/* ---- parameter store: read the fields freely; write only via link_param_set() ---- */
typedef struct {
    int16_t   speed_setpoint;  /* rpm, raw x 0.149207756, [-17425, 17425], default 0 */
    uint8_t   controller;      /* enum, raw x 1, [0, 1], default 1, persisted */
    int16_t   premise_low;     /* rpm, raw x 0.149207756, [0, 32767], default 0, persisted */
    int16_t   premise_high;    /* rpm, raw x 0.149207756, [0, 32767], default 17425, persisted */
    int16_t   setpoint_weight; /* 1, raw x 6.10351562e-05, [0, 32767], default 17589, persisted */
    int16_t   u_min;           /* V, raw x 0.00390625, [-11304, 0], default -11304, persisted */
    int16_t   u_max;           /* V, raw x 0.00390625, [0, 11304], default 11304, persisted */
    int16_t   current_limit;   /* A, raw x 0.0048828125, [0, 1023], default 307, persisted */
    uint16_t  accel_limit;     /* rpm/s, raw x 149.207764, [0, 65535], default 0, persisted */
    uint16_t  link_timeout;    /* ms, raw x 1, [20, 60000], default 500, persisted */
    uint16_t  stall_timeout;   /* ms, raw x 1, [10, 60000], default 500, persisted */
    int16_t   rule1_kp;        /* V/(rad/s), raw x 0.000244140625, [-32768, 32767], default 9033, persisted */
    int16_t   rule1_ki;        /* V/rad, raw x 0.0152587891, [-32768, 32767], default 12249, persisted */
    int16_t   rule1_kd;        /* V s^2/rad, raw x 1.52587898e-08, [-32768, 32767], default 0, persisted */
    int16_t   rule1_kc;        /* V/A, raw x 0.00312500005, [-32768, 32767], default 8569, persisted */
    int16_t   rule2_kp;        /* V/(rad/s), raw x 0.000244140625, [-32768, 32767], default 7895, persisted */
    int16_t   rule2_ki;        /* V/rad, raw x 0.0152587891, [-32768, 32767], default 10452, persisted */
    int16_t   rule2_kd;        /* V s^2/rad, raw x 1.52587898e-08, [-32768, 32767], default 0, persisted */
    int16_t   rule2_kc;        /* V/A, raw x 0.00312500005, [-32768, 32767], default 5478, persisted */
} link_params_t;

extern link_params_t link_params;

/* ---- the module ----
 * Contracts (CMSIS-DSP style): inputs and their ranges, the result and its range, what happens
 * at the edges (saturation or refusal, never wrap-around), the context it may run in.  Raw
 * values are the table's integers (scale in the entry's row); ranges are inclusive. */

/* link_init: every parameter to its default (within [min, max] by construction), counters and
 * queues cleared, the BOOT event queued.  Main context, interrupts that call the link masked. */
void     link_init(void);

/* link_rx_byte: b any byte (0x00 = delimiter).  Stores it in the frame buffer (index < LINK_RX_BYTES)
 * or, while link_poll holds that buffer (a frame being checked and answered), in the spill ring
 * (LINK_RX_SPILL - 1 bytes), which link_poll passes through the same framing when it is done with
 * the frame; a byte that finds the ring full is counted lost in an 8-bit counter (wraps; link_poll
 * adds the difference to the saturating 16-bit rx_overflows and drops the frame it belonged to);
 * a frame longer than LINK_RX_BYTES is discarded up to the next delimiter.  Any interrupt
 * priority; touches single bytes only; no helper, no flash read; at most 20 cycles (PIC18). */
void     link_rx_byte(uint8_t b) LINK_WPARAM;

/* link_poll: decodes and answers at most 8 frames per call (frames of 0..LINK_MAX_PAYLOAD payload
 * bytes; anything else is dropped and counted in the saturating crc_errors), sends events and
 * telemetry as app_tx_free() allows (never more bytes than it reports), then announces changed
 * parameters (app_param_changed).  Main context only (not reentrant). */
void     link_poll(void);

/* link_tick_ms: uptime_ms += 1 (uint32, wraps after 49.7 days), watchdog: wd_ms saturates at
 * 65535 and fires at link_params.link_timeout (then app_link_lost, disarmed until the next RUN).
 * 1 kHz interrupt; about 20 cycles (PIC18). */
void     link_tick_ms(void);

/* link_sample: one speed-loop sample.  Telemetry: every tm_dec-th call appends the selected
 * signals (int16, little-endian) to the frame being filled; a frame not sent yet when the next
 * is due counts a drop (tm_dropped, saturating at 65535).  Capture: every cap_dec-th call one
 * sample into the ring (at most LINK_CAPTURE_WORDS words), trigger by setpoint write or a signed
 * int16 threshold crossing (speed - thr cannot overflow: the comparison is on 17 bits).  Signal
 * values are copied as they are (no scaling, no saturation).  Speed-loop interrupt; no helper;
 * saves the table pointer around its one flash-table read (app_signal_src). */
void     link_sample(void);

/* link_event: event LINK_EVENT_BOOT (code: reset cause), LINK_EVENT_FAULT (code: LINK_FAULT_*) or
 * LINK_EVENT_WATCHDOG (code unused), others ignored; one pending event of each kind (a newer code
 * replaces an unsent one).  Any context (single bytes). */
void     link_event(uint8_t event, uint8_t code);

/* link_param_i16: the raw value of table entry id, saturated to [-32768, 32767] (an out-of-range
 * 32-bit value gives the nearer limit, never its low half); 0 for an unknown id.  Main context
 * (or with the link's interrupts masked: it reads the store and may call app_signal). */
int16_t  link_param_i16(uint8_t id) LINK_WPARAM;

/* link_param_get: the raw value of entry id, sign- or zero-extended from its C type to int32
 * (exact: every type fits); signals through app_signal; 0 for an unknown id.  Main context. */
int32_t  link_param_get(uint8_t id);
#if LINK_WITH_HOST_API
/* link_param_set: raw any int32; stored only if id is writable and min <= raw <= max (compared
 * on 32 bits, no truncation), else LINK_NACK_UNKNOWN_PARAM / READ_ONLY / OUT_OF_RANGE and the
 * store unchanged; app_param_changed(id) before it returns.  Main context. */
uint8_t  link_param_set(uint8_t id, int32_t raw);
#endif

/* link_eeprom_load: LINK_EE_OK only if the image's magic, version, table hash, length and
 * CRC-16 match and every value is within its entry's [min, max]; then all persisted parameters
 * are stored and announced.  Any other result (BLANK, OTHER_BUILD, CORRUPT) changes nothing.
 * Main context (startup or link_poll); reads at most LINK_EE_IMAGE_BYTES EEPROM bytes. */
uint8_t  link_eeprom_load(void);

/* link_eeprom_save: writes the image (LINK_EE_IMAGE_BYTES bytes from LINK_EE_BASE) and reads it
 * back: 0, or LINK_NACK_EEPROM_ERROR if any byte or the CRC differs.  Main context; takes as
 * long as the EEPROM writes (about 4 ms a byte on the PIC18F4431). */
uint8_t  link_eeprom_save(void);
#if LINK_WITH_HOST_API
/* link_crc16: CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF, no reflection, no final XOR) of
 * p[0..n-1], n 0..255 (0: 0xFFFF). */
uint16_t link_crc16(const uint8_t *p, uint8_t n);
#endif

/* ---- implemented by the application ---- */
/* app_command: cmd one of LINK_CMD_START/STOP/BRAKE/FAULT_CLEAR (arg, n: the command's argument
 * bytes, none today); 0 or a LINK_NACK_* code.  From link_poll. */
uint8_t  app_command(uint8_t cmd, const uint8_t *arg, uint8_t n);
/* app_param_changed: id a table id whose stored value changed (already range-checked): take it
 * into use.  From link_poll (after the reply is sealed), link_eeprom_load, link_param_set. */
void     app_param_changed(uint8_t id) LINK_WPARAM;
/* app_signal: signal 0..LINK_N_SIGNALS-1 (LINK_SIG_*): its raw int16 value (the application
 * saturates computed ones to int16).  From link_poll, and from link_sample for a NULL entry of
 * app_signal_src (the speed-loop interrupt: then it must not take long). */
int16_t  app_signal(uint8_t signal) LINK_WPARAM;
/* Where each signal's int16 value lives, in data space (a flash table, indexed by LINK_SIG_*):
 * link_sample() copies a selected signal straight from there, without a call; a NULL entry (a
 * computed or 8-bit signal) is read through app_signal() instead.  Read in the speed-loop
 * interrupt: the application writes these values in that interrupt, or atomically. */
extern LINK_DATA int16_t * const app_signal_src[LINK_N_SIGNALS];
/* app_link_lost: the watchdog expired (from link_tick_ms, the 1 kHz interrupt): outputs off,
 * latch LINK_FAULT_LINK_LOST. */
void     app_link_lost(void);
/* app_tx_free: free bytes in the UART TX queue, 0..255; app_tx_byte: queue one (called only
 * while app_tx_free() > 0).  From link_poll. */
uint8_t  app_tx_free(void);
void     app_tx_byte(uint8_t b) LINK_WPARAM;
/* app_eeprom_read/write: one data-EEPROM byte at addr 0..255 (a write may wait for the previous
 * one).  From link_poll and link_eeprom_load. */
uint8_t  app_eeprom_read(uint8_t addr);
void     app_eeprom_write(uint8_t addr, uint8_t value);

#endif /* LINK_FW_H */

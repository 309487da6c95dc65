/* Internal state of the PIC18F4431 peripheral model and the event loop
 * (pic.c, twin.c).  Register offsets and bit numbers come from pic_regs.h,
 * generated at build time from Microchip's p18f4431.inc (picdrive_hil.regs). */
#ifndef PICDRIVE_PIC_INTERNAL_H
#define PICDRIVE_PIC_INTERNAL_H

#include <stdint.h>
#include "twin.h"
#include "pic_regs.h"

#define NEVER INT64_MAX
#define PS_PER_S 1000000000000.0
#define POLL_TCY 6           /* instruction cycles of one firmware poll iteration */

extern volatile uint8_t picsim_sfr[256];
void picsim_sfr_written(uint16_t addr);
void picsim_sfr_read(uint16_t addr);

/* firmware entry points (architecture.md seam 4) */
void fw_init(void);
void fw_poll(void);
void fw_isr_high(void);
void fw_isr_low(void);

typedef struct {
    int on;
    int64_t t_ref;        /* time of the last anchor */
    uint32_t cnt_ref;     /* count at t_ref */
    int64_t tick_ps;      /* one count */
    uint32_t modulus;     /* counts per wrap (256, 65536, PR+1) */
    int64_t next;         /* next wrap/match */
    uint32_t post;        /* Timer2 postscaler counter */
} timer_t_;

#define HOSTQ 65536       /* host <-> board byte rings (power of two) */

typedef struct {
    twin_config_t cfg;
    plant_params_t pp;
    plant_state_t ps;
    plant_cache_t pcache;     /* step coefficients (plant_step_cached) */
    int initialised;
    int64_t now;
    int64_t tosc_ps, tcy_ps;
    uint8_t shadow[256];
    int in_fw;
    int64_t call_cycles;      /* Tcy the firmware spent polling in the present call */
    int64_t main_busy_until;  /* the main loop is still in a blocking wait */
    uint32_t errors;

    /* PCPWM */
    int pwm_on;
    int64_t pwm_start, pwm_period, pwm_next;
    uint32_t pwm_post;
    uint16_t ptper_act, pdc_act[4];
    uint8_t ovd_act, ovs_act;
    int flt_latched;          /* FLTAS, inactive mode */
    int flt_cbc;              /* cycle-by-cycle: outputs off to the end of the period */
    leg_t leg[3];
    int legs_dirty;           /* PWM state changed: recompute the legs */
    int pwm_buf_stale;        /* a PCPWM register or the time base changed: reload PTPER/PDC at the period */
    int per_key_valid;        /* period length cached for (PTPER, PTCON0) */
    uint16_t per_key_ptper;
    uint8_t per_key_ptcon0;
    int64_t per_key_ps;
    int poll_due;             /* something the main loop can see changed since its last pass */
    int irq_dirty;            /* an SFR changed since no interrupt was found pending */
    int64_t last_poll;
    uint8_t gate_hi[3], gate_lo[3];
    double duty[4], dead_frac;
    uint32_t shoot_through;

    timer_t_ t0, t1, t2, t5;

    /* QEI */
    int64_t enc_count;        /* x4 count from the (measured) angle, unwrapped */
    int64_t enc_prev;
    double th_meas_prev;      /* measured angle at the end of the previous step */
    int64_t enc_index_count;  /* count at the last index pulse */
    int32_t poscnt;
    int64_t vel_last_t;       /* last velocity capture */
    uint32_t vel_pdec;
    int qei_dir;
    int enc_frozen;
    int64_t rev, rev_base, rev_cpr;   /* enc_rev() cache */
    int rev_valid;
    int halls_on_enc_pins;    /* a hall sits on RA2..RA4: the encoder pins are not driven */
    int64_t enc_frozen_at;

    /* EUSART */
    int64_t bit_ps;           /* board bit time */
    int tx_busy, txreg_full;
    uint8_t tsr, txbuf;
    int64_t tx_done;
    uint8_t rxfifo[2];
    int rx_n;
    uint8_t hq_in[HOSTQ];     /* host -> board, not yet on the wire */
    uint32_t hin_head, hin_tail;
    uint8_t hq_out[HOSTQ];    /* board -> host, off the wire */
    uint32_t hout_head, hout_tail;
    int64_t rx_arrive;        /* arrival of the byte on the wire, NEVER if none */
    uint8_t rx_byte;
    int64_t host_frame_ps;
    uint32_t rx_overruns, rx_framing, rx_dropped, tx_overwrites;
    int baud_bad;

    /* EEPROM */
    uint8_t ee[256];
    int ee_unlock;
    int64_t ee_done;
    uint8_t ee_addr, ee_data;
    uint32_t ee_writes, ee_rejected;

    /* ADC */
    int64_t adc_done;
    uint8_t adc_ch;
    int64_t sev_at;           /* the PCPWM special event (PTMR = SEVTCMP) in this period, NEVER if none */
    int sev_lazy;             /* processor twin: a special event that starts a conversion does not end a
                                 step; it is processed at its cycle (cycle_t0 + n Tcy) when the program
                                 next touches an SFR or the run ends, whichever first */
    int64_t cycle_t0;         /* processor twin: the time of cycle 0 */

    /* pins and inputs */
    uint8_t ext[5];           /* external pin levels A..E */
    uint8_t hall_pins;        /* code on the hall pins */
    int hall_override;        /* -1 = none */
    int64_t hall_override_until;
    int64_t oc_until;         /* forced comparator until */
    int flta_asserted;
    int hall_ext_ok;          /* ext[] shows hall_pins on the hall pins */
    int hall_pin_shared;      /* a hall pin is also the FLTA or RX pin: always rewrite the levels */

    /* next hall edge (electrical angle from hall_offset) and the direction it was found for */
    double edge_th;
    int edge_dir;

    /* load */
    double load_t[1024], load_v[1024];
    int load_n;
    int load_k;               /* index of the next knot after now */
    int64_t load_next_ps;     /* its time (cache) */

    /* noise */
    uint64_t rng;
    int64_t noise_bucket;
    double noise_theta;

    /* trace */
    trace_rec_t *trace;
    int trace_cap, trace_n;
    int64_t trace_period, trace_next;

    /* bookkeeping */
    uint32_t isr_high_calls, isr_low_calls, poll_calls;
} twin_t;

/* the processor twin counts speed-loop periods its interrupt missed (pil.c) */
#ifdef TWIN_PIL
static void pil_timer2_fired(int flag_was_set, int64_t at_ps);
static void pil_adc_started(void);
#define PIL_TIMER2_FIRED(was, at) pil_timer2_fired(was, at)
#define PIL_ADC_STARTED() pil_adc_started()
#else
#define PIL_TIMER2_FIRED(was, at) ((void)0)
#define PIL_ADC_STARTED() ((void)0)
#endif

/* one twin per loaded copy of the library; prefixed names keep clear of the firmware's */
#define g picsim_twin
extern twin_t g;

/* pic.c */
void pic_reset(void);
void pic_sync_inputs(void);
void pic_process_writes(void);
void pic_compute_legs(void);
int64_t pic_next_event(void);
void pic_events_due(void);
void pic_after_plant_step(int64_t t_prev, double theta_meas);
int pic_irq_pending(void);            /* 0 none, 1 high, 2 low */
#define IRQ_LINE_HIGH 1u                 /* = PIC18_IRQ_HIGH / _LOW (pic18cpu.h) */
#define IRQ_LINE_LOW 2u
unsigned pic_irq_lines(void);
void pic_set_pins_from_plant(void);
void pic_uart_rx_schedule(void);
double pic_board_baud(void);
/* a hardware event changes an SFR: the main loop has something new to see */
static inline void hw_write(uint8_t idx, uint8_t v)
{
    if (picsim_sfr[idx] != v) g.poll_due = g.irq_dirty = 1;
    picsim_sfr[idx] = v;
    g.shadow[idx] = v;
}
static inline void hw_setbit(uint8_t idx, int bit) { hw_write(idx, (uint8_t)(picsim_sfr[idx] | (1u << bit))); }
static inline void hw_clrbit(uint8_t idx, int bit) { hw_write(idx, (uint8_t)(picsim_sfr[idx] & ~(1u << bit))); }
static inline int sfr_bit(uint8_t idx, int bit) { return (picsim_sfr[idx] >> bit) & 1; }

#endif

/* picdrive motor twin: BLDC plant + PIC18F4431 peripheral model.
 *
 * Shared declarations of the plant (plant.c), the peripheral model (pic.c)
 * and the event loop (twin.c).  Python drives this through ctypes
 * (hil/picdrive_hil/cmodel.py mirrors every struct below field for field;
 * keep the two in step).  docs/twin.md describes the equations.
 *
 * Units: SI everywhere (s, A, V, rad, N m).  The plant integrates in double
 * precision seconds; the peripheral model and the event loop keep time as
 * int64 picoseconds, so every clock edge of a 40 MHz PIC is exact.
 */
#ifndef PICDRIVE_TWIN_H
#define PICDRIVE_TWIN_H

#include <stdint.h>

#define TWIN_ABI_VERSION 3

/* ------------------------------------------------------------------ plant */

enum { EMF_TRAPEZOIDAL = 0, EMF_SINUSOIDAL = 1 };
enum { LOAD_ACTIVE = 0,    /* signed torque, acts at standstill too (2016 eq 5) */
       LOAD_PASSIVE = 1 }; /* opposes motion, holds a standing rotor (friction-like) */

typedef struct {
    double r_phase_ohm;      /* per-phase resistance of the wye winding */
    double l_phase_h;        /* per-phase (synchronous) inductance, (Ld + Lq)/2 */
    double lambda_m_v_s;     /* PM flux linkage, V s per electrical rad, phase peak */
    int32_t pole_pairs;
    int32_t emf_shape;       /* EMF_TRAPEZOIDAL | EMF_SINUSOIDAL */
    double inertia_kg_m2;
    double friction_n_m_s;   /* viscous B */
    double bus_voltage_v;
    double diode_drop_v;     /* body-diode forward drop (0 = ideal) */
    double hall_offset_rad;  /* electrical angle of hall A's rising edge after e_a's rising zero */
    double hall_spacing_rad; /* 2pi/3 or pi/3 */
    int32_t encoder_lines;   /* 0 = none */
    int32_t load_mode;       /* LOAD_ACTIVE | LOAD_PASSIVE */
    /* The DC bus: its capacitor behind the supply (bus_voltage_v) that sources any current and
     * sinks at most supply_sink_a; a brake resistor switched across it above brake_chopper_v.
     * bus_capacitance_f = 0: a stiff bus, always bus_voltage_v. */
    double bus_capacitance_f;
    double supply_sink_a;
    double brake_resistor_ohm;   /* 0 = none */
    double brake_chopper_v;
} plant_params_t;

/* One inverter leg over a step: fraction of the time its high / low switch
 * conducts (the PWM-period average; see docs/twin.md "Inverter"). */
typedef struct {
    double f_hi;
    double f_lo;
} leg_t;

typedef struct {
    double t_s;              /* simulated time */
    double i_a[3];           /* phase currents into the motor, A (sum 0) */
    double w_rad_s;          /* mechanical speed */
    double theta_rad;        /* mechanical angle, unwrapped */
    double v_term[3];        /* terminal (leg) voltages over the last step, V (vs bus minus) */
    double v_neutral;        /* star point voltage over the last step */
    double e_v[3];           /* back-EMF over the last step */
    double torque_e_n_m;     /* electromagnetic torque at the end of the step */
    double torque_load_n_m;  /* load torque applied over the last step (incl. passive sign) */
    double i_bus_a;          /* average DC-link current over the last step (out of +bus) */
    double i_link_on_a;      /* DC-link current while the PWM'd high switch conducts */
    double i_peak_a;         /* largest |phase current| at the end of the step, plus the rise of a PWM'd
                                high side's switched current above the period average (comparator input) */
    double energy_j;         /* energy drawn from the bus since reset */
    int32_t locked;          /* rotor locked by injection */
    int32_t te_valid;        /* torque_e_n_m is the torque of the present i and theta (to O(h^2)) */
    double v_bus_v;          /* DC bus (capacitor) voltage at the end of the step; 0 = not yet stepped
                                (the supply's voltage) */
    double i_brake_a;        /* brake-resistor current over the last step */
} plant_state_t;

/* The C API (ctypes) keeps default visibility; the rest of the twin's C is built with
 * -fvisibility=hidden, so its internal calls bind directly (no PLT, no interposition). */
#pragma GCC visibility push(default)
void   plant_reset(plant_state_t *s);
void   plant_step(const plant_params_t *p, plant_state_t *s, const leg_t leg[3],
                  double t_load_n_m, double h_s);
double plant_emf_shape(const plant_params_t *p, double theta_e);   /* phase A, per unit */
int    plant_hall_code(const plant_params_t *p, double theta_mech); /* bits: 0=A 1=B 2=C */
double plant_theta_e(const plant_params_t *p, const plant_state_t *s);
int    plant_sizeof(int which);
void   plant_sin_cos_probe(double anchor, double th, double out[2]);   /* tests: the sinusoidal EMF's sin/cos */
#pragma GCC visibility pop

/* Coefficients of a step of length h (exponentials of the RL solution, the rotor's implicit
 * factors over h and h/2) and the anchor of the sinusoidal EMF's sin/cos, kept by whoever
 * steps the plant repeatedly (plant_step_cached).  plant_step() starts from an empty cache
 * each call; with the trapezoidal EMF both give the same bits, with the sinusoidal one they
 * agree to a few units in the last place (plant.c, sin_cos).  Not part of the ctypes API. */
typedef struct {
    double h, r, l, j, b;          /* key: step length and the parameters used */
    double a, k;                   /* exp(-h R/L), (1 - a)/R */
    double hj[2], hb[2], den[2];   /* over h and h/2: h/J, h B/(2J), 1/(1 + h B/(2J)) */
} step_coef_t;
/* The step lengths of a run repeat: the PWM period, and the pieces the events inside it (the
 * ADC's conversions, the speed loop's timer, UART frames) cut from it at the same phases period
 * after period.  PLANT_COEF_SLOTS coefficient sets, direct-mapped by the step length's bits;
 * and the two exponentials of a PWM'd high side's ripple peak (plant.c, substep), which repeat
 * while the duty and the pieces do, in PLANT_EXP_SLOTS (argument, value) pairs.  Either cache
 * returns exactly what it would compute. */
#define PLANT_COEF_SLOTS 32
#define PLANT_EXP_SLOTS 64
typedef struct {
    step_coef_t slot[PLANT_COEF_SLOTS];
    double exp_x[PLANT_EXP_SLOTS], exp_v[PLANT_EXP_SLOTS];
    double sin_ref, sin_s, sin_c;  /* sinusoidal EMF: anchor angle, its sin and cos (libm) */
} plant_cache_t;
void plant_cache_reset(plant_cache_t *cc);
double plant_bus_voltage(const plant_params_t *p, const plant_state_t *s);
void plant_step_cached(const plant_params_t *p, plant_state_t *s, const leg_t leg[3],
                       double t_load_n_m, double h_s, plant_cache_t *cc);

/* ------------------------------------------------------------------ twin */

/* A pin: port 0..4 = A..E, bit 0..7; port 0xFF = not connected. */
typedef struct { uint8_t port, bit; } pin_t;

enum { ASIG_NONE = 0, ASIG_CURRENT = 1, ASIG_BUS_VOLTAGE = 2 };
enum { CURSIG_LINK_ON = 0, CURSIG_BUS_AVG = 1, CURSIG_PEAK = 2 };

typedef struct {
    int32_t abi_version;
    plant_params_t plant;
    double fosc_hz;                /* 40 MHz (HSPLL) */
    pin_t hall_pin[3];             /* hall A, B, C */
    pin_t flta_pin;                /* RC1 (FLTA, active low) */
    uint8_t phase_pair[3];         /* PWM output pair (0..3) driving phase a, b, c */
    uint8_t analog_signal[9];      /* AN0..AN8: ASIG_* */
    uint8_t current_signal;        /* CURSIG_*: what the current-sense amplifier shows */
    uint8_t pad0[3];
    double current_sense_v_per_a;
    double current_sense_offset_v;
    double bus_sense_v_per_v;      /* divider of the bus-voltage sense */
    double adc_vref_v;             /* AVDD reference, 5 V */
    double overcurrent_trip_a;     /* comparator threshold on FLTA */
    double host_baud;              /* the host's serial line */
    double max_step_s;             /* plant step ceiling while the PWM time base is off */
    double speed_noise_rad_s;      /* std of speed-measurement noise (encoder angle jitter) */
    double noise_sample_s;         /* noise redraw interval (the speed-loop period) */
    uint64_t seed;
    double eeprom_write_s;         /* EEPROM write time, 4 ms */
} twin_config_t;

/* Everything Python reads about the twin, in one snapshot. */
typedef struct {
    plant_state_t plant;
    int64_t now_ps;
    uint8_t hall_code;             /* what the hall pins show (after injection) */
    uint8_t hall_true;             /* what the rotor angle says */
    uint8_t flta_asserted;         /* comparator output */
    uint8_t pwm_outputs_active;    /* any switch commanded on */
    int32_t enc_count;             /* true quadrature count (x4), unwrapped */
    leg_t leg[3];
    uint8_t gate_hi[3];            /* 0 off, 1 on, 2 PWM */
    uint8_t gate_lo[3];
    uint8_t pwm_fault_latched;     /* FLTAS */
    uint8_t pad1;
    uint32_t shoot_through;        /* steps where a leg's high and low conducted together */
    uint32_t uart_rx_overruns;
    uint32_t uart_rx_framing;
    uint32_t isr_high_calls, isr_low_calls, poll_calls;
    uint32_t eeprom_writes;
    uint32_t eeprom_rejected;      /* WR without the 0x55/0xAA unlock or WREN */
    uint32_t errors;               /* twin_error bits */
    double duty[4];                /* active duty of each PWM generator, 0..1 */
    double pwm_period_s;
    double board_baud;             /* what SPBRG etc. give */
    double dead_time_s;
    int64_t outputs_off_ps;        /* when the outputs last went from some switch on to all off; -1: never */
} twin_state_t;

enum {
    TWIN_ERR_IRQ_STORM  = 1 << 0,  /* a flag stayed set after its handler ran 1000 times */
    TWIN_ERR_ADC_MODE   = 1 << 1,  /* ADC mode the model does not implement */
    TWIN_ERR_BAUD       = 1 << 2,  /* board and host baud differ by more than 2.5 % */
    TWIN_ERR_NOT_INIT   = 1 << 3,
    TWIN_ERR_CPU        = 1 << 4,  /* processor twin: the core stopped (fault PC, illegal opcode, stack) */
};

/* The processor twin's measurements (pil.c); cycles are instruction cycles (Tcy). */
typedef struct {
    uint64_t cycles, insns;
    uint64_t cpu_status;           /* PIC18_* of the stop that ended the run (0: running) */
    uint64_t fault_pc, fault_word, insn_pc;   /* insn_pc: the instruction that stopped the core */
    uint64_t pc, stkptr, stack_high;   /* return stack: STKPTR and its high-water mark (levels) */
    uint64_t fsr1_lo, fsr1_hi;     /* software stack: lowest address reached through FSR1, top (POSTDEC1) */
    uint64_t ram_written;          /* GPR bytes written since power-on, not counting a first store of
                                      zero (the start-up code's clear of all RAM) */
    uint64_t speed_n, speed_min, speed_max, speed_sum, speed_last;   /* speed-loop interrupt, entry to RETFIE */
    uint64_t speed_overrun;        /* Timer2 fired while the speed-loop interrupt still ran */
    uint64_t speed_lost;           /* Timer2 fired while its flag was still set (a period lost) */
    uint64_t high_n, high_min, high_max, high_sum;   /* every high-priority interrupt */
    uint64_t low_n, low_min, low_max, low_sum;       /* every low-priority interrupt */
    uint64_t retfie_outside;       /* RETFIE without an interrupt in progress */
    uint64_t in_isr;               /* interrupts in progress now */
    uint64_t resets, sleep_runs, adc_starts, rcreg_reads;
    /* the chip-only timing hazards (docs/firmware.md), measured on the running code */
    uint64_t speed_preempted;      /* high-priority interrupts taken inside the speed-loop interrupt */
    uint64_t overrun_first_cycle;  /* cycle of the first overrun (0: none) */
    uint64_t pos_reads, pos_delay_min, pos_delay_max;  /* speed ISR entry -> its first POSCNT/TMR5 read, cycles */
    uint64_t pos_read_unmasked;    /* ... with GIEH set (a hall/UART interrupt could split the capture) */
    uint64_t pos_read_after_adc;   /* ... after an ADC start in the same interrupt */
    uint64_t adc_pwm_starts;       /* conversions of the current signal while the PWM runs with a duty > 0 */
    uint64_t adc_in_on_time;       /* ... of them inside the PWM'd switch's on-time */
    uint64_t adc_phase_min_ppm, adc_phase_max_ppm;    /* PWM phase of those starts, 1e-6 of the period */
    uint64_t missed_at_start;      /* of speed_overrun + speed_lost: before the first speed-loop interrupt ended
                                      (fw_init still running with the interrupts off, or that first one late) */
    uint64_t lat_n, lat_min, lat_max, lat_sum;   /* Timer2 interrupt entry latency: cycles from TMR2IF set to
                                                    the vectoring (masked sections, other interrupts): the
                                                    speed sample's instant moves by that much */
    uint64_t steps, stops;         /* event-loop steps (core run + plant step + events); runs an SFR access
                                      ended early (an event moved earlier or the inverter state changed) */
    /* the watchdog timer (CONFIG2H WDTEN, or WDTCON.SWDTEN) and what it did */
    uint64_t wdt_period_cycles;    /* 4 ms x the postscale (CONFIG2H WDPS), in cycles; 0: off */
    uint64_t wdt_resets;           /* time-outs that reset the chip (outputs off, program from 0) */
    uint64_t wdt_reset_cycle;      /* cycle of the last of them */
    uint64_t wdt_wakes;            /* time-outs in Sleep: the core woke up and went on (no reset) */
    /* the speed-loop interrupt's arrivals: a gap longer than its period means it stopped arriving */
    uint64_t speed_entry_last;     /* cycle of the last speed-loop interrupt's entry */
    uint64_t speed_gap_max;        /* longest time between two entries, cycles */
} pil_stats_t;

enum { INJ_HALL = 1, INJ_OVERCURRENT = 2, INJ_LOCK_ROTOR = 3, INJ_ENCODER = 4,
       INJ_BUS_VOLTAGE = 5 };

/* trace: one record per trace period */
typedef struct {
    double t_s, w_rad_s, theta_rad, i_a, i_b, i_c, i_bus_a, torque_e_n_m, torque_load_n_m;
    double v_a, v_b, v_c, duty_max;
    double hall, fault, v_bus_v;
} trace_rec_t;

#pragma GCC visibility push(default)
int  twin_init(const twin_config_t *cfg);
int  twin_power_on(void);                   /* chip reset + fw_init */
int  twin_run_until(int64_t t_end_ps);      /* 0, or twin error bits */
void twin_get_state(twin_state_t *out);
void twin_set_load_table(const double *t_s, const double *torque, int32_t n);
int  twin_uart_host_write(const uint8_t *buf, int32_t n);
int  twin_uart_host_read(uint8_t *buf, int32_t max);
int  twin_uart_host_pending(void);         /* host bytes not yet on the board */
int  twin_uart_host_flush(void);           /* drop the queued host bytes; returns how many */
void twin_inject(int32_t kind, double value, double duration_s);
void twin_eeprom_get(uint8_t *buf256);
void twin_eeprom_set(const uint8_t *buf256);
void twin_trace_start(double period_s, trace_rec_t *buf, int32_t capacity);
int  twin_trace_count(void);
uint8_t twin_sfr_get(uint16_t idx);
void twin_set_plant_state(double w_rad_s, double theta_rad);
int  twin_sizeof(int which);
int  twin_data_region(uint64_t out[2]);   /* this library's writable data: address, bytes (0: found) */
/* processor twin only (-DTWIN_PIL) */
int  pil_load(const uint8_t *flash, uint32_t n, const uint8_t *config14);
uint32_t pil_flash_bytes(void);
uint32_t pil_ram_end(void);
void pil_get_stats(pil_stats_t *out);
uint8_t pil_peek(uint16_t addr);
int  pil_patch_flash(uint32_t addr, const uint8_t *data, uint32_t n);   /* program memory changed under the
                                                                         running program (fault injection) */
int  pil_sizeof(void);
#pragma GCC visibility pop

#endif

/* The processor-in-the-loop twin: the PIC18 instruction-set simulator
 * (pic18cpu.c) runs the HEX against the same peripheral model (pic.c) and plant
 * (plant.c) as the software-in-the-loop twin; only the event loop differs.
 *
 * Included at the end of twin.c when the library is built with -DTWIN_PIL (twin_pil_all.c),
 * so it shares the event loop's helpers (next_hall_edge, load_at, trace_record, ...).
 *
 * Time.  g.now is the processor's time, P.t0 + cycles x Tcy.  One loop iteration: find the
 * next event as the SIL loop does (PWM boundary, timer wrap, UART frame, ADC/EEPROM done,
 * hall edge, load knot, trace sample, injection end; at most one PWM period); take the
 * inverter state the peripherals show now; run the core until the cycle that reaches the
 * event, or earlier when an SFR write moved an event earlier or changed the inverter state;
 * step the plant over the same interval with the inverter state of its start; update the
 * pins and process the due events; drive the interrupt lines.  Every SFR access of the
 * program reaches the model at the cycle it happens (pil_sfr_read / pil_sfr_write): timers,
 * PTMR and the ports are read as they are at that cycle.  Events are processed at the end
 * of the instruction that crosses them (at most 3 Tcy late); periodic ones (timer wraps,
 * PWM periods) keep their exact period.  Two kinds of event do not end a step, since nothing
 * the program or the plant sees changes with them until later: Timer2's wraps short of its
 * postscale count (pic.c, t2_flag_time: TMR2 is computed at the read, the wraps are counted
 * when the flag's wrap comes or before a write to T2CON/TMR2/PR2), and a PCPWM special event
 * that starts a conversion (the step ends at the conversion's end, where the plant is sampled;
 * the event itself is processed at its own cycle before the program's next SFR access or at
 * the run's end, pil_sev_due), and a PWM period boundary that loads nothing new
 * (pwm_boundary_quiet: same duty and period, no override or fault to apply, PTIF's interrupt
 * off), processed likewise at its exact time; the step then ends at the next conversion's end.
 * What remains ends a step: conversion ends (the plant is sampled), trace samples, boundaries
 * that load a new duty, timer flags, UART frames, hall edges.
 */
#include "pic18cpu.h"
#ifdef PIL_TRACE            /* -DPIL_TRACE: log every SFR write (cycle, PC, address, value) on stderr */
#include <stdio.h>
#endif

#define PIL_NEST 8
#if IRQ_LINE_HIGH != PIC18_IRQ_HIGH || IRQ_LINE_LOW != PIC18_IRQ_LOW
#error "the model's request lines and the core's differ"
#endif

typedef struct {
    pic18_t cpu;
    int loaded;
    int64_t t0;               /* time of cycle 0 */
    int64_t target;           /* time the present run is heading for */
    int64_t t_plant;          /* the plant's time (<= g.now) */
    leg_t run_leg[3];         /* inverter state over the present run (the plant step's) */
    uint8_t lines;            /* interrupt request lines driven */
    int dead;                 /* the core stopped on a fault: outputs off until power-on */
    uint64_t t2_fired;        /* cycle Timer2 last set TMR2IF (its interrupt not yet entered) */
    int t2_waiting;
    /* interrupts in progress (nesting: low, then high) */
    int nest_n;
    struct { uint8_t what, speed, pos_read, adc_started; uint64_t start; } nest[PIL_NEST];
    uint8_t wdt_cfg;          /* CONFIG2H WDTEN: the watchdog always on (else WDTCON.SWDTEN decides) */
    uint8_t wdt_ps;           /* CONFIG2H WDPS: the postscale is 2^wdt_ps */
    pil_stats_t st;
} pil_t;

static pil_t P;

static inline void pil_clock(void) { g.now = P.t0 + (int64_t)P.cpu.cycles * g.tcy_ps; }

static void pil_update_irq(void)
{
    if (!g.irq_dirty) return;
    g.irq_dirty = 0;
    unsigned l = pic_irq_lines();
    if (l != P.lines) {
        P.lines = (uint8_t)l;
        pic18_set_irq(&P.cpu, l);
    }
}

/* INTCON writes the core may store without pil_sfr_write (pic18_share_intcon): with the
   priorities on, GIEH/GIEL alone -- the request lines (pic_irq_lines: flags, enables, priorities),
   the events and the outputs do not depend on them; the core masks the interrupts itself.  The
   write hook did nothing else for them: the deferred events it would process first (pil_sev_due)
   are processed at their own cycles at the next SFR access, as before; nothing they do reads
   INTCON's enable bits.  IPEN changes only through an RCON write or a reset */
static void pil_intcon_quiet(void)
{
#ifndef PIL_TRACE
    pic18_set_intcon_quiet(&P.cpu, sfr_bit(R_RCON, B_RCON_IPEN) ? 0xC0 : 0);
#endif
}

/* ------------------------------------------------------------ plant */

/* the plant (and the pins and QEI it drives) up to g.now, with the inverter state of the
   present run: before the program reads an input the plant sets (ports, POSCNT, TMR5 with its
   capture resets), so that what it reads is the state at that cycle */
static void pil_plant_to_now(void)
{
    if (g.now <= P.t_plant) return;
    int64_t t_prev = P.t_plant;
    double h = (double)(g.now - t_prev) / PS_PER_S;
    double tmid = ((double)t_prev + 0.5 * (double)(g.now - t_prev)) / PS_PER_S;
    plant_step_cached(&g.pp, &g.ps, P.run_leg, load_at(tmid), h, &g.pcache);
    P.t_plant = g.now;
    pic_after_plant_step(t_prev, theta_measured());
}

/* ------------------------------------------------------------ hazard measurements */

/* the interrupt now executing, if it is the speed-loop interrupt */
static int speed_top(void)
{
    int k = P.nest_n - 1;
    return k >= 0 && k < PIL_NEST && P.nest[k].speed ? k : -1;
}

static void note_pos_read(void)
{
    int k = speed_top();
    if (k < 0 || P.nest[k].pos_read) return;
    P.nest[k].pos_read = 1;
    uint64_t d = P.cpu.cycles - P.nest[k].start;
    if (P.st.pos_reads == 0 || d < P.st.pos_delay_min) P.st.pos_delay_min = d;
    if (d > P.st.pos_delay_max) P.st.pos_delay_max = d;
    P.st.pos_reads++;
    if (sfr_bit(R_INTCON, B_INTCON_GIEH)) P.st.pos_read_unmasked++;
    if (P.nest[k].adc_started) P.st.pos_read_after_adc++;
}

static void note_adc_start(void)
{
    P.st.adc_starts++;
    int k = speed_top();
    if (k >= 0) P.nest[k].adc_started = 1;
}

/* every conversion of the current signal, started by software (GO) or by the PCPWM's special
   event: the PWM phase it samples at (pic.c's adc_start) */
static void pil_adc_started(void)
{
    if (!P.loaded || g.adc_ch > 8 || g.cfg.analog_signal[g.adc_ch] != ASIG_CURRENT) return;
    if (!g.pwm_on || g.pwm_period <= 0) return;
    double dmax = 0.0;
    for (int x = 0; x < 4; x++) if (g.duty[x] > dmax) dmax = g.duty[x];
    if (!(dmax > 0.0)) return;
    /* edge-aligned: the PWM'd switch conducts from the period start for duty x period */
    double ph = (double)(g.now - g.pwm_start) / (double)g.pwm_period;
    uint64_t ppm = (uint64_t)(ph * 1e6);
    if (P.st.adc_pwm_starts == 0 || ppm < P.st.adc_phase_min_ppm) P.st.adc_phase_min_ppm = ppm;
    if (ppm > P.st.adc_phase_max_ppm) P.st.adc_phase_max_ppm = ppm;
    P.st.adc_pwm_starts++;
    if (ph < dmax) P.st.adc_in_on_time++;
}

/* ------------------------------------------------------------ SFR hooks */

/* a special event or a quiet PWM boundary passed during the run (they do not end the step:
   g.sev_lazy): processed in time order at their own cycles before the program sees any SFR, so
   PTMR, PTIF and the conversion started (GO, the ADC's sample and completion times) are as if
   the run had stopped there */
static void pil_sev_due(void)
{
    for (;;) {
        int64_t ts = g.sev_at <= g.now ? g.sev_at : NEVER;
        /* a quiet PWM boundary passed (pwm_boundary_quiet): the next period starts at its exact
           time (PTMR, PTIF, the next special event) */
        int64_t tb = g.pwm_on && g.pwm_next <= g.now && pwm_boundary_quiet() ? g.pwm_next : NEVER;
        if (ts == NEVER && tb == NEVER) return;
        int64_t now = g.now;
        if (ts <= tb) { g.now = cycle_ceil(ts); sev_fire(); }
        else { g.now = cycle_ceil(tb); pwm_boundary(); }
        g.now = now;
    }
}

static uint8_t pil_sfr_read(void *ctx, uint16_t addr)
{
    (void)ctx;
    uint8_t idx = (uint8_t)addr;
    /* INTCON (read by every atomic section): only step-end events and the core change it */
    if (idx == R_INTCON) return picsim_sfr[idx];
    pil_clock();
    pil_sev_due();
    uint32_t c;
    switch (idx) {
    case R_PORTA: case R_PORTB: case R_PORTC: case R_PORTD: case R_PORTE:
    case R_POSCNTL: case R_POSCNTH: case R_TMR5L: case R_VELRL: case R_VELRH:
        if (idx != R_VELRL && idx != R_VELRH) note_pos_read();
        pil_plant_to_now();
        if (pic_next_event() < P.target) pic18_request_stop(&P.cpu);
        pil_update_irq();
        break;
    default:
        break;
    }
    switch (idx) {
    case R_PORTA: return picsim_sfr[idx] = port_value(0);
    case R_PORTB: return picsim_sfr[idx] = port_value(1);
    case R_PORTC: return picsim_sfr[idx] = port_value(2);
    case R_PORTD: return picsim_sfr[idx] = port_value(3);
    case R_PORTE: return picsim_sfr[idx] = port_value(4);
    case R_TMR0L:
        /* 16-bit mode: reading TMR0L latches TMR0H into its buffer */
        if (!g.t0.on) return picsim_sfr[idx];
        c = timer_count(&g.t0);
        if (g.t0.modulus > 256) picsim_sfr[R_TMR0H] = (uint8_t)(c >> 8);
        return picsim_sfr[idx] = (uint8_t)c;
    case R_TMR1L:
        if (!g.t1.on) return picsim_sfr[idx];
        c = timer_count(&g.t1);
        if (sfr_bit(R_T1CON, B_T1CON_RD16)) picsim_sfr[R_TMR1H] = (uint8_t)(c >> 8);
        return picsim_sfr[idx] = (uint8_t)c;
    case R_TMR1H:
        if (g.t1.on && !sfr_bit(R_T1CON, B_T1CON_RD16)) picsim_sfr[idx] = (uint8_t)(timer_count(&g.t1) >> 8);
        return picsim_sfr[idx];
    case R_TMR2:
        if (g.t2.on) picsim_sfr[idx] = (uint8_t)timer_count(&g.t2);
        return picsim_sfr[idx];
    case R_TMR5L:
        /* Timer5's 16-bit reads are buffered: TMR5L latches TMR5H */
        if (!g.t5.on) return picsim_sfr[idx];
        c = timer_count(&g.t5);
        picsim_sfr[R_TMR5H] = (uint8_t)(c >> 8);
        return picsim_sfr[idx] = (uint8_t)c;
    case R_POSCNTL: case R_POSCNTH:
        if (qei_mode()) {
            picsim_sfr[R_POSCNTL] = (uint8_t)g.poscnt;
            picsim_sfr[R_POSCNTH] = (uint8_t)(g.poscnt >> 8);
        }
        return picsim_sfr[idx];
    case R_PTMRL: case R_PTMRH: case R_PTCON1:
        if (g.pwm_on && g.pwm_period > 0) {
            int64_t tick = tcy(ptckps());
            int64_t n = (g.now - g.pwm_start) / tick;
            if (ptmod() >= 2) {
                int64_t half = g.ptper_act;
                int down = n > half;
                n = n <= half ? n : 2 * half - n;
                picsim_sfr[R_PTCON1] = (uint8_t)((picsim_sfr[R_PTCON1] & ~(1u << B_PTCON1_PTDIR)) | (down << B_PTCON1_PTDIR));
            }
            picsim_sfr[R_PTMRL] = (uint8_t)n;
            picsim_sfr[R_PTMRH] = (uint8_t)((n >> 8) & 0x0F);
        }
        return picsim_sfr[idx];
    case R_RCREG:
        rcreg_read();
        P.st.rcreg_reads++;
        g.irq_dirty = 1;
        pil_update_irq();
        return picsim_sfr[idx];
    default:
        return picsim_sfr[idx];
    }
}

static void pil_sfr_write(void *ctx, uint16_t addr, uint8_t v)
{
    (void)ctx;
    uint8_t idx = (uint8_t)addr;
    pil_clock();
    pil_sev_due();
#ifdef PIL_TRACE
    fprintf(stderr, "W %llu pc=%05X %03X=%02X\n", (unsigned long long)P.cpu.cycles, P.cpu.insn_pc, addr, v);
#endif
    /* GIEH/GIEL alone toggled with the priorities on (an atomic section): the request lines
       (pic_irq_lines: flags, enables, priorities), the events and the outputs stay as they are;
       the core masks the interrupts itself */
    if (idx == R_INTCON && !((v ^ picsim_sfr[idx]) & 0x3F) && sfr_bit(R_RCON, B_RCON_IPEN)) {
        picsim_sfr[idx] = g.shadow[idx] = v;
        return;
    }
    if (idx == R_T2CON || idx == R_TMR2 || idx == R_PR2) t2_catch_up();   /* with the old setting */
    picsim_sfr[idx] = v;
    g.shadow[idx] = v;
    /* high bytes of the buffered 16-bit timers: written to the buffer, loaded with the low byte */
    if ((idx == R_TMR0H && g.t0.modulus > 256) || (idx == R_TMR1H && sfr_bit(R_T1CON, B_T1CON_RD16)) ||
        idx == R_TMR5H)
        return;
    if (idx == R_ADCON0 && sfr_bit(R_ADCON0, B_ADCON0_GO) && g.adc_done == NEVER) note_adc_start();
    reg_written(idx);
    if (idx == R_PIR1 || idx == R_TXSTA || idx == R_TXREG || idx == R_RCSTA) enforce_readonly();
    if (idx == R_RCON) pil_intcon_quiet();
    g.irq_dirty = 1;
    pil_update_irq();
    /* the run stops here when the write moved an event before its end or changed the inverter
       state: the plant steps to this cycle with the state that held until it */
    if (pic_next_event() < P.target) { pic18_request_stop(&P.cpu); return; }
    if (g.legs_dirty) {
        pic_compute_legs();
        if (memcmp(g.leg, P.run_leg, sizeof P.run_leg) != 0) pic18_request_stop(&P.cpu);
    }
}

/* ------------------------------------------------------------ interrupt statistics */

static int speed_source_pending(int what)
{
    if (!(sfr_bit(R_PIR1, B_PIR1_TMR2IF) && sfr_bit(R_PIE1, B_PIE1_TMR2IE))) return 0;
    if (!sfr_bit(R_RCON, B_RCON_IPEN)) return 1;
    return (sfr_bit(R_IPR1, B_IPR1_TMR2IP) ? PIC18_HOOK_HIGH : PIC18_HOOK_LOW) == what;
}

static void stat_add(uint64_t d, uint64_t *n, uint64_t *mn, uint64_t *mx, uint64_t *sum)
{
    if (*n == 0 || d < *mn) *mn = d;
    if (d > *mx) *mx = d;
    *sum += d;
    (*n)++;
}

static void pil_irq_hook(void *ctx, int what)
{
    (void)ctx;
    pil_clock();
    if (what == PIC18_HOOK_HIGH || what == PIC18_HOOK_LOW) {
        if (what == PIC18_HOOK_HIGH) g.isr_high_calls++; else g.isr_low_calls++;   /* state()'s counters */
        if (what == PIC18_HOOK_HIGH)
            for (int k = 0; k < P.nest_n && k < PIL_NEST; k++)
                if (P.nest[k].speed) { P.st.speed_preempted++; break; }
        if (P.nest_n < PIL_NEST) {
            P.nest[P.nest_n].what = (uint8_t)what;
            P.nest[P.nest_n].pos_read = P.nest[P.nest_n].adc_started = 0;
            P.nest[P.nest_n].speed = (uint8_t)speed_source_pending(what);
            P.nest[P.nest_n].start = P.cpu.cycles - P.cpu.irq_vector_cycles;
            /* after the first speed-loop interrupt: fw_init runs with the interrupts off */
            if (P.nest[P.nest_n].speed && P.t2_waiting && P.st.speed_n > 0) {
                uint64_t st0 = P.nest[P.nest_n].start;
                uint64_t lat = st0 > P.t2_fired ? st0 - P.t2_fired : 0;
                stat_add(lat, &P.st.lat_n, &P.st.lat_min, &P.st.lat_max, &P.st.lat_sum);
            }
            if (P.nest[P.nest_n].speed) {
                P.t2_waiting = 0;
                uint64_t st0 = P.nest[P.nest_n].start;
                if (P.st.speed_entry_last && st0 - P.st.speed_entry_last > P.st.speed_gap_max)
                    P.st.speed_gap_max = st0 - P.st.speed_entry_last;
                P.st.speed_entry_last = st0;
            }
        }
        P.nest_n++;
        return;
    }
    if (P.nest_n == 0) { P.st.retfie_outside++; return; }   /* RETFIE with no interrupt taken */
    P.nest_n--;
    if (P.nest_n >= PIL_NEST) return;
    uint64_t d = P.cpu.cycles - P.nest[P.nest_n].start;
    if (P.nest[P.nest_n].what == PIC18_HOOK_HIGH)
        stat_add(d, &P.st.high_n, &P.st.high_min, &P.st.high_max, &P.st.high_sum);
    else
        stat_add(d, &P.st.low_n, &P.st.low_min, &P.st.low_max, &P.st.low_sum);
    if (P.nest[P.nest_n].speed) {
        stat_add(d, &P.st.speed_n, &P.st.speed_min, &P.st.speed_max, &P.st.speed_sum);
        P.st.speed_last = d;
    }
}

/* Timer2 (the speed-loop timer) set TMR2IF: a period is missed when its interrupt is still
   running (it will be re-entered late) or the previous flag was never taken (lost) */
static void pil_timer2_fired(int flag_was_set, int64_t at_ps)
{
    if (!P.loaded) return;
    if (!flag_was_set) {
        /* the event runs at the end of the instruction that crossed it: its own time, in cycles
           (the first cycle boundary at or after it: the flag is seen from there) */
        P.t2_fired = (uint64_t)((at_ps - P.t0 + g.tcy_ps - 1) / g.tcy_ps);
        P.t2_waiting = 1;
    }
    if (flag_was_set) {
        P.st.speed_lost++;
        if (P.st.speed_n == 0) P.st.missed_at_start++;
        return;
    }
    for (int k = 0; k < P.nest_n && k < PIL_NEST; k++)
        if (P.nest[k].speed) {
            if (P.st.speed_n == 0) P.st.missed_at_start++;
            if (!P.st.speed_overrun) P.st.overrun_first_cycle = P.cpu.cycles;
            P.st.speed_overrun++;
            return;
        }
}

/* ------------------------------------------------------------ faults */

static void pil_fault(int st)
{
    P.dead = 1;
    P.st.cpu_status = (uint64_t)st;
    P.st.fault_pc = P.cpu.fault_pc;
    P.st.fault_word = P.cpu.fault_word;
    P.st.insn_pc = st == PIC18_FAULT_PC || st == PIC18_FAULT_ILLEGAL ? P.cpu.insn_pc : P.cpu.fault_pc;
    g.errors |= TWIN_ERR_CPU;
    /* outputs off: the peripherals go to their reset state (PWM time base and pins off) */
    pic_reset();
    g.legs_dirty = 1;
    pic_compute_legs();
}

/* ------------------------------------------------------------ watchdog timer */

/* DS39616 section 23.2: the WDT runs from the INTRC (4 ms nominal period, here exact) through a
   postscaler of 1:2^WDPS; CLRWDT, SLEEP and every reset clear it.  On with CONFIG2H WDTEN, or
   with WDTEN off by WDTCON.SWDTEN.  A time-out resets the chip, as MCLR does, with RCON.TO = 0:
   the peripherals take their reset state (PCPWM outputs off: PWMPIN = OFF) and the program
   starts again at 0; in Sleep it wakes the core, which goes on after the SLEEP. */
static int pil_wdt_on(void)
{
    return P.wdt_cfg || sfr_bit(R_WDTCON, B_WDTCON_SWDTEN);
}

static uint64_t pil_wdt_cycles(void)
{
    return (uint64_t)llround(4e-3 * PS_PER_S / (double)g.tcy_ps) << P.wdt_ps;
}

static uint64_t pil_wdt_deadline(void)
{
    return pil_wdt_on() ? P.cpu.wdt_clr + pil_wdt_cycles() : UINT64_MAX;
}

static void pil_wdt_timeout(void)
{
    if (P.cpu.sleeping) {
        P.cpu.sleeping = 0;
        P.cpu.wdt_clr = P.cpu.cycles;
        picsim_sfr[R_RCON] = (uint8_t)(picsim_sfr[R_RCON] & ~(1u << B_RCON_TO) & ~(1u << B_RCON_PD));
        P.st.wdt_wakes++;
        return;
    }
    P.st.wdt_resets++;
    P.st.wdt_reset_cycle = P.cpu.cycles;
    pic_reset();                                 /* the peripherals: PWM time base and pins off */
    picsim_sfr[R_RCON] = g.shadow[R_RCON] = (uint8_t)(picsim_sfr[R_RCON] & ~(1u << B_RCON_TO));
    pic18_reset(&P.cpu);                         /* the core: PC 0, return stack cleared */
    P.nest_n = 0;
    P.t2_waiting = 0;
    g.irq_dirty = 1;
    g.legs_dirty = 1;
    pic_compute_legs();
}

/* ------------------------------------------------------------ API */

int pil_load(const uint8_t *flash, uint32_t n, const uint8_t *config)
{
    if (n > PIC18_FLASH_BYTES) return -1;
    pic18_init(&P.cpu);
    pic18_load_flash(&P.cpu, 0, flash, n);
    pic18_set_config(&P.cpu, config);
    P.wdt_cfg = (uint8_t)(config[3] & 1u);                  /* CONFIG2H: WDTEN bit 0, WDPS bits 4:1 */
    P.wdt_ps = (uint8_t)((config[3] >> 1) & 0x0F);
    uint8_t owned[256];
    memset(owned, 0, sizeof owned);
    for (int i = 0x60; i < 0x100; i++) owned[i] = 1;     /* the core keeps its own registers anyway */
    pic18_attach(&P.cpu, NULL, pil_sfr_read, pil_sfr_write, owned);
    pic18_set_irq_hook(&P.cpu, pil_irq_hook);
#ifndef PIL_TRACE
    pic18_share_intcon(&P.cpu, &picsim_sfr[R_INTCON], &g.shadow[R_INTCON]);
#endif
    P.loaded = 1;
    return 0;
}

uint32_t pil_flash_bytes(void) { return PIC18_FLASH_BYTES; }
uint32_t pil_ram_end(void) { return PIC18_RAM_END; }

void pil_get_stats(pil_stats_t *o)
{
    P.st.cycles = P.cpu.cycles;
    P.st.insns = P.cpu.insns;
    P.st.stack_high = P.cpu.stack_high;
    P.st.stkptr = P.cpu.stkptr;
    P.st.pc = P.cpu.pc;
    P.st.fsr1_lo = P.cpu.fsr1_lo;
    P.st.fsr1_hi = P.cpu.fsr1_hi;
    P.st.ram_written = pic18_ram_written(&P.cpu);
    P.st.in_isr = (uint64_t)P.nest_n;
    P.st.wdt_period_cycles = pil_wdt_on() ? pil_wdt_cycles() : 0;
    *o = P.st;
}

uint8_t pil_peek(uint16_t addr) { return pic18_peek(&P.cpu, addr); }

int pil_patch_flash(uint32_t addr, const uint8_t *data, uint32_t n)
{
    if (!P.loaded || addr >= PIC18_FLASH_BYTES || n > PIC18_FLASH_BYTES - addr) return -1;
    pic18_load_flash(&P.cpu, addr, data, n);      /* decoded again: the next fetch runs the new words */
    return 0;
}

int twin_power_on(void)
{
    if (!g.initialised || !P.loaded) return TWIN_ERR_NOT_INIT;
    board_reset();
    g.errors &= ~(uint32_t)TWIN_ERR_CPU;
    pic18_power_on(&P.cpu);
    P.t0 = g.now;
    g.cycle_t0 = P.t0;
    g.sev_lazy = 1;
    P.t_plant = g.now;
    P.dead = 0;
    P.nest_n = 0;
    P.t2_waiting = 0;
    P.lines = 0;
    memset(&P.st, 0, sizeof P.st);
    pic18_set_irq(&P.cpu, 0);
    g.irq_dirty = 1;
    pil_update_irq();
    pil_intcon_quiet();
    return (int)g.errors;
}

int twin_run_until(int64_t t_end)
{
    if (!g.initialised || !P.loaded) return TWIN_ERR_NOT_INIT;
    int64_t max_off = (int64_t)llround((g.cfg.max_step_s > 0 ? g.cfg.max_step_s : 50e-6) * PS_PER_S);
    g.irq_dirty = 1;
    while (g.now < t_end && !g.errors) {
        int64_t tn = next_step_end(t_end, max_off);
        P.st.steps++;

        pic_compute_legs();
        memcpy(P.run_leg, g.leg, sizeof P.run_leg);
        int64_t t_prev = g.now;
        /* the processor, up to the first cycle boundary at or after tn */
        uint64_t cyc_target = (uint64_t)((tn - P.t0 + g.tcy_ps - 1) / g.tcy_ps);
        /* the core stops at the watchdog's time-out, if it comes first (the step ends there) */
        uint64_t wdt_at = pil_wdt_deadline();
        if (!P.dead && wdt_at < cyc_target) cyc_target = wdt_at > P.cpu.cycles ? wdt_at : P.cpu.cycles + 1;
        if (!P.dead && P.cpu.cycles < cyc_target) {
            P.target = tn;
            pil_update_irq();
            pil_intcon_quiet();                   /* RCON after a reset or a fault */
            int st = pic18_run(&P.cpu, cyc_target - P.cpu.cycles, UINT64_MAX, ~0u);
            if (P.cpu.cycles < cyc_target && st == PIC18_OK) P.st.stops++;
            if (st == PIC18_SLEEP) {
                P.cpu.cycles = cyc_target;           /* asleep until an interrupt request */
                P.st.sleep_runs++;
            } else if (st == PIC18_RESET_INSN) {
                P.st.resets++;
                pic_reset();                          /* the whole chip resets */
                g.irq_dirty = 1;
            } else if (st != PIC18_OK) {
                pil_clock();
                pil_fault(st);
            }
            if (!P.dead && P.cpu.cycles >= pil_wdt_deadline()) {
                pil_clock();
                pil_wdt_timeout();
            }
        } else if (P.dead) {
            P.cpu.cycles = cyc_target;
        }
        pil_clock();
        pil_sev_due();
        (void)t_prev;
        /* the plant over the same interval (or what a read left of it), with the inverter
           state of its start */
        pil_plant_to_now();
        pic_events_due();
        if (g.trace_next <= g.now) {
            trace_record();
            g.trace_next += g.trace_period;
        }
        pil_update_irq();
    }
    return (int)g.errors;
}

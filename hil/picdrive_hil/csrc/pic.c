/* PIC18F4431 peripheral model: the parts of the chip the generated firmware
 * touches (docs/firmware.md "Peripheral usage"; docs/twin.md lists what is
 * modelled and how).
 *
 * How the firmware and the model meet (architecture.md seam 4): all SFRs are
 * bytes of picsim_sfr[].  Firmware code runs in zero simulated time.  Before
 * every firmware call the model writes the registers that change with time
 * (ports, timer counts, POSCNT, PTMR) and keeps a shadow copy; after the call
 * it compares the SFRs with the shadow and applies the side effects of every
 * register the firmware changed.  Registers whose access itself has an effect
 * (TXREG, RCREG, EECON1, EECON2, ADRES with the FIFO) arrive through
 * picsim_sfr_written / picsim_sfr_read, which the shim calls at the access.
 */
#include "pic_internal.h"

#include <math.h>
#include <string.h>

volatile uint8_t picsim_sfr[256];

/* ------------------------------------------------------------ helpers */

static void hw_putbit(uint8_t idx, int bit, int v) { if (v) hw_setbit(idx, bit); else hw_clrbit(idx, bit); }
static uint16_t sfr16(uint8_t lo, uint8_t hi) { return (uint16_t)(picsim_sfr[lo] | (picsim_sfr[hi] << 8)); }

static int64_t tosc(int64_t n) { return n * g.tosc_ps; }
static int64_t tcy(int64_t n) { return n * g.tcy_ps; }
static int64_t secs(double s) { return (int64_t)llround(s * PS_PER_S); }
/* the present instant as the firmware sees it: inside a call, polling takes time */
static int64_t vnow(void) { return g.now + g.call_cycles * g.tcy_ps; }

/* ------------------------------------------------------------ reset */

static void timer_off(timer_t_ *t) { memset(t, 0, sizeof *t); t->next = NEVER; t->modulus = 1; t->tick_ps = 1; }

void pic_reset(void)
{
    memset((void *)picsim_sfr, 0, sizeof picsim_sfr);
    /* power-on values that are not zero (DS39616D register summary) */
    picsim_sfr[R_OVDCOND] = 0xFF;
    picsim_sfr[R_TRISA] = 0xFF; picsim_sfr[R_TRISB] = 0xFF; picsim_sfr[R_TRISC] = 0xFF;
    picsim_sfr[R_TRISD] = 0xFF; picsim_sfr[R_TRISE] = 0x07;
    picsim_sfr[R_PR2] = 0xFF; picsim_sfr[R_PR5L] = 0xFF; picsim_sfr[R_PR5H] = 0xFF;
    picsim_sfr[R_MAXCNTL] = 0xFF; picsim_sfr[R_MAXCNTH] = 0xFF;
    picsim_sfr[R_T0CON] = 0xFF;
    picsim_sfr[R_TXSTA] = 0x02;                     /* TRMT */
    picsim_sfr[R_IPR1] = 0x7F; picsim_sfr[R_IPR2] = 0xFF; picsim_sfr[R_IPR3] = 0x1F;
    picsim_sfr[R_INTCON2] = 0xF5; picsim_sfr[R_INTCON3] = 0xC0;
    picsim_sfr[R_RCON] = 0x1C;
    picsim_sfr[R_ANSEL0] = 0xFF; picsim_sfr[R_ANSEL1] = 0x01;
    picsim_sfr[R_BAUDCON] = 1u << B_BAUDCON_RCIDL;
    memcpy(g.shadow, (const void *)picsim_sfr, sizeof g.shadow);

    g.pwm_on = 0; g.pwm_next = NEVER; g.pwm_start = g.now; g.pwm_period = 0; g.pwm_post = 0;
    g.ptper_act = 0; memset(g.pdc_act, 0, sizeof g.pdc_act);
    g.ovd_act = 0xFF; g.ovs_act = 0; g.flt_latched = 0; g.flt_cbc = 0;
    timer_off(&g.t0); timer_off(&g.t1); timer_off(&g.t2); timer_off(&g.t5);
    g.poscnt = 0; g.vel_last_t = g.now; g.vel_pdec = 0; g.qei_dir = 1;
    g.bit_ps = 0; g.tx_busy = 0; g.txreg_full = 0; g.tx_done = NEVER; g.rx_n = 0;
    g.rx_arrive = NEVER; g.baud_bad = 0;
    g.ee_unlock = 0; g.ee_done = NEVER;
    g.adc_done = NEVER;
    g.sev_at = NEVER;
    g.pwm_buf_stale = 1;
    g.hall_ext_ok = 0;
    g.irq_dirty = 1;
}

/* ------------------------------------------------------------ ports */

static uint8_t port_value(int port)
{
    static const uint8_t lat[5] = {R_LATA, R_LATB, R_LATC, R_LATD, R_LATE};
    static const uint8_t tris[5] = {R_TRISA, R_TRISB, R_TRISC, R_TRISD, R_TRISE};
    uint8_t t = picsim_sfr[tris[port]], v = (uint8_t)((picsim_sfr[lat[port]] & ~t) | (g.ext[port] & t));
    /* analog pins read 0 as digital inputs: AN0..AN4 = RA0..RA4, AN5..AN7 = RE0..RE2, AN8 = RA5 */
    if (port == 0) {
        uint8_t an = (uint8_t)(picsim_sfr[R_ANSEL0] & 0x1F);
        if (picsim_sfr[R_ANSEL1] & 1) an |= 0x20;
        v &= (uint8_t)~an;
    } else if (port == 4) {
        v &= (uint8_t)~((picsim_sfr[R_ANSEL0] >> 5) & 0x07);
    }
    return v;
}

/* ------------------------------------------------------------ timers */

static uint32_t timer_count(const timer_t_ *t)
{
    if (!t->on) return t->cnt_ref;
    uint64_t c = t->cnt_ref + (uint64_t)((g.now - t->t_ref) / t->tick_ps);
    return (uint32_t)(c < t->modulus ? c : c % t->modulus);
}

static uint32_t timer_count_at(const timer_t_ *t, int64_t when)
{
    if (!t->on) return t->cnt_ref;
    int64_t n = (when - t->t_ref) / t->tick_ps;
    if (n < 0) n = 0;
    uint64_t c = t->cnt_ref + (uint64_t)n;
    return (uint32_t)(c < t->modulus ? c : c % t->modulus);
}

static void timer_anchor_at(timer_t_ *t, uint32_t cnt, int64_t when)
{
    t->t_ref = when;
    t->cnt_ref = t->modulus ? cnt % t->modulus : cnt;
    t->next = t->on ? when + (int64_t)(t->modulus - t->cnt_ref) * t->tick_ps : NEVER;
}

static void timer_anchor(timer_t_ *t, uint32_t cnt)
{
    t->t_ref = g.now;
    t->cnt_ref = t->modulus ? cnt % t->modulus : cnt;
    t->next = t->on ? g.now + (int64_t)(t->modulus - t->cnt_ref) * t->tick_ps : NEVER;
}

static void timer_config(timer_t_ *t, int on, int64_t tick_ps, uint32_t modulus)
{
    uint32_t c = timer_count(t);
    t->on = on;
    t->tick_ps = tick_ps > 0 ? tick_ps : 1;
    t->modulus = modulus ? modulus : 1;
    if (c >= t->modulus) c = 0;
    timer_anchor(t, c);
}

static void t0_config(void)
{
    uint8_t c = picsim_sfr[R_T0CON];
    int on = (c >> B_T0CON_TMR0ON) & 1;
    if ((c >> B_T0CON_T0CS) & 1) on = 0;        /* external clock: nothing drives T0CKI */
    int64_t ps = ((c >> B_T0CON_PSA) & 1) ? 1 : (2 << (c & 7));
    timer_config(&g.t0, on, tcy(ps), ((c >> B_T0CON_T016BIT) & 1) ? 256u : 65536u);
}

static void t1_config(void)
{
    uint8_t c = picsim_sfr[R_T1CON];
    int on = (c >> B_T1CON_TMR1ON) & 1;
    if ((c >> B_T1CON_TMR1CS) & 1) on = 0;
    timer_config(&g.t1, on, tcy(1 << ((c >> B_T1CON_T1CKPS0) & 3)), 65536u);
}

static void t2_config(void)
{
    uint8_t c = picsim_sfr[R_T2CON];
    int pre = c & 3;
    int64_t ps = pre == 0 ? 1 : pre == 1 ? 4 : 16;
    timer_config(&g.t2, (c >> B_T2CON_TMR2ON) & 1, tcy(ps), (uint32_t)picsim_sfr[R_PR2] + 1u);
}

static void t5_config(void)
{
    uint8_t c = picsim_sfr[R_T5CON];
    int on = (c >> B_T5CON_TMR5ON) & 1;
    if ((c >> B_T5CON_TMR5CS) & 1) on = 0;
    timer_config(&g.t5, on, tcy(1 << ((c >> B_T5CON_T5PS0) & 3)), (uint32_t)sfr16(R_PR5L, R_PR5H) + 1u);
}

static void timer_event(timer_t_ *t, int which)
{
    /* wrap/match at t->next (== g.now in the SIL twin; the processor twin reaches it at the end
       of the instruction that crosses it, so the period is anchored on the exact time) */
    int64_t at = t->next;
    t->t_ref = at;
    t->cnt_ref = 0;
    t->next = at + (int64_t)t->modulus * t->tick_ps;
    switch (which) {
    case 0: hw_setbit(R_INTCON, B_INTCON_TMR0IF); break;
    case 1: hw_setbit(R_PIR1, B_PIR1_TMR1IF); break;
    case 2: {
        uint32_t post = ((picsim_sfr[R_T2CON] >> B_T2CON_T2OUTPS0) & 15) + 1;
        if (++t->post >= post) {
            t->post = 0;
            PIL_TIMER2_FIRED(sfr_bit(R_PIR1, B_PIR1_TMR2IF), at);
            hw_setbit(R_PIR1, B_PIR1_TMR2IF);
        }
        break;
    }
    case 5: hw_setbit(R_PIR3, B_PIR3_TMR5IF); break;
    }
}

/* Timer2's postscaler: only the wrap that completes the postscale count sets TMR2IF, so the
   event loop is not stopped at the others.  The count (TMR2) is computed from the anchor at any
   instant, whatever number of periods passed; the wraps passed are counted (t->post) when the
   flag's wrap is processed, and by the processor twin before a program write to T2CON, TMR2 or
   PR2 (the SIL's writes come at a step's end, where every wrap due was processed). */
static uint32_t t2_postscale(void) { return ((picsim_sfr[R_T2CON] >> B_T2CON_T2OUTPS0) & 15) + 1; }

static int64_t t2_flag_time(void)
{
    uint32_t post = t2_postscale();
    int64_t left = (int64_t)post - 1 - (int64_t)g.t2.post;
    if (left <= 0) return g.t2.next;
    return g.t2.next + left * (int64_t)g.t2.modulus * g.t2.tick_ps;
}

/* the wraps up to now that leave TMR2IF alone (the one that sets it is an event of its own) */
static void t2_catch_up(void)
{
    while (g.t2.on && g.t2.next <= g.now && g.t2.post + 1 < t2_postscale()) timer_event(&g.t2, 2);
}

/* ------------------------------------------------------------ PCPWM */

static int ptckps(void) { return 1 << (2 * ((picsim_sfr[R_PTCON0] >> B_PTCON0_PTCKPS0) & 3)); }
static int ptmod(void) { return picsim_sfr[R_PTCON0] & 3; }

static int64_t pwm_period_ps(uint16_t ptper)
{
    int64_t ps = ptckps();
    if (ptmod() >= 2) return tcy(2 * (int64_t)ptper * ps);   /* continuous up/down (center aligned) */
    return tcy(((int64_t)ptper + 1) * ps);
}

static double dead_time_s(void)
{
    uint8_t d = picsim_sfr[R_DTCON];
    int dtps = (d >> B_DTCON_DTPS0) & 3;               /* Fosc/2, /4, /8, /16 */
    return (double)tosc((int64_t)(d & 0x3F) * (2 << dtps)) / PS_PER_S;
}

static void pwm_load_buffers(void)
{
    /* PTPER, PDCx, UDIS and the time base's state are all it reads: unchanged since the
       last load (no firmware write to the PCPWM block, pwm_on the same), nothing to do */
    if (!g.pwm_buf_stale) return;
    g.pwm_buf_stale = 0;
    uint16_t per = (uint16_t)(sfr16(R_PTPERL, R_PTPERH) & 0x0FFF);
    if (per != g.ptper_act) g.legs_dirty = 1;
    g.ptper_act = per;
    if (!((picsim_sfr[R_PWMCON1] >> B_PWMCON1_UDIS) & 1) || !g.pwm_on)
        for (int k = 0; k < 4; k++) {
            static const uint8_t lo[4] = {R_PDC0L, R_PDC1L, R_PDC2L, R_PDC3L};
            static const uint8_t hi[4] = {R_PDC0H, R_PDC1H, R_PDC2H, R_PDC3H};
            uint16_t v = (uint16_t)(sfr16(lo[k], hi[k]) & 0x3FFF);
            if (v != g.pdc_act[k]) g.legs_dirty = 1;
            g.pdc_act[k] = v;
        }
}

static void pwm_start_period(int64_t at)
{
    pwm_load_buffers();
    if ((picsim_sfr[R_PWMCON1] >> B_PWMCON1_OSYNC) & 1 &&
        (g.ovd_act != picsim_sfr[R_OVDCOND] || g.ovs_act != picsim_sfr[R_OVDCONS])) {
        g.ovd_act = picsim_sfr[R_OVDCOND];
        g.ovs_act = picsim_sfr[R_OVDCONS];
        g.legs_dirty = 1;
    }
    g.pwm_start = at;
    int64_t per;
    if (g.per_key_valid && g.per_key_ptper == g.ptper_act && g.per_key_ptcon0 == picsim_sfr[R_PTCON0]) {
        per = g.per_key_ps;                  /* same PTPER and PTCON0 as the last period */
    } else {
        per = pwm_period_ps(g.ptper_act);
        if (per <= 0) per = tcy(1);
        g.per_key_valid = 1;
        g.per_key_ptper = g.ptper_act;
        g.per_key_ptcon0 = picsim_sfr[R_PTCON0];
        g.per_key_ps = per;
    }
    if (per != g.pwm_period) g.legs_dirty = 1;
    g.pwm_period = per;
    g.pwm_next = at + g.pwm_period;
    /* special event trigger (edge-aligned, counting up, postscale 1:1: what the firmware uses):
       PTMR = SEVTCMP starts an A/D conversion when ADCON3.SSRC4 selects the PCPWM */
    g.sev_at = NEVER;
    if (ptmod() < 2 && ((picsim_sfr[R_ADCON3] >> B_ADCON3_SSRC4) & 1)) {
        uint16_t sev = (uint16_t)(sfr16(R_SEVTCMPL, R_SEVTCMPH) & 0x0FFF);
        if (sev <= g.ptper_act) g.sev_at = at + (int64_t)sev * tcy(ptckps());
    }
    if (g.flt_cbc && !g.flta_asserted) {
        g.flt_cbc = 0;
        g.legs_dirty = 1;
        if (!g.flt_latched) hw_clrbit(R_FLTCONFIG, B_FLTCONFIG_FLTAS);
    }
}

static void pwm_time_base(void)
{
    g.legs_dirty = 1;
    g.pwm_buf_stale = 1;
    int on = (picsim_sfr[R_PTCON1] >> B_PTCON1_PTEN) & 1;
    if (on && !g.pwm_on) {
        g.pwm_on = 1;
        g.pwm_post = 0;
        pwm_start_period(g.now);
    } else if (!on && g.pwm_on) {
        g.pwm_on = 0;
        g.pwm_next = NEVER;
        g.sev_at = NEVER;
    }
    if (!g.pwm_on) pwm_load_buffers();
}

static void pwm_boundary(void)
{
    uint32_t post = ((picsim_sfr[R_PTCON0] >> B_PTCON0_PTOPS0) & 15) + 1;
    if (++g.pwm_post >= post) { g.pwm_post = 0; hw_setbit(R_PIR3, B_PIR3_PTIF); }
    if (ptmod() == 1) {                       /* single shot: the time base stops */
        hw_clrbit(R_PTCON1, B_PTCON1_PTEN);
        g.pwm_on = 0;
        g.pwm_buf_stale = 1;
        g.pwm_next = NEVER;
        return;
    }
    pwm_start_period(g.pwm_next);   /* the exact boundary (== g.now in the SIL twin) */
}

/* PWMEN<2:0> -> outputs driven by the module (DS39616D register 18-3) */
static uint8_t pwm_pin_mask(void)
{
    switch ((picsim_sfr[R_PWMCON0] >> B_PWMCON0_PWMEN0) & 7) {
    case 0: return 0x00;
    case 1: return 0x02;          /* PWM1 */
    case 2: return 0x03;          /* PWM0, PWM1 */
    case 3: return 0x0F;          /* PWM0..3 */
    case 4: return 0x3F;          /* PWM0..5 */
    case 5: return 0xFF;          /* all */
    case 6: return 0x0A;          /* PWM1, PWM3 */
    default: return 0xAA;         /* odd pins */
    }
}

/* output state of pin n (ignoring fault): 0 off, 1 on, 2 PWM at duty */
static int pin_state(int n)
{
    if ((g.ovd_act >> n) & 1) return g.pwm_on ? 2 : 0;
    return (g.ovs_act >> n) & 1;
}

void pic_compute_legs(void)
{
    if (!g.legs_dirty) return;
    g.legs_dirty = 0;
    uint8_t en = pwm_pin_mask();
    int fault = g.flt_latched || g.flt_cbc;
    int64_t per = g.pwm_period > 0 ? g.pwm_period : 1;
    double dt = g.pwm_on ? dead_time_s() / ((double)per / PS_PER_S) : 0.0;
    g.dead_frac = dt;
    for (int k = 0; k < 4; k++) {
        double den = ptmod() >= 2 ? 4.0 * g.ptper_act : 4.0 * (g.ptper_act + 1.0);
        double d = den > 0 ? g.pdc_act[k] / den : 0.0;
        g.duty[k] = d > 1.0 ? 1.0 : d;
    }
    for (int x = 0; x < 3; x++) {
        int pair = g.cfg.phase_pair[x] & 3, odd = 2 * pair + 1, even = 2 * pair;
        double d = g.duty[pair], fh = 0.0, fl = 0.0;
        int sh = 0, sl = 0;
        if (!fault) {
            int compl = !((picsim_sfr[R_PWMCON0] >> pair) & 1);   /* PMODn = 0: complementary */
            int so = ((en >> odd) & 1) ? pin_state(odd) : 0;
            if (compl) {
                /* the even pin is the complement of the odd one, dead time on each turn-on */
                if (so == 2) {
                    fh = d >= 1.0 ? 1.0 : (d > dt ? d - dt : 0.0);
                    fl = d <= 0.0 ? 1.0 : (1.0 - d > dt ? 1.0 - d - dt : 0.0);
                } else {
                    fh = so ? 1.0 : 0.0;
                    fl = so ? 0.0 : 1.0;
                }
                if (!((en >> even) & 1)) fl = 0.0;
                sh = so; sl = so == 2 ? 2 : (fl > 0.0);
            } else {
                int se = ((en >> even) & 1) ? pin_state(even) : 0;
                fh = so == 2 ? d : so;
                fl = se == 2 ? d : se;
                sh = so; sl = se;
                /* independent pins can both conduct: shoot-through */
                double ov = 0.0;
                if (so && se) ov = (so == 2 && se == 2) ? d : (so == 1 ? fl : fh);
                if (ov > 0.0) g.shoot_through++;
            }
        }
        g.leg[x].f_hi = fh;
        g.leg[x].f_lo = fl;
        g.gate_hi[x] = (uint8_t)(fh > 0.0 ? sh : 0);
        g.gate_lo[x] = (uint8_t)(fl > 0.0 ? sl : 0);
    }
    /* the instant the outputs went off, on the twin's clock (tests time the watchdog by it) */
    int on = 0;
    for (int x = 0; x < 3; x++) on |= g.leg[x].f_hi > 0.0 || g.leg[x].f_lo > 0.0;
    if (g.outputs_were_on && !on) g.outputs_off_ps = g.now;
    g.outputs_were_on = on;
}

static void flt_update(int64_t t_prev)
{
    /* the comparator drives FLTA low while the current is over the trip level
       (or an injected overcurrent overlaps the step just taken) */
    int asserted = g.ps.i_peak_a > g.cfg.overcurrent_trip_a || t_prev < g.oc_until;
    g.flta_asserted = asserted;
    if (g.cfg.flta_pin.port < 5) {
        uint8_t m = (uint8_t)(1u << g.cfg.flta_pin.bit);
        if (asserted) g.ext[g.cfg.flta_pin.port] &= (uint8_t)~m; else g.ext[g.cfg.flta_pin.port] |= m;
    }
    if (!asserted) return;
    g.legs_dirty = 1;
    uint8_t f = picsim_sfr[R_FLTCONFIG];
    if (!((f >> B_FLTCONFIG_FLTAEN) & 1)) return;
    hw_setbit(R_FLTCONFIG, B_FLTCONFIG_FLTAS);
    if ((f >> B_FLTCONFIG_FLTAMOD) & 1) g.flt_cbc = 1;
    else g.flt_latched = 1;
}

/* ------------------------------------------------------------ QEI */

static int qei_mode(void) { return (picsim_sfr[R_QEICON] >> B_QEICON_QEIM0) & 7; }

/* floor(n / cpr): the revolution of x4 count n.  The counts move a few per step, so the
   revolution of the last count asked is kept and the division done only on a new one. */
static int64_t enc_rev(int64_t n, int64_t cpr)
{
    if (!(g.rev_valid && g.rev_cpr == cpr && n >= g.rev_base && n - g.rev_base < cpr)) {
        g.rev = n >= 0 ? n / cpr : -((-n + cpr - 1) / cpr);
        g.rev_base = g.rev * cpr;
        g.rev_cpr = cpr;
        g.rev_valid = 1;
    }
    return g.rev;
}

/* encoder counts n_from -> n_to while the (measured) angle went th0 -> th1
   over t0 -> t1; edge times are interpolated on the angle */
static void qei_counts(int64_t n_from, int64_t n_to, double th0, double th1, double t0_ps, double t1_ps)
{
    int mode = qei_mode();
    if (mode == 0 || mode == 3 || mode == 4 || mode == 7 || n_from == n_to) return;
    int x4 = mode >= 5;
    int64_t a = x4 ? n_from : (n_from >> 1), b = x4 ? n_to : (n_to >> 1);  /* x2: QEA edges */
    int64_t d = b - a;
    if (d == 0) return;
    int dir = d > 0 ? 1 : -1;
    if (dir != g.qei_dir) { g.qei_dir = dir; hw_setbit(R_PIR3, B_PIR3_IC3DRIF); }
    hw_putbit(R_QEICON, B_QEICON_UP_DOWN, dir > 0);
    /* position counter */
    if (mode == 2 || mode == 6) {                       /* reset on MAXCNT match */
        int64_t m = (int64_t)sfr16(R_MAXCNTL, R_MAXCNTH) + 1;
        int64_t p = (int64_t)g.poscnt + d;
        if (p >= m || p < 0) {
            hw_setbit(R_PIR3, B_PIR3_IC2QEIF);
            p %= m;
            if (p < 0) p += m;
        }
        g.poscnt = (int32_t)p;
    } else {                                            /* reset by the index pulse */
        int64_t cpr = 4 * (int64_t)g.pp.encoder_lines;
        int64_t ia = enc_rev(n_from, cpr);
        int64_t ib = enc_rev(n_to, cpr);
        if (ia != ib) {
            g.enc_index_count = (dir > 0 ? ib : ia) * cpr;
            hw_setbit(R_PIR3, B_PIR3_IC2QEIF);
        }
        int64_t p = n_to - g.enc_index_count;
        g.poscnt = (int32_t)(x4 ? p : p / 2);
    }
    /* velocity captures: every 1, 4, 16 or 64 counts TMR5 is captured into VELR and reset */
    if (!((picsim_sfr[R_QEICON] >> B_QEICON_VELM) & 1) && g.t5.on) {
        int lg = 2 * (picsim_sfr[R_QEICON] & 3);    /* every 1, 4, 16, 64 counts */
        uint32_t r = 1u << lg;
        int64_t ad = d > 0 ? d : -d;
        uint64_t total = g.vel_pdec + (uint64_t)ad;
        if (total >= r) {
            /* the k-th count (1-based) of this step sits at count n_from + k (forward) or
               n_from - k + 1 (reverse, the edge is the lower boundary of the count left) */
            uint64_t n_caps = total >> lg;
            uint64_t last_k = n_caps * r - g.vel_pdec;
            double q = x4 ? 1.0 : 2.0;           /* counts of the x4 grid per QEI count */
            double dth = th1 - th0;
            double scale = fabs(dth) > 0.0 ? (t1_ps - t0_ps) / dth : 0.0;
            double cnt_rad = q * 2.0 * M_PI / (4.0 * g.pp.encoder_lines);
#define EDGE_T(k) (scale != 0.0 ? t0_ps + scale * \
        ((dir > 0 ? (double)a + (double)(k) : (double)a - (double)(k) + 1.0) * cnt_rad - th0) : t1_ps)
            double tl = EDGE_T(last_k);
            double tp = n_caps >= 2 ? EDGE_T(last_k - r) : (double)g.vel_last_t;
#undef EDGE_T
            if (tl < t0_ps) tl = t0_ps;
            if (tl > t1_ps) tl = t1_ps;
            if (tp > tl) tp = tl;
            int reset = (picsim_sfr[R_CAP1CON] >> B_CAP1CON_CAP1REN) & 1;
            if (reset && n_caps >= 2) timer_anchor_at(&g.t5, 0, (int64_t)tp);
            uint32_t v = timer_count_at(&g.t5, (int64_t)tl);
            hw_write(R_VELRL, (uint8_t)v);
            hw_write(R_VELRH, (uint8_t)(v >> 8));
            g.vel_last_t = (int64_t)tl;
            if (reset) timer_anchor_at(&g.t5, 0, (int64_t)tl);   /* CAP1REN: TMR5 restarts at the capture */
            hw_setbit(R_PIR3, B_PIR3_IC1IF);
        }
        g.vel_pdec = (uint32_t)(total & (r - 1u));
    }
}

/* ------------------------------------------------------------ EUSART */

double pic_board_baud(void)
{
    uint8_t tx = picsim_sfr[R_TXSTA];
    int brgh = (tx >> B_TXSTA_BRGH) & 1, brg16 = (picsim_sfr[R_BAUDCON] >> B_BAUDCON_BRG16) & 1;
    uint32_t n = brg16 ? sfr16(R_SPBRG, R_SPBRGH) : picsim_sfr[R_SPBRG];
    uint32_t div = brg16 ? (brgh ? 4u : 16u) : (brgh ? 16u : 64u);
    if ((tx >> B_TXSTA_SYNC) & 1) return 0.0;
    return g.cfg.fosc_hz / ((double)div * (n + 1.0));
}

static void uart_config(void)
{
    uint8_t tx = picsim_sfr[R_TXSTA];
    int brgh = (tx >> B_TXSTA_BRGH) & 1, brg16 = (picsim_sfr[R_BAUDCON] >> B_BAUDCON_BRG16) & 1;
    uint32_t n = brg16 ? sfr16(R_SPBRG, R_SPBRGH) : picsim_sfr[R_SPBRG];
    uint32_t div = brg16 ? (brgh ? 4u : 16u) : (brgh ? 16u : 64u);
    g.bit_ps = tosc((int64_t)div * (n + 1));
    double b = pic_board_baud();
    g.baud_bad = !(b > 0.0) || fabs(b - g.cfg.host_baud) > 0.025 * g.cfg.host_baud;
}

static int uart_on(void) { return (picsim_sfr[R_RCSTA] >> B_RCSTA_SPEN) & 1; }

static int64_t frame_ps(void)
{
    int bits = 10 + ((picsim_sfr[R_TXSTA] >> B_TXSTA_TX9) & 1);
    return g.bit_ps * bits;
}

static void tx_start(uint8_t b)
{
    g.tsr = b;
    g.tx_busy = 1;
    g.tx_done = g.now + frame_ps();
    hw_clrbit(R_TXSTA, B_TXSTA_TRMT);
}

static void txreg_written(void)
{
    uint8_t b = picsim_sfr[R_TXREG];
    if (!uart_on() || !((picsim_sfr[R_TXSTA] >> B_TXSTA_TXEN) & 1)) return;
    if (!g.tx_busy) {
        tx_start(b);
        hw_setbit(R_PIR1, B_PIR1_TXIF);
    } else {
        if (g.txreg_full) g.tx_overwrites++;
        g.txbuf = b;
        g.txreg_full = 1;
        hw_clrbit(R_PIR1, B_PIR1_TXIF);
    }
}

static void tx_complete(void)
{
    if (g.baud_bad) g.errors |= TWIN_ERR_BAUD;
    if (((g.hout_tail + 1) & (HOSTQ - 1)) != g.hout_head) {
        g.hq_out[g.hout_tail] = g.baud_bad ? (uint8_t)(g.tsr ^ 0xA5) : g.tsr;
        g.hout_tail = (g.hout_tail + 1) & (HOSTQ - 1);
    }
    g.tx_busy = 0;
    g.tx_done = NEVER;
    if (g.txreg_full) {
        g.txreg_full = 0;
        tx_start(g.txbuf);
        hw_setbit(R_PIR1, B_PIR1_TXIF);
    } else {
        hw_setbit(R_TXSTA, B_TXSTA_TRMT);
    }
}

void pic_uart_rx_schedule(void)
{
    if (g.rx_arrive != NEVER || g.hin_head == g.hin_tail) return;
    g.rx_byte = g.hq_in[g.hin_head];
    g.hin_head = (g.hin_head + 1) & (HOSTQ - 1);
    g.rx_arrive = g.now + g.host_frame_ps;
}

static void rx_arrival(void)
{
    uint8_t b = g.rx_byte;
    g.rx_arrive = NEVER;
    if (!uart_on() || !((picsim_sfr[R_RCSTA] >> B_RCSTA_CREN) & 1) ||
        ((picsim_sfr[R_RCSTA] >> B_RCSTA_OERR) & 1)) {
        g.rx_dropped++;
    } else if (g.rx_n >= 2) {
        g.rx_overruns++;
        hw_setbit(R_RCSTA, B_RCSTA_OERR);
    } else {
        if (g.baud_bad) {
            g.rx_framing++;
            g.errors |= TWIN_ERR_BAUD;
            b ^= 0x5A;
            hw_setbit(R_RCSTA, B_RCSTA_FERR);
        }
        g.rxfifo[g.rx_n++] = b;
        if (g.rx_n == 1) hw_write(R_RCREG, b);
        hw_setbit(R_PIR1, B_PIR1_RCIF);
    }
    pic_uart_rx_schedule();
}

static void rcreg_read(void)
{
    if (g.rx_n == 0) return;
    hw_write(R_RCREG, g.rxfifo[0]);
    g.rxfifo[0] = g.rxfifo[1];
    g.rx_n--;
    if (g.rx_n == 0) {
        hw_clrbit(R_PIR1, B_PIR1_RCIF);
        hw_clrbit(R_RCSTA, B_RCSTA_FERR);
    }
}

/* ------------------------------------------------------------ EEPROM */

static void eecon1_written(void)
{
    uint8_t c = picsim_sfr[R_EECON1];
    int data = !((c >> B_EECON1_EEPGD) & 1) && !((c >> B_EECON1_CFGS) & 1);
    if ((c >> B_EECON1_RD) & 1) {
        if (data) hw_write(R_EEDATA, g.ee[picsim_sfr[R_EEADR]]);
        hw_clrbit(R_EECON1, B_EECON1_RD);
    }
    c = picsim_sfr[R_EECON1];
    if (((c >> B_EECON1_WR) & 1) && g.ee_done == NEVER) {
        if (data && ((c >> B_EECON1_WREN) & 1) && g.ee_unlock == 2) {
            g.ee_addr = picsim_sfr[R_EEADR];
            g.ee_data = picsim_sfr[R_EEDATA];
            g.ee_done = vnow() + secs(g.cfg.eeprom_write_s);
        } else {
            g.ee_rejected++;
            hw_clrbit(R_EECON1, B_EECON1_WR);      /* WR cannot be set without the unlock sequence */
        }
        g.ee_unlock = 0;
    }
}

static void eecon2_written(void)
{
    uint8_t v = picsim_sfr[R_EECON2];
    if (v == 0x55) g.ee_unlock = 1;
    else if (v == 0xAA && g.ee_unlock == 1) g.ee_unlock = 2;
    else g.ee_unlock = 0;
    hw_write(R_EECON2, 0);                          /* EECON2 is not a physical register */
}

static void ee_complete(void)
{
    g.ee[g.ee_addr] = g.ee_data;
    g.ee_writes++;
    g.ee_done = NEVER;
    hw_clrbit(R_EECON1, B_EECON1_WR);
    hw_setbit(R_PIR2, B_PIR2_EEIF);
}

/* ------------------------------------------------------------ ADC */

static double analog_volts(int ch)
{
    if (ch < 0 || ch > 8) return 0.0;
    switch (g.cfg.analog_signal[ch]) {
    case ASIG_CURRENT: {
        double i = g.cfg.current_signal == CURSIG_BUS_AVG ? g.ps.i_bus_a
                 : g.cfg.current_signal == CURSIG_PEAK ? g.ps.i_peak_a : g.ps.i_link_on_a;
        return g.cfg.current_sense_offset_v + g.cfg.current_sense_v_per_a * i;
    }
    case ASIG_BUS_VOLTAGE:
        /* the bus capacitor's voltage (it rises when the bridge returns energy the supply cannot take) */
        return g.cfg.bus_sense_v_per_v * plant_bus_voltage(&g.pp, &g.ps);
    default:
        return 0.0;
    }
}

static void adc_start(void)
{
    uint8_t c0 = picsim_sfr[R_ADCON0];
    if (!((c0 >> B_ADCON0_ADON) & 1)) { hw_clrbit(R_ADCON0, B_ADCON0_GO); return; }
    if ((c0 >> B_ADCON0_ACSCH) & 1) {
        g.errors |= TWIN_ERR_ADC_MODE;       /* multi-channel sequencing is not modelled */
        hw_clrbit(R_ADCON0, B_ADCON0_GO);
        return;
    }
    /* single channel: ACMOD picks group A..D, ADCHS the channel of that group */
    int grp = (c0 >> B_ADCON0_ACMOD0) & 3;
    static const int shift[4] = {0, 4, 2, 6};            /* GASEL, GBSEL, GCSEL, GDSEL */
    int sel = (picsim_sfr[R_ADCHS] >> shift[grp]) & 3;
    static const int chan[4][3] = {{0, 4, 8}, {1, 5, -1}, {2, 6, -1}, {3, 7, -1}};
    g.adc_ch = (uint8_t)(sel < 3 ? chan[grp][sel] : -1);
    PIL_ADC_STARTED();
    uint8_t c2 = picsim_sfr[R_ADCON2];
    static const int tad_div[8] = {2, 8, 32, 0, 4, 16, 64, 0};
    int div = tad_div[c2 & 7];
    int64_t tad = div ? tosc(div) : secs(1e-6);          /* FRC ~1 us */
    int acq = 2 * ((c2 >> B_ADCON2_ACQT0) & 15);
    g.adc_done = vnow() + tad * (12 + acq);
}

/* the conversion time adc_start would give now (acquisition + 12 TAD) */
static int64_t adc_conv_ps(void)
{
    uint8_t c2 = picsim_sfr[R_ADCON2];
    static const int tad_div[8] = {2, 8, 32, 0, 4, 16, 64, 0};
    int div = tad_div[c2 & 7];
    int64_t tad = div ? tosc(div) : secs(1e-6);
    return tad * (12 + 2 * ((c2 >> B_ADCON2_ACQT0) & 15));
}

/* the special event trigger: it starts a conversion unless one is running (GO already set) */
static int sev_starts_conversion(void)
{
    return ((picsim_sfr[R_ADCON3] >> B_ADCON3_SSRC4) & 1) && g.adc_done == NEVER &&
           ((picsim_sfr[R_ADCON0] >> B_ADCON0_ADON) & 1);
}

static void sev_fire(void)
{
    g.sev_at = NEVER;
    if (sev_starts_conversion()) {
        hw_setbit(R_ADCON0, B_ADCON0_GO);
        adc_start();
    }
}

static int64_t cycle_ceil(int64_t t) { return g.cycle_t0 + (t - g.cycle_t0 + g.tcy_ps - 1) / g.tcy_ps * g.tcy_ps; }

/* processor twin (sev_lazy): a PWM period boundary that changes nothing the plant or the request
   lines see -- free-running edge-aligned time base, no buffered write to load (PTPER, PDCx,
   PTCON0: pwm_buf_stale), no synchronised override or cycle-by-cycle fault to apply, PTIF's
   interrupt off -- need not end a step: it is processed at its own time (pil_lazy_due) */
static int pwm_boundary_quiet(void)
{
    if (!g.sev_lazy || !g.pwm_on || ptmod() != 0 || g.pwm_buf_stale) return 0;
    if ((picsim_sfr[R_PIE3] >> B_PIR3_PTIF) & 1) return 0;
    if (((picsim_sfr[R_PWMCON1] >> B_PWMCON1_OSYNC) & 1) &&
        (g.ovd_act != picsim_sfr[R_OVDCOND] || g.ovs_act != picsim_sfr[R_OVDCONS])) return 0;
    if (g.flt_cbc && !g.flta_asserted) return 0;
    return 1;
}

/* the time the step must end at for the next PWM boundary: a quiet one's next special event's
   conversion end (single channel, started by the trigger) when it comes before the boundary
   after; otherwise the boundary itself */
static int64_t pwm_boundary_horizon(void)
{
    if (!pwm_boundary_quiet() || !((picsim_sfr[R_ADCON3] >> B_ADCON3_SSRC4) & 1) ||
        !((picsim_sfr[R_ADCON0] >> B_ADCON0_ADON) & 1) || ((picsim_sfr[R_ADCON0] >> B_ADCON0_ACSCH) & 1))
        return g.pwm_next;
    uint16_t sev = (uint16_t)(sfr16(R_SEVTCMPL, R_SEVTCMPH) & 0x0FFF);
    if (sev > g.ptper_act) return g.pwm_next;
    int64_t h = cycle_ceil(g.pwm_next + (int64_t)sev * tcy(ptckps())) + adc_conv_ps();
    return h < g.pwm_next + g.pwm_period ? h : g.pwm_next;
}

/* processor twin (sev_lazy): the time the step must end at for a pending special event -- the
   end of the conversion it starts (at its own cycle, cycle_t0 + n Tcy) when it starts one in
   single-channel mode, else the event itself */
static int64_t sev_horizon(void)
{
    if (!g.sev_lazy || !sev_starts_conversion() || ((picsim_sfr[R_ADCON0] >> B_ADCON0_ACSCH) & 1))
        return g.sev_at;
    return cycle_ceil(g.sev_at) + adc_conv_ps();
}

static void adc_complete(void)
{
    g.adc_done = NEVER;
    double vref = g.cfg.adc_vref_v > 0 ? g.cfg.adc_vref_v : 5.0;
    double v = analog_volts((int8_t)g.adc_ch) / vref * 1023.0;
    int code = v < 0.0 ? 0 : v > 1023.0 ? 1023 : (int)lround(v);
    if ((picsim_sfr[R_ADCON2] >> B_ADCON2_ADFM) & 1) {
        hw_write(R_ADRESH, (uint8_t)(code >> 8));
        hw_write(R_ADRESL, (uint8_t)code);
    } else {
        hw_write(R_ADRESH, (uint8_t)(code >> 2));
        hw_write(R_ADRESL, (uint8_t)((code & 3) << 6));
    }
    hw_setbit(R_PIR1, B_PIR1_ADIF);
    if ((picsim_sfr[R_ADCON0] >> B_ADCON0_ACONV) & 1) adc_start();
    else hw_clrbit(R_ADCON0, B_ADCON0_GO);
}

/* ------------------------------------------------------------ pin edges */

static void pin_edge(int port, int bit, int level)
{
    /* INT0..2 on RC3..RC5 */
    if (port == 2 && bit >= 3 && bit <= 5) {
        int n = bit - 3;
        static const int edg[3] = {B_INTCON2_INTEDG0, B_INTCON2_INTEDG1, B_INTCON2_INTEDG2};
        if (((picsim_sfr[R_INTCON2] >> edg[n]) & 1) == level) {
            if (n == 0) hw_setbit(R_INTCON, B_INTCON_INT0IF);
            else hw_setbit(R_INTCON3, n == 1 ? B_INTCON3_INT1IF : B_INTCON3_INT2IF);
        }
    }
    /* interrupt-on-change RB4..RB7 (inputs only) */
    if (port == 1 && bit >= 4 && ((picsim_sfr[R_TRISB] >> bit) & 1))
        hw_setbit(R_INTCON, B_INTCON_RBIF);
    /* input capture IC1..IC3 on RA2..RA4 when the QEI is off */
    if (port == 0 && bit >= 2 && bit <= 4 && qei_mode() == 0) {
        static const uint8_t con[3] = {R_CAP1CON, R_CAP2CON, R_CAP3CON};
        static const uint8_t bufl[3] = {R_CAP1BUFL, R_CAP2BUFL, R_CAP3BUFL};
        static const int flag[3] = {B_PIR3_IC1IF, B_PIR3_IC2QEIF, B_PIR3_IC3DRIF};
        int n = bit - 2, m = picsim_sfr[con[n]] & 15;
        /* 0001 rising, 0010 falling, 1000 every state change (hall mode) */
        if ((m == 1 && level) || (m == 2 && !level) || m == 8) {
            uint32_t c = timer_count(&g.t5);
            hw_write(bufl[n], (uint8_t)c);
            hw_write((uint8_t)(bufl[n] + 1), (uint8_t)(c >> 8));
            if ((picsim_sfr[con[n]] >> 6) & 1) timer_anchor(&g.t5, 0);   /* CAPxREN */
            hw_setbit(R_PIR3, flag[n]);
        }
    }
}

void pic_set_pins_from_plant(void)
{
    int code = g.hall_override >= 0 ? g.hall_override : plant_hall_code(&g.pp, g.ps.theta_rad);
    if (g.hall_override >= 0 && g.hall_override_until != NEVER && g.now >= g.hall_override_until) {
        g.hall_override = -1;
        code = plant_hall_code(&g.pp, g.ps.theta_rad);
    }
    uint8_t changed = (uint8_t)(code ^ g.hall_pins);
    g.hall_pins = (uint8_t)code;
    /* the levels on the pins already show the code (nothing else drives those pins) */
    if (!changed && g.hall_ext_ok && !g.hall_pin_shared) return;
    g.hall_ext_ok = 1;
    for (int k = 0; k < 3; k++) {
        pin_t pn = g.cfg.hall_pin[k];
        if (pn.port >= 5) continue;
        int lvl = (code >> k) & 1;
        uint8_t m = (uint8_t)(1u << pn.bit);
        if (lvl) g.ext[pn.port] |= m; else g.ext[pn.port] &= (uint8_t)~m;
        if ((changed >> k) & 1) pin_edge(pn.port, pn.bit, lvl);
    }
}

static void set_enc_pins(int64_t n)
{
    /* QEA = RA3, QEB = RA4, INDX = RA2 (not when the board puts the halls there) */
    if (g.halls_on_enc_pins) return;
    int ph = (int)(n & 3);                       /* n mod 4, also for n < 0 */
    int a = ph == 1 || ph == 2, b = ph == 2 || ph == 3;
    int64_t cpr = 4 * (int64_t)g.pp.encoder_lines;
    int idx = cpr > 0 && n == enc_rev(n, cpr) * cpr;
    uint8_t v = g.ext[0] & (uint8_t)~0x1C;
    g.ext[0] = (uint8_t)(v | (a << 3) | (b << 4) | (idx << 2));
}

void pic_after_plant_step(int64_t t_prev, double th_meas)
{
    double th_prev = g.th_meas_prev;
    g.th_meas_prev = th_meas;
    flt_update(t_prev);
    pic_set_pins_from_plant();
    if (g.pp.encoder_lines > 0 && !g.enc_frozen) {
        double cpr = 4.0 * g.pp.encoder_lines;
        int64_t n = (int64_t)floor(th_meas * cpr / (2.0 * M_PI));
        if (n != g.enc_count) {
            qei_counts(g.enc_count, n, th_prev, th_meas, (double)t_prev, (double)g.now);
            g.enc_count = n;
            set_enc_pins(n);
        }
    }
}

/* ------------------------------------------------------------ firmware writes */

/* side effects of a register the firmware changed */
static void reg_written(uint8_t idx)
{
    if (idx >= R_OVDCONS && idx <= R_PTCON0) g.legs_dirty = g.pwm_buf_stale = 1;   /* the PCPWM block */
    if (idx == R_FLTCONFIG) g.legs_dirty = 1;
    switch (idx) {
    case R_PTCON0: case R_PTCON1:
        pwm_time_base();
        break;
    case R_PTPERL: case R_PTPERH:
    case R_PDC0L: case R_PDC0H: case R_PDC1L: case R_PDC1H:
    case R_PDC2L: case R_PDC2H: case R_PDC3L: case R_PDC3H:
        if (!g.pwm_on) pwm_load_buffers();
        break;
    case R_OVDCOND: case R_OVDCONS: case R_PWMCON1:
        if (!((picsim_sfr[R_PWMCON1] >> B_PWMCON1_OSYNC) & 1) || !g.pwm_on) {
            g.ovd_act = picsim_sfr[R_OVDCOND];
            g.ovs_act = picsim_sfr[R_OVDCONS];
        }
        break;
    case R_FLTCONFIG:
        /* FLTAS is cleared by software (inactive mode) only while the pin is deasserted */
        if (!((picsim_sfr[R_FLTCONFIG] >> B_FLTCONFIG_FLTAS) & 1)) {
            if (g.flta_asserted && ((picsim_sfr[R_FLTCONFIG] >> B_FLTCONFIG_FLTAEN) & 1))
                hw_setbit(R_FLTCONFIG, B_FLTCONFIG_FLTAS);
            else g.flt_latched = 0;
        }
        break;
    case R_T0CON: t0_config(); break;
    case R_TMR0L: case R_TMR0H:
        timer_anchor(&g.t0, (uint32_t)(picsim_sfr[R_TMR0L] | ((g.t0.modulus > 256 ? picsim_sfr[R_TMR0H] : 0) << 8)));
        break;
    case R_T1CON: t1_config(); break;
    case R_TMR1L: case R_TMR1H: timer_anchor(&g.t1, sfr16(R_TMR1L, R_TMR1H)); break;
    case R_T2CON: case R_PR2: t2_config(); break;
    case R_TMR2: timer_anchor(&g.t2, picsim_sfr[R_TMR2]); break;
    case R_T5CON: case R_PR5L: case R_PR5H: t5_config(); break;
    case R_TMR5L: case R_TMR5H: timer_anchor(&g.t5, sfr16(R_TMR5L, R_TMR5H)); break;
    case R_QEICON:
        g.vel_pdec = 0;
        g.vel_last_t = g.now;
        break;
    case R_POSCNTL: case R_POSCNTH:          /* also CAP2BUF when the QEI is off */
        if (qei_mode()) {
            g.poscnt = sfr16(R_POSCNTL, R_POSCNTH);
            g.enc_index_count = g.enc_count - g.poscnt;
        }
        break;
    case R_TXSTA: case R_SPBRG: case R_SPBRGH: case R_BAUDCON:
        uart_config();
        break;
    case R_RCSTA:
        if (!((picsim_sfr[R_RCSTA] >> B_RCSTA_CREN) & 1)) {
            hw_clrbit(R_RCSTA, B_RCSTA_OERR);
        }
        if (!uart_on()) { g.rx_n = 0; hw_clrbit(R_PIR1, B_PIR1_RCIF); }
        uart_config();
        break;
    case R_TXREG: txreg_written(); break;
    case R_EECON1: eecon1_written(); break;
    case R_EECON2: eecon2_written(); break;
    case R_ADCON0:
        if (((picsim_sfr[R_ADCON0] >> B_ADCON0_GO) & 1) && g.adc_done == NEVER) adc_start();
        if (!((picsim_sfr[R_ADCON0] >> B_ADCON0_ADON) & 1)) { g.adc_done = NEVER; hw_clrbit(R_ADCON0, B_ADCON0_GO); }
        break;
    default:
        break;
    }
}

/* bits the firmware cannot write: the hardware state wins */
static void enforce_readonly(void)
{
    int txen = (picsim_sfr[R_TXSTA] >> B_TXSTA_TXEN) & 1;
    hw_putbit(R_PIR1, B_PIR1_TXIF, txen && !g.txreg_full);     /* TXREG empty (with TXEN) */
    hw_putbit(R_PIR1, B_PIR1_RCIF, g.rx_n > 0);
    hw_putbit(R_TXSTA, B_TXSTA_TRMT, !g.tx_busy);
}

void picsim_sfr_written(uint16_t addr)
{
    uint8_t idx = (uint8_t)(addr >= 0xF00 ? addr - 0xF00 : addr);
    /* docs/firmware.md: RCSTA is notified after CREN was toggled 0 -> 1, which
       clears an overrun (the 0 in between is not visible to the model) */
    if (idx == R_RCSTA && ((picsim_sfr[R_RCSTA] >> B_RCSTA_CREN) & 1))
        picsim_sfr[R_RCSTA] &= (uint8_t)~(1u << B_RCSTA_OERR);
    g.shadow[idx] = picsim_sfr[idx];
    reg_written(idx);
    if (idx == R_PIR1 || idx == R_TXSTA) enforce_readonly();
}

static void port_refresh(uint8_t idx);

void picsim_sfr_read(uint16_t addr)
{
    uint8_t idx = (uint8_t)(addr >= 0xF00 ? addr - 0xF00 : addr);
    if (idx >= R_PORTA && idx <= R_PORTE) {
        /* the shim notifies every port access: the read sees the pins now, with the
           TRIS/LAT/ANSEL the firmware has set so far in this call */
        port_refresh(idx);
    } else if (idx == R_RCREG) {
        rcreg_read();
    } else if (idx == R_ADCON0 || idx == R_EECON1) {
        /* a poll of GO_DONE or WR: the firmware spends POLL_TCY per iteration,
           and an operation due by then completes */
        g.call_cycles += POLL_TCY;
        if (idx == R_ADCON0 && g.adc_done != NEVER && g.adc_done <= vnow()) adc_complete();
        if (idx == R_EECON1 && g.ee_done != NEVER && g.ee_done <= vnow()) ee_complete();
    }
}

/* registers the model changes with time, written before each firmware call */
static inline void sync_write(uint8_t idx, uint8_t v) { picsim_sfr[idx] = v; g.shadow[idx] = v; }

static void port_refresh(uint8_t idx)
{
    static const uint8_t port[5] = {R_PORTA, R_PORTB, R_PORTC, R_PORTD, R_PORTE};
    for (int k = 0; k < 5; k++)
        if (port[k] == idx) { sync_write(idx, port_value(k)); return; }
}

void pic_sync_inputs(void)
{
    static const uint8_t port[5] = {R_PORTA, R_PORTB, R_PORTC, R_PORTD, R_PORTE};
    for (int k = 0; k < 5; k++) sync_write(port[k], port_value(k));
    uint32_t c;
    if (g.t0.on) {
        c = timer_count(&g.t0);
        sync_write(R_TMR0L, (uint8_t)c);
        sync_write(R_TMR0H, (uint8_t)(g.t0.modulus > 256 ? c >> 8 : picsim_sfr[R_TMR0H]));
    }
    if (g.t1.on) {
        c = timer_count(&g.t1);
        sync_write(R_TMR1L, (uint8_t)c); sync_write(R_TMR1H, (uint8_t)(c >> 8));
    }
    if (g.t2.on) sync_write(R_TMR2, (uint8_t)timer_count(&g.t2));
    if (g.t5.on) {
        c = timer_count(&g.t5);
        sync_write(R_TMR5L, (uint8_t)c); sync_write(R_TMR5H, (uint8_t)(c >> 8));
    }
    if (qei_mode()) {
        sync_write(R_POSCNTL, (uint8_t)g.poscnt);
        sync_write(R_POSCNTH, (uint8_t)(g.poscnt >> 8));
    }
    if (g.pwm_on && g.pwm_period > 0) {
        int64_t tick = tcy(ptckps());
        int64_t n = (g.now - g.pwm_start) / tick;
        if (ptmod() >= 2) {                        /* up/down: 0 .. PTPER .. 0 */
            int64_t half = g.ptper_act;
            n = n <= half ? n : 2 * half - n;
            int down = (g.now - g.pwm_start) / tick > half;
            sync_write(R_PTCON1, (uint8_t)((picsim_sfr[R_PTCON1] & ~(1u << B_PTCON1_PTDIR)) | (down << B_PTCON1_PTDIR)));
        }
        sync_write(R_PTMRL, (uint8_t)n);
        sync_write(R_PTMRH, (uint8_t)((n >> 8) & 0x0F));
    }
}

void pic_process_writes(void)
{
    /* the changed registers, in address order: compared 8 bytes at a time (a call
       changes a few registers or none) */
    uint8_t changed[256];
    int n = 0;
    const uint8_t *sfr = (const uint8_t *)picsim_sfr;
    for (int w = 0; w < 256; w += 8) {
        uint64_t a, b;
        memcpy(&a, g.shadow + w, 8);
        memcpy(&b, sfr + w, 8);
        if (a == b) continue;
        for (int i = w; i < w + 8; i++)
            if (g.shadow[i] != sfr[i]) changed[n++] = (uint8_t)i;
    }
    if (n == 0) return;
    /* time base first, then everything else in address order */
    int pt = g.shadow[R_PTCON1] != picsim_sfr[R_PTCON1] || g.shadow[R_PTCON0] != picsim_sfr[R_PTCON0];
    memcpy(g.shadow, sfr, sizeof g.shadow);
    int did_pwm_buf = 0;
    for (int k = 0; k < n; k++) {
        uint8_t i = changed[k];
        if (i == R_PTCON0 || i == R_PTCON1) continue;
        if ((i >= R_PDC3H && i <= R_PTPERL)) { if (did_pwm_buf) continue; did_pwm_buf = 1; }
        reg_written(i);
    }
    if (pt) pwm_time_base();
    enforce_readonly();
}

/* ------------------------------------------------------------ events */

int64_t pic_next_event(void)
{
    int64_t t = g.sev_lazy ? pwm_boundary_horizon() : g.pwm_next;
    if (g.t0.on && g.t0.next < t) t = g.t0.next;
    if (g.t1.on && g.t1.next < t) t = g.t1.next;
    if (g.t2.on) { int64_t f = t2_flag_time(); if (f < t) t = f; }
    if (g.t5.on && g.t5.next < t) t = g.t5.next;
    if (g.tx_done < t) t = g.tx_done;
    if (g.rx_arrive < t) t = g.rx_arrive;
    if (g.ee_done < t) t = g.ee_done;
    if (g.adc_done < t) t = g.adc_done;
    if (g.sev_at < t) { int64_t h = sev_horizon(); if (h < t) t = h; }
    return t;
}

void pic_events_due(void)
{
    if (g.tx_done <= g.now) tx_complete();
    if (g.rx_arrive <= g.now) rx_arrival();
    pic_uart_rx_schedule();
    if (g.t0.on && g.t0.next <= g.now) timer_event(&g.t0, 0);
    if (g.t1.on && g.t1.next <= g.now) timer_event(&g.t1, 1);
    while (g.t2.on && g.t2.next <= g.now) timer_event(&g.t2, 2);
    if (g.t5.on && g.t5.next <= g.now) timer_event(&g.t5, 5);
    if (g.ee_done <= g.now) ee_complete();
    if (g.adc_done <= g.now) adc_complete();
    if (g.sev_at <= g.now) sev_fire();
    if (g.pwm_on && g.pwm_next <= g.now) pwm_boundary();
}

/* ------------------------------------------------------------ interrupts */

typedef struct { uint8_t fr, fb, er, eb, pr, pb; } irq_src_t;   /* pr = 0: always high */

static const irq_src_t core_src[] = {
    {R_INTCON, B_INTCON_TMR0IF, R_INTCON, B_INTCON_TMR0IE, R_INTCON2, B_INTCON2_TMR0IP},
    {R_INTCON, B_INTCON_INT0IF, R_INTCON, B_INTCON_INT0IE, 0, 0},
    {R_INTCON, B_INTCON_RBIF, R_INTCON, B_INTCON_RBIE, R_INTCON2, B_INTCON2_RBIP},
    {R_INTCON3, B_INTCON3_INT1IF, R_INTCON3, B_INTCON3_INT1IE, R_INTCON3, B_INTCON3_INT1IP},
    {R_INTCON3, B_INTCON3_INT2IF, R_INTCON3, B_INTCON3_INT2IE, R_INTCON3, B_INTCON3_INT2IP},
};

/* request lines (IRQ_LINE_HIGH | IRQ_LINE_LOW) from the flags, enables and priorities
   (DS39616 Fig. 10-1), before GIEH/GIEL: with IPEN = 0 every source is high and the
   peripherals need PEIE (GIEL) */
unsigned pic_irq_lines(void)
{
    int ipen = (picsim_sfr[R_RCON] >> B_RCON_IPEN) & 1;
    unsigned lines = 0;
    for (unsigned k = 0; k < sizeof core_src / sizeof core_src[0]; k++) {
        const irq_src_t *s = &core_src[k];
        if (!(((picsim_sfr[s->fr] >> s->fb) & 1) && ((picsim_sfr[s->er] >> s->eb) & 1))) continue;
        lines |= (!ipen || s->pr == 0 || ((picsim_sfr[s->pr] >> s->pb) & 1)) ? IRQ_LINE_HIGH : IRQ_LINE_LOW;
    }
    static const uint8_t pir[3] = {R_PIR1, R_PIR2, R_PIR3}, pie[3] = {R_PIE1, R_PIE2, R_PIE3},
                         ipr[3] = {R_IPR1, R_IPR2, R_IPR3};
    for (int k = 0; k < 3; k++) {
        uint8_t act = (uint8_t)(picsim_sfr[pir[k]] & picsim_sfr[pie[k]]);
        if (!act) continue;
        if (!ipen) { if ((picsim_sfr[R_INTCON] >> B_INTCON_GIEL) & 1) lines |= IRQ_LINE_HIGH; continue; }
        if (act & picsim_sfr[ipr[k]]) lines |= IRQ_LINE_HIGH;
        if (act & (uint8_t)~picsim_sfr[ipr[k]]) lines |= IRQ_LINE_LOW;
    }
    return lines;
}

/* 0: nothing to take; 1: the high vector; 2: the low vector */
int pic_irq_pending(void)
{
    int ipen = (picsim_sfr[R_RCON] >> B_RCON_IPEN) & 1;
    int gieh = (picsim_sfr[R_INTCON] >> B_INTCON_GIEH) & 1;
    int giel = (picsim_sfr[R_INTCON] >> B_INTCON_GIEL) & 1;
    if (!gieh) return 0;
    unsigned lines = pic_irq_lines();
    if (lines & IRQ_LINE_HIGH) return 1;
    if ((lines & IRQ_LINE_LOW) && ipen && giel) return 2;
    return 0;
}

/* The twin's event loop and its C API (called from Python through ctypes).
 *
 * One loop iteration: find the next event (PWM period boundary, timer wrap,
 * UART bit-frame completion, EEPROM/ADC completion, predicted hall edge,
 * load-profile knot, trace sample, injection end), advance the plant to it
 * with the inverter state of the PCPWM, update the pins (halls, encoder,
 * FLTA comparator), process the due peripheral events, deliver pending
 * interrupts to the firmware's handlers, then run one pass of the firmware's
 * main loop (fw_poll).  Firmware code takes zero simulated time.
 */
#include "pic_internal.h"

#include <math.h>
#include <string.h>

twin_t g;

#define MAIN_LOOP_MAX_PS 1000000000LL    /* 1 ms */

/* ------------------------------------------------------------ noise */

static uint64_t rng_next(void)
{
    /* xorshift64* */
    uint64_t x = g.rng;
    x ^= x >> 12; x ^= x << 25; x ^= x >> 27;
    g.rng = x;
    return x * 0x2545F4914F6CDD1DULL;
}

static double rng_gauss(void)
{
    double u1 = ((rng_next() >> 11) + 0.5) * (1.0 / 9007199254740992.0);
    double u2 = ((rng_next() >> 11) + 0.5) * (1.0 / 9007199254740992.0);
    return sqrt(-2.0 * log(u1)) * cos(2.0 * M_PI * u2);
}

static double theta_measured(void)
{
    if (!(g.cfg.speed_noise_rad_s > 0.0) || !(g.cfg.noise_sample_s > 0.0))
        return g.ps.theta_rad;
    int64_t per = (int64_t)llround(g.cfg.noise_sample_s * PS_PER_S);
    int64_t b = g.now / per;
    if (b != g.noise_bucket) {
        g.noise_bucket = b;
        /* angle jitter whose differences over one speed-loop period have the
           requested speed standard deviation */
        g.noise_theta = rng_gauss() * g.cfg.speed_noise_rad_s * g.cfg.noise_sample_s / sqrt(2.0);
    }
    return g.ps.theta_rad + g.noise_theta;
}

/* ------------------------------------------------------------ firmware calls */
#ifndef TWIN_PIL

static void fw_call(void (*fn)(void))
{
    pic_sync_inputs();
    g.call_cycles = 0;
    g.in_fw = 1;
    fn();
    g.in_fw = 0;
    g.irq_dirty = 1;            /* the firmware may have changed any flag or enable */
    pic_process_writes();
}

static int service_irqs(void)
{
    for (int guard = 0;; guard++) {
        /* pic_irq_pending() reads only SFRs: none changed since it found nothing, nothing to take */
        if (!g.irq_dirty) return 0;
        int v = pic_irq_pending();
        if (!v) { g.irq_dirty = 0; return 0; }
        g.poll_due = 1;
        if (guard >= 1000) {
            g.errors |= TWIN_ERR_IRQ_STORM;
            return -1;
        }
        if (v == 1) {
            /* the core clears GIEH on entry; RETFIE sets it again */
            hw_clrbit(R_INTCON, B_INTCON_GIEH);
            fw_call(fw_isr_high);
            hw_setbit(R_INTCON, B_INTCON_GIEH);
            g.isr_high_calls++;
        } else {
            hw_clrbit(R_INTCON, B_INTCON_GIEL);
            fw_call(fw_isr_low);
            hw_setbit(R_INTCON, B_INTCON_GIEL);
            g.isr_low_calls++;
        }
    }
}

#endif

/* ------------------------------------------------------------ load */

static double load_at(double t_s)
{
    int n = g.load_n;
    if (n <= 0) return 0.0;
    if (n == 1) return g.load_v[0];
    if (t_s <= g.load_t[0]) return g.load_v[0];
    if (t_s >= g.load_t[n - 1]) return g.load_v[n - 1];
    int k = g.load_k > 0 ? g.load_k : 1;
    while (k < n - 1 && g.load_t[k] < t_s) k++;
    while (k > 1 && g.load_t[k - 1] > t_s) k--;
    double t0 = g.load_t[k - 1], t1 = g.load_t[k];
    double f = t1 > t0 ? (t_s - t0) / (t1 - t0) : 1.0;
    return g.load_v[k - 1] + f * (g.load_v[k] - g.load_v[k - 1]);
}

static int64_t next_load_knot(void)
{
    if (g.load_k >= g.load_n) return NEVER;
    if (g.load_next_ps > g.now) return g.load_next_ps;        /* cached */
    double t = (double)g.now / PS_PER_S;
    while (g.load_k < g.load_n && g.load_t[g.load_k] <= t) g.load_k++;
    if (g.load_k >= g.load_n) return NEVER;
    int64_t k = (int64_t)llround(g.load_t[g.load_k] * PS_PER_S);
    g.load_next_ps = k > g.now ? k : g.now + 1;
    return g.load_next_ps;
}

/* ------------------------------------------------------------ hall edges */

static int64_t next_hall_edge(void)
{
    /* hall edges sit every 60 electrical degrees from hall_offset; keep the next one
       in the direction of motion and divide the angle still to go by the speed */
    double we = g.pp.pole_pairs * g.ps.w_rad_s;
    if (fabs(we) < 1e-3) return NEVER;
    int dir = we > 0 ? 1 : -1;
    double th = g.pp.pole_pairs * g.ps.theta_rad - g.pp.hall_offset_rad;
    if (dir != g.edge_dir || (dir > 0 ? th >= g.edge_th : th <= g.edge_th) ||
        fabs(g.edge_th - th) > M_PI / 3.0 + 1e-9) {
        double sec = M_PI / 3.0, x = th / sec;
        g.edge_th = (dir > 0 ? floor(x) + 1.0 : ceil(x) - 1.0) * sec;
        g.edge_dir = dir;
    }
    double dt = (g.edge_th - th) / we;
    if (!(dt >= 0.0) || dt > 1.0) return NEVER;
    return g.now + (int64_t)(dt * PS_PER_S) + 1000;          /* +1 ns: land past the edge */
}

/* the end of the next step of the event loop (SIL and processor twin): the first of the
   peripherals' next event, a PWM period (or max_off), a hall edge, a load knot, the trace,
   the end of an injected hall code or overcurrent, and t_end; always after now */
static int64_t next_step_end(int64_t t_end, int64_t max_off)
{
    int64_t tn = pic_next_event();
    int64_t cap = g.now + (g.pwm_on && g.pwm_period > 0 && g.pwm_period < max_off ? g.pwm_period : max_off);
    if (cap < tn) tn = cap;
    int64_t e = next_hall_edge();
    if (e < tn) tn = e;
    e = next_load_knot();
    if (e < tn) tn = e;
    if (g.trace_next < tn) tn = g.trace_next;
    if (g.hall_override >= 0 && g.hall_override_until < tn) tn = g.hall_override_until;
    if (g.oc_until > g.now && g.oc_until < tn) tn = g.oc_until;
    if (t_end < tn) tn = t_end;
    if (tn <= g.now) tn = g.now + 1;
    return tn;
}

/* ------------------------------------------------------------ trace */

static void trace_record(void)
{
    if (!g.trace || g.trace_n >= g.trace_cap) return;
    trace_rec_t *r = &g.trace[g.trace_n++];
    double dmax = 0.0;
    for (int x = 0; x < 3; x++) if (g.leg[x].f_hi > dmax) dmax = g.leg[x].f_hi;
    r->t_s = (double)g.now / PS_PER_S;
    r->w_rad_s = g.ps.w_rad_s;
    r->theta_rad = g.ps.theta_rad;
    r->i_a = g.ps.i_a[0]; r->i_b = g.ps.i_a[1]; r->i_c = g.ps.i_a[2];
    r->i_bus_a = g.ps.i_bus_a;
    r->torque_e_n_m = g.ps.torque_e_n_m;
    r->torque_load_n_m = g.ps.torque_load_n_m;
    r->v_a = g.ps.v_term[0]; r->v_b = g.ps.v_term[1]; r->v_c = g.ps.v_term[2];
    r->duty_max = dmax;
    r->hall = g.hall_pins;
    r->fault = (double)(g.flt_latched | (g.flt_cbc << 1) | (g.flta_asserted << 2));
    r->v_bus_v = plant_bus_voltage(&g.pp, &g.ps);
}

/* ------------------------------------------------------------ API */

int twin_sizeof(int which)
{
    switch (which) {
    case 0: return (int)sizeof(twin_config_t);
    case 1: return (int)sizeof(twin_state_t);
    case 2: return (int)sizeof(trace_rec_t);
    default: return plant_sizeof(which - 3);
    }
}

int twin_init(const twin_config_t *cfg)
{
    if (cfg->abi_version != TWIN_ABI_VERSION) return -1;
    memset(&g, 0, sizeof g);
    g.cfg = *cfg;
    g.pp = cfg->plant;
    plant_reset(&g.ps);
    g.ps.v_bus_v = g.pp.bus_voltage_v;       /* the capacitor charged to the supply */
    plant_cache_reset(&g.pcache);
    g.tosc_ps = (int64_t)llround(PS_PER_S / cfg->fosc_hz);
    g.tcy_ps = 4 * g.tosc_ps;
    g.host_frame_ps = (int64_t)llround(10.0 * PS_PER_S / cfg->host_baud);
    g.hall_override = -1;
    g.hall_override_until = NEVER;
    g.oc_until = -1;
    g.outputs_off_ps = -1;
    g.load_n = 1;
    g.load_t[0] = 0.0;
    g.load_v[0] = 0.0;
    g.rng = cfg->seed ? cfg->seed : 0x9E3779B97F4A7C15ULL;
    g.noise_bucket = -1;
    memset(g.ee, 0xFF, sizeof g.ee);          /* erased */
    g.ext[2] = 0x80;                          /* RX idle high */
    g.trace_next = NEVER;
    g.legs_dirty = 1;
    g.pwm_buf_stale = 1;
    g.irq_dirty = 1;
    for (int k = 0; k < 3; k++) {
        pin_t pn = cfg->hall_pin[k];
        if (pn.port == 0 && pn.bit >= 2 && pn.bit <= 4) g.halls_on_enc_pins = 1;
        if (pn.port < 5 && ((pn.port == cfg->flta_pin.port && pn.bit == cfg->flta_pin.bit) ||
                            (pn.port == 2 && pn.bit == 7)))          /* RC7 = RX, idle high */
            g.hall_pin_shared = 1;
    }
    g.initialised = 1;
    return 0;
}

/* the chip's reset as the peripherals and pins see it, the motor keeping its state: the hall and
 * encoder inputs from the rotor's angle, the bridge off (both twins' power-on) */
static void board_reset(void)
{
    pic_reset();
    g.legs_dirty = 1;
    g.hall_pins = (uint8_t)plant_hall_code(&g.pp, g.ps.theta_rad);
    pic_set_pins_from_plant();
    if (g.pp.encoder_lines > 0) {
        g.enc_count = (int64_t)floor(theta_measured() * 4.0 * g.pp.encoder_lines / (2.0 * M_PI));
        g.enc_index_count = g.enc_count;
    }
    g.th_meas_prev = theta_measured();
    pic_after_plant_step(g.now, theta_measured());
    pic_compute_legs();
}

#ifndef TWIN_PIL
/* reset the chip and run fw_init (the motor keeps its state) */
int twin_power_on(void)
{
    if (!g.initialised) return TWIN_ERR_NOT_INIT;
    board_reset();
    fw_call(fw_init);
    service_irqs();
    return (int)g.errors;
}

int twin_run_until(int64_t t_end)
{
    if (!g.initialised) return TWIN_ERR_NOT_INIT;
    int64_t max_off = (int64_t)llround((g.cfg.max_step_s > 0 ? g.cfg.max_step_s : 50e-6) * PS_PER_S);
    g.irq_dirty = 1;
    while (g.now < t_end && !g.errors) {
        int64_t tn = next_step_end(t_end, max_off);

        pic_compute_legs();
        double h = (double)(tn - g.now) / PS_PER_S;
        double tmid = ((double)g.now + 0.5 * (double)(tn - g.now)) / PS_PER_S;
        plant_step_cached(&g.pp, &g.ps, g.leg, load_at(tmid), h, &g.pcache);
        int64_t t_prev = g.now;
        g.now = tn;
        pic_after_plant_step(t_prev, theta_measured());
        pic_events_due();
        if (g.trace_next <= g.now) {
            trace_record();
            g.trace_next += g.trace_period;
        }
        if (service_irqs()) break;
        /* the main loop runs after anything it could see changed (an interrupt, a hardware
           flag or a byte), and at least every MAIN_LOOP_MAX_PS */
        if (g.now >= g.main_busy_until && (g.poll_due || g.now - g.last_poll >= MAIN_LOOP_MAX_PS)) {
            g.poll_due = 0;
            g.last_poll = g.now;
            fw_call(fw_poll);
            g.poll_calls++;
            /* a blocking wait in the main loop (EEPROM write) holds it for that long */
            if (g.call_cycles) g.main_busy_until = g.now + g.call_cycles * g.tcy_ps;
            if (service_irqs()) break;
        }
    }
    return (int)g.errors;
}
#endif

void twin_get_state(twin_state_t *o)
{
    memset(o, 0, sizeof *o);
    o->plant = g.ps;
    o->now_ps = g.now;
    o->hall_code = g.hall_pins;
    o->hall_true = (uint8_t)plant_hall_code(&g.pp, g.ps.theta_rad);
    o->flta_asserted = (uint8_t)g.flta_asserted;
    int act = 0;
    for (int x = 0; x < 3; x++) {
        o->leg[x] = g.leg[x];
        o->gate_hi[x] = g.gate_hi[x];
        o->gate_lo[x] = g.gate_lo[x];
        if (g.leg[x].f_hi > 0.0 || g.leg[x].f_lo > 0.0) act = 1;
    }
    o->pwm_outputs_active = (uint8_t)act;
    o->outputs_off_ps = g.outputs_off_ps;
    o->enc_count = (int32_t)g.enc_count;
    o->pwm_fault_latched = (uint8_t)((picsim_sfr[R_FLTCONFIG] >> B_FLTCONFIG_FLTAS) & 1);
    o->shoot_through = g.shoot_through;
    o->uart_rx_overruns = g.rx_overruns;
    o->uart_rx_framing = g.rx_framing;
    o->isr_high_calls = g.isr_high_calls;
    o->isr_low_calls = g.isr_low_calls;
    o->poll_calls = g.poll_calls;
    o->eeprom_writes = g.ee_writes;
    o->eeprom_rejected = g.ee_rejected;
    o->errors = g.errors;
    for (int k = 0; k < 4; k++) o->duty[k] = g.duty[k];
    o->pwm_period_s = g.pwm_on ? (double)g.pwm_period / PS_PER_S : 0.0;
    o->board_baud = pic_board_baud();
    o->dead_time_s = g.dead_frac * o->pwm_period_s;
}

void twin_set_load_table(const double *t_s, const double *torque, int32_t n)
{
    if (n < 1) { g.load_n = 1; g.load_t[0] = 0.0; g.load_v[0] = 0.0; g.load_k = 0; return; }
    if (n > 1024) n = 1024;
    for (int k = 0; k < n; k++) { g.load_t[k] = t_s[k]; g.load_v[k] = torque[k]; }
    g.load_n = n;
    g.load_k = 0;
    g.load_next_ps = -1;
}

int twin_uart_host_write(const uint8_t *buf, int32_t n)
{
    int k = 0;
    for (; k < n; k++) {
        uint32_t nt = (g.hin_tail + 1) & (HOSTQ - 1);
        if (nt == g.hin_head) break;
        g.hq_in[g.hin_tail] = buf[k];
        g.hin_tail = nt;
    }
    pic_uart_rx_schedule();
    return k;
}

/* drop the host bytes the board has not started to receive (the sender went away);
   a byte already on the wire completes.  Returns how many were dropped. */
int twin_uart_host_flush(void)
{
    int n = (int)((g.hin_tail - g.hin_head) & (HOSTQ - 1));
    g.hin_head = g.hin_tail;
    return n;
}

int twin_uart_host_read(uint8_t *buf, int32_t max)
{
    int k = 0;
    while (k < max && g.hout_head != g.hout_tail) {
        buf[k++] = g.hq_out[g.hout_head];
        g.hout_head = (g.hout_head + 1) & (HOSTQ - 1);
    }
    return k;
}

int twin_uart_host_pending(void)
{
    return (int)((g.hin_tail - g.hin_head) & (HOSTQ - 1)) + (g.rx_arrive != NEVER);
}

void twin_inject(int32_t kind, double value, double duration_s)
{
    int64_t until = duration_s > 0.0 ? g.now + (int64_t)llround(duration_s * PS_PER_S) : NEVER;
    switch (kind) {
    case INJ_HALL:
        g.hall_override = value < 0.0 ? -1 : ((int)value & 7);
        g.hall_override_until = until;
        pic_set_pins_from_plant();
        break;
    case INJ_OVERCURRENT:
        g.oc_until = duration_s > 0.0 ? until : g.now + (int64_t)llround(1e-3 * PS_PER_S);
        break;
    case INJ_LOCK_ROTOR:
        g.ps.locked = value != 0.0;
        if (g.ps.locked) g.ps.w_rad_s = 0.0;
        break;
    case INJ_ENCODER:
        g.enc_frozen = value == 0.0;
        break;
    case INJ_BUS_VOLTAGE:
        if (value > 0.0) g.pp.bus_voltage_v = value;
        break;
    default:
        break;
    }
}

void twin_eeprom_get(uint8_t *buf) { memcpy(buf, g.ee, 256); }
void twin_eeprom_set(const uint8_t *buf) { memcpy(g.ee, buf, 256); }

void twin_trace_start(double period_s, trace_rec_t *buf, int32_t capacity)
{
    g.trace = buf;
    g.trace_cap = capacity;
    g.trace_n = 0;
    g.trace_period = (int64_t)llround(period_s * PS_PER_S);
    g.trace_next = buf && g.trace_period > 0 ? g.now : NEVER;
}

int twin_trace_count(void) { return g.trace_n; }

uint8_t twin_sfr_get(uint16_t idx) { return picsim_sfr[idx & 0xFF]; }

void twin_set_plant_state(double w_rad_s, double theta_rad)
{
    g.ps.w_rad_s = w_rad_s;
    g.ps.theta_rad = theta_rad;
    g.ps.te_valid = 0;
    g.edge_dir = 0;
    pic_set_pins_from_plant();
}

#ifdef TWIN_PIL
#include "pil.c"
#endif
int pil_sizeof(void)
{
#ifdef TWIN_PIL
    return (int)sizeof(pil_stats_t);
#else
    return 0;
#endif
}

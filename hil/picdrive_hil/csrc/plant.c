/* BLDC plant: three-phase wye winding, back-EMF, six-switch inverter with
 * body diodes, rotor mechanics.  docs/twin.md "Plant" gives the equations;
 * tests/support/plant_reference.py is the scipy model of the same equations
 * that the tests compare this against.
 *
 * Phase x (a, b, c):   L di_x/dt = v_x - v_n - e_x - R i_x,   sum i_x = 0
 * back-EMF:            e_x = lambda_m * P * w * f(P theta - k 2pi/3)
 *                      f = 120-degree flat-top trapezoid, or sin (2016 eq 2)
 * torque:              T_e = P lambda_m sum f_x i_x
 * rotor:               J dw/dt = T_e - B w - T_load
 *
 * Inverter leg x over a step (PWM-period average): the high switch conducts
 * a fraction f_hi, the low switch f_lo, neither the rest (dead time, off
 * time, floating phase); then the body diode carrying the current sets the
 * node: 0 V for i_x > 0, V_bus for i_x < 0, and with i_x = 0 the leg is open
 * and its node floats at v_n + e_x.  So each leg is a monotone set-valued
 * source  v_x(i) = v+ (i > 0), v- (i < 0), [v+, v-] (i = 0)  with
 *   v+ = V_bus f_hi - V_d f_off,   v- = V_bus (1 - f_lo) + V_d f_off.
 * A step of length h holds v+, v-, e constant (e at mid-step) and solves
 * the RL equations exactly (exponential) with the diode states taken at the
 * end of the step (implicit): the star-point voltage v_n is the root of a
 * piecewise-linear monotone function, found exactly.  A floating phase's
 * decay through the diodes, discontinuous conduction and diode
 * rectification with all switches off all come out of the same rule.
 */
#include "twin.h"

#include <math.h>
#include <string.h>

#define TWO_PI 6.283185307179586476925286766559
#define PI_3   1.0471975511965977461542144610932
#define PI_6   0.52359877559829887307710723054658

static double wrap2pi(double x)
{
    x -= TWO_PI * floor(x * (1.0 / TWO_PI));
    return x >= TWO_PI ? x - TWO_PI : (x < 0.0 ? 0.0 : x);
}

/* trapezoid of an angle already in [0, 2pi) */
static double trap_w(double th)
{
    double t = th + PI_6;
    if (t >= TWO_PI) t -= TWO_PI;
    if (t < PI_3) return (t - PI_6) / PI_6;
    if (t < M_PI) return 1.0;
    if (t < M_PI + PI_3) return 1.0 - (t - M_PI) / PI_6;
    return -1.0;
}

double plant_emf_shape(const plant_params_t *p, double th_e)
{
    if (p->emf_shape == EMF_SINUSOIDAL)
        return sin(th_e);
    /* trapezoid: rising zero at 0, flat +1 over [30, 150] deg, flat -1 over [210, 330] */
    double t = wrap2pi(th_e + PI_6);
    if (t < PI_3) return (t - PI_6) / PI_6;
    if (t < M_PI) return 1.0;
    if (t < M_PI + PI_3) return 1.0 - (t - M_PI) / PI_6;
    return -1.0;
}

double plant_theta_e(const plant_params_t *p, const plant_state_t *s)
{
    return (double)p->pole_pairs * s->theta_rad;
}

/* sin and cos of th_e for the sinusoidal EMF, without libm in the common path: from an
 * anchor angle (libm's sin and cos there) turned by the difference d, |d| < SIN_REACH,
 * with the Taylor series of sin d (to d^11) and cos d (to d^10), truncation below 1e-20;
 * the result is within a few units in the last place of libm's (tests/test_plant.py).  The
 * anchor moves to th_e when th_e is out of reach: at the 2016 motor's 400 rpm the angle
 * advances ~0.01 rad a PWM period, and one pair of libm calls serves ~20 evaluations. */
#define SIN_REACH 0.1
static inline __attribute__((always_inline)) void sin_cos(double th_e, plant_cache_t *cc, double *s, double *c)
{
    double d = th_e - cc->sin_ref;
    if (!(fabs(d) < SIN_REACH)) {
        cc->sin_ref = th_e;
        cc->sin_s = sin(th_e);
        cc->sin_c = cos(th_e);
        *s = cc->sin_s;
        *c = cc->sin_c;
        return;
    }
    double d2 = d * d;
    double sd = d * (1.0 - d2 * (1.0 / 6.0) * (1.0 - d2 * (1.0 / 20.0) * (1.0 - d2 * (1.0 / 42.0) *
                     (1.0 - d2 * (1.0 / 72.0) * (1.0 - d2 * (1.0 / 110.0))))));
    double cd = 1.0 - d2 * 0.5 * (1.0 - d2 * (1.0 / 12.0) * (1.0 - d2 * (1.0 / 30.0) *
                     (1.0 - d2 * (1.0 / 56.0) * (1.0 - d2 * (1.0 / 90.0)))));
    *s = cc->sin_s * cd + cc->sin_c * sd;
    *c = cc->sin_c * cd - cc->sin_s * sd;
}

static inline __attribute__((always_inline)) void shapes(const plant_params_t *p, double th_e, double f[3],
                                                         plant_cache_t *cc)
{
    if (p->emf_shape == EMF_SINUSOIDAL) {
        double s, c;
        sin_cos(th_e, cc, &s, &c);
        const double h = 0.86602540378443864676;          /* sin 120 deg */
        f[0] = s;
        f[1] = -0.5 * s - h * c;                          /* sin(th - 120) */
        f[2] = -0.5 * s + h * c;                          /* sin(th + 120) */
        return;
    }
    double a = wrap2pi(th_e);
    double b = a - 2.0 * PI_3; if (b < 0.0) b += TWO_PI;
    double c = a + 2.0 * PI_3; if (c >= TWO_PI) c -= TWO_PI;
    f[0] = trap_w(a);
    f[1] = trap_w(b);
    f[2] = trap_w(c);
}

/* for tests: sin and cos of th the way the plant computes them from an anchor at `anchor`
   (|th - anchor| < SIN_REACH; else from libm at th) */
void plant_sin_cos_probe(double anchor, double th, double out[2])
{
    plant_cache_t cc;
    plant_cache_reset(&cc);
    double s, c;
    sin_cos(anchor, &cc, &s, &c);
    sin_cos(th, &cc, &out[0], &out[1]);
}

int plant_hall_code(const plant_params_t *p, double theta_mech)
{
    double x = wrap2pi((double)p->pole_pairs * theta_mech - p->hall_offset_rad);
    int code = 0;
    for (int k = 0; k < 3; k++) {
        double y = x - k * p->hall_spacing_rad;
        if (y < 0.0) y += TWO_PI;
        if (y < M_PI) code |= 1 << k;
    }
    return code;
}

void plant_reset(plant_state_t *s)
{
    memset(s, 0, sizeof *s);
}

static double torque_at(const plant_params_t *p, double theta_mech, const double i[3], plant_cache_t *cc)
{
    double f[3];
    shapes(p, (double)p->pole_pairs * theta_mech, f, cc);
    return (double)p->pole_pairs * p->lambda_m_v_s * (f[0] * i[0] + f[1] * i[1] + f[2] * i[2]);
}

/* end-of-step current of one leg for a star-point voltage vn */
static double leg_current(double A, double k, double cp, double cm, double vn)
{
    double up = A + k * (cp - vn);
    double dn = A + k * (cm - vn);
    return (up > 0.0 ? up : 0.0) + (dn < 0.0 ? dn : 0.0);
}

/* the coefficients of a step of length h: they depend on h and the parameters only */
static void step_coef(const plant_params_t *p, double h, step_coef_t *c)
{
    double R = p->r_phase_ohm, L = p->l_phase_h, J = p->inertia_kg_m2, B = p->friction_n_m_s;
    c->h = h; c->r = R; c->l = L; c->j = J; c->b = B;
    c->a = exp(-h * R / L);
    c->k = -expm1(-h * R / L) / R;              /* (1 - a) / R, accurate for small h */
    for (int m = 0; m < 2; m++) {               /* the rotor over h and over h/2 */
        double hm = m ? 0.5 * h : h;
        double hj = hm / J, hb = 0.5 * hj * B;
        c->hj[m] = hj;
        c->hb[m] = hb;
        c->den[m] = 1.0 / (1.0 + hb);
    }
}

/* a hash of a double's bits, for the caches' direct-mapped slots */
static inline unsigned slot_of(double x, unsigned n)
{
    uint64_t u;
    memcpy(&u, &x, sizeof u);
    u *= 0x9E3779B97F4A7C15ULL;
    return (unsigned)(u >> 40) & (n - 1u);
}

/* the coefficients for h, from the cache (plant_cache_t), computed into its slot on a miss */
static const step_coef_t *coef_for(const plant_params_t *p, double h, plant_cache_t *cc)
{
    double R = p->r_phase_ohm, L = p->l_phase_h, J = p->inertia_kg_m2, B = p->friction_n_m_s;
    step_coef_t *c = &cc->slot[slot_of(h, PLANT_COEF_SLOTS)];
    if (!(c->h == h && c->r == R && c->l == L && c->j == J && c->b == B))
        step_coef(p, h, c);
    return c;
}

/* exp(x), from the cache (plant_cache_t) when it computed it before */
static inline double exp_cached(double x, plant_cache_t *cc)
{
    unsigned k = slot_of(x, PLANT_EXP_SLOTS);
    if (cc->exp_x[k] == x) return cc->exp_v[k];
    double v = exp(x);
    cc->exp_x[k] = x;
    cc->exp_v[k] = v;
    return v;
}

static void solve_currents(const double i0[3], const double vp[3], const double vm[3],
                           const double e[3], const step_coef_t *c, double i1[3], double *vn_out)
{
    double a = c->a, k = c->k;
    double A[3], cp[3], cm[3], bp[6], g[6];
    for (int x = 0; x < 3; x++) {
        A[x] = a * i0[x];
        cp[x] = vp[x] - e[x];
        cm[x] = vm[x] - e[x];
    }
    /* fast path: the conduction mode of the start of the step holds to its end (legs
       with current keep their sign and rail, open legs stay between theirs); then v_n
       follows from sum i = 0 in closed form, and it is the root of G below */
    {
        double sum = 0.0, n = 0.0;
        for (int x = 0; x < 3; x++)
            if (i0[x] != 0.0) { sum += A[x] / k + (i0[x] > 0.0 ? cp[x] : cm[x]); n += 1.0; }
        if (n >= 2.0) {
            double vn = sum / n;
            int ok = 1;
            for (int x = 0; x < 3 && ok; x++) {
                if (i0[x] > 0.0) { i1[x] = A[x] + k * (cp[x] - vn); ok = i1[x] > 0.0; }
                else if (i0[x] < 0.0) { i1[x] = A[x] + k * (cm[x] - vn); ok = i1[x] < 0.0; }
                else { i1[x] = 0.0; ok = cp[x] <= vn && vn <= cm[x]; }
            }
            if (ok) {
                *vn_out = vn;
                return;
            }
        }
    }
    for (int x = 0; x < 3; x++) {
        bp[2 * x] = cp[x] + A[x] / k;
        bp[2 * x + 1] = cm[x] + A[x] / k;
    }
    /* insertion sort of the six breakpoints */
    for (int m = 1; m < 6; m++) {
        double v = bp[m];
        int n = m - 1;
        while (n >= 0 && bp[n] > v) { bp[n + 1] = bp[n]; n--; }
        bp[n + 1] = v;
    }
    for (int m = 0; m < 6; m++) {
        g[m] = 0.0;
        for (int x = 0; x < 3; x++) g[m] += leg_current(A[x], k, cp[x], cm[x], bp[m]);
    }
    /* G is nonincreasing, G(bp[0]) >= 0 >= G(bp[5]); find the sign change */
    double vn;
    if (g[0] <= 0.0) {
        /* G(v) = G(bp0) - 3k (v - bp0) left of bp0 */
        vn = bp[0] + g[0] / (3.0 * k);
    } else if (g[5] >= 0.0) {
        vn = bp[5] + g[5] / (3.0 * k);
    } else {
        int m = 0;
        while (m < 5 && g[m + 1] > 0.0) m++;
        /* g[m] > 0 >= g[m+1] */
        double d = g[m] - g[m + 1];
        vn = bp[m] + (bp[m + 1] - bp[m]) * (d > 0.0 ? g[m] / d : 0.5);
    }
    double sum = 0.0, nz = 0.0;
    for (int x = 0; x < 3; x++) {
        i1[x] = leg_current(A[x], k, cp[x], cm[x], vn);
        sum += i1[x];
        if (i1[x] != 0.0) nz += 1.0;
    }
    /* the root is exact up to rounding; put the residue on the conducting legs */
    if (nz > 0.0 && sum != 0.0)
        for (int x = 0; x < 3; x++)
            if (i1[x] != 0.0) i1[x] -= sum / nz;
    *vn_out = vn;
}

/* rotor speed after a step (m = 0: the whole step h, m = 1: its first half), trapezoidal in
   torque, implicit in B w */
static inline __attribute__((always_inline)) double next_speed(const plant_params_t *p, double w0, double te_avg, double tl,
                         const step_coef_t *c, int m, double *tl_applied)
{
    double hj = c->hj[m], hb = c->hb[m], den = c->den[m];
    if (p->load_mode == LOAD_ACTIVE) {
        *tl_applied = tl;
        return (w0 * (1.0 - hb) + hj * (te_avg - tl)) * den;
    }
    double mag = fabs(tl);
    if (w0 == 0.0) {
        if (fabs(te_avg) <= mag) { *tl_applied = te_avg; return 0.0; }
        double sg = te_avg > 0.0 ? 1.0 : -1.0;
        *tl_applied = sg * mag;
        return hj * (te_avg - sg * mag) * den;
    }
    double sg = w0 > 0.0 ? 1.0 : -1.0;
    *tl_applied = sg * mag;
    double w1 = (w0 * (1.0 - hb) + hj * (te_avg - sg * mag)) * den;
    if (w1 * sg < 0.0) w1 = 0.0;       /* friction-like load stops the rotor, never reverses it */
    return w1;
}

/* The bus voltage now (a step starts from it, the AN1 divider and the twin's state read it): the
 * capacitor's, or the supply's before the first step and on a stiff bus. */
double plant_bus_voltage(const plant_params_t *p, const plant_state_t *s)
{
    return (p->bus_capacitance_f > 0.0 && s->v_bus_v > 0.0) ? s->v_bus_v : p->bus_voltage_v;
}

/* The bus capacitor over a step that drew i_bus_a from it (negative: the bridge returned
 * current).  The supply is an ideal source behind a diode (the capacitor cannot sit below it)
 * that takes back at most supply_sink_a; the brake resistor conducts above brake_chopper_v and
 * is integrated implicitly (R C may be far below the step), never taking the bus under that
 * threshold.  Backward Euler in each piece: stable for any C and h. */
static void bus_step(const plant_params_t *p, plant_state_t *s, double i_bus_a, double h)
{
    double vs = p->bus_voltage_v, C = p->bus_capacitance_f;
    s->i_brake_a = 0.0;
    if (!(C > 0.0)) { s->v_bus_v = vs; return; }
    double v0 = plant_bus_voltage(p, s);
    double v1 = v0 - h * i_bus_a / C;
    if (v1 <= vs) {                      /* the supply sources: the capacitor sits at its voltage */
        s->v_bus_v = vs;
        return;
    }
    v1 = v0 - h * (i_bus_a + p->supply_sink_a) / C;
    if (v1 < vs) v1 = vs;                /* the supply's sinking brings it back to, not under, vs */
    if (p->brake_resistor_ohm > 0.0 && v1 > p->brake_chopper_v) {
        double floor_v = p->brake_chopper_v > vs ? p->brake_chopper_v : vs;
        double vr = v1 / (1.0 + h / (p->brake_resistor_ohm * C));
        if (vr < floor_v) vr = floor_v;   /* the chopper opens at its threshold */
        s->i_brake_a = C * (v1 - vr) / h; /* the charge the resistor took over the step */
        v1 = vr;
    }
    s->v_bus_v = v1;
}

static void substep(const plant_params_t *p, plant_state_t *s, const leg_t leg[3],
                    double t_load_n_m, double h, plant_cache_t *cc)
{
    const step_coef_t *c = coef_for(p, h, cc);
    double P = (double)p->pole_pairs, J = p->inertia_kg_m2, vbus = plant_bus_voltage(p, s);
    double vp[3], vm[3], foff[3], i0[3], f[3], e[3], i1[3], vn, tl_applied;
    for (int x = 0; x < 3; x++) {
        double fh = leg[x].f_hi, fl = leg[x].f_lo;
        double fo = 1.0 - fh - fl;
        if (fo < 0.0) {               /* shoot-through: counted by the caller; share the time */
            double tot = fh + fl;
            fh /= tot; fl /= tot; fo = 0.0;
        }
        foff[x] = fo;
        vp[x] = vbus * fh - p->diode_drop_v * fo;
        vm[x] = vbus * (1.0 - fl) + p->diode_drop_v * fo;
        i0[x] = s->i_a[x];
    }
    double w0 = s->w_rad_s, th0 = s->theta_rad;
    int open = i0[0] == 0.0 && i0[1] == 0.0 && i0[2] == 0.0;
    for (int x = 0; x < 3 && open; x++)
        if (leg[x].f_hi != 0.0 || leg[x].f_lo != 0.0) open = 0;
    if (open && !s->locked) {
        /* bridge off, no current: it stays off while the line-to-line EMF peak is under
           the rails (2 lambda P w for the trapezoid, sqrt 3 lambda P w for the sine) */
        double wmax = fabs(w0) + h * (fabs(t_load_n_m) + p->friction_n_m_s * fabs(w0)) / J;
        double peak = (p->emf_shape == EMF_SINUSOIDAL ? 1.7320508075688772 : 2.0) * p->lambda_m_v_s * P * wmax;
        if (peak < vbus + 2.0 * p->diode_drop_v) {
            double w1 = next_speed(p, w0, 0.0, t_load_n_m, c, 0, &tl_applied);
            for (int x = 0; x < 3; x++) { s->v_term[x] = 0.0; s->e_v[x] = 0.0; }
            s->i_bus_a = s->i_link_on_a = s->i_peak_a = 0.0;
            bus_step(p, s, 0.0, h);
            s->v_neutral = 0.0;
            s->theta_rad = th0 + 0.5 * h * (w0 + w1);
            s->w_rad_s = w1;
            s->torque_e_n_m = 0.0;
            s->te_valid = 1;
            s->torque_load_n_m = tl_applied;
            s->t_s += h;
            return;
        }
    }
    /* the torque left by the previous step (at its predicted end angle, O(h^2) from th0) */
    double te0 = open ? 0.0 : (s->te_valid ? s->torque_e_n_m : torque_at(p, th0, i0, cc));
    double w_mid;
    if (s->locked) {
        w_mid = 0.0;
    } else {
        double tmp;
        w_mid = next_speed(p, w0, te0, t_load_n_m, c, 1, &tmp);
    }
    double th_mid = th0 + 0.25 * h * (w0 + w_mid);
    shapes(p, P * th_mid, f, cc);
    for (int x = 0; x < 3; x++) e[x] = p->lambda_m_v_s * P * w_mid * f[x];
    solve_currents(i0, vp, vm, e, c, i1, &vn);

    double w1;
    double te1p = torque_at(p, th0 + h * w_mid, i1, cc);
    if (s->locked) {
        w1 = 0.0;
        tl_applied = 0.0;
    } else {
        w1 = next_speed(p, w0, 0.5 * (te0 + te1p), t_load_n_m, c, 0, &tl_applied);
    }
    double th1 = th0 + 0.5 * h * (w0 + w1);
    (void)J;

    double ibus = 0.0, ilink = 0.0, ipk = 0.0;
    for (int x = 0; x < 3; x++) {
        double im = 0.5 * (i0[x] + i1[x]);
        double hi = leg[x].f_hi > 1.0 ? 1.0 : leg[x].f_hi;
        ibus += im * (hi + (im < 0.0 ? foff[x] : 0.0));
        if (leg[x].f_hi > 0.0) ilink += i1[x];
        if (fabs(i1[x]) > ipk) ipk = fabs(i1[x]);
        if (hi > 0.0 && hi < 1.0 && i1[x] > 0.0) {
            /* the step is the PWM-period average; the switched current of a PWM'd high side rises
               above it inside the period: the periodic RL solution of the pair (Vbus for d h, 0 for
               the rest, tau = L/R) peaks (Vbus/2R) ((1-a)/(1-ab) - d) above its mean
               (picdrive.models.simulate.pwm_ripple_peak_a); the comparator sees that peak */
            double tau = p->l_phase_h / p->r_phase_ohm;
            double a = exp_cached(-hi * h / tau, cc), b = exp_cached(-(1.0 - hi) * h / tau, cc);
            double pk = i1[x] + vbus / (2.0 * p->r_phase_ohm) * ((1.0 - a) / (1.0 - a * b) - hi);
            if (pk > ipk) ipk = pk;
        }
        double v;
        if (i1[x] > 0.0) v = vp[x];
        else if (i1[x] < 0.0) v = vm[x];
        else {
            v = vn + e[x];
            if (v < vp[x]) v = vp[x];
            if (v > vm[x]) v = vm[x];
        }
        s->v_term[x] = v;
        s->e_v[x] = e[x];
        s->i_a[x] = i1[x];
    }
    s->v_neutral = vn;
    s->i_bus_a = ibus;
    s->i_link_on_a = ilink;
    s->i_peak_a = ipk;
    s->energy_j += vbus * ibus * h;
    bus_step(p, s, ibus, h);
    s->w_rad_s = w1;
    s->theta_rad = th1;
    s->torque_e_n_m = te1p;          /* at th0 + h w_mid, within O(h^2) of th1 */
    s->te_valid = 1;
    s->torque_load_n_m = tl_applied;
    s->t_s += h;
}

/* struct sizes, so Python can check its ctypes mirrors */
int plant_sizeof(int which)
{
    switch (which) {
    case 0: return (int)sizeof(plant_params_t);
    case 1: return (int)sizeof(plant_state_t);
    case 2: return (int)sizeof(leg_t);
    default: return -1;
    }
}

/* A step, split once where a conducting phase's current reaches zero: the
 * implicit diode rule alone would switch that phase off at the end of the
 * step (first-order error in the other phases); locating the crossing keeps
 * the step second order.  The crossing time comes from the exponential
 * solution of that phase with the conduction mode at the start of the step. */
void plant_step_cached(const plant_params_t *p, plant_state_t *s, const leg_t leg[3],
                       double t_load_n_m, double h, plant_cache_t *cc)
{
    if (!(h > 0.0)) return;
    plant_state_t save = *s;
    substep(p, s, leg, t_load_n_m, h, cc);
    double best = h;
    int bx = -1;
    for (int x = 0; x < 3; x++) {
        double i0 = save.i_a[x], i1 = s->i_a[x];
        if (i0 == 0.0 || (i1 != 0.0 && (i1 > 0.0) == (i0 > 0.0)))
            continue;
        /* start-of-step mode: legs with current conduct at their current's rail */
        double vn = 0.0, n = 0.0, v[3], vb = plant_bus_voltage(p, &save);
        for (int y = 0; y < 3; y++) {
            double fh = leg[y].f_hi, fl = leg[y].f_lo, fo = 1.0 - fh - fl;
            if (fo < 0.0) fo = 0.0;
            v[y] = save.i_a[y] > 0.0 ? vb * fh - p->diode_drop_v * fo
                                     : vb * (1.0 - fl) + p->diode_drop_v * fo;
            if (save.i_a[y] != 0.0) { vn += v[y] - s->e_v[y]; n += 1.0; }
        }
        if (n < 2.0) continue;
        vn /= n;
        double R = p->r_phase_ohm, tau = p->l_phase_h / R;
        double ss = (v[x] - vn - s->e_v[x]) / R;       /* steady-state current of that mode */
        double q = ss / (ss - i0);
        if (!(q > 0.0 && q < 1.0)) continue;
        double ts = -tau * log(q);
        if (ts < best) { best = ts; bx = x; }
    }
    if (bx < 0 || best < 1e-3 * h || best > 0.999 * h)
        return;
    *s = save;
    substep(p, s, leg, t_load_n_m, best, cc);
    /* the crossing phase ends at zero; the rest keep the sum at zero */
    double r = s->i_a[bx];
    s->te_valid = 0;                  /* the currents are adjusted below */
    if (fabs(r) > 0.02 * fabs(save.i_a[bx])) {   /* estimate off: leave it to the implicit rule */
        substep(p, s, leg, t_load_n_m, h - best, cc);
        return;
    }
    s->i_a[bx] = 0.0;
    int others = 0;
    for (int y = 0; y < 3; y++) if (y != bx && s->i_a[y] != 0.0) others++;
    for (int y = 0; y < 3; y++) if (y != bx && s->i_a[y] != 0.0) s->i_a[y] += r / others;
    if (others == 1) for (int y = 0; y < 3; y++) if (y != bx) s->i_a[y] = 0.0;
    substep(p, s, leg, t_load_n_m, h - best, cc);
}

void plant_step(const plant_params_t *p, plant_state_t *s, const leg_t leg[3],
                double t_load_n_m, double h)
{
    plant_cache_t cc;
    plant_cache_reset(&cc);
    plant_step_cached(p, s, leg, t_load_n_m, h, &cc);
}

void plant_cache_reset(plant_cache_t *cc)
{
    memset(cc, 0, sizeof *cc);
    for (int k = 0; k < PLANT_COEF_SLOTS; k++)
        cc->slot[k].h = -1.0;                   /* no step has a negative length */
    for (int k = 0; k < PLANT_EXP_SLOTS; k++)
        cc->exp_x[k] = NAN;                     /* equal to no argument */
    cc->sin_ref = NAN;                          /* no anchor: the first sin_cos() makes one */
}

"""The transfer-function model of a six-step BLDC drive (Duy et al. 2008, eq 1).

The speed of a six-step (trapezoidal, two phases conducting) BLDC drive
follows the DC-motor equivalent (Ong 1998)::

    P(s) = w(s) / v(s) = Kt / ((L s + R)(J s + D) + Kt Kb)            (eq 1)

with the terminal (line-to-line) resistance R and inductance L, the
six-step DC-equivalent torque and back-EMF constants Kt, Kb, the inertia J
and the viscous friction D.  Input: the DC-equivalent line voltage v (V);
output: the mechanical speed w (rad/s).  The profile gives these as
``Motor.r_line_ohm``, ``l_line_h``, ``kt_n_m_per_a``, ``kb_v_s_per_rad``,
``inertia_kg_m2`` and ``viscous_friction_n_m_s``.

Polynomials are numpy coefficient arrays in *descending* powers of s (or z),
as ``numpy.polyval`` and ``scipy.signal`` use them.  Batched functions take
gains as arrays of any shape and return coefficient arrays with the power
axis last.

Besides the nominal plant this module holds the 2008 paper's perturbation
``xi(s) = d / (s^2 + 0.1 s + 10)`` (eq 19), the perturbed plant
``P (1 + xi)`` (eq 23), the load model of eq 6, the PID (eq 2) and its loops
(eqs 20, 21, 24, 25), and the sampled model of the loop the firmware runs
(zero-order hold, computation delay, speed measured by position
differencing) used by the "drive" design variant.
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
from scipy.linalg import expm

__all__ = [
    "TF", "motor_tf", "xi_tf", "XI_DEN", "perturbed_plant", "load_gains", "load_tf",
    "pid_num", "loop_polys", "closed_loop_tf", "tracking_error_tf", "perturbed_loop_tf",
    "SampledPlant", "sampled_plant", "speed_quantum_rad_s", "motor_ss", "simulate_sampled",
    "simulate_sampled_batch",
]

# xi(s) = d / (s^2 + 0.1 s + 10), eq 19
XI_DEN = np.array([1.0, 0.1, 10.0])


@dataclass(frozen=True)
class TF:
    """A SISO transfer function num(s)/den(s), descending powers."""

    num: np.ndarray
    den: np.ndarray

    def __post_init__(self):
        object.__setattr__(self, "num", np.atleast_1d(np.asarray(self.num, dtype=float)))
        object.__setattr__(self, "den", np.atleast_1d(np.asarray(self.den, dtype=float)))

    def __call__(self, s):
        """Frequency response at complex s (scalar or array)."""
        return np.polyval(self.num, s) / np.polyval(self.den, s)

    def __mul__(self, other: "TF") -> "TF":
        return TF(np.polymul(self.num, other.num), np.polymul(self.den, other.den))

    def monic(self) -> "TF":
        """Same transfer function with the leading denominator coefficient 1."""
        return TF(self.num / self.den[0], self.den / self.den[0])

    def poles(self) -> np.ndarray:
        return np.roots(self.den)

    def dcgain(self) -> float:
        return float(self.num[-1] / self.den[-1])

    def to_ss(self):
        """Controllable-canonical state space (A, B, C, D), for a proper TF."""
        from scipy.signal import tf2ss
        return tf2ss(self.num, self.den)


def motor_tf(profile) -> TF:
    """Eq 1 from a profile (or a ``Motor``): P(s) in rad/s per V, monic denominator.

    ``P(s) = (Kt/(L J)) / (s^2 + (L D + R J)/(L J) s + (R D + Kt Kb)/(L J))``.
    """
    m = getattr(profile, "motor", profile)
    L, R = m.l_line_h, m.r_line_ohm
    J, D = m.inertia_kg_m2, m.viscous_friction_n_m_s
    kt, kb = m.kt_n_m_per_a, m.kb_v_s_per_rad
    den = np.polyadd(np.polymul([L, R], [J, D]), [kt * kb])
    return TF([kt], den).monic()


def xi_tf(d: float) -> TF:
    """The perturbation bound xi(s) = d / (s^2 + 0.1 s + 10) of eq 19.

    Note: |xi(jw)| peaks at w = sqrt(10 - 0.005) rad/s with about 3.16 |d|,
    not at 0.1 |d| as eq 19 prints (0.1 |d| is its value at w = 0).
    """
    return TF([float(d)], XI_DEN)


def perturbed_plant(plant: TF, d: float) -> TF:
    """Eq 23: P_b(s) = P(s) (1 + xi(s)) = P (s^2 + 0.1 s + 10 + d) / (s^2 + 0.1 s + 10)."""
    return TF(np.polymul(plant.num, np.polyadd(XI_DEN, [float(d)])), np.polymul(plant.den, XI_DEN))


def load_gains(profile) -> tuple[float, float]:
    """Eq 6: k_pl = R / (Kb Kt) (rad/s per N m) and k_dl = L / (Kb Kt) (rad per N m).

    The paper's load l(t) = k_pl r_l + k_dl dr_l/dt is an *output*
    disturbance: for a torque step r_l it is the speed droop the load would
    cause through the DC gain 1/Kb of the plant (friction neglected), i.e.
    ``P(s) (L s + R)/Kt`` with P(s) replaced by 1/Kb.
    """
    m = getattr(profile, "motor", profile)
    kk = m.kt_n_m_per_a * m.kb_v_s_per_rad
    return m.r_line_ohm / kk, m.l_line_h / kk


def load_tf(profile, plant: TF | None = None) -> TF:
    """The physical load path: speed per N m of load torque, -P(s) (L s + R) / Kt.

    (A load torque T_L enters eq 1 as an input-voltage disturbance
    (L s + R) T_L / Kt.)  Returned with a positive sign: y = P C r/(1+PC) - S * load_tf * T_L.
    """
    m = getattr(profile, "motor", profile)
    plant = plant or motor_tf(profile)
    return TF(np.polymul(plant.num, [m.l_line_h / m.kt_n_m_per_a, m.r_line_ohm / m.kt_n_m_per_a]), plant.den)


def pid_num(kp, ki, kd) -> np.ndarray:
    """Numerator of C(s) = kp + ki/s + kd s = (kd s^2 + kp s + ki)/s (eq 2), batched: (..., 3)."""
    kp, ki, kd = np.broadcast_arrays(np.asarray(kp, float), np.asarray(ki, float), np.asarray(kd, float))
    return np.stack([kd, kp, ki], axis=-1)


def _pad(p: np.ndarray, n: int) -> np.ndarray:
    """Left-pad the last axis of a coefficient array to length n."""
    p = np.asarray(p, float)
    if p.shape[-1] >= n:
        return p
    pad = [(0, 0)] * (p.ndim - 1) + [(n - p.shape[-1], 0)]
    return np.pad(p, pad)


def loop_polys(plant: TF, kp, ki, kd):
    """Batched loop polynomials of the PID loop around a plant P = n/m.

    Returns ``(char, lnum)``: the characteristic polynomial
    ``s m(s) + n(s) (kd s^2 + kp s + ki)`` and the loop-gain numerator
    ``n(s) (kd s^2 + kp s + ki)``, both padded to the same length
    (shape (..., deg+1)).  For eq 18 the characteristic polynomial is eq 20's
    ``s^3 + a2 s^2 + a1 s + a0``.
    """
    c = pid_num(kp, ki, kd)
    n = plant.num
    lnum = np.zeros(c.shape[:-1] + (c.shape[-1] + n.size - 1,))
    for i, ni in enumerate(n):                      # batched polymul by a fixed polynomial
        lnum[..., i:i + 3] += ni * c
    sm = np.append(plant.den, 0.0)
    size = max(sm.size, lnum.shape[-1])
    char = _pad(sm, size) + _pad(lnum, size)
    return char, _pad(lnum, size)


def closed_loop_tf(plant: TF, kp: float, ki: float, kd: float, *, derivative: str = "error") -> TF:
    """Reference-to-speed closed loop (eq 20).

    ``derivative="error"``: the paper's C(s) on e = r - y (eq 5);
    ``"measurement"``: picdrive's law (kd acts on -y only, b = 1), which keeps
    the poles and removes the kd s^2 term from the numerator.
    """
    char, lnum = loop_polys(plant, kp, ki, kd)
    if derivative == "measurement":
        _, lnum = loop_polys(plant, kp, ki, 0.0)
    elif derivative != "error":
        raise ValueError(f"derivative must be 'error' or 'measurement', not {derivative!r}")
    return TF(np.trim_zeros(lnum, "f"), char)


def tracking_error_tf(plant: TF, kp: float, ki: float, kd: float, *, derivative: str = "error") -> TF:
    """Error e(s) for a unit-step reference (eq 21 without its factor 1000), e = (1 - G_n)/s."""
    g = closed_loop_tf(plant, kp, ki, kd, derivative=derivative)
    diff = np.polysub(g.den, g.num)             # s * (something): the constant term cancels
    if abs(diff[-1]) > 1e-9 * np.max(np.abs(diff)):
        raise ValueError("the loop has no integral action: the step error does not vanish")
    return TF(diff[:-1], g.den)


def perturbed_loop_tf(plant: TF, d: float, kp: float, ki: float, kd: float, *,
                      derivative: str = "error") -> tuple[TF, TF]:
    """Eqs 24 and 25: (G_b(s), e_b(s)) of the loop around P_b = P (1 + xi) for a unit step."""
    pb = perturbed_plant(plant, d)
    gb = closed_loop_tf(pb, kp, ki, kd, derivative=derivative)
    eb = tracking_error_tf(pb, kp, ki, kd, derivative=derivative)
    return gb, eb


# ---------------------------------------------------------------------------
# The sampled loop the firmware runs
# ---------------------------------------------------------------------------
@dataclass(frozen=True)
class SampledPlant:
    """Zero-order-hold model of the plant as the speed loop sees it.

    State ``x = [plant states (n), speed measurement, delayed u]`` (the last
    only when ``delay_samples == 1``), one sample of ``ts`` seconds::

        x[k+1] = Ad x[k] + Bd u_cmd[k]
        y[k]   = Cd x[k]          measured speed, rad/s

    ``measurement``: ``"average"`` — the speed the firmware computes from
    the encoder count difference over the last period (the mean speed over
    [k-1, k] Ts); ``"instant"`` — the speed at the sampling instant.
    ``delay_samples``: 0 — the voltage computed at tick k is applied at once;
    1 — it is applied at tick k+1 (computation delay, worst case).
    """

    Ad: np.ndarray
    Bd: np.ndarray
    Cd: np.ndarray
    ts: float
    delay_samples: int
    measurement: str

    @property
    def n(self) -> int:
        return self.Ad.shape[0]

    @functools.cached_property
    def tf_z(self) -> TF:
        """Pulse transfer function y/u_cmd in z (descending powers); computed once."""
        from scipy.signal import ss2tf
        num, den = ss2tf(self.Ad, self.Bd, self.Cd, np.zeros((1, 1)))
        num = np.atleast_1d(np.squeeze(num))
        num[np.abs(num) < 1e-12 * np.max(np.abs(num))] = 0.0
        return TF(np.trim_zeros(num, "f"), den)


def sampled_plant(plant: TF, ts: float, *, delay_samples: int = 1, measurement: str = "average") -> SampledPlant:
    """Discretise a strictly proper plant for the speed loop (see :class:`SampledPlant`)."""
    if delay_samples not in (0, 1):
        raise ValueError("delay_samples must be 0 or 1")
    if measurement not in ("average", "instant"):
        raise ValueError("measurement must be 'average' or 'instant'")
    A, B, C, D = plant.to_ss()
    if np.any(np.abs(D) > 0):
        raise ValueError("the plant must be strictly proper")
    n = A.shape[0]
    # augmented with q' = y (integral of speed over the period), ZOH on u
    M = np.zeros((n + 2, n + 2))
    M[:n, :n] = A
    M[:n, n + 1] = B[:, 0]
    M[n, :n] = C[0]
    E = expm(M * ts)
    phi, gam = E[:n, :n], E[:n, n + 1]
    qx, qu = E[n, :n], E[n, n + 1]             # integral of y over the period
    if measurement == "average":
        # states [x, y_meas]; y_meas[k+1] = (qx x[k] + qu u_app[k]) / ts
        nx = n + 1
        A1 = np.zeros((nx, nx)); B1 = np.zeros(nx)
        A1[:n, :n] = phi; B1[:n] = gam
        A1[n, :n] = qx / ts; B1[n] = qu / ts
        C1 = np.zeros(nx); C1[n] = 1.0
    else:
        nx = n
        A1, B1, C1 = phi, gam.copy(), C[0].copy()
    if delay_samples == 1:
        A2 = np.zeros((nx + 1, nx + 1))
        A2[:nx, :nx] = A1
        A2[:nx, nx] = B1                       # plant driven by the stored command
        B2 = np.zeros(nx + 1); B2[nx] = 1.0
        C2 = np.append(C1, 0.0)
        A1, B1, C1 = A2, B2, C2
    return SampledPlant(A1, B1.reshape(-1, 1), C1.reshape(1, -1), float(ts), delay_samples, measurement)


def speed_quantum_rad_s(profile) -> float:
    """Resolution of the measured speed at the speed-loop rate, rad/s.

    Encoder (quadrature, 4 counts per line) counted over one period:
    ``2 pi / (4 lines Ts)``; hall sensors: one of ``6 pole_pairs`` edges per
    revolution per period.  (How the firmware actually measures is its
    generator's business; this is the figure of a position-difference
    estimate, used to judge what one count does to the voltage.)
    """
    ts = 1.0 / profile.control.speed_loop_hz
    if profile.sensors.speed_source == "encoder" and profile.sensors.encoder_lines > 0:
        counts = 4 * profile.sensors.encoder_lines
    else:
        counts = 6 * profile.motor.pole_pairs
    return 2.0 * math.pi / (counts * ts)


# ---------------------------------------------------------------------------
# nonlinear (saturating) simulation of the sampled speed loop on eq 1
# ---------------------------------------------------------------------------
def motor_ss(profile):
    """Physical state space of eq 1: x = [i (A), w (rad/s)], inputs [v (V), T_L (N m)].

    ``L di/dt = v - R i - Kb w``, ``J dw/dt = Kt i - D w - T_L``.  Returns (A, B) with B (2, 2).
    """
    m = getattr(profile, "motor", profile)
    L, R, J, D = m.l_line_h, m.r_line_ohm, m.inertia_kg_m2, m.viscous_friction_n_m_s
    kt, kb = m.kt_n_m_per_a, m.kb_v_s_per_rad
    A = np.array([[-R / L, -kb / L], [kt / J, -D / J]])
    B = np.array([[1.0 / L, 0.0], [0.0, -1.0 / J]])
    return A, B


def simulate_sampled(profile, law, *, t_end_s: float, ref_rad_s: float, load_n_m: float = 0.0,
                     t_load_s: float | None = None, delay_samples: int = 1, measurement: str = "average",
                     x0=None) -> dict:
    """Simulate picdrive's law (``control_law.law_step``, with its saturation and
    anti-windup) sampled at ``law.sample_time_s`` around the eq 1 motor.

    The plant is integrated exactly between samples (zero-order hold on the
    voltage and on the load torque, which steps at the first sample at or
    after ``t_load_s``).  Returns arrays at the sample instants: ``t_s``,
    ``speed_rad_s`` (true), ``speed_meas_rad_s``, ``u_v`` (applied voltage),
    ``current_a``.
    """
    from ..control_law import LawState, law_step

    if delay_samples not in (0, 1) or measurement not in ("average", "instant"):
        raise ValueError("delay_samples must be 0 or 1 and measurement 'average' or 'instant'")
    ts = law.sample_time_s
    A, B = motor_ss(profile)
    M = np.zeros((5, 5))
    M[:2, :2] = A
    M[:2, 3:] = B
    M[2, 1] = 1.0                                     # q' = w
    E = expm(M * ts)
    phi, gam = E[:2, :2], E[:2, 3:]
    qx, qu = E[2, :2], E[2, 3:]
    n = int(round(t_end_s / ts)) + 1
    x = np.zeros(2) if x0 is None else np.asarray(x0, float).copy()
    y_avg = x[1]
    u_app = 0.0
    st = LawState()
    out = {k: np.zeros(n) for k in ("t_s", "speed_rad_s", "speed_meas_rad_s", "u_v", "current_a")}
    for k in range(n):
        t = k * ts
        tl = load_n_m if (t_load_s is not None and t >= t_load_s - 1e-12) else 0.0
        y = y_avg if measurement == "average" else x[1]
        u_cmd = law_step(law, st, ref_rad_s, y)
        if delay_samples == 0:
            u_app = u_cmd
        out["t_s"][k] = t
        out["speed_rad_s"][k] = x[1]
        out["speed_meas_rad_s"][k] = y
        out["u_v"][k] = u_app
        out["current_a"][k] = x[0]
        inp = np.array([u_app, tl])
        y_avg = float(qx @ x + qu @ inp) / ts
        x = phi @ x + gam @ inp
        if delay_samples == 1:
            u_app = u_cmd
    return out


@functools.lru_cache(maxsize=32)
def _zoh_motor(L, R, J, D, kt, kb, ts):
    """Exact ZOH discretisation of eq 1 with the speed integral: (phi, gam, qx, qu)."""
    A = np.array([[-R / L, -kb / L], [kt / J, -D / J]])
    M = np.zeros((4, 4))
    M[:2, :2] = A
    M[0, 3] = 1.0 / L
    M[2, 1] = 1.0
    E = expm(M * ts)
    return E[:2, :2], E[:2, 3], E[2, :2], E[2, 3]


def simulate_sampled_batch(profile, kp, ki, kd, *, ts: float, u_max_v: float, t_end_s: float, ref_rad_s: float,
                           delay_samples: int = 1, measurement: str = "average",
                           i_lim_v: float | None = None) -> dict:
    """:func:`simulate_sampled` for many one-rule PID laws at once (no load torque).

    The law is ``control_law.law_step`` written out for arrays (one rule,
    b = 1, unfiltered derivative on measurement, integration only into the
    output headroom, integrator range +-``i_lim_v`` (default ``u_max_v``, the
    law's default), output clamp to +-``u_max_v``), so that a GA can judge
    the saturated step of every chromosome.  A test keeps it equal to
    :func:`simulate_sampled` with ``law_step``.  Returns ``speed_rad_s`` and ``current_a`` of shape
    (samples, batch) at the sample instants.
    """
    kp, ki, kd = (np.atleast_1d(np.asarray(v, float)) for v in (kp, ki, kd))
    kp, ki, kd = np.broadcast_arrays(kp, ki, kd)
    m_ = getattr(profile, "motor", profile)
    phi, gam, qx, qu = _zoh_motor(m_.l_line_h, m_.r_line_ohm, m_.inertia_kg_m2, m_.viscous_friction_n_m_s,
                                  m_.kt_n_m_per_a, m_.kb_v_s_per_rad, float(ts))
    n = int(round(t_end_s / ts)) + 1
    m = kp.size
    x = np.zeros((2, m))
    y_avg = np.zeros(m)
    u_app = np.zeros(m)
    integ = np.zeros(m)
    y_prev = None
    r = float(ref_rad_s)
    i_lim = float(u_max_v if i_lim_v is None else i_lim_v)
    w_out = np.zeros((n, m)); i_out = np.zeros((n, m))
    for k in range(n):
        w_out[k] = x[1]; i_out[k] = x[0]
        y = y_avg if measurement == "average" else x[1]
        e = r - y
        q = kp * e + kd * ((y if y_prev is None else y_prev) - y) / ts      # b = 1, kc = 0
        di = ki * ts * e
        up = np.minimum(integ + di, np.maximum(integ, u_max_v - q))       # headroom rule of law_step
        dn = np.maximum(integ + di, np.minimum(integ, -u_max_v - q))
        integ = np.where(di > 0, up, np.where(di < 0, dn, integ))
        integ = np.minimum(np.maximum(integ, -i_lim), i_lim)
        u_cmd = np.minimum(np.maximum(q + integ, -u_max_v), u_max_v)
        y_prev = y
        if delay_samples == 0:
            u_app = u_cmd
        y_avg = (qx[0] * x[0] + qx[1] * x[1] + qu * u_app) / ts
        x = phi @ x + gam[:, None] * u_app
        if delay_samples == 1:
            u_app = u_cmd
    return {"speed_rad_s": w_out, "current_a": i_out}

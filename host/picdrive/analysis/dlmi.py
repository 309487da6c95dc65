"""The fuzzy H-inf design at the speed-loop rate: the sampled TS model and its LMIs as numbers.

:func:`sampled_model` turns a continuous TS model of the six-step drive
(:func:`picdrive.models.tsfuzzy.six_step_model` and friends: states ``[omega, i(, i_d), z]``)
into the discrete model the firmware's law actually closes, one per rule and
uncertainty vertex:

* the plant held by the PWM (zero-order hold) over one speed-loop period ``Ts``,
  with the command of sample k applied one PWM period after the sample (the
  firmware's computation delay: ``u_prev`` is a state);
* the firmware's speed measurement, ``y_k = 1.5 w_avg[k] - 0.5 w_avg[k-1]``
  (``w_avg`` the mean speed over the last sample; ``w_avg``, ``w_avg_prev`` are states) --
  exactly :func:`picdrive.analysis.sampled.six_step_closed_loop`, the
  verification's ``sampled_spectral_radius`` check, so design and check close the
  same loop;
* the law's integrator, ``z_{k+1} = z_k - Ts y_k`` (rad; the law's ``I = ki z``).

States (physical) ``X = [x_p, w_avg, w_avg_prev, u_prev, z]`` with ``x_p`` the
continuous model's plant states.  The law ``u = -kp y + I_{k+1} - kc i`` is the
static feedback ``u = F [y, i, z]`` with ``F = [-(kp + ki Ts), -kc, ki]`` of the
*measured* coordinates only; :func:`sampled_model` changes coordinates so
that these come first (``X' = T X``: ``[y, i, z]`` then the unmeasured ones)
and scales them to O(1) (``X' = S Xs``), so a structured gain
``K = [K_m, 0]`` is the law.

:func:`brl_blocks` is the discrete bounded-real lemma in the extended (slack
variable) form of de Oliveira, Geromel and Bernussou (2002)::

    M_ij = [ Q                  A_i G + B_i Y_j    Bw_i    0           ]
           [ *                  G + G^T - Q        0       G^T C_i^T   ]  > 0
           [ *                  *                  g I     0           ]
           [ *                  *                  *       g I         ]

``K_j = Y_j G^-1``.  With ``G = Q`` it is the textbook discrete BRL (``K_j = Y_j
Q^-1``; the Schur complement of ``Q`` gives ``A_cl^T Q^-1 A_cl - Q^-1 + ... < 0``);
the slack ``G`` carries the gain structure (``G = [[G_m, 0], [G_um, G_u]]`` block
lower-triangular and ``Y_j = [Y_m, 0]`` give ``K_j = [Y_m G_m^-1, 0]``) so the Lyapunov
matrix ``Q`` stays full, which a block-diagonal ``Q`` (the continuous design's
structure for its zero-gain states) would not: on duy2008 the continuous design's law,
fixed, has no certificate with a block-diagonal ``G`` and reaches its own H-inf norm
with the triangular one.  Feasible at
every rule pair (``M_ii > 0``, ``M_ij + M_ji > 0`` for ``i < j``: Tanaka and Wang's
relaxation; the closed loop ``sum_ij h_i h_j (A_i + B_i K_j)`` is affine in each
pair's matrices) and every vertex, it certifies ``||w -> z||_inf < g`` for
every blend of the rules at every vertex.  :func:`disk_blocks` likewise: every
closed-loop eigenvalue inside ``|z - c| < r`` (``[[r^2 Q_d, (A_cl - c I) G], [*, G + G^T - Q_d]] > 0``,
with its own ``Q_d``).

:func:`dhinf_norm` computes the discrete H-inf norm independently (bilinear map
to continuous time, where :func:`picdrive.analysis.h2hinf.hinf_norm` bisects the
Hamiltonian).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg as sla

__all__ = ["SampledTS", "sampled_model", "sampled_stages", "normalised", "rescaled", "brl_blocks", "disk_blocks", "dlmi_margins", "dhinf_norm",
           "closed_loop_radius", "law_gains"]


@dataclass
class SampledTS:
    """The sampled TS model, in the design's scaled coordinates ``Xs`` (``X = T^-1 S Xs``).

    ``A[i][v]``, ``B[i][v]``, ``Bw[i][v]``: rule i at vertex v (n x n, n x 1, n x p);
    ``C[i]`` (s x n) the performance output; the first ``n_meas`` coordinates are
    the measured ones ``[y, i.., z]`` (the law's inputs).  ``vertices`` names
    each vertex (plant, R factor, EMF constant)."""

    A: list
    B: list
    Bw: list
    C: list
    n_meas: int
    T: np.ndarray                   # X' = T X (measured coordinates first)
    S: np.ndarray                   # X' = diag(S) Xs (typical magnitudes)
    su: float                       # u = su us
    ts_s: float
    delay_s: float
    state_names: tuple
    meas_names: tuple
    current_gain: float             # measured current = current_gain x the model's current state (dq: i_bus/i_q)
    vertices: list = field(default_factory=list)
    D: list | None = None           # D[i] (s x 1): the command's weight in the performance output (None: 0)

    @property
    def r(self) -> int:
        return len(self.A)

    @property
    def nv(self) -> int:
        return len(self.A[0])

    @property
    def n(self) -> int:
        return self.A[0][0].shape[0]


def _zoh(Ac, Bc, h):
    """ZOH of ``x' = Ac x + Bc v`` over ``h`` s: ``(F, G)``."""
    n, m = Bc.shape
    M = sla.expm(np.block([[Ac, Bc], [np.zeros((m, n + m))]]) * h)
    return M[:n, :n], M[:n, n:]


def _discretise(Ap, Bp, Bwp, ts_s, delay_s):
    """One vertex: the continuous plant ``x_p' = Ap x_p + Bp u + Bwp w`` -> the discrete
    ``X = [x_p, w_avg, w_avg_prev, u_prev, z]`` (speed is ``x_p[0]``): ``(A, B, Bw)``."""
    npl = Ap.shape[0]
    p = Bwp.shape[1]
    # augment with s' = omega (s: the angle turned since the sample, so w_avg = s(Ts)/Ts)
    Ac = np.zeros((npl + 1, npl + 1))
    Ac[:npl, :npl] = Ap
    Ac[npl, 0] = 1.0
    Bc = np.zeros((npl + 1, 1 + p))
    Bc[:npl, :1] = Bp
    Bc[:npl, 1:] = Bwp
    F1, G1 = _zoh(Ac, Bc, delay_s)            # [t_k, t_k + delay]: the previous command still applies
    F2, G2 = _zoh(Ac, Bc, ts_s - delay_s)     # [t_k + delay, t_k+1]: this sample's command
    n = npl + 4
    iwa, iwp, iup, iz = npl, npl + 1, npl + 2, npl + 3
    A = np.zeros((n, n))
    B = np.zeros((n, 1))
    Bw = np.zeros((n, p))
    # x_aug(t_k+1) = F2 (F1 [x_p; 0] + G1 [u_prev; w]) + G2 [u; w]
    Fx = F2 @ F1[:, :npl]
    Fu_prev = F2 @ G1[:, :1]
    Fw = F2 @ G1[:, 1:] + G2[:, 1:]
    Fu = G2[:, :1]
    A[:npl, :npl] = Fx[:npl]
    A[:npl, iup] = Fu_prev[:npl, 0]
    B[:npl] = Fu[:npl]
    Bw[:npl] = Fw[:npl]
    A[iwa, :npl] = Fx[npl] / ts_s
    A[iwa, iup] = Fu_prev[npl, 0] / ts_s
    B[iwa] = Fu[npl] / ts_s
    Bw[iwa] = Fw[npl] / ts_s
    A[iwp, iwa] = 1.0
    B[iup, 0] = 1.0
    # the law's integrator of the measured speed error (r = 0 in deviation coordinates)
    A[iz, iz] = 1.0
    A[iz, iwa] = -1.5 * ts_s
    A[iz, iwp] = 0.5 * ts_s
    return A, B, Bw


def sampled_model(profile, ts, *, zero_gain_states=(), delay_s: float | None = None, dc_vertices: bool = False,
                  current_gain: float = 1.0, effort_weight: float = 0.0) -> SampledTS:
    """The sampled TS model of the law's loop (module docstring) from the continuous TS model ``ts``.

    Parameters
    ----------
    profile : picdrive.profile.Profile
        Gives the speed-loop rate (``control.speed_loop_hz``), the PWM period (the computation delay)
        and ``design.resistance_uncertainty``.
    ts : picdrive.models.tsfuzzy.TSModel
        A tracking model whose last state is the speed-error integral ``z`` and whose first is the
        speed (rad/s); its rule matrices are each rule's plant.
    zero_gain_states : sequence of int
        States of ``ts`` the law does not measure (e.g. ``i_d`` of the dq model).
    delay_s : float, optional
        When the command of a sample starts to act, s after the sample (default one PWM period,
        as the verification's check; at most ``Ts``).
    dc_vertices : bool
        Add the DC equivalent (the verification's sampled-loop plant) as vertices of every rule,
        at R nominal and at its uncertainty extremes: with a speed-dependent (averaged) model the
        certificate then also covers the plant the verification checks.
    current_gain : float
        The measured current per unit of the model's current state (dq: ``i_bus / i_q``).
    effort_weight : float
        Weight of the command in the performance output, rad/s per V: an output row ``z_u = effort_weight u``
        beside the speed error (0: none).  It prices the command against the speed error in the H-inf
        norm, so a larger weight gives gentler gains.

    Vertices: each rule's plant at R nominal and x (1 -+ eps) (``ts.E H1``, Assumption 1's
    direction, at ``F = -+rho``), at each polytope offset of ``ts`` (the EMF range) and at the
    offsets' mean (the nominal EMF the verification's plant has).
    """
    from ..models.tfmodel import motor_ss
    Ts = 1.0 / profile.control.speed_loop_hz
    hd = (1.0 / profile.inverter.pwm_frequency_hz) if delay_s is None else float(delay_s)
    hd = min(max(hd, 0.0), Ts)
    n_ts = ts.n
    npl = n_ts - 1                            # the plant: every state but z
    zs = set(int(k) for k in zero_gain_states)
    rho = float(ts.rho)
    offs = list(ts.offsets)
    if len(offs) > 1:
        offs = offs + [np.mean(offs, axis=0)]
    A, B, Bw, C, names = [], [], [], [], []
    E = ts.E_matrix
    for i in range(ts.r):
        Ai, Bi, Bwi = [], [], []
        for k, off in enumerate(offs):
            for f in (0.0, -1.0, 1.0):
                dA = f * rho * E @ ts.H1[i]
                Ac = (ts.A[i] + off + dA)[:npl, :npl]
                a, b, bw = _discretise(Ac, ts.B[i][:npl], ts.Bw[:npl], Ts, hd)
                Ai.append(a)
                Bi.append(b)
                Bwi.append(bw)
                if i == 0:
                    names.append(f"rule plant, R x {1 + f * rho * float(ts.info.get('resistance_uncertainty', 0.1)):g}"
                                 + (f", EMF vertex {k + 1}" if len(offs) > 1 else ""))
        if dc_vertices:
            eps = float(profile.design.get("resistance_uncertainty", 0.1))
            for rs in (1.0, 1.0 - eps, 1.0 + eps):
                Am, Bm = motor_ss(profile, r_factor=rs)          # [i, w]
                if npl != 2:
                    raise ValueError("dc_vertices needs the six-step model (states [omega, i, z])")
                P = np.array([[0.0, 1.0], [1.0, 0.0]])           # [i, w] -> [w, i]
                a, b, bw = _discretise(P @ Am @ P, P @ Bm[:, :1], ts.Bw[:npl], Ts, hd)
                Ai.append(a)
                Bi.append(b)
                Bwi.append(bw)
                if i == 0:
                    names.append(f"DC equivalent, R x {rs:g}")
        A.append(Ai)
        B.append(Bi)
        Bw.append(Bwi)
        # the performance output on X: the plant's columns, z last
        Ci = np.zeros((ts.C.shape[1], npl + 4))
        Ci[:, :npl] = ts.C[i][:, :npl]
        Ci[:, -1] = ts.C[i][:, -1]
        C.append(Ci)
    n = npl + 4
    iwa, iwp, iup, iz = npl, npl + 1, npl + 2, npl + 3
    cur = [k for k in range(1, npl) if k not in zs]
    rows = []
    y = np.zeros(n)
    y[iwa], y[iwp] = 1.5, -0.5
    rows.append(y)
    for k in cur:
        rows.append(np.eye(n)[k])
    rows.append(np.eye(n)[iz])
    n_meas = len(rows)
    pivots = {iwp, iz, *cur}
    rest = [k for k in range(n) if k not in pivots]
    T = np.vstack(rows + [np.eye(n)[k] for k in rest])
    # typical magnitudes (numerics only): speeds as the model's speed scale, currents as its, z as its, u_prev
    # as the input's
    sx = np.asarray(ts.info.get("state_scale", np.ones(n_ts)), float)
    su = float(np.asarray(ts.info.get("input_scale", [1.0]), float).reshape(-1)[0])
    phys = np.ones(n)
    phys[:npl] = sx[:npl]
    phys[iwa] = phys[iwp] = sx[0]
    phys[iup] = su
    phys[iz] = sx[-1]
    S = np.array([sx[0]] + [sx[k] for k in cur] + [sx[-1]] + [phys[k] for k in rest])
    Ti = np.linalg.inv(T)
    Sm = np.diag(S)
    Si = np.diag(1.0 / S)
    A = [[Si @ T @ a @ Ti @ Sm for a in Ai] for Ai in A]
    B = [[Si @ T @ b * su for b in Bi] for Bi in B]
    Bw = [[Si @ T @ bw for bw in Bwi] for Bwi in Bw]
    C = [c @ Ti @ Sm for c in C]
    D = [np.zeros((c.shape[0], 1)) for c in C]
    if effort_weight > 0:
        C = [np.vstack([c, np.zeros((1, n))]) for c in C]
        D = [np.vstack([d, [[float(effort_weight) * su]]]) for d in D]
    st = list(ts.state_names)
    plant_names = st[:npl]
    meas = ("y (measured speed)",) + tuple(plant_names[k] for k in cur) + (st[-1],)
    all_names = tuple(plant_names) + ("w_avg", "w_avg_prev", "u_prev", st[-1])
    return SampledTS(A=A, B=B, Bw=Bw, C=C, n_meas=n_meas, T=T, S=S, su=su, ts_s=Ts, delay_s=hd,
                     state_names=meas + tuple(all_names[k] for k in rest), meas_names=meas,
                     current_gain=float(current_gain), vertices=names, D=D)


def normalised(sm: SampledTS) -> tuple[SampledTS, float, float]:
    """``sm`` with the disturbance and output matrices divided by their largest norms over the rules and
    vertices, ``(sm_n, nb, nc)``: ``||w -> z||`` of ``sm`` is ``nb nc`` times that of ``sm_n``, the gains are the
    same.  In these units the LMIs' variables are O(1) at a gamma of O(1) (the BRL bounds ``Q`` below by
    ``Bw Bw^T / g`` and ``G`` above by ``g / ||C||^2``), which the solver's tolerances need: unnormalised, they
    sit at 1e-4 .. 1e-2 on duy2008."""
    from dataclasses import replace
    nb = max(float(np.linalg.norm(bw, 2)) for bwi in sm.Bw for bw in bwi)
    nb = nb if nb > 0 else 1.0
    nc = max(float(np.linalg.norm(np.hstack([c, d]), 2)) for c, d in zip(sm.C, sm.D or [np.zeros((c.shape[0], 1))
                                                                                        for c in sm.C]))
    nc = nc if nc > 0 else 1.0
    return replace(sm, Bw=[[bw / nb for bw in bwi] for bwi in sm.Bw], C=[c / nc for c in sm.C],
                   D=None if sm.D is None else [d / nc for d in sm.D]), nb, nc


def rescaled(sm: SampledTS, d) -> SampledTS:
    """``sm`` in the coordinates ``Xs = diag(d) Xs'`` (``d > 0``): the same loop, the states' typical
    magnitudes ``S`` multiplied by ``d`` (a diagonal scaling keeps the measured coordinates first and the
    gain structure)."""
    from dataclasses import replace
    d = np.asarray(d, float).reshape(-1)
    D, Di = np.diag(d), np.diag(1.0 / d)
    return replace(sm, A=[[Di @ a @ D for a in Ai] for Ai in sm.A], B=[[Di @ b for b in Bi] for Bi in sm.B],
                   Bw=[[Di @ bw for bw in Bwi] for Bwi in sm.Bw], C=[c @ D for c in sm.C], S=sm.S * d)


# ---------------------------------------------------------------------------
# The LMIs (numpy or cvxpy operands)
# ---------------------------------------------------------------------------
def brl_blocks(sm: SampledTS, i: int, j: int, v: int, Q, G, Yj, gamma, *, scale_gamma: bool = False):
    """``M_ij`` at vertex v as a 4 x 4 block list (module docstring).  ``scale_gamma``: the congruence
    ``diag(I, I, I/sqrt g, I/sqrt g)`` (``g`` a number): the same inequality with O(1) gamma rows."""
    A, B, Bw, C = sm.A[i][v], sm.B[i][v], sm.Bw[i][v], sm.C[i]
    n, p, s = A.shape[0], Bw.shape[1], C.shape[0]
    AG = A @ G + B @ Yj
    CG = C @ G if sm.D is None else C @ G + sm.D[i] @ Yj
    if scale_gamma:
        sg = math.sqrt(float(gamma))
        bw, cg, gi_p, gi_s = Bw / sg, CG / sg, np.eye(p), np.eye(s)
    else:
        bw, cg, gi_p, gi_s = Bw, CG, gamma * np.eye(p), gamma * np.eye(s)
    Z = np.zeros
    return [[Q, AG, bw, Z((n, s))],
            [None, G + G.T - Q, Z((n, p)), cg.T],
            [None, None, gi_p, Z((p, s))],
            [None, None, None, gi_s]]


def disk_blocks(sm: SampledTS, i: int, j: int, v: int, Qd, G, Yj, radius: float, centre: float = 0.0):
    """Pole-disk LMI ``[[r^2 Q_d, (A_i G + B_i Y_j - c G)], [*, G + G^T - Q_d]]`` (> 0) as blocks, divided
    by r (O(1) data)."""
    A, B = sm.A[i][v], sm.B[i][v]
    r = float(radius)
    return [[r * Qd, (A @ G + B @ Yj - centre * G) / r], [None, (G + G.T - Qd) / r]]


def _fill(blocks, backend, transpose):
    k = len(blocks)
    rows = []
    for a in range(k):
        row = []
        for b in range(k):
            row.append(blocks[a][b] if blocks[a][b] is not None else transpose(blocks[b][a]))
        rows.append(row)
    return backend(rows)


def assemble(blocks, backend=np.block, transpose=lambda M: M.T):
    """Symmetric block matrix from the upper blocks (``None`` below the diagonal)."""
    return _fill(blocks, backend, transpose)


def pair_sum(fn, i, j):
    """``fn(i, j)`` (i == j) or ``fn(i, j) + fn(j, i)``, block by block (the relaxation's sums)."""
    if i == j:
        return fn(i, i)
    a, b = fn(i, j), fn(j, i)
    return [[None if x is None else x + y for x, y in zip(ra, rb)] for ra, rb in zip(a, b)]


def dlmi_margins(sm: SampledTS, Q, G, Y, gamma, *, Qd=None, radius=None, centre=0.0) -> dict[str, float]:
    """Smallest eigenvalue of each LMI at a candidate solution, negated (all < 0: satisfied), in the
    scaled coordinates (a congruence of the physical ones: same signs)."""
    Q, G = np.asarray(Q, float), np.asarray(G, float)
    Y = [np.asarray(y, float) for y in Y]
    out = {"Q>0": float(-np.linalg.eigvalsh(0.5 * (Q + Q.T)).min())}
    if Qd is not None:
        Qd = np.asarray(Qd, float)
        out["Qd>0"] = float(-np.linalg.eigvalsh(0.5 * (Qd + Qd.T)).min())
    for v in range(sm.nv):
        for i in range(sm.r):
            for j in range(i, sm.r):
                tag = (f"M_{i + 1}{j + 1}" if i == j else f"M_{i + 1}{j + 1}+M_{j + 1}{i + 1}") + f"@v{v + 1}"
                M = assemble(pair_sum(lambda a, b: brl_blocks(sm, a, b, v, Q, G, Y[b], gamma, scale_gamma=True), i, j))
                out[tag] = float(-np.linalg.eigvalsh(0.5 * (M + M.T)).min())
                if Qd is not None:
                    D = assemble(pair_sum(lambda a, b: disk_blocks(sm, a, b, v, Qd, G, Y[b], radius, centre), i, j))
                    out["disk " + tag] = float(-np.linalg.eigvalsh(0.5 * (D + D.T)).min())
    return out


# ---------------------------------------------------------------------------
# Independent checks
# ---------------------------------------------------------------------------
def dhinf_norm(A, B, C, D=None) -> float:
    """H-inf norm of the discrete system ``(A, B, C, D)`` (real matrices): the sup over the unit circle of the
    largest singular value; ``inf`` if A is not Schur.

    Two estimates, the larger kept: the bilinear map ``z = (1 + s)/(1 - s)`` (unit circle onto the imaginary
    axis, norm kept) and :func:`picdrive.analysis.h2hinf.hinf_norm`'s Hamiltonian bisection there; and a sweep
    of ``theta`` in ``[0, pi]`` (4,097 points, then a bounded scalar search around the five largest).  The
    bisection alone misses a lightly damped peak of a pole near ``z = -1`` (mapped to a fast continuous pole:
    14.19 against 18.76 on a 4-state test system), the sweep alone can miss a peak narrower than its step;
    each is a lower bound where the other errs."""
    from scipy.optimize import minimize_scalar
    from .h2hinf import hinf_norm
    A, B, C = (np.atleast_2d(np.asarray(M, float)) for M in (A, B, C))
    D = np.zeros((C.shape[0], B.shape[1])) if D is None else np.atleast_2d(np.asarray(D, float))
    if np.max(np.abs(np.linalg.eigvals(A))) >= 1.0:
        return math.inf
    n = A.shape[0]
    Mi = np.linalg.inv(A + np.eye(n))
    Ac = Mi @ (A - np.eye(n))
    Bc = math.sqrt(2.0) * Mi @ B
    Cc = math.sqrt(2.0) * C @ Mi
    Dc = D - C @ Mi @ B
    h_bil = float(hinf_norm(Ac, Bc, Cc, Dc)[0])

    def sigma(th):
        return float(np.linalg.svd(C @ np.linalg.solve(np.exp(1j * th) * np.eye(n) - A, B) + D,
                                   compute_uv=False)[0])
    th = np.linspace(0.0, math.pi, 4097)
    sg = np.array([sigma(t) for t in th])
    best = float(sg.max())
    step = th[1] - th[0]
    for k in np.argsort(-sg)[:5]:
        lo, hi = max(0.0, th[k] - step), min(math.pi, th[k] + step)
        r = minimize_scalar(lambda t: -sigma(t), bounds=(lo, hi), method="bounded", options={"xatol": 1e-12})
        best = max(best, -float(r.fun))
    return max(h_bil, best)


def closed_loop_radius(sm: SampledTS, K, mu=None) -> tuple[float, str]:
    """Largest spectral radius of ``sum_ij h_i h_j (A_iv + B_iv K_j)`` over the vertices v, at every
    rule (``h = e_i``) and, with ``mu`` (a list of membership vectors), at those blends too."""
    worst, where = -1.0, ""
    blends = [np.eye(sm.r)[i] for i in range(sm.r)] + [np.asarray(m, float) for m in (mu or [])]
    for v in range(sm.nv):
        for h in blends:
            Acl = sum(h[i] * h[j] * (sm.A[i][v] + sm.B[i][v] @ np.asarray(K[j], float))
                      for i in range(sm.r) for j in range(sm.r))
            rad = float(np.max(np.abs(np.linalg.eigvals(Acl))))
            if rad > worst:
                worst, where = rad, f"memberships {np.round(h, 3).tolist()}, {sm.vertices[v]}"
    return worst, where


def law_gains(sm: SampledTS, K) -> list[tuple[float, float, float]]:
    """The law's ``(kp, ki, kc)`` per rule from the scaled gains ``K_j = [K_m, 0]``.

    In physical measured coordinates ``u = F [y, i, z]`` with ``F = su K_m / S_m``; the law's
    ``u = -kp y + ki (z - Ts y) - kc i`` gives ``ki = F_z``, ``kp = -F_y - ki Ts``, ``kc = -F_i /
    current_gain``."""
    out = []
    for k in K:
        k = np.asarray(k, float).reshape(-1)
        F = sm.su * k[:sm.n_meas] / sm.S[:sm.n_meas]
        ki = float(F[-1])
        kp = float(-F[0] - ki * sm.ts_s)
        kc = float(-F[1] / sm.current_gain) if sm.n_meas == 3 else 0.0
        out.append((kp, ki, kc))
    return out


def sampled_stages(profile, ts, model, zero, effort_weight: float = 0.0):
    """The sampled model of the law's loop for a six-step TS model (:func:`picdrive.analysis.dlmi.sampled_model`)
    and the synthesis's continuation stages: the rule plants at the nominal EMF, then with the EMF range, then
    (the averaged model) with the DC equivalent added -- each stage starts from the previous one's gains."""
    k_i = 1.0
    if ts.n == 4:
        from ..models.dqmodel import dq_params
        k_i = dq_params(profile).ki_ibus_per_iq
    dc = model == "six-step-averaged"
    kw = dict(zero_gain_states=zero, current_gain=k_i, effort_weight=effort_weight)
    sm = sampled_model(profile, ts, dc_vertices=dc, **kw)
    stages = [sampled_model(profile, ts.with_(dA=None), **kw)]
    if dc and ts.dA is not None:
        stages.append(sampled_model(profile, ts, **kw))
    return sm, stages

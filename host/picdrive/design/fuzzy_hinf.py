"""Robust H-inf TS-fuzzy state feedback: Theorem 1 of the 2016 paper, in cvxpy.

The LMIs (12)-(15) as derived from the proof (eqs 18-29), for a TS model
(:class:`picdrive.models.tsfuzzy.TSModel`) and given ``gamma, delta, alpha, rho``::

    P > 0,   Xi_ii < 0,   Xi_ij + Xi_ji < 0 (i < j)        (for every polytope vertex v)

    Xi_ij = [ Psi_1ij   *        *        *       *          *          *         *      ]
            [ d I       -g I     *        *       *          *          *         *      ]
            [ d I       0        -g I     *       *          *          *         *      ]   (only if H2 != 0)
            [ Bw^T      0        0        -g I    *          *          *         *      ]
            [ Psi_2ij   0        0        0       -g I       *          *         *      ]
            [ Psi_3ij   0        0        0       0          -g I       *         *      ]   (only if H2 != 0)
            [ Psi_4ij   0        0        0       0          0          -g I      *      ]   (only if H3, H4 != 0)
            [ Psi_5ij   0        0        0       0          0          0         -g I   ]

    Psi_1ij = A_i P + P A_i^T + B_i Y_j + Y_j^T B_i^T
    Psi_2ij = (g rho/d) H1_i P          Psi_3ij = (g rho/d) H2_i Y_j
    Psi_4ij = sqrt(a) rho (H3_i P + H4_i Y_j)
    Psi_5ij = sqrt(a) (C_i P + D_i Y_j)

i.e. eq. (23), ``[[sym(A P + B Y), Bt_w, (Ct P + Dt Y)^T], [Bt_w^T, -g I, 0],
[Ct P + Dt Y, 0, -g I]] < 0`` with ``Bt_w = [d I, d I, Bw]`` and
``Ct = [g rho/d H1; 0; sqrt(a) rho H3; sqrt(a) C]``, ``Dt = [0; g rho/d H2;
sqrt(a) rho H4; sqrt(a) D]`` written out.  The printed (15) has ``Bw`` where
the proof needs ``Bw^T`` and ``H^T``, ``C^T``, ``D^T`` where it needs ``H``,
``C``, ``D`` (with H2 of size n x m the printed ``H2^T Y_j`` does not even have
compatible sizes); the empty ``0`` slot of ``w~`` is dropped (a decoupled
``-g I`` block changes nothing).  ``K_j = Y_j P^-1``.

What the certificate says: with ``V = g x^T P^-1 x`` every feasible point
gives ``dV/dt + |z~|^2 - g^2 |w~|^2 < 0``, hence ``int alpha |(C + D K) x|^2 +
alpha rho^2 |(H3 + H4 K) x|^2 <= g^2 int |w|^2``; by the triangle inequality
``|z|^2 <= 2 |(C+DK)x|^2 + 2 rho^2 |(H3+H4K)x|^2``, so alpha >= 2 gives the
theorem's L2 gain ``<= gamma``; with ``H3 = H4 = 0`` the bound is the sharper
``gamma / sqrt(alpha)``  (:func:`picdrive.analysis.lmi.certified_gain`).

Beyond the paper (``design()`` variants ``tracking`` and ``six-step``):
integral action on the speed error (:func:`picdrive.models.tsfuzzy.tracking_model`),
an input bound ``|K_j xi| <= mu`` on the invariant ellipsoid
``{xi: xi^T P^-1 xi <= 1}`` containing given points (Boyd et al. 1994,
sec. 7.2.3), an optional pole disk, and a structured gain with zero weight on
``i_d`` (block-diagonal ``P``, ``Y_j[:, i_d] = 0``) so that the six-step drive,
which measures only speed and bus current and has no ``v_d``, can run it.
"""
from __future__ import annotations

import math
import time
import warnings
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np

from ..analysis.dlmi import sampled_stages
from ..analysis.lmi import assemble, certified_gain, lmi_margins, nonzero, quiet_solve, xi_blocks
from ..analysis.sampled import sampled_radius, six_step_equilibrium
from ..control_law import ScheduledLaw
from ..errors import PicdriveError
from ..models.tsfuzzy import mechanical_corner_rad_s, model_for

__all__ = ["Theorem1Solution", "solve_theorem1", "minimise_gamma", "design", "DEFAULT_SOLVER", "FuzzyHinfError",
           "OPTIONS"]

DEFAULT_SOLVER = "CLARABEL"


class FuzzyHinfError(PicdriveError, ValueError):
    """Bad option or an infeasible fuzzy H-inf design request."""


@dataclass
class Theorem1Solution:
    """Result of one LMI solve."""

    feasible: bool
    status: str
    gamma: float
    delta: float
    alpha: float
    rho: float
    P: np.ndarray | None = None
    Y: list[np.ndarray] = field(default_factory=list)
    K: list[np.ndarray] = field(default_factory=list)
    max_eig: float = math.nan            # largest eigenvalue over all assembled LMIs (< 0: satisfied)
    solve_time_s: float = 0.0
    extra: dict[str, Any] = field(default_factory=dict)

    def certificate(self) -> dict[str, Any]:
        return {"gamma": self.gamma, "delta": self.delta, "alpha": self.alpha, "rho": self.rho,
                "P": self.P, "Y": self.Y, "K": self.K, "lmi_max_eig": self.max_eig,
                "solver_status": self.status, **self.extra}


# ---------------------------------------------------------------------------
# The cvxpy problem
# ---------------------------------------------------------------------------
class _Problem:
    """Theorem 1 as a cvxpy problem, compiled once.

    Two forms:

    * ``delta`` given (the paper's form): gamma is a cvxpy Parameter; the
      LMIs are not jointly linear in gamma (``g rho/d H1 P``), so gamma is
      minimised by bisection (:meth:`solve` per gamma).
    * ``delta=None``: the S-procedure multiplier ``tau = d^2/g`` is a variable
      (see :func:`picdrive.analysis.lmi.xi_blocks`) and gamma enters linearly, so the smallest gamma
      is one SDP.  With an input bound the Lyapunov matrix cannot be rescaled
      freely any more; the variables are then ``Q = P/t``, ``Yh = Y/t`` with
      separate diagonals ``-g_w`` (disturbance block) and ``-g_z`` (output
      block); the congruence ``diag(sqrt t, 1/sqrt t, sqrt t)`` with
      ``t = sqrt(g_w/g_z)`` maps a solution back to the paper's form with
      ``g = sqrt(g_w g_z)``, ``d = sqrt(g tau t)``.  The objective is
      ``g_w + g_z`` (>= 2 g).

    Numerics: the variables are scaled, ``P = S Pt S``, ``Y_j = Su Yt_j S``
    (``S``, ``Su`` diagonal typical magnitudes from ``ts.info``), and each LMI
    is multiplied on both sides by ``diag(S^-1, I, ...)`` -- an exact
    congruence, so the feasible set is unchanged while the solver sees O(1)
    data.  ``balanced`` (always for the centred solve, ``centre=gamma``: the
    analytic centre of the LMIs at that gamma) goes further: ``tau`` in units
    of a balancing scale with the uncertainty rows congruence-scaled to match,
    the pole-disk LMIs divided by the radius, and (centred solve) the gamma
    rows congruence-scaled by ``1/sqrt(gamma)``; without it the problem is
    posed as before, which :func:`minimise_gamma` without a back-off keeps
    (its infimum figures, e.g. ``picdrive report``'s, are solver-dependent
    anyway: the infimum is not attained).  Every returned solution is re-checked in numpy in the paper's form
    (:func:`picdrive.analysis.lmi.lmi_margins`).
    """

    def __init__(self, ts, delta, alpha, rho, *, zero_gain_states=(), input_bound=None, pole_disk_rad_s=None,
                 margin=1e-7, solver=DEFAULT_SOLVER, state_scale=None, input_scale=None, fixed_gamma=False,
                 centre: float | None = None, tau_scale: float | None = None, balanced: bool = False):
        import cvxpy as cp
        self.cp, self.ts, self.solver = cp, ts, solver
        self.delta = None if delta is None else float(delta)
        self.centre = centre is not None
        balanced = bool(balanced) or self.centre
        if self.centre and (self.delta is not None or input_bound is not None):
            raise ValueError("the centred solve is for delta=None without an input bound")
        self.fixed_gamma = bool(fixed_gamma) or self.delta is not None or self.centre
        self.alpha, self.rho = float(alpha), float(ts.rho if rho is None else rho)
        n, m, r = ts.n, ts.m, ts.r
        sx = np.asarray(state_scale if state_scale is not None else ts.info.get("state_scale", np.ones(n)), float)
        su = np.asarray(input_scale if input_scale is not None else ts.info.get("input_scale", np.ones(m)), float)
        S, Si, Su = np.diag(sx), np.diag(1.0 / sx), np.diag(su)
        zs = [k for k in range(n) if k in zero_gain_states]
        free = [k for k in range(n) if k not in zs]
        Pf = cp.Variable((len(free), len(free)), symmetric=True)
        Ef = np.zeros((n, len(free)))
        for a, k in enumerate(free):
            Ef[k, a] = 1.0
        Pt = Ef @ Pf @ Ef.T
        if zs:
            pz = cp.Variable(len(zs))
            Ez = np.zeros((n, len(zs)))
            for a, k in enumerate(zs):
                Ez[k, a] = 1.0
            Pt = Pt + Ez @ cp.diag(pz) @ Ez.T
        self.Pt = Pt
        self.Ytf = [cp.Variable((m, len(free))) for _ in range(r)]
        Yt = [y @ Ef.T for y in self.Ytf]
        P = S @ Pt @ S
        Y = [Su @ y @ S for y in Yt]
        self.P, self.Y = P, Y
        # centre: the analytic centre of the LMIs at the given gamma (the point that maximises the sum of the
        # log-determinants of every LMI's slack, in the scaled coordinates): a point deep inside the feasible set,
        # unique (the barrier is strictly concave), instead of one on its boundary
        self.slacks = []
        eps = 0.0 if self.centre else margin
        cons = [Pt >> eps * np.eye(n)]
        self.slacks.append(Pt)
        self.bounded = input_bound is not None
        if self.delta is not None:
            self.gamma = cp.Parameter(pos=True, value=1.0)
            g_w = g_z = self.gamma
            self.tau = None
            objective = cp.Minimize(0)
        else:
            # tau in units of its balancing scale (the uncertainty rows are congruence-scaled by 1/sqrt(c) in
            # xi(), so its blocks (sqrt(c) tau_t E^T, -tau_t), (rho H1 P / sqrt(c), -tau_t) are of the order of the
            # others): unscaled, tau is O(1e4) on the bundled motors and the solver's tolerances lose the gains
            et = float(np.linalg.norm(ts.E_matrix.T @ Si))
            h1 = max(float(np.linalg.norm(ts.H1[i] @ S)) for i in range(r))
            self.tau_scale = c_tau = (float(tau_scale) if tau_scale is not None
                                      else self.rho * h1 / et if balanced and et > 0 and h1 > 0 else 1.0)
            self.tau_t = cp.Variable(pos=True)
            self.tau = c_tau * self.tau_t
            cons.append(self.tau_t >= eps)
            self.slacks.append(cp.reshape(self.tau_t, (1, 1), order="C"))
            if self.centre:
                # gamma a constant (not a parameter), so that the gamma rows can be congruence-scaled by
                # 1/sqrt(gamma) in xi() (their diagonals -gamma -> -1): on duy2008 gamma is O(1e3)
                self.gamma = cp.Parameter(pos=True, value=float(centre))
                g_w = g_z = float(centre)
                objective = cp.Minimize(0)
            elif self.fixed_gamma and not self.bounded:
                self.gamma = cp.Parameter(pos=True, value=1.0)
                g_w = g_z = self.gamma
                objective = cp.Minimize(0)
            elif self.bounded:
                self.g_w, self.g_z = cp.Variable(pos=True), cp.Variable(pos=True)
                g_w, g_z = self.g_w, self.g_z
                objective = cp.Minimize(g_w + g_z)
            else:
                self.gamma = cp.Variable(pos=True)
                g_w = g_z = self.gamma
                objective = cp.Minimize(self.gamma)
        nv = ts.offsets.shape[0]

        def xi(i, j, v):
            psi1, col = xi_blocks(ts, i, j, v, P, Y[j], g_z, self.delta, self.alpha, self.rho, tau=self.tau,
                                   gamma_w=g_w)
            psi1 = Si @ psi1 @ Si          # congruence diag(S^-1, I, ...)
            col = [(blk @ Si, k, dg) for blk, k, dg in col]
            if self.tau is not None:       # congruence 1/sqrt(c) on the uncertainty rows (the -tau diagonals)
                h = int(nonzero(ts.H1[i])) + int(nonzero(ts.H2[i]))
                unc = set(range(h)) | set(range(h + 1, 2 * h + 1))
                col = [(blk / math.sqrt(c_tau), k, dg / c_tau) if a in unc else (blk, k, dg)
                       for a, (blk, k, dg) in enumerate(col)]
                if self.centre:            # congruence 1/sqrt(gamma) on the gamma rows
                    sg = math.sqrt(g_z)
                    col = [(blk, k, dg) if a in unc else (blk / sg, k, dg / g_z) for a, (blk, k, dg) in enumerate(col)]
            return assemble(psi1, col, cp.bmat)

        for v in range(nv):
            for i in range(r):
                X = xi(i, i, v)
                cons.append(0.5 * (X + X.T) << -eps * np.eye(X.shape[0]))
                self.slacks.append(-0.5 * (X + X.T))
                for j in range(i + 1, r):
                    X = xi(i, j, v) + xi(j, i, v)
                    cons.append(0.5 * (X + X.T) << -eps * np.eye(X.shape[0]))
                    self.slacks.append(-0.5 * (X + X.T))
        if self.bounded:
            if self.delta is not None:
                raise ValueError("an input bound needs delta=None (free S-procedure multiplier)")
            mu = np.asarray(input_bound["mu"], float).reshape(-1) * np.ones(m)
            for y in Yt:
                M = cp.bmat([[np.diag((mu / su) ** 2), y], [y.T, Pt]])
                cons.append(0.5 * (M + M.T) >> 0)
            for pt in input_bound.get("points", []):
                pt = (Si @ np.asarray(pt, float).reshape(n)).reshape(n, 1)
                M = cp.bmat([[np.ones((1, 1)), pt.T], [pt, Pt]])
                cons.append(0.5 * (M + M.T) >> 0)
        if pole_disk_rad_s is not None:
            q = float(pole_disk_rad_s)
            for v in range(nv):
                for i in range(r):
                    for j in range(i, r):
                        pairs = [(i, j)] if i == j else [(i, j), (j, i)]
                        blk = sum(Si @ ((ts.A[a] + ts.offsets[v]) @ P + ts.B[a] @ Y[b]) @ Si for a, b in pairs)
                        k = len(pairs)
                        qs = q if balanced else 1.0                       # divided by q: O(1) data
                        M = cp.bmat([[-q / qs * k * Pt, blk / qs], [blk.T / qs, -q / qs * k * Pt]])
                        cons.append(0.5 * (M + M.T) << -eps * np.eye(2 * n))
                        self.slacks.append(-0.5 * (M + M.T))
        if self.centre:
            objective = cp.Maximize(sum(cp.log_det(z) if z.shape[0] > 1 else cp.log(z[0, 0]) for z in self.slacks))
        self.prob = cp.Problem(objective, cons)

    def solve(self, gamma: float | None = None) -> Theorem1Solution:
        """Solve (``gamma`` is required in the paper's form and ignored otherwise)."""
        cp, ts = self.cp, self.ts
        if self.centre:
            gamma = self.gamma.value
        elif self.fixed_gamma:
            self.gamma.value = float(gamma)
        t0 = time.perf_counter()
        status, notes = quiet_solve(self.prob, self.solver)
        dt = time.perf_counter() - t0
        g0 = float(gamma) if self.fixed_gamma else math.nan
        sol = Theorem1Solution(False, str(status), g0, self.delta if self.delta is not None else math.nan,
                               self.alpha, self.rho, solve_time_s=dt)
        if notes:
            sol.extra["solver_notes"] = notes
        if status not in ("optimal", "optimal_inaccurate"):
            return sol
        if self.centre:
            sol.extra["centre_margin"] = min(float(np.linalg.eigvalsh(np.atleast_2d(z.value)).min())
                                             for z in self.slacks)
        P = np.asarray(self.P.value, float)
        Y = [np.asarray(y.value, float) for y in self.Y]
        if not np.all(np.isfinite(P)) or any(not np.all(np.isfinite(y)) for y in Y):
            return sol
        if self.delta is None:
            tau = float(self.tau.value)
            if self.bounded:
                gw, gz = float(self.g_w.value), float(self.g_z.value)
                t = math.sqrt(gw / gz)
                g = math.sqrt(gw * gz)
                P, Y = t * P, [t * y for y in Y]
                sol.extra.update(gamma_w=gw, gamma_z=gz, ellipsoid_scale=t,
                                 ellipsoid_P=np.asarray(self.P.value, float))
            else:
                t, g = 1.0, (float(gamma) if self.fixed_gamma else float(self.gamma.value))
            sol.gamma = g
            sol.delta = math.sqrt(g * tau * t)
            sol.extra["tau"] = tau
        P = 0.5 * (P + P.T)
        sol.P, sol.Y = P, Y
        sol.K = [y @ np.linalg.inv(P) for y in Y]
        marg = lmi_margins(ts, P, Y, sol.gamma, sol.delta, self.alpha, self.rho)
        sol.max_eig = max(marg.values())
        sol.extra["lmi_margins"] = marg
        sol.feasible = sol.max_eig < 0.0
        return sol


def solve_theorem1(ts, gamma: float, delta: float | None = 1.0, alpha: float = 2.0, rho: float | None = None, *,
                   zero_gain_states: Sequence[int] = (), pole_disk_rad_s: float | None = None,
                   solver: str = DEFAULT_SOLVER) -> Theorem1Solution:
    """Solve LMIs (12)-(15) for a given gamma and delta; ``K_j = Y_j P^-1``.

    ``feasible`` is True only when the solver found a point *and* the
    assembled inequalities, re-evaluated in numpy, are strictly negative
    (``max_eig < 0``).  ``delta=None`` searches the best delta for this gamma
    (free S-procedure multiplier; the gamma is then fixed by a constraint).
    """
    pr = _Problem(ts, delta, alpha, rho, zero_gain_states=tuple(zero_gain_states),
                  pole_disk_rad_s=pole_disk_rad_s, solver=solver, fixed_gamma=True)
    return pr.solve(gamma)


#: design()'s back-off from the gamma infimum: the gains are taken at (1 + GAMMA_BACK_OFF) x gamma_min, at the
#: centre of the feasible set there (see minimise_gamma)
GAMMA_BACK_OFF = 0.05


def minimise_gamma(ts, delta: float | None = None, alpha: float = 2.0, rho: float | None = None, *,
                   gamma_hi: float = 1e3, gamma_lo: float = 1e-4, rel_tol: float = 0.01,
                   zero_gain_states: Sequence[int] = (), input_bound: dict | None = None,
                   pole_disk_rad_s: float | None = None, solver: str = DEFAULT_SOLVER,
                   progress=None, back_off: float = 0.0) -> Theorem1Solution:
    """Smallest feasible gamma, or with ``back_off`` a well-conditioned point a little above it.

    ``delta=None`` (default): delta is optimised with gamma -- one SDP (with an
    input bound: minimises ``g_w + g_z``, see :class:`_Problem`).
    ``delta`` given (the paper's form): bisection on gamma in
    ``[gamma_lo, gamma_hi]`` to a relative tolerance; ``extra`` then holds
    ``gamma_infeasible`` (the largest gamma found infeasible) and ``n_solves``.

    ``back_off`` (``delta=None`` without an input bound; :func:`design` uses
    :data:`GAMMA_BACK_OFF`): the infimum is approached with gains that grow
    without bound and the feasible set thins to nothing there, so a point at
    (or within the bisection's tolerance of) the infimum is whatever the
    solver stopped on -- it moves with the solver's tolerances, its scaling and
    the last digits of the data.  Instead the gains are taken at ``gamma =
    (1 + back_off) gamma_min`` at the analytic centre of the LMIs there (the
    point that maximises the sum of the log-determinants of their slacks:
    unique, strictly inside every LMI, :func:`_analytic_centre`; its smallest
    slack eigenvalue in the scaled coordinates is ``extra["centre_margin"]``);
    ``gamma_min`` is the SDP's optimal value (a well-conditioned number even
    where the point is not), or the bisection's when the SDP does not end
    ``optimal``.  ``extra`` records ``gamma_min``, ``gamma_back_off`` and, when
    the centred solve does not end ``optimal`` at ``back_off``, 2 ``back_off``
    and 4 ``back_off``, ``centring`` (why) with the infimum point kept.
    """
    if back_off and delta is None and input_bound is None:
        return _centred(ts, alpha, rho, back_off=back_off, gamma_hi=gamma_hi, gamma_lo=gamma_lo, rel_tol=rel_tol,
                        zero_gain_states=zero_gain_states, pole_disk_rad_s=pole_disk_rad_s, solver=solver,
                        progress=progress)
    return _infimum(ts, delta, alpha, rho, gamma_hi=gamma_hi, gamma_lo=gamma_lo, rel_tol=rel_tol,
                    zero_gain_states=zero_gain_states, input_bound=input_bound, pole_disk_rad_s=pole_disk_rad_s,
                    solver=solver, progress=progress)


def _centred(ts, alpha, rho, *, back_off, zero_gain_states, pole_disk_rad_s, solver, progress,
             **bisection) -> Theorem1Solution:
    """:func:`minimise_gamma` with a back-off: the centred point at ``(1 + back_off) gamma_min``."""
    t0 = time.perf_counter()
    zero = tuple(zero_gain_states)
    sdp = _Problem(ts, None, alpha, rho, zero_gain_states=zero, pole_disk_rad_s=pole_disk_rad_s,
                   solver=solver, balanced=True).solve()
    n_solves = 1
    infimum = None
    if sdp.status in ("infeasible", "infeasible_inaccurate", "unbounded"):
        sdp.extra.update(n_solves=n_solves, bisection_time_s=time.perf_counter() - t0)
        return sdp
    if sdp.status == "optimal" and math.isfinite(sdp.gamma):
        g_min = sdp.gamma
    else:
        infimum = _infimum(ts, None, alpha, rho, zero_gain_states=zero, pole_disk_rad_s=pole_disk_rad_s,
                           solver=solver, progress=progress, **bisection)
        n_solves += int(infimum.extra.get("n_solves", 0))
        if not infimum.feasible:
            return infimum
        g_min = infimum.gamma
    why = []
    for k in (1.0, 2.0, 4.0):
        s, n = _analytic_centre(ts, alpha, rho, (1.0 + k * back_off) * g_min, zero, pole_disk_rad_s, solver,
                                hint=sdp if infimum is None else infimum)
        n_solves += n
        if s.status == "optimal" and s.feasible:
            s.extra.update(gamma_min=g_min, gamma_back_off=k * back_off, n_solves=n_solves,
                           gamma_min_from="sdp" if infimum is None else "bisection",
                           bisection_time_s=time.perf_counter() - t0)
            return s
        why.append(f"gamma = {1 + k * back_off:g} gamma_min: status {s.status!r}"
                   + ("" if s.status != "optimal" else f", largest LMI eigenvalue {s.max_eig:.3g}"))
    if infimum is None:
        infimum = _infimum(ts, None, alpha, rho, zero_gain_states=zero, pole_disk_rad_s=pole_disk_rad_s,
                           solver=solver, progress=progress, **bisection)
        n_solves += int(infimum.extra.get("n_solves", 0))
    infimum.extra.update(gamma_min=g_min, n_solves=n_solves, bisection_time_s=time.perf_counter() - t0,
                         centring="the centred solve failed (" + "; ".join(why) + "): the infimum's point is kept")
    return infimum


def _analytic_centre(ts, alpha, rho, gamma, zero, pole_disk_rad_s, solver, hint=None) -> tuple[Theorem1Solution, int]:
    """The analytic centre of Theorem 1's LMIs (delta free) at ``gamma``, and the number of solves.

    The centre maximises the sum of the log-determinants of every LMI's slack.  It does not depend on the
    variables' scaling (a congruence adds a constant to each log-determinant), but the solver's accuracy does:
    with the model's typical magnitudes alone the Lyapunov matrix's eigenvalues spread over three decades on
    duy2008 and Clarabel stops short ("AlmostSolved"), at gains that move by 1e-2 with the solver's settings.
    So a solve only supplies the scaling of the next (the state scale ``sqrt(diag P)``, the multiplier's scale
    ``tau``), and a rescaled solve that ends ``optimal`` decides.  The first solve starts from the model's
    magnitudes, then (when that gives no point) from ``hint`` (a solution near the infimum)."""
    def solve(scale):
        sx, ct = scale
        return _Problem(ts, None, alpha, rho, zero_gain_states=zero, pole_disk_rad_s=pole_disk_rad_s, solver=solver,
                        centre=gamma, state_scale=sx, tau_scale=ct).solve()

    def scale_of(sol):
        if sol is None or sol.P is None or not np.all(np.isfinite(sol.P)) or np.min(np.diag(sol.P)) <= 0.0 \
                or not sol.extra.get("tau", 0.0) > 0.0:
            return None
        return np.sqrt(np.diag(sol.P)), float(sol.extra["tau"])

    n = 0
    s = None
    for start in [(None, None), scale_of(hint)]:
        if start is None:
            continue
        s = solve(start)
        n += 1
        for _ in range(2):
            scale = scale_of(s)
            if scale is None:
                break
            s = solve(scale)
            n += 1
            if s.status == "optimal" and s.feasible:
                return s, n
    return s, n


def _infimum(ts, delta, alpha, rho, *, gamma_hi=1e3, gamma_lo=1e-4, rel_tol=0.01, zero_gain_states=(),
             input_bound=None, pole_disk_rad_s=None, solver=DEFAULT_SOLVER, progress=None) -> Theorem1Solution:
    """:func:`minimise_gamma` without a back-off: the smallest gamma found feasible."""
    t0 = time.perf_counter()
    n_solves = 0
    sdp = None               # the one-SDP solution (delta=None), kept if its refinement cannot start
    if delta is None:
        pr = _Problem(ts, None, alpha, rho, zero_gain_states=tuple(zero_gain_states), input_bound=input_bound,
                      pole_disk_rad_s=pole_disk_rad_s, solver=solver)
        s = sdp = pr.solve()
        n_solves += 1
        if input_bound is not None or not (s.feasible or math.isfinite(s.gamma)):
            s.extra.update(n_solves=n_solves, bisection_time_s=time.perf_counter() - t0)
            return s
        # the SDP optimum is often not attained (gains grow without bound towards the infimum) and
        # interior-point solvers stop early there (sometimes a hair outside the strict LMIs); refine
        # by bisection on fixed-gamma feasibility
        gamma_hi = s.gamma if s.feasible else 2.0 * s.gamma
    pr = _Problem(ts, delta, alpha, rho, zero_gain_states=tuple(zero_gain_states),
                  pole_disk_rad_s=pole_disk_rad_s, solver=solver, fixed_gamma=True)
    hi = pr.solve(gamma_hi)
    n_solves += 1
    if not hi.feasible and sdp is not None and sdp.feasible:
        # the re-solve sits exactly at the SDP's optimum, the infimum, where the strict LMIs leave no room: the
        # solver can fail there (Clarabel: "solver error") although the SDP's own point, re-checked in numpy,
        # is feasible; keep that point instead of calling the disk infeasible
        sdp.extra.update(n_solves=n_solves, gamma_infeasible=None, bisection_time_s=time.perf_counter() - t0,
                         refinement=f"not refined: the fixed-gamma re-solve at the SDP's gamma gave {hi.status!r}")
        return sdp
    if not hi.feasible:
        hi.extra.update(n_solves=n_solves, gamma_infeasible=gamma_hi, bisection_time_s=time.perf_counter() - t0)
        return hi
    lo_g = gamma_lo
    lo = pr.solve(lo_g)
    n_solves += 1
    if lo.feasible:
        lo.extra.update(n_solves=n_solves, gamma_infeasible=None, bisection_time_s=time.perf_counter() - t0)
        return lo
    best, g_hi = hi, hi.gamma
    while g_hi / lo_g > 1.0 + rel_tol:
        g = math.sqrt(g_hi * lo_g)
        s = pr.solve(g)
        n_solves += 1
        if progress is not None:
            progress(g, s.feasible)
        if s.feasible:
            best, g_hi = s, g
        else:
            lo_g = g
    best.extra.update(n_solves=n_solves, gamma_infeasible=lo_g, bisection_time_s=time.perf_counter() - t0)
    return best




# ---------------------------------------------------------------------------
# picdrive design --method fuzzy-hinf
# ---------------------------------------------------------------------------
VARIANTS = ("six-step", "tracking", "paper")

#: options of design() (besides variant, gamma, progress), with their meaning
OPTIONS: dict[str, str] = {
    "delta": "Theorem 1 delta (default: optimised with gamma; the profile's design.delta is the paper's 1)",
    "alpha": "Theorem 1 alpha (default profile design.alpha = 2)",
    "rho": "uncertainty bound rho (default profile design.rho)",
    "rules": "number of fuzzy rules r (default profile design.rules)",
    "resistance_uncertainty": "relative R uncertainty (default profile design.resistance_uncertainty)",
    "pole_disk_rad_s": "closed-loop poles inside |s| < this (six-step default: the largest of pi/(2 Ts) x 0.8^k "
                       "whose sampled loop with the firmware's measurement has spectral radius <= "
                       "max_spectral_radius and passes the verification)",
    "integral_weight_rad_s": "weight of the speed-error integral in z (default: six-step, the motor's mechanical "
                             "corner (B + Kt Kb/R)/J; dq tracking, 0.2 of it)",
    "max_spectral_radius": "six-step: the disk search's bound on the sampled loop's spectral radius (default 0.95)",
    "emf_polytope": "six-step: the EMF polytope over the commutated pair's EMF range (default true)",
    "plant_model": "six-step: 'averaged' (default profile design.plant_model = \"averaged\": the "
                   "speed-dependent averaged six-step model identified from the drive's three-phase plant, "
                   "picdrive.models.averaged: one linearisation per rule centre, distinct rule gains), 'six-step' "
                   "(the DC equivalent with the commutated EMF range) or 'dq' (the dq tracking model with v_d = 0, "
                   "zero gain on i_d)",
    "solver": f"cvxpy solver (default {DEFAULT_SOLVER})",
    "simulate": "run the nonlinear verification simulation (default true)",
    "setpoint_weight": "six-step: law's b (default: the largest of 1 + Kb/kp, its midpoint with 1, and 1 that "
                       "passes the verification; the certified loop is the same for every b)",
    "time_domain": "six-step: 'continuous' (Theorem 1 in continuous time with the pole-disk search, checked on "
                   "the sampled loop afterwards) or 'discrete' (the H-inf synthesis at the speed-loop rate on the "
                   "sampled model with the computation delay and the firmware's speed measurement, "
                   "picdrive.design.fuzzy_dhinf); default: the continuous design, and where it fails for the "
                   "law's sake the loop-rate one",
    "effort_weight_rad_s_per_v": "six-step, discrete: weight of the command in the H-inf output (default: 0, "
                                 "then w_top/u_max x 1, 4, 16 until the law verifies)",
    "pole_disk_radius": "six-step, discrete: every closed-loop pole inside |z| < this (default none: the H-inf "
                        "certificate alone, which already puts them inside the unit circle)",
    "zero_gain_states": "six-step: states with zero gain (default none; [1] drops the current feedback, which the "
                        "block-diagonal Lyapunov structure then makes infeasible on the bundled motors)",
}


def loop_bandwidth_rad_s(profile) -> float:
    """The speed bandwidth the sampled loop can carry, rad/s: a quarter of the inverse of its delays.

    The delays: the zero-order hold and the command applied one sample after its measurement (1.5 Ts at
    ``control.speed_loop_hz``) and the speed measurement's lag -- half a sample for the encoder's M/T
    measurement (a mean over the sample), half a hall sector at half the step target for the speed from
    the halls (a sector's mean; the verification judges the drive at half the target too).  At
    ``1 / (4 tau)`` a pure delay ``tau`` costs 0.25 rad (14 degrees) of phase, the usual allowance that keeps
    a loop's phase margin for its own dynamics.  duy2008 (1 kHz, encoder): 125 rad/s; a 4-pole-pair motor
    at a 3000 rpm step from the halls: 107 rad/s.
    """
    ts = 1.0 / float(profile.control.speed_loop_hz)
    if profile.sensors.speed_source == "hall":
        n_half = 0.5 * profile.speed_step_rpm()
        sector_s = 60.0 / (max(n_half, 1.0) * profile.motor.pole_pairs * 6.0)
        lag = 0.5 * sector_s
    else:
        lag = 0.5 * ts
    return 1.0 / (4.0 * (1.5 * ts + lag))


def default_pole_disk(profile, ts) -> float:
    """Pole-disk radius, rad/s: a quarter of the sample rate in rad/s
    (``pi/(2 Ts)``: the hold's half-sample delay costs at most 22 deg there),
    but never inside the plant's own modes (the dq model's i_d mode cannot be
    moved by a six-step drive), which get 25 % room."""
    ts_s = 1.0 / profile.control.speed_loop_hz
    plant = max(float(np.max(np.abs(np.linalg.eigvals(ts.A[i] + ts.offsets[v]))))
                for i in range(ts.r) for v in range(ts.offsets.shape[0]))
    return max(math.pi / (2.0 * ts_s), 1.25 * plant)


def no_certificate_reason(profile, ts, disk_rad_s: float) -> str | None:
    """Why Theorem 1 with a pole disk of ``disk_rad_s`` has no solution on the six-step model, at any
    gamma, or None when this argument does not apply.

    The winding's current mode sits at ``-R/L``.  Only the current feedback ``kc`` can move it
    (to ``-(R' + kc)/L``), and the certificate must hold for every ``R'`` in
    ``R (1 -+ eps)`` (Assumption 1): stability at ``R (1 - eps)`` needs ``kc > -R (1 - eps)``, which
    leaves the mode at ``|s| > eps R / L`` at the nominal ``R`` on which the disk is imposed.  When
    ``eps R/L`` is outside the disk (a winding whose L/R is short against the speed-loop period) no
    gain places the loop in it -- a larger gamma cannot help."""
    m = profile.motor
    eps = float(ts.info.get("resistance_uncertainty", profile.design.get("resistance_uncertainty", 0.1)))
    r_over_l = m.r_line_ohm / m.l_line_h
    if eps * r_over_l < disk_rad_s:
        return None
    return (f"no fuzzy-hinf certificate exists at any gamma: the winding's current mode is at R/L = "
            f"{r_over_l:.4g} 1/s (L/R = {1e6 / r_over_l:.3g} us); only current feedback can slow it, and it must "
            f"stay stable for R within -+{100 * eps:g} % (design.resistance_uncertainty), so it cannot come closer "
            f"than eps R/L = {eps * r_over_l:.4g} rad/s, outside the largest pole disk the "
            f"{profile.control.speed_loop_hz:g} Hz sampled law allows (pi/(2 Ts) = {disk_rad_s:.4g} rad/s); "
            f"use mixed-pid or zn (no current feedback), or a speed loop of at least "
            f"{2 * eps * r_over_l / math.pi:.4g} Hz")


def integrator_need_v(profile, rules, b: float) -> float:
    """Largest ``|I*| = |u* + kp (1 - b) w* + kc i*|`` the law's integrator holds at the six-step
    equilibria (standstill and the step target, with and without the load, R at its uncertainty
    extremes), V."""
    eps = float(profile.design.get("resistance_uncertainty", 0.1))
    need = 0.0
    for w in (0.0, profile.speed_step_rpm() * 2 * math.pi / 60):
        for load in (0.0, profile.control.load_torque_n_m):
            for rs in (1.0 - eps, 1.0, 1.0 + eps):
                i, u = six_step_equilibrium(profile, w, load, rs)
                for g in rules:
                    need = max(need, abs(u + g.kp * (1.0 - b) * w + g.kc * i))
    return need


def _law_from_gains(profile, ts, K, setpoint_weight: float | None = None) -> "ScheduledLaw":
    """Six-step gains -> the firmware's law.

    Six-step model (states ``[d_omega, d_i, d_z]``): ``u = K_w w + K_i i + K_z z``
    is the law's ``u = kp (b r - y) + I - kc i`` with ``kp = -K_w``, ``kc = -K_i``,
    ``ki = K_z`` (``I = int ki (r - y)``).  dq tracking model (``[d_omega, d_i_q,
    d_i_d, d_z]``, ``i_bus = k_i i_q``): ``kc = -K_iq / k_i``, ``K_id = 0`` by
    construction.  The law carries the firmware's current window and an
    integrator range of 1.25 x what its equilibria need.
    """
    from ..control_law import Rule, ScheduledLaw
    rules = []
    dq = ts.n == 4
    k_i = 1.0
    if dq:
        from ..models.dqmodel import dq_params
        k_i = dq_params(profile).ki_ibus_per_iq
    for k in K:
        k = np.asarray(k, float).reshape(-1)
        if dq and abs(k[2]) > 1e-9 * max(1.0, np.max(np.abs(k))):
            raise FuzzyHinfError(f"six-step gain has a nonzero i_d weight {k[2]:g}: the structure constraint failed")
        rules.append(Rule(kp=float(-k[0]), ki=float(k[-1]), kd=0.0, kc=float(-k[1] / k_i)))
    return _law_from_rules(profile, ts, rules, setpoint_weight)


def _law_from_rules(profile, ts, rules, setpoint_weight: float | None = None) -> "ScheduledLaw":
    """The firmware's law from its rules (:class:`picdrive.control_law.Rule`): the current window, an
    integrator range of 1.25 x what the equilibria need, the premise of ``ts``."""
    from ..control_law import ScheduledLaw
    u_max = profile.inverter.bus_voltage_v * profile.max_duty()
    b = 1.0 if setpoint_weight is None else float(setpoint_weight)
    i_lim = 1.25 * max(u_max, integrator_need_v(profile, rules, b))
    m = profile.motor
    return ScheduledLaw(rules=tuple(rules), premise_rad_s=tuple(ts.premise_rad_s),
                        sample_time_s=1.0 / profile.control.speed_loop_hz, u_min_v=-u_max, u_max_v=u_max,
                        setpoint_weight=b, derivative_filter_hz=None, integrator_limit_v=i_lim,
                        current_limit_a=profile.inverter.current_limit_a, kb_v_s_per_rad=m.kb_v_s_per_rad,
                        r_ohm=m.r_line_ohm,
                        notes=f"fuzzy-hinf six-step: u = kp ({b:g} r - w) - kc i_bus + int ki (r - w) per rule")


# option -> (kind, low, high) of its value; the profile's [design] bounds where the profile has the field
_OPTION_KINDS: dict[str, tuple] = {
    "pole_disk_rad_s": (float, 1e-6, 1e9),
    "integral_weight_rad_s": (float, 0.0, 1e9),
    "max_spectral_radius": (float, 1e-6, 1.0),
    "emf_polytope": (bool, None, None),
    "simulate": (bool, None, None),
    "plant_model": (str, None, None),
    "solver": (str, None, None),
    "setpoint_weight": (float, 0.0, 1.999),
    "zero_gain_states": (list, None, None),
    "time_domain": (str, None, None),
    "pole_disk_radius": (float, 1e-3, 0.9999),
    "effort_weight_rad_s_per_v": (float, 0.0, 1e9),
}


def _check_options(options: dict, gamma) -> None:
    """Refuse an option value of the wrong type or range (None: the default), naming option and range."""
    from ..profile import SCHEMA
    for name, v in [("gamma", gamma), *options.items()]:
        if v is None:
            continue
        if name in _OPTION_KINDS:
            kind, lo, hi = _OPTION_KINDS[name]
        else:
            k, _default, lo, hi, _doc = SCHEMA["design"][name]
            kind = int if k == "int" else float
        if kind is list:
            if not (isinstance(v, list) and all(isinstance(z, int) and not isinstance(z, bool) and 0 <= z <= 3
                                                for z in v)):
                raise FuzzyHinfError(f"option {name}={v!r}: expected a list of state indices 0..3, e.g. [1]")
            continue
        if kind is bool or kind is str:
            if not isinstance(v, kind):
                raise FuzzyHinfError(f"option {name}={v!r}: expected {'true or false' if kind is bool else 'a name'}")
            continue
        ok = isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and lo <= v <= hi
        if kind is int and ok:
            ok = float(v).is_integer()
        if not ok:
            raise FuzzyHinfError(f"option {name}={v!r}: expected {'an integer' if kind is int else 'a number'} "
                                 f"in [{lo:g}, {hi:g}] ({OPTIONS.get(name, 'prescribed H-inf level')})")


def design(profile, *, drive=None, progress: bool = True, variant: str = "six-step", gamma: float | None = None,
           **options):
    """Design, verify and return a :class:`picdrive.result.DesignResult`.

    ``variant``: ``six-step`` (default; one voltage, speed + bus current,
    integral action, runs on the firmware), ``tracking`` (two inputs v_q, v_d,
    full state + integral; needs a field-oriented drive, ``law: null``) or
    ``paper`` (Theorem 1 exactly as the 2016 paper: regulator ``u = K x``,
    ``law: null``).  ``gamma``: prescribed level (default: minimised).

    Six-step: Theorem 1 on :func:`picdrive.models.tsfuzzy.six_step_model` (the drive's
    DC equivalent with the commutated EMF polytope and R uncertainty) with a
    pole disk; the disk is the largest of ``pi/(2 Ts) x 0.8^k`` at which the law
    (gamma minimised) keeps the sampled loop with the firmware's measurement
    within ``max_spectral_radius`` and passes :func:`picdrive.design.verify.verify_design`.
    Every tried disk is recorded (``certificate.disk_tries``).
    """
    import time as _t
    from ..result import DesignResult
    from .verify import drive_limit_failed, verify_design      # verify reads this module's certificates
    if variant not in VARIANTS:
        raise FuzzyHinfError(f"unknown fuzzy-hinf variant {variant!r}; choose one of {', '.join(VARIANTS)}")
    unknown = sorted(set(options) - set(OPTIONS))
    if unknown:
        raise FuzzyHinfError(f"unknown fuzzy-hinf option(s) {', '.join(map(repr, unknown))}; known options: "
                             f"{', '.join(OPTIONS)}")
    _check_options(options, gamma)
    if variant == "six-step" and "time_domain" not in options and gamma is None:
        # the default: the continuous Theorem 1 (seconds, reproducible to 1e-4), and where it fails for the
        # law's sake -- no certificate for a fast winding, a sampled loop it did not design for -- the
        # synthesis at the loop rate (minutes); a limit of the drive no gains pass ends it there
        discrete_only = ("pole_disk_radius", "effort_weight_rad_s_per_v")
        cont = design(profile, drive=drive, progress=progress, variant=variant,
                      **{k: v for k, v in options.items() if k not in discrete_only}, time_domain="continuous")
        if cont.ok or drive_limit_failed(cont):
            return cont
        return _fall_back_to_discrete(profile, cont, drive=drive, progress=progress, options=options,
                                      limit_failed=drive_limit_failed)
    d = profile.design
    alpha = float(options.get("alpha", d.get("alpha", 2.0)))
    rho = float(options.get("rho", d.get("rho", 1.0)))
    delta = options.get("delta")
    delta = None if delta is None else float(delta)
    solver = options.get("solver", DEFAULT_SOLVER)
    simulate = bool(options.get("simulate", True))
    # the six-step design's plant: the option, else the profile's design.plant_model (default "averaged");
    # the other variants have their own model
    plant_model = options.get("plant_model")
    plant_note = None
    # the averaged model by default, not asked for (no option, not in the profile's [design]): it may fall back
    by_default = (plant_model is None and variant == "six-step"
                  and "plant_model" not in (profile.raw.get("design") or {}))
    if plant_model is None and variant != "six-step":
        plant_model = "six-step"
    elif plant_model is None:
        plant_model = d.get("plant_model", "averaged")
        if plant_model == "averaged" and drive is None and by_default:
            # the default, not asked for, cannot be had without the drive's plant: say so, never silently
            plant_note = ("designed on the DC equivalent (plant_model 'six-step'), not the default averaged model: "
                          "no built drive was given to identify it from (pass drive=picdrive.gate.BuiltDrive(), "
                          "as picdrive design does)")
            warnings.warn(f"fuzzy-hinf, profile {profile.name!r}: {plant_note}", stacklevel=2)
            plant_model = "six-step"
    if plant_model not in ("six-step", "averaged", "dq"):
        raise FuzzyHinfError(f"option plant_model={plant_model!r}: expected 'averaged' (the default), 'six-step' "
                             "(the DC equivalent) or 'dq'")
    if plant_model == "averaged" and variant != "six-step":
        raise FuzzyHinfError(f"option plant_model='averaged' is a six-step model: drop --variant {variant} "
                             "(or the option)")
    if plant_model == "averaged" and drive is None:
        raise FuzzyHinfError("option plant_model='averaged' identifies the speed-dependent model from the drive's "
                             "three-phase plant: it needs the built drive (picdrive design passes it; in Python "
                             "pass drive=picdrive.gate.BuiltDrive())")
    time_domain = options.get("time_domain", "continuous")
    if time_domain not in ("discrete", "continuous"):
        raise FuzzyHinfError(f"option time_domain={time_domain!r}: expected 'continuous' (Theorem 1) or 'discrete' "
                             "(the synthesis at the loop rate; by default tried where the continuous design fails)")
    if time_domain == "discrete" and variant != "six-step":
        raise FuzzyHinfError(f"option time_domain='discrete' designs the six-step drive's sampled loop: drop "
                             f"--variant {variant} (or the option)")
    if time_domain == "discrete" and gamma is not None:
        raise FuzzyHinfError("a prescribed gamma is the continuous design's (Theorem 1): at the loop rate gamma is "
                             "minimised; drop gamma or pass time_domain='continuous'")
    if time_domain == "discrete" and options.get("pole_disk_rad_s") is not None:
        raise FuzzyHinfError("option pole_disk_rad_s is the continuous design's (rad/s); at the loop rate the "
                             "pole region is pole_disk_radius (|z| < radius), or time_domain='continuous'")
    if time_domain == "continuous" and options.get("pole_disk_radius") is not None:
        raise FuzzyHinfError("option pole_disk_radius is the discrete design's; the continuous one takes "
                             "pole_disk_rad_s")
    model_opts = {k: options.get(k) for k in ("rules", "resistance_uncertainty", "integral_weight_rad_s")}
    model_opts["rho"] = rho
    t_ident = None
    if variant == "six-step" and plant_model in ("six-step", "averaged"):
        model = "six-step"
        if options.get("emf_polytope") is not None:
            model_opts["emf_polytope"] = bool(options["emf_polytope"])
        if model_opts["integral_weight_rad_s"] is None:
            model_opts["integral_weight_rad_s"] = mechanical_corner_rad_s(profile.motor)
        # a winding no pole disk can hold (no_certificate_reason: R/L alone decides) is refused before the
        # identification, which would cost seconds for nothing (the continuous design only: at the loop rate
        # the current mode is a sampled pole like any other)
        top_disk = math.pi / 2.0 * profile.control.speed_loop_hz if options.get("pole_disk_rad_s") is None \
            else float(options["pole_disk_rad_s"])
        if plant_model == "averaged" and (time_domain == "discrete" or not no_certificate_reason(
                profile, model_for(profile, "six-step", model_opts), top_disk)):
            from ..models.averaged import identify_cached
            model = "six-step-averaged"
            ti = _t.perf_counter()
            model_opts["averaged"] = identify_cached(profile, drive.three_phase_plant).to_dict()
            t_ident = _t.perf_counter() - ti
    else:
        model = {"paper": "paper", "tracking": "tracking-dq", "six-step": "tracking-six-step"}[variant]
    t0 = _t.perf_counter()
    ts = model_for(profile, model, model_opts)
    t_model = _t.perf_counter() - t0
    if variant == "six-step":
        zero = tuple(int(z) for z in options.get("zero_gain_states", (2,) if model == "tracking-six-step" else ()))
    else:
        zero = ()
    sw = options.get("setpoint_weight")
    b = None if sw is None else float(sw)
    rho_max = float(options.get("max_spectral_radius", 0.95))
    res_opts = {"gamma": gamma, **{k: v for k, v in options.items()}, "alpha": alpha, "rho": rho, "delta": delta}
    if variant == "six-step":
        res_opts["plant_model"] = plant_model      # the record names the model the gains were designed on
    if time_domain == "discrete":
        res_opts["time_domain"] = time_domain
    else:
        # a continuous design's record carries no time_domain: every record made before the loop-rate synthesis
        # became the default is one (the bundled designs under examples/), and they stay valid
        res_opts.pop("time_domain", None)

    def solve(disk):
        if gamma is None:
            return minimise_gamma(ts, delta=delta, alpha=alpha, rho=rho, zero_gain_states=zero,
                                  pole_disk_rad_s=disk, solver=solver, back_off=GAMMA_BACK_OFF)
        return solve_theorem1(ts, float(gamma), delta=delta, alpha=alpha, rho=rho, zero_gain_states=zero,
                              pole_disk_rad_s=disk, solver=solver)

    def result_of(sol, disk):
        res = DesignResult(method="fuzzy-hinf", variant=variant, status="verified", profile_name=profile.name,
                           profile_sha256=profile.sha256, law=None,
                           profile_path=None if profile.path is None else str(profile.path),
                           options={**res_opts, "pole_disk_rad_s": disk})
        if not sol.feasible:
            res.fail(f"Theorem 1 LMIs infeasible for {variant!r} (gamma={gamma if gamma is not None else 'minimised'}, "
                     f"delta={delta if delta is not None else 'free'}, alpha={alpha:g}, rho={rho:g}, pole disk "
                     f"{disk if disk is not None else 'none'}): solver status {sol.status!r}, largest LMI eigenvalue "
                     f"{sol.max_eig:.3g}; " + ("gamma was a variable of the problem, so a larger gamma cannot help: "
                                               "try a smaller pole disk (option pole_disk_rad_s)" if gamma is None
                                               and delta is None else "try a larger gamma or delta=None"))
            res.certificate = {"model": model, "model_options": model_opts, "solver_status": sol.status,
                               "gamma": sol.gamma, "feasible": False, "pole_disk_rad_s": disk}
            if plant_note:
                res.certificate["plant_model_fallback"] = plant_note
            return res
        cert = sol.certificate()
        cert.update(model=model, model_options=model_opts, certified_gain=certified_gain(ts, sol.gamma, alpha),
                    pole_disk_rad_s=disk, premise_rad_s=list(ts.premise_rad_s),
                    state_names=list(ts.state_names), input_names=list(ts.input_names))
        cert.pop("ellipsoid_P", None)
        if plant_note:
            cert["plant_model_fallback"] = plant_note
        if "emf_range_v_s" in ts.info:
            cert["emf_range_v_s"] = list(ts.info["emf_range_v_s"])
        res.certificate = cert
        if variant == "six-step":
            res.law = _law_from_gains(profile, ts, sol.K, b)
        elif variant == "tracking":
            cert["why_no_law"] = ("two inputs (v_q, v_d) and full dq state feedback: needs a field-oriented "
                                  "drive; the six-step firmware commands one voltage and measures speed and "
                                  "bus current only (use --variant six-step)")
        else:
            cert["why_no_law"] = ("the 2016 paper's regulator u = K x (two inputs v_q, v_d, no integral "
                                  "action, regulates x to 0): not a speed tracker and not realisable on a "
                                  "six-step drive (use --variant six-step)")
        return res

    t1 = _t.perf_counter()
    timings = {"model": t_model} if t_ident is None else {"identify": t_ident, "model": t_model}
    if variant != "six-step":
        disk = None
        if variant != "paper":
            disk = float(options["pole_disk_rad_s"]) if options.get("pole_disk_rad_s") is not None \
                else default_pole_disk(profile, ts)
        sol = solve(disk)
        timings["lmi"] = _t.perf_counter() - t1
        res = result_of(sol, disk)
        res.timings_s = timings
        if sol.feasible:
            t2 = _t.perf_counter()
            verify_design(profile, res, drive=drive, simulate=simulate)
            res.timings_s["verify"] = _t.perf_counter() - t2
        return res

    if time_domain == "discrete":
        res = _design_discrete(profile, ts, model, model_opts, zero, b, drive=drive, simulate=simulate,
                               solver=solver, res_opts={**res_opts, "time_domain": "discrete"},
                               radius=options.get("pole_disk_radius"), plant_note=plant_note, timings=timings,
                               effort_weight=options.get("effort_weight_rad_s_per_v"))
        if by_default and model == "six-step-averaged" and not res.ok and not drive_limit_failed(res):
            res = _fall_back_to_dc(profile, res, drive=drive, progress=progress, gamma=gamma, options=options)
        return res

    # six-step: the pole disk from the sampled loop with the firmware's measurement and the verification
    if options.get("pole_disk_rad_s") is not None:
        disks = [float(options["pole_disk_rad_s"])]
    else:
        top = math.pi / 2.0 * profile.control.speed_loop_hz
        floor = default_pole_disk(profile, ts) if model == "tracking-six-step" else 0.0
        disks = [top * 0.8 ** k for k in range(12) if top * 0.8 ** k >= floor]
    tries: list[dict] = []
    res = None
    t_lmi = t_ver = 0.0
    why_none = no_certificate_reason(profile, ts, max(disks)) if model in ("six-step", "six-step-averaged") else None
    if why_none:
        res = result_of(Theorem1Solution(False, "not attempted", math.nan, math.nan, alpha, rho), max(disks))
        res.reasons.clear()
        res.fail(why_none)
        res.certificate["why_no_certificate"] = why_none
        disks = []
    for disk in disks:
        ta = _t.perf_counter()
        sol = solve(disk)
        t_lmi += _t.perf_counter() - ta
        r = result_of(sol, disk)
        entry: dict[str, Any] = {"pole_disk_rad_s": disk, "gamma": sol.gamma if sol.feasible else None}
        if not sol.feasible:
            entry["status"] = f"infeasible ({sol.status})"
            tries.append(entry)
            res = res or r
            continue
        rad, _ = sampled_radius(profile, r.law)
        entry["sampled_spectral_radius"] = rad
        if rad > rho_max and len(disks) > 1:
            entry["status"] = f"sampled spectral radius {rad:.4f} > {rho_max:g}"
            tries.append(entry)
            res = r
            continue
        # the setpoint weight: b = 1 + Kb/kp makes the reference path carry the back-EMF (kp (b - 1) r =
        # Kb r), so the integrator, which the law fills only into its output headroom, has only the IR
        # drop of friction and load to find; b does not enter the certified loop w -> z
        if b is None:
            kp_t = r.law.gains_at(profile.speed_step_rpm() * 2 * math.pi / 60).kp
            b_emf = 1.0 + profile.motor.kb_v_s_per_rad / kp_t if kp_t > 0 else 1.0
            b_emf = min(b_emf, 1.9)
            b_list = [b_emf, 0.5 * (1.0 + b_emf), 1.0] if b_emf > 1.0 + 1e-6 else [1.0]
        else:
            b_list = [b]
        entry["setpoint_weights"] = []
        for bb in b_list:
            rb = result_of(sol, disk) if bb != b_list[0] else r
            rb.law = _law_from_gains(profile, ts, sol.K, bb)
            tb = _t.perf_counter()
            verify_design(profile, rb, drive=drive, simulate=simulate)
            t_ver += _t.perf_counter() - tb
            note = _weight_margin_note(rb, bb != b_list[-1] and simulate)
            entry["setpoint_weights"].append({"b": bb, "status": rb.status if not note else "not kept",
                                              "reasons": [x[:160] for x in rb.reasons] + ([note] if note else [])})
            r = rb
            if rb.ok and not note:
                break
        entry["status"] = r.status
        entry["reasons"] = list(r.reasons)
        tries.append(entry)
        res = r
        if r.ok:
            break
    if res is None:
        raise FuzzyHinfError("no pole disk to try: give pole_disk_rad_s")
    if res.law is not None and res.status != "failed" and not res.verification:
        verify_design(profile, res, drive=drive, simulate=simulate)
    if not res.ok and not res.reasons:
        res.fail("no pole disk gave a law within the sampled-loop bound: " +
                 "; ".join(f"{t['pole_disk_rad_s']:.0f} rad/s: {t['status']}" for t in tries))
    res.certificate["disk_tries"] = tries
    res.timings_s = {**timings, "lmi": t_lmi, "verify": t_ver}
    if by_default and model == "six-step-averaged" and not res.ok and not drive_limit_failed(res):
        return _fall_back_to_dc(profile, res, drive=drive, progress=progress, gamma=gamma, options=options)
    return res


def _weight_margin_note(rb, above_one: bool) -> str:
    """Why a verified law with a setpoint weight above 1 (``above_one``) is not kept: a weight above 1 is
    kept only with the 0.5 % overshoot margin (mixed-pid's GA bound), at R nominal and -+ its uncertainty:
    the model under-predicts the twin's overshoot by up to ~0.7 point (docs/design-fuzzy.md).  Empty: kept."""
    if not (rb.ok and above_one):
        return ""
    v = rb.verification
    worst = max([v["sim_overshoot_pct"]["value"]] +
                [f["overshoot_pct"] for f in v["sim_resistance_uncertainty"]["value"].values() if isinstance(f, dict)])
    return f"overshoot {worst:.3g} % > the 0.5 % margin kept for b > 1" if worst > 0.5 else ""


def _fall_back_to_discrete(profile, failed, *, drive, progress, options, limit_failed):
    """The default continuous design failed for the law's sake: the synthesis at the loop rate, judged by the
    same verification; when it verifies it is returned with the reason in ``certificate.time_domain_fallback``
    and a warning (never silently), else the continuous failure with the loop-rate design's reason added.
    Seen on the corpus: fast windings (L/R 15-40 us) have no continuous certificate at any gamma and verify at
    the loop rate (docs/design-fuzzy.md)."""
    why = "; ".join(x[:200] for x in failed.reasons[:2]) or failed.status
    continuous_only = ("pole_disk_rad_s",)
    disc_opts = {**{k: v for k, v in options.items() if k not in continuous_only}, "time_domain": "discrete"}
    disc = design(profile, drive=drive, progress=progress, variant="six-step", **disc_opts)
    weight_note = ""
    if not disc.ok and not limit_failed(disc) and options.get("integral_weight_rad_s") is None:
        # the default integral weight is the motor's mechanical corner; where that is faster than the loop
        # with its delays and speed measurement can follow, the H-inf optimum is an integrator-dominated law
        # that overshoots (kp near 0): the design asks again for the bandwidth the loop can carry
        corner = mechanical_corner_rad_s(profile.motor)
        cap = loop_bandwidth_rad_s(profile)
        if cap < corner:
            # the loop's bandwidth, then half of it: the first that verifies is kept (as the continuous design
            # walks its pole disk down and the loop-rate design its effort weight up)
            spent = float(sum(disc.timings_s.values()))
            why_corner = "; ".join(x[:160] for x in disc.reasons[:1]) or disc.status
            for w in (cap, 0.5 * cap):
                capped = design(profile, drive=drive, progress=progress, variant="six-step",
                                **{**disc_opts, "integral_weight_rad_s": w})
                capped.timings_s = {"corner_weight_attempt": spent, **capped.timings_s}
                spent += float(sum(v for k, v in capped.timings_s.items() if k != "corner_weight_attempt"))
                if capped.ok or limit_failed(capped):
                    break
            weight_note = (f"integral weight {w:.4g} rad/s ({w / cap:g} x loop_bandwidth_rad_s: the loop's delays "
                           f"and speed measurement) instead of the motor's mechanical corner {corner:.4g} rad/s, at "
                           f"which the loop-rate design failed ({why_corner})")
            if capped.ok:
                capped.certificate["integral_weight_note"] = weight_note
            else:
                capped.reasons.append(f"at integral weights {cap:.4g} and {0.5 * cap:.4g} rad/s (the loop's bandwidth "
                                      f"and half of it) and at the mechanical corner's {corner:.4g} it fails too: "
                                      + why_corner)
            disc = capped
    if not disc.ok:
        failed.reasons.append("the synthesis at the loop rate (time_domain 'discrete') fails too: "
                              + ("; ".join(x[:200] for x in disc.reasons[:1]) or disc.status))
        failed.timings_s = {"discrete_attempt": float(sum(disc.timings_s.values())), **failed.timings_s}
        return failed
    note = f"designed at the loop rate, not by the continuous Theorem 1: the continuous design failed ({why})"
    if weight_note:
        note += "; " + weight_note
    disc.certificate["time_domain_fallback"] = note
    disc.timings_s = {"continuous_attempt": float(sum(failed.timings_s.values())), **disc.timings_s}
    warnings.warn(f"fuzzy-hinf, profile {profile.name!r}: {note}", stacklevel=3)
    return disc


def _design_discrete(profile, ts, model, model_opts, zero, b, *, drive, simulate, solver, res_opts, radius,
                     plant_note, timings, effort_weight=None):
    """The six-step law designed at the speed-loop rate (:mod:`picdrive.design.fuzzy_dhinf`), verified.

    The gains are the centred solution of the sampled-loop LMIs on every rule, R vertex and EMF vertex (and,
    on the averaged model, the DC equivalent the verification's sampled check uses); the setpoint weight is
    chosen as the continuous design's (the largest of ``1 + Kb/kp``, its midpoint with 1, and 1 that verifies).
    """
    # the command's weight in the H-inf output, rad/s per V: none first (the speed error alone), then the
    # full command priced as the full speed error (w_top / u_max) and 4 and 16 times that -- gentler gains at
    # each step, the first that verifies is kept (as the continuous design walks its pole disk down)
    u_max = profile.inverter.bus_voltage_v * profile.max_duty()
    w_top = max(float(ts.info.get("state_scale", [1.0])[0]), 1.0)
    base = w_top / u_max
    weights = [float(effort_weight)] if effort_weight is not None else [0.0, base, 4.0 * base, 16.0 * base]
    tries: list[dict] = []
    out = None
    t_all = 0.0
    for ew in weights:
        r = _design_discrete_at(profile, ts, model, model_opts, zero, b, ew, drive=drive, simulate=simulate,
                                solver=solver, res_opts=res_opts, radius=radius, plant_note=plant_note,
                                timings=timings)
        t_all += sum(v for k, v in r.timings_s.items() if k in ("lmi", "verify"))
        tries.append({"effort_weight_rad_s_per_v": ew, "status": r.status, "gamma": r.certificate.get("gamma"),
                      "reasons": [x[:200] for x in r.reasons[:3]]})
        if out is None or r.ok or (not out.ok and r.certificate.get("feasible") and
                                   not out.certificate.get("feasible")):
            out = r
        if r.ok:
            break
    out.certificate["effort_tries"] = tries
    if not out.ok and len(tries) > 1:
        out.reasons.append("tried effort weights " + ", ".join(f"{t['effort_weight_rad_s_per_v']:.3g}" for t in tries)
                           + " rad/s per V: " + "; ".join(f"{t['effort_weight_rad_s_per_v']:.3g}: "
                                                          f"{(t['reasons'] or [t['status']])[0][:120]}"
                                                          for t in tries))
    return out


def _status_words(status: str) -> str:
    """A solver status for a picdrive message: a solver exception's text (which suggests options picdrive
    does not have, e.g. cvxpy's "solve with verbose=True") is replaced by what it means."""
    if status.startswith("solver error"):
        return "numerical failure (the interior-point solver stopped without a point)"
    return status


def _design_discrete_at(profile, ts, model, model_opts, zero, b, effort_weight, *, drive, simulate, solver,
                        res_opts, radius, plant_note, timings):
    """:func:`_design_discrete` at one effort weight."""
    import time as _t
    from ..analysis.dlmi import closed_loop_radius, law_gains
    from ..control_law import Rule
    from ..result import DesignResult
    from .fuzzy_dhinf import solve_discrete
    from .verify import verify_design
    t0 = _t.perf_counter()
    sm, stages = sampled_stages(profile, ts, model, zero, effort_weight)
    sol = solve_discrete(sm, radius=None if radius is None else float(radius), solver=solver, start=stages)
    t_lmi = _t.perf_counter() - t0
    opts = {**res_opts, "pole_disk_radius": radius}
    opts.pop("pole_disk_rad_s", None)
    res = DesignResult(method="fuzzy-hinf", variant="six-step", status="verified", profile_name=profile.name,
                       profile_sha256=profile.sha256, law=None,
                       profile_path=None if profile.path is None else str(profile.path), options=opts)
    cert: dict[str, Any] = {"time_domain": "discrete", "model": model, "model_options": model_opts,
                            "effort_weight_rad_s_per_v": effort_weight,
                            "solver_status": sol.status, "gamma": sol.gamma, "pole_disk_radius": radius,
                            "sample_time_s": sm.ts_s, "delay_s": sm.delay_s, "vertices": list(sm.vertices),
                            "zero_gain_states": list(zero), "premise_rad_s": list(ts.premise_rad_s),
                            "state_names": list(sm.state_names), "measured": list(sm.meas_names),
                            **{k: v for k, v in sol.extra.items() if k not in ("lmi_margins", "solver_notes")}}
    if plant_note:
        cert["plant_model_fallback"] = plant_note
    if "emf_range_v_s" in ts.info:
        cert["emf_range_v_s"] = list(ts.info["emf_range_v_s"])
    res.certificate = cert
    res.timings_s = {**timings, "lmi": t_lmi}
    if not sol.feasible:
        why = sol.extra.get("why") or sol.extra.get("centring") or ""
        res.fail(f"no H-inf certificate for the sampled loop ({sm.r} rules x {sm.nv} vertices: "
                 f"{', '.join(sm.vertices[:3])}{', ...' if sm.nv > 3 else ''}) at {profile.control.speed_loop_hz:g} Hz"
                 f" with the firmware's law (kp, ki, kc): solver status {_status_words(sol.status)!r}"
                 + (f", largest LMI eigenvalue {sol.max_eig:.3g}" if math.isfinite(sol.max_eig) else "")
                 + (f"; {why}" if why else "")
                 + "; try mixed-pid or zn, or time_domain='continuous'")
        cert["feasible"] = False
        return res
    ms = sol.model
    cert.update(feasible=True, lmi_max_eig=sol.max_eig, K=[np.asarray(k) for k in sol.K], Q=sol.Q, G=sol.G,
                Y=[np.asarray(y) for y in sol.Y], Qd=sol.Qd, state_scale=np.asarray(ms.S),
                certified_gain=sol.gamma)
    rad, _ = closed_loop_radius(ms, sol.K)
    cert["design_spectral_radius"] = rad
    rules = tuple(Rule(kp=kp, ki=ki, kd=0.0, kc=kc) for kp, ki, kc in law_gains(ms, sol.K))
    if b is None:
        law0 = _law_from_rules(profile, ts, rules, 1.0)
        kp_t = law0.gains_at(profile.speed_step_rpm() * 2 * math.pi / 60).kp
        b_emf = 1.0 + profile.motor.kb_v_s_per_rad / kp_t if kp_t > 0 else 1.0
        b_emf = min(b_emf, 1.9)
        b_list = [b_emf, 0.5 * (1.0 + b_emf), 1.0] if b_emf > 1.0 + 1e-6 else [1.0]
    else:
        b_list = [b]
    tries = []
    t_ver = 0.0
    out = None
    for bb in b_list:
        rb = DesignResult(method="fuzzy-hinf", variant="six-step", status="verified", profile_name=profile.name,
                          profile_sha256=profile.sha256, law=_law_from_rules(profile, ts, rules, bb),
                          profile_path=res.profile_path, options=dict(opts))
        rb.certificate = dict(cert)
        rb.timings_s = dict(res.timings_s)
        tb = _t.perf_counter()
        verify_design(profile, rb, drive=drive, simulate=simulate)
        t_ver += _t.perf_counter() - tb
        note = _weight_margin_note(rb, bb != b_list[-1] and simulate)
        tries.append({"b": bb, "status": rb.status if not note else "not kept",
                      "reasons": [x[:160] for x in rb.reasons] + ([note] if note else [])})
        out = rb
        if rb.ok and not note:
            break
    out.certificate["setpoint_weights"] = tries
    out.timings_s["verify"] = t_ver
    return out


def _fall_back_to_dc(profile, failed, *, drive, progress, gamma, options):
    """The default averaged-model design failed: design on the DC equivalent; when that verifies, return it
    with the reason in ``certificate.plant_model_fallback`` and a warning (never silently), else the
    averaged-model failure with the DC equivalent's reason added.

    Seen on motors picdrive has never seen (docs/motors.md): on some windings (BLY171D, Multistar 4225)
    the averaged rules' effective resistance at speed (1.6-2.1 R) lets Theorem 1 drop the top rule's current
    feedback, and the verification's sampled-loop check, on the DC equivalent (R), rejects those gains at every
    disk; the DC-equivalent design verifies there (docs/scheduling.md, bench/averaged_sampled.py)."""
    why = "; ".join(x[:200] for x in failed.reasons[:2]) or failed.status
    dc = design(profile, drive=drive, progress=progress, variant="six-step", gamma=gamma,
                **{**options, "plant_model": "six-step"})
    if not dc.ok:
        failed.reasons.append("on the DC equivalent (plant_model 'six-step') the design fails too: "
                              + ("; ".join(x[:200] for x in dc.reasons[:1]) or dc.status))
        return failed
    note = (f"designed on the DC equivalent (plant_model 'six-step'), not the default averaged model: the "
            f"averaged-model design failed ({why})")
    dc.certificate["plant_model_fallback"] = note
    dc.timings_s = {"averaged_attempt": float(sum(failed.timings_s.values())), **dc.timings_s}
    warnings.warn(f"fuzzy-hinf, profile {profile.name!r}: {note}", stacklevel=3)
    return dc

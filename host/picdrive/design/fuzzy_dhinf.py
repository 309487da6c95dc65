"""Robust H-inf TS-fuzzy state feedback at the speed-loop rate: the LMIs of
:mod:`picdrive.analysis.dlmi` in cvxpy, minimised and then centred.

:func:`solve_discrete` returns the gains of the law at ``(1 + back_off) gamma_min``,
at the analytic centre of the LMIs there (the point that maximises the sum of the
log-determinants of every LMI's slack): unique and strictly inside every
inequality, so the gains do not move with the solver's last digits the way a point
on the boundary at ``gamma_min`` does (the continuous design's
:func:`picdrive.design.fuzzy_hinf.minimise_gamma` does the same).  Every returned
point is re-checked in numpy (:func:`picdrive.analysis.dlmi.dlmi_margins`).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..analysis.dlmi import (SampledTS, assemble, brl_blocks, disk_blocks, dlmi_margins, normalised, pair_sum,
                             rescaled)

__all__ = ["DiscreteSolution", "solve_discrete", "GAMMA_BACK_OFF"]

#: the gains are taken at (1 + GAMMA_BACK_OFF) x gamma_min, at the analytic centre of the LMIs there
GAMMA_BACK_OFF = 0.05

#: bound on ||G|| (normalised units, :func:`picdrive.analysis.dlmi.normalised`).  The extended BRL leaves
#: the slack unbounded along the closed loop's deadbeat directions (``A_cl v = 0``, ``C v = 0``: the
#: held command and the averaged speed's memory are such states), where ``Q`` and ``G`` grow together and
#: every log-determinant with them: no analytic centre exists without a bound, and the minimisation drifts
#: there too.  The part of ``G`` the output sees is at most ~2 gamma (normalised: O(1)), so the bound only
#: closes the degenerate directions; it is part of the centred problem's definition (the centre depends on it).
G_BOUND = 1e3
#: weight of trace(Q) (+ trace(Q_d)) added to gamma in the minimisations (normalised units): it keeps the
#: solver off the same degenerate directions; gamma_min moves by about REG x trace(Q), a fraction of a percent
REG = 1e-4
#: centred rounds after the alternation (solve_discrete)
CENTRE_ROUNDS = 3
#: most alternations of the gains and the slack (solve_discrete)
MAX_ALTERNATIONS = 5


@dataclass
class DiscreteSolution:
    """One solve of the sampled-loop LMIs (scaled coordinates of :class:`picdrive.analysis.dlmi.SampledTS`)."""

    feasible: bool
    status: str
    gamma: float = math.nan
    Q: np.ndarray | None = None
    Qd: np.ndarray | None = None
    G: np.ndarray | None = None
    Y: list = field(default_factory=list)
    K: list = field(default_factory=list)
    max_eig: float = math.nan           # largest negated smallest eigenvalue over the LMIs (< 0: satisfied)
    solve_time_s: float = 0.0
    extra: dict[str, Any] = field(default_factory=dict)
    model: SampledTS | None = None      # the (normalised, rescaled) model Q, G, Y, K refer to


def _problem(sm: SampledTS, radius: float | None, centre_gamma: float | None, solver: str,
             g_bound: float | None = None, *, K_fixed=None, G_fixed=None):
    """The cvxpy problem: minimise gamma (``centre_gamma`` None) or the analytic centre at that gamma.

    Three forms of the same inequalities (:mod:`picdrive.analysis.dlmi`), ``K_j = [K_m, 0]`` in each:

    * default (*structured*): ``G = [[G_m, 0], [G_um, G_u]]``, ``Y_j = [Y_m, 0]``: jointly convex, the start;
    * ``K_fixed`` (the rules' ``K_j``): the gains given, ``G`` full, ``Y_j = K_j G``;
    * ``G_fixed``: ``G`` given (full), the measured gains ``K_m`` free, ``Y_j = [K_m, 0] G``.

    Alternating the last two (:func:`solve_discrete`) lowers gamma below the structured form's, whose
    zero block in ``G`` is what makes it conservative."""
    import cvxpy as cp
    n, nm, r = sm.n, sm.n_meas, sm.r
    nu = n - nm
    Q = cp.Variable((n, n), symmetric=True)
    Qd = cp.Variable((n, n), symmetric=True)
    Gm = Gu = Gum = None
    Ym = []
    if K_fixed is not None:
        G = cp.Variable((n, n))
        Y = [np.asarray(k, float).reshape(1, n) @ G for k in K_fixed]
    elif G_fixed is not None:
        G = np.asarray(G_fixed, float)
        Ym = [cp.Variable((1, nm)) for _ in range(r)]
        Y = [cp.hstack([k, np.zeros((1, nu))]) @ G for k in Ym]
    else:
        # G block lower-triangular: with Y_j = [Y_m, 0], K_j = Y_j G^-1 = [Y_m G_m^-1, 0] (G^-1 is
        # lower-triangular too): the usual static-output-feedback condition C G = M C, in coordinates where the
        # measurements are the first states
        Gm, Gu, Gum = cp.Variable((nm, nm)), cp.Variable((nu, nu)), cp.Variable((nu, nm))
        G = cp.bmat([[Gm, np.zeros((nm, nu))], [Gum, Gu]])
        Ym = [cp.Variable((1, nm)) for _ in range(r)]
        Y = [cp.hstack([y, np.zeros((1, nu))]) for y in Ym]
    if centre_gamma is None:
        gamma = cp.Variable(pos=True)
        scale = False
    else:
        gamma = float(centre_gamma)
        scale = True
    eps = 0.0 if centre_gamma is not None else 1e-7
    gb = G_BOUND if g_bound is None else float(g_bound)
    slacks = [Q]
    cons = [Q >> eps * np.eye(n)]
    if radius is not None:
        slacks.append(Qd)
        cons.append(Qd >> eps * np.eye(n))
    if math.isfinite(gb) and G_fixed is None:
        Gb = cp.bmat([[gb * np.eye(n), G], [G.T, gb * np.eye(n)]])
        Gb = 0.5 * (Gb + Gb.T)
        slacks.append(Gb)
        cons.append(Gb >> 0)
    tr = lambda M: M.T  # noqa: E731
    for v in range(sm.nv):
        for i in range(r):
            for j in range(i, r):
                M = assemble(pair_sum(lambda a, b: brl_blocks(sm, a, b, v, Q, G, Y[b], gamma, scale_gamma=scale),
                                      i, j), cp.bmat, tr)
                M = 0.5 * (M + M.T)
                cons.append(M >> eps * np.eye(M.shape[0]))
                slacks.append(M)
                if radius is None:
                    continue
                D = assemble(pair_sum(lambda a, b: disk_blocks(sm, a, b, v, Qd, G, Y[b], radius), i, j), cp.bmat, tr)
                D = 0.5 * (D + D.T)
                cons.append(D >> eps * np.eye(D.shape[0]))
                slacks.append(D)
    if centre_gamma is None:
        obj = cp.Minimize(gamma + REG * (cp.trace(Q) + (cp.trace(Qd) if radius is not None else 0)))
    else:
        obj = cp.Maximize(sum(cp.log_det(z) for z in slacks))
    var = dict(Q=Q, Qd=Qd, G=G, Y=Y, gamma=gamma, Ym=Ym)
    if K_fixed is not None:
        var["K_fixed"] = K_fixed
    return cp.Problem(obj, cons), var


def _read(sm, prob, var, status, radius, dt) -> DiscreteSolution:
    sol = DiscreteSolution(False, status, solve_time_s=dt)
    if status not in ("optimal", "optimal_inaccurate"):
        return sol
    g = var["gamma"]
    sol.gamma = float(g.value) if hasattr(g, "value") else float(g)
    def val(x):
        return x if isinstance(x, np.ndarray) else x.value
    if val(var["Q"]) is None or val(var["G"]) is None or (radius is not None and var["Qd"].value is None):
        return sol
    Q, G = (np.asarray(val(var[k]), float) for k in ("Q", "G"))
    Qd = np.asarray(var["Qd"].value, float) if radius is not None else np.eye(Q.shape[0])
    Y = [np.asarray(val(y), float) for y in var["Y"]]
    if not all(np.all(np.isfinite(M)) for M in [Q, Qd, G, *Y]):
        return sol
    sol.Q, sol.G, sol.Y = 0.5 * (Q + Q.T), G, Y
    sol.Qd = 0.5 * (Qd + Qd.T) if radius is not None else None
    try:
        Gi = np.linalg.inv(G)
    except np.linalg.LinAlgError:
        return sol
    nm = sm.n_meas
    if "K_fixed" in var:
        K = [np.asarray(k, float).reshape(1, -1) for k in var["K_fixed"]]
    else:
        K = [y @ Gi for y in Y]
    # K_j = [K_m, 0] exactly (the structure makes the unmeasured part zero up to rounding)
    K = [np.hstack([k[:, :nm], np.zeros((1, k.shape[1] - nm))]) for k in K]
    sol.K = K
    try:
        marg = dlmi_margins(sm, sol.Q, G, Y, sol.gamma, Qd=sol.Qd, radius=radius)
    except np.linalg.LinAlgError:
        # a point with finite entries so large (SCS's, seen at 1e300) that the LMIs' eigenvalues do not
        # converge: no certificate, said as such rather than raised
        sol.K = []
        sol.extra["why"] = "the solver's point is numerically unusable (the LMIs' eigenvalues do not converge there)"
        return sol
    sol.max_eig = max(marg.values())
    sol.extra["lmi_margins"] = marg
    sol.feasible = sol.max_eig < 0.0
    return sol


def solve_discrete(sm: SampledTS, *, radius: float | None = 0.95, back_off: float = GAMMA_BACK_OFF,
                   solver: str = "CLARABEL", start=None) -> DiscreteSolution:
    """Smallest gamma of the sampled-loop LMIs with every closed-loop pole in ``|z| < radius``, then
    the analytic centre at ``(1 + back_off) gamma_min`` (module docstring).

    Returns the centred solution (``extra``: ``gamma_min``, ``gamma_back_off``, ``centre_margin`` the
    smallest slack eigenvalue, ``n_solves``); when the centred solve does not end ``optimal`` and
    strictly feasible at ``back_off``, 2 ``back_off`` and 4 ``back_off``, the minimising point is kept
    with the reason in ``extra["centring"]``; an infeasible minimisation is returned as it ended.
    """
    from ..analysis.lmi import quiet_solve
    from dataclasses import replace
    t0 = time.perf_counter()
    n_solves = 0
    notes_all: list[str] = []
    # equal rules (the DC equivalent: the r rules share their matrices): one rule's LMIs, the gains copied --
    # the analytic centre of the r-rule problem has Y_1 = ... = Y_r anyway (it is unique and symmetric)
    r_all = sm.r
    same = all(all(np.array_equal(x[i][v], x[0][v]) for v in range(sm.nv)) for x in (sm.A, sm.B, sm.Bw)
               for i in range(sm.r)) and all(np.array_equal(c, sm.C[0]) for c in sm.C)
    if same and sm.r > 1:
        sm = replace(sm, A=sm.A[:1], B=sm.B[:1], Bw=sm.Bw[:1], C=sm.C[:1], D=None if sm.D is None else sm.D[:1])

    def run(model, centre=None, disk=True, sv=solver, **kw):
        nonlocal n_solves
        t1 = time.perf_counter()
        prob, var = _problem(model, radius if disk else None, centre, sv, **kw)
        status, notes = quiet_solve(prob, sv, **({"max_iters": 4000} if sv == "SCS" else {}))
        n_solves += 1
        notes_all.extend(notes)
        s = _read(model, prob, var, status, radius if disk else None, time.perf_counter() - t1)
        s.model = model
        return s

    def done(sol, nb, nc):
        sol.extra.update(n_solves=n_solves, total_time_s=time.perf_counter() - t0)
        if notes_all:
            sol.extra["solver_notes"] = list(notes_all)
        if sol.K and same and r_all > 1:
            sol.K = [sol.K[0]] * r_all
            sol.Y = [sol.Y[0]] * r_all
        return _physical(sol, nb, nc)

    # the states' scaling from a first solve: the model's typical magnitudes put the Lyapunov matrix's
    # eigenvalues over five decades (duy2008: 1e-2 .. 4e2, the held command's direction largest), where the
    # interior-point solver stops on numerical errors; sqrt(diag Q) of a first solve makes them O(1).  The
    # first solve is the structured one on the start model (default: the model itself) without the pole disk
    # (with it, on the unscaled model, the solver fails outright); SCS when Clarabel fails there (only its
    # scale is used)
    stages = [] if start is None else (list(start) if isinstance(start, (list, tuple)) else [start])
    if same:
        stages = [replace(x, A=x.A[:1], B=x.B[:1], Bw=x.Bw[:1], C=x.C[:1], D=None if x.D is None else x.D[:1])
                  for x in stages]
    st = sm if not stages else stages[0]
    st0, _, _ = normalised(st)
    first = run(st0, disk=False)
    if first.Q is None and solver != "SCS":
        first = run(st0, disk=False, sv="SCS")
    if first.Q is None or not np.all(np.diag(first.Q) > 0):
        return done(first, 1.0, 1.0)
    d = np.sqrt(np.diag(first.Q))
    st1, _, _ = normalised(rescaled(st, d))
    sm1, nb, nc = normalised(rescaled(sm, d))

    def alternate(model, best, G_last=None, disk=True):
        """Alternate: the gains fixed, the best full slack G; that G fixed, the best gains.  Each step is
        feasible at the previous point, so gamma never rises; stop when it falls by less than 1 %."""
        for _ in range(MAX_ALTERNATIONS):
            a = run(model, K_fixed=best.K, disk=disk)
            if not a.feasible:
                return best, G_last, a
            b = run(model, G_fixed=a.G, disk=disk)
            if not b.feasible:
                return best, G_last, b
            G_last = a.G
            gain = (best.gamma - b.gamma) / best.gamma if math.isfinite(best.gamma) else 1.0
            best = b
            if gain < 1e-2:
                break
        return best, G_last, None

    # the start: the structured solve on the start model, then the alternation there; then (a start model
    # given) the alternation on the model itself from the start's gains
    best = run(st1, disk=False)
    if not best.feasible:
        return done(best, nb, nc)
    best, G_last, _ = alternate(st1 if stages else sm1, best, disk=False)
    # continuation: each further stage (then the model itself) from the previous stage's gains
    for nxt in [normalised(rescaled(x, d))[0] for x in stages[1:]] + ([sm1] if stages else []):
        trial = DiscreteSolution(True, "start", gamma=math.inf, K=best.K)
        prev = best
        best, G_last, fail = alternate(nxt, trial, disk=False)
        if G_last is None:
            # the previous stage's gains do not hold here: this stage's own structured solve, then alternate
            own = run(nxt, disk=False)
            if own.feasible:
                best, G_last, fail = alternate(nxt, own, disk=False)
        if G_last is None:
            return done(_no_certificate(fail, prev, f"no certificate on the vertex set of {nxt.nv} vertices per "
                                        "rule, neither from the previous stage's gains nor from its own structured "
                                        "solve"), nb, nc)
    if radius is not None and G_last is not None:
        # the pole disk last: from the disk-free optimum's gains (with the disk from the start the structured
        # solve is infeasible on the bundled motors)
        best, G_disk, fail = alternate(sm1, DiscreteSolution(True, "no disk", gamma=math.inf, K=best.K), disk=True)
        if G_disk is None:
            return done(_no_certificate(fail, best, f"no certificate with every closed-loop pole inside "
                                        f"|z| < {radius:g} from the disk-free design's gains"), nb, nc)
        G_last = G_disk
    best.extra["alternations_gamma"] = best.gamma
    if G_last is None:
        best.extra["centring"] = "no alternation step was feasible: the structured solve's point is kept"
        return done(best, nb, nc)
    g_min = best.gamma
    why = []
    for k in (1.0, 2.0, 4.0):
        gc = (1.0 + k * back_off) * g_min
        # centred rounds: the slack G at the analytic centre of the LMIs with the gains fixed, then the gains at
        # the analytic centre with that G fixed, at the same gamma -- both points unique; the alternation's G
        # (a minimiser, on the boundary) moved the gains by 10 % under a 1e-9 perturbation of the model
        s, K = None, best.K
        for _ in range(CENTRE_ROUNDS):
            a = run(sm1, gc, K_fixed=K)
            if not (a.status == "optimal" and a.feasible):
                s = a
                break
            s = run(sm1, gc, G_fixed=a.G)
            if not (s.status == "optimal" and s.feasible):
                break
            s.G, K = a.G, s.K
        if s is not None and s.status == "optimal" and s.feasible:
            s.extra.update(gamma_min=g_min, gamma_back_off=k * back_off, centre_margin=-s.max_eig)
            return done(s, nb, nc)
        why.append(f"gamma = {1 + k * back_off:g} gamma_min: status {s.status if s else 'none'!r}"
                   + ("" if s is None or s.status != "optimal" else f", largest LMI eigenvalue {s.max_eig:.3g}"))
    best.extra.update(gamma_min=g_min,
                      centring="the centred solve failed (" + "; ".join(why) + "): the minimising point is kept")
    return done(best, nb, nc)


def _no_certificate(fail, last, why: str):
    """A stage without a certificate: the failed solve (else the last good one) marked infeasible, with why."""
    out = fail if fail is not None else last
    out.feasible = False
    out.extra["why"] = why
    return out


def _physical(sol: DiscreteSolution, nb: float, nc: float) -> DiscreteSolution:
    """The normalised solve's figures in physical units: gamma (and gamma_min) times ``nb nc``; ``Q``,
    ``G``, ``Y`` stay the normalised problem's (``gamma_normalised``, ``w_scale = nb``, ``z_scale = nc``
    say how to re-assemble them)."""
    sol.extra.update(gamma_normalised=sol.gamma, w_scale=nb, z_scale=nc)
    sol.gamma = sol.gamma * nb * nc
    if "gamma_min" in sol.extra:
        sol.extra["gamma_min_normalised"] = sol.extra["gamma_min"]
        sol.extra["gamma_min"] = sol.extra["gamma_min"] * nb * nc
    return sol

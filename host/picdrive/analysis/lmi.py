"""Theorem 1 of the 2016 paper as numbers: the blocks of its LMI ``Xi_ij``,
their assembly, the margins of a candidate solution and the L2 gain it
certifies.

:mod:`picdrive.design.fuzzy_hinf` builds the same blocks with cvxpy operands
to solve the LMIs; :mod:`picdrive.design.verify` re-assembles them with numpy
to check a certificate.  The module docstring of ``fuzzy_hinf`` writes the
inequality out.
"""
from __future__ import annotations

import math
import warnings
from typing import Sequence

import numpy as np

__all__ = ["nonzero", "xi_blocks", "assemble", "assemble_xi", "lmi_margins", "certified_gain", "quiet_solve"]


# ---------------------------------------------------------------------------
# The assembled inequality (numpy or cvxpy operands)
# ---------------------------------------------------------------------------
def nonzero(M) -> bool:
    return M is not None and np.any(np.asarray(M) != 0)


def xi_blocks(ts, i: int, j: int, v: int, P, Yj, gamma, delta, alpha, rho, tau=None, gamma_w=None):
    """Blocks of Xi_ij: ``psi1`` and a list of ``(off-diagonal block, size, diagonal coefficient)``.

    Paper form (``tau is None``): the uncertainty pairs are ``(d E^T, -g)`` and
    ``(g rho/d H1 P, -g)``.  Multiplier form (``tau`` given, a cvxpy variable):
    ``(tau E^T, -tau)`` and ``(rho H1 P, -tau)``: both forms have the same
    Schur complement ``tau E E^T + rho^2/tau P H1^T H1 P`` with ``tau = d^2/g``,
    so optimising ``tau`` is Theorem 1 with the best delta, and gamma then
    enters linearly.  ``gamma_w`` (default gamma) is the diagonal of the
    ``Bw`` block (see :class:`_Problem`).
    """
    A = ts.A[i] + ts.offsets[v]
    B, C, D = ts.B[i], ts.C[i], ts.D[i]
    E = ts.E_matrix
    k = E.shape[1]
    AP = A @ P + B @ Yj
    psi1 = AP + AP.T
    unc_w, unc_z = [], []
    h1, h2 = nonzero(ts.H1[i]), nonzero(ts.H2[i])
    if tau is None:
        g_over = gamma * rho / delta
        if h1:
            unc_w.append((delta * E.T, k, -gamma))
            unc_z.append((g_over * (ts.H1[i] @ P), ts.H1.shape[1], -gamma))
        if h2:
            unc_w.append((delta * E.T, k, -gamma))
            unc_z.append((g_over * (ts.H2[i] @ Yj), ts.H2.shape[1], -gamma))
    else:
        if h1:
            unc_w.append((tau * E.T, k, -tau))
            unc_z.append((rho * (ts.H1[i] @ P), ts.H1.shape[1], -tau))
        if h2:
            unc_w.append((tau * E.T, k, -tau))
            unc_z.append((rho * (ts.H2[i] @ Yj), ts.H2.shape[1], -tau))
    col = unc_w + [(ts.Bw.T, ts.Bw.shape[1], -(gamma if gamma_w is None else gamma_w))] + unc_z
    if nonzero(ts.H3[i]) or nonzero(ts.H4[i]):
        col.append((math.sqrt(alpha) * rho * (ts.H3[i] @ P + ts.H4[i] @ Yj), ts.H3.shape[1], -gamma))
    col.append((math.sqrt(alpha) * (C @ P + D @ Yj), C.shape[0], -gamma))
    return psi1, col


def assemble(psi1, col, backend):
    rows = [[psi1] + [c[0].T for c in col]]
    for a, (blk, na, dg) in enumerate(col):
        row = [blk]
        for b, (_, nb, _) in enumerate(col):
            row.append(dg * np.eye(na) if a == b else np.zeros((na, nb)))
        rows.append(row)
    return backend(rows)


def assemble_xi(ts, P, Y: Sequence, i: int, j: int, gamma, delta, alpha, rho=None, v: int = 0) -> np.ndarray:
    """The numeric matrix ``Xi_ij`` (vertex v) of LMI (15) in the paper's form, for a candidate solution."""
    rho = ts.rho if rho is None else rho
    psi1, col = xi_blocks(ts, i, j, v, np.asarray(P), np.asarray(Y[j]), gamma, delta, alpha, rho)
    return assemble(psi1, col, np.block)


def lmi_margins(ts, P, Y, gamma, delta, alpha, rho=None, *, scaled: bool = True) -> dict[str, float]:
    """Largest eigenvalue of each LMI (12)-(14) at a candidate solution (all < 0: satisfied).

    ``scaled``: evaluate ``T Xi T`` with ``T = diag(S^-1, I, ...)`` (``S`` the
    model's state scale) -- an exact congruence, so the sign of every
    eigenvalue is that of the unscaled inequality, but the numbers are not
    swamped by the spread of the physical units.
    """
    sx = np.asarray(ts.info.get("state_scale", np.ones(ts.n)), float) if scaled else np.ones(ts.n)
    P = np.asarray(P, float)
    Si = np.diag(1.0 / sx)
    Ps = Si @ P @ Si
    out = {"P>0": float(-np.linalg.eigvalsh(0.5 * (Ps + Ps.T)).min())}

    def scaled_xi(i, j, v):
        X = assemble_xi(ts, P, Y, i, j, gamma, delta, alpha, rho, v)
        T = np.eye(X.shape[0])
        T[:ts.n, :ts.n] = Si
        return T @ X @ T
    for v in range(ts.offsets.shape[0]):
        for i in range(ts.r):
            X = scaled_xi(i, i, v)
            out[f"Xi_{i+1}{i+1}" + (f"@v{v+1}" if ts.offsets.shape[0] > 1 else "")] = float(np.linalg.eigvalsh(0.5 * (X + X.T)).max())
            for j in range(i + 1, ts.r):
                X = scaled_xi(i, j, v) + scaled_xi(j, i, v)
                out[f"Xi_{i+1}{j+1}+Xi_{j+1}{i+1}" + (f"@v{v+1}" if ts.offsets.shape[0] > 1 else "")] = \
                    float(np.linalg.eigvalsh(0.5 * (X + X.T)).max())
    return out


def certified_gain(ts, gamma: float, alpha: float) -> float:
    """L2 gain w -> z the theorem certifies: gamma/sqrt(alpha) when H3 = H4 = 0
    (no output uncertainty), else gamma (which needs alpha >= 2)."""
    if not (nonzero(ts.H3) or nonzero(ts.H4)):
        return gamma / math.sqrt(alpha)
    return gamma


def quiet_solve(prob, solver, **settings) -> tuple[str, list[str]]:
    """Solve a cvxpy problem without letting the solver's or cvxpy's text reach the user.

    cvxpy warns ("Solution may be inaccurate. Try another solver, adjusting the solver settings, or solve
    with verbose=True ...") when the solver stops short of its tolerances and may log through the ``cvxpy``
    logger; neither names anything a picdrive user can act on.  The status says the same (``optimal_inaccurate``)
    and the callers act on it; the text is returned (``notes``) for the record, never printed.  A solver
    exception is a status (``"solver error: ..."``)."""
    import logging

    import cvxpy as cp
    log = logging.getLogger("cvxpy")
    level = log.level
    log.setLevel(logging.CRITICAL + 1)
    try:
        with warnings.catch_warnings(record=True) as seen:
            warnings.simplefilter("always")
            try:
                prob.solve(solver=solver, **settings)
                status = str(prob.status)
            except cp.error.SolverError as e:
                status = f"solver error: {e}"
    finally:
        log.setLevel(level)
    return status, [str(w.message) for w in seen]

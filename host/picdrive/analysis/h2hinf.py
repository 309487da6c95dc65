"""H2 cost and H-infinity constraint of a PID loop (Duy et al. 2008, eqs 6-10, 13-15, 22).

Everything here is *batched*: gains, polynomial coefficients and matrices
carry any leading batch shape (a GA population) and the polynomial power or
matrix axes last, so that one GA generation is a handful of numpy calls.
Polynomials are in descending powers (``numpy.polyval`` order) unless a
name says ``_asc``.

H2 (tracking) cost, continuous time
    ``j3_jury_dewey(b, a)`` is eq 22: the integral of e(t)^2 for
    e(s) = B(s)/A(s) with deg A = 3 (Jury & Dewey 1965, via the residue
    theorem).  ``h2_lyapunov(num, den)`` is the same integral for any
    degree from the controllability Gramian of a canonical realisation
    (A X + X A^T + B B^T = 0, J = C X C^T); the two agree to rounding.

Robust constraint, continuous time
    ``hinf_exact(num, den)``: sup_w |H(jw)| computed as the paper's eqs 7-10
    do: beta/alpha = |N(jw)|^2/|D(jw)|^2 is a ratio of polynomials in
    x = w^2, its peaks are at the real non-negative roots of
    alpha dbeta/dx - beta dalpha/dx (eq 9, in x instead of w: the root w = 0
    of eq 9 and the pairs +-w collapse), plus the end points x = 0 and
    x -> inf.  Cross-checks: ``hinf_grid`` (dense grid) and
    ``hinf_statespace`` (Boyd-Balakrishnan-Bruinsma-Steinbuch iteration on
    the Hamiltonian of a state-space realisation).

Sampled loop (what the firmware runs)
    ``sampled_loop`` builds the closed loop of a :class:`~picdrive.models.tfmodel.SampledPlant`
    with picdrive's discrete PID law (derivative on measurement, integral
    including the current sample); ``j3_discrete`` is Ts * sum e[k]^2 of
    its unit-step error (discrete Lyapunov); ``hinf_exact_z`` is the exact
    peak of |H(e^{j theta})| on the unit circle (bilinear map to the
    imaginary axis, then the same root computation).

Stability: ``routh_hurwitz`` (Step 1 of the paper, batched Routh array) and
``schur_stable`` (spectral radius of the sampled closed loop).
"""
from __future__ import annotations

import functools
import math

import numpy as np

from ..models.tfmodel import TF, SampledPlant, loop_polys

__all__ = [
    "j3_jury_dewey", "h2_lyapunov", "routh_hurwitz", "hinf_exact", "hinf_grid", "hinf_statespace",
    "robust_constraint", "sensitivity_peak", "tracking_error_polys",
    "sampled_loop", "sampled_loop_polys", "schur_stable", "j3_discrete", "hinf_exact_z",
    "xi_tustin", "robust_constraint_z", "sensitivity_peak_z", "schur_char",
]


# A pole within this distance of the unit circle counts as unstable: the
# integrator of a loop with ki = 0 sits at z = 1 exactly and rounds either way.
SCHUR_MARGIN = 1e-9


# ---------------------------------------------------------------------------
# batched polynomial helpers (ascending powers inside this block)
# ---------------------------------------------------------------------------
def _bmul_asc(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Batched product of ascending coefficient arrays (..., na) x (..., nb)."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    shape = np.broadcast_shapes(a.shape[:-1], b.shape[:-1])
    out = np.zeros(shape + (a.shape[-1] + b.shape[-1] - 1,))
    for i in range(a.shape[-1]):
        out[..., i:i + b.shape[-1]] += a[..., i:i + 1] * b
    return out


def _bder_asc(p: np.ndarray) -> np.ndarray:
    n = p.shape[-1]
    if n == 1:
        return np.zeros_like(p)
    return p[..., 1:] * np.arange(1, n)


def _bsub_asc(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    n = max(a.shape[-1], b.shape[-1])
    pa = np.pad(a, [(0, 0)] * (a.ndim - 1) + [(0, n - a.shape[-1])])
    pb = np.pad(b, [(0, 0)] * (b.ndim - 1) + [(0, n - b.shape[-1])])
    return pa - pb


def _bpolyval_asc(p: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Evaluate batched ascending polynomials p (..., n) at x (..., m) -> (..., m)."""
    out = np.zeros(np.broadcast_shapes(p.shape[:-1], x.shape[:-1]) + x.shape[-1:], dtype=np.result_type(p, x))
    for k in range(p.shape[-1] - 1, -1, -1):
        out = out * x + p[..., k:k + 1]
    return out


def _real_roots_asc(q: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """Real roots in [lo, hi] of batched ascending polynomials q (B, n).

    Returns (B, n-1) with NaN where there is no root.  Rows are grouped by
    effective degree (leading zero coefficients trimmed) and each group's
    roots are the eigenvalues of its companion matrices, then polished by
    two Newton steps.
    """
    B, n = q.shape
    out = np.full((B, max(n - 1, 1)), np.nan)
    scale = np.max(np.abs(q), axis=1, keepdims=True)
    scale[scale == 0] = 1.0
    qs = q / scale
    nz = np.abs(qs) > 1e-300
    deg = np.where(nz.any(axis=1), n - 1 - np.argmax(nz[:, ::-1], axis=1), 0)
    for m in np.unique(deg):
        if m < 1:
            continue
        rows = np.nonzero(deg == m)[0]
        c = qs[rows, :m + 1]
        comp = np.zeros((rows.size, m, m))
        comp[:, 0, :] = -c[:, m - 1::-1] / c[:, m:m + 1]
        if m > 1:
            comp[:, 1:, :-1] = np.eye(m - 1)
        lam = np.linalg.eigvals(comp)
        re = lam.real.copy()
        tol = 1e-6 * (1.0 + np.abs(lam))
        real = np.abs(lam.imag) <= tol
        dc = _bder_asc(c)
        with np.errstate(all="ignore"):
            for _ in range(2):                  # Newton polish, kept only where it helps
                f = _bpolyval_asc(c, re)
                fp = _bpolyval_asc(dc, re)
                nxt = re - f / np.where(fp == 0, 1.0, fp)
                better = np.isfinite(nxt) & (np.abs(_bpolyval_asc(c, nxt)) < np.abs(f))
                re = np.where(better, nxt, re)
        ok = real & (re >= lo) & (re <= hi)
        out[rows, :m] = np.where(ok, re, np.nan)
    return out


# ---------------------------------------------------------------------------
# H2 cost
# ---------------------------------------------------------------------------
def j3_jury_dewey(b, a):
    """Eq 22: integral of e(t)^2 for e(s) = (b2 s^2 + b1 s + b0)/(a3 s^3 + a2 s^2 + a1 s + a0).

    ``b``: (..., 3) = [b2, b1, b0]; ``a``: (..., 4) = [a3, a2, a1, a0]
    (descending).  Valid only for Hurwitz A (check with :func:`routh_hurwitz`);
    returns inf where a0 a3 (a1 a2 - a0 a3) <= 0.
    """
    b = np.asarray(b, float); a = np.asarray(a, float)
    b2, b1, b0 = b[..., 0], b[..., 1], b[..., 2]
    a3, a2, a1, a0 = a[..., 0], a[..., 1], a[..., 2], a[..., 3]
    den = 2.0 * a0 * a3 * (a1 * a2 - a0 * a3)
    num = b2 ** 2 * a0 * a1 + (b1 ** 2 - 2.0 * b0 * b2) * a0 * a3 + b0 ** 2 * a2 * a3
    with np.errstate(divide="ignore", invalid="ignore"):
        j = num / den
    return np.where(den > 0, j, np.inf)


def h2_lyapunov(num, den):
    """Integral of h(t)^2 (squared H2 norm) of H(s) = num/den, strictly proper, batched.

    ``num`` (..., <= n), ``den`` (..., n + 1), descending.  Solves
    ``A X + X A^T + B B^T = 0`` for the controllable canonical realisation
    (Kronecker form, batched) and returns ``C X C^T``; inf where ``den`` is
    not Hurwitz.
    """
    num = np.asarray(num, float); den = np.asarray(den, float)
    n = den.shape[-1] - 1
    if num.shape[-1] > n:
        if np.any(num[..., : num.shape[-1] - n] != 0):
            raise ValueError("h2_lyapunov needs a strictly proper transfer function")
        num = num[..., num.shape[-1] - n:]
    num = np.pad(num, [(0, 0)] * (num.ndim - 1) + [(n - num.shape[-1], 0)])
    shape = np.broadcast_shapes(num.shape[:-1], den.shape[:-1])
    num = np.broadcast_to(num, shape + (n,)); den = np.broadcast_to(den, shape + (n + 1,))
    an = den[..., 1:] / den[..., :1]
    cn = num / den[..., :1]
    A = np.zeros(shape + (n, n))
    A[..., 0, :] = -an                          # x1' = -a1 x1 - ... - an xn + u
    if n > 1:
        A[..., 1:, :-1] = np.eye(n - 1)
    C = cn                                      # y = sum c_k x_k
    eye = np.eye(n)
    kron = np.einsum("...ij,kl->...ikjl", A, eye).reshape(shape + (n * n, n * n)) + \
        np.einsum("ij,...kl->...ikjl", eye, A).reshape(shape + (n * n, n * n))
    q = np.zeros(shape + (n * n,)); q[..., 0] = -1.0     # -B B^T with B = e1
    stable = routh_hurwitz(den)
    kron = np.where(stable[..., None, None], kron, np.eye(n * n))
    X = np.linalg.solve(kron, q[..., None])[..., 0].reshape(shape + (n, n))
    j = np.einsum("...i,...ij,...j->...", C, X, C)
    return np.where(stable, j, np.inf)


def tracking_error_polys(plant: TF, kp, ki, kd, *, derivative: str = "error"):
    """Batched (num, den) of e(s) for a unit-step reference (eq 21 / 25 without the 1000).

    ``den`` is the characteristic polynomial s m(s) + n(s) C_num(s);
    ``num`` = m(s) + n(s) kd s (derivative on measurement) or m(s) (on error).
    """
    char, _ = loop_polys(plant, kp, ki, kd)
    m = np.asarray(plant.den, float)
    num = np.broadcast_to(m, char.shape[:-1] + m.shape).copy()
    if derivative == "measurement":
        kd = np.broadcast_to(np.asarray(kd, float), char.shape[:-1])
        nk = np.polymul(plant.num, [1.0, 0.0])  # n(s) s
        add = kd[..., None] * nk
        size = max(num.shape[-1], add.shape[-1])
        num = np.pad(num, [(0, 0)] * (num.ndim - 1) + [(size - num.shape[-1], 0)]) + \
            np.pad(add, [(0, 0)] * (add.ndim - 1) + [(size - add.shape[-1], 0)])
    elif derivative != "error":
        raise ValueError(f"derivative must be 'error' or 'measurement', not {derivative!r}")
    return num, char


# ---------------------------------------------------------------------------
# stability
# ---------------------------------------------------------------------------
def routh_hurwitz(den) -> np.ndarray:
    """Batched Routh-Hurwitz test: True where every root of ``den`` has Re < 0.

    ``den`` (..., n+1) descending.  A polynomial is Hurwitz iff the first
    column of its Routh array is non-zero and of one sign (a zero pivot means
    a root on or right of the imaginary axis).
    """
    den = np.asarray(den, float)
    n = den.shape[-1] - 1
    shape = den.shape[:-1]
    if n == 0:
        return np.ones(shape, bool)
    width = n // 2 + 1
    r0 = np.zeros(shape + (width,)); r1 = np.zeros(shape + (width,))
    r0[..., : (n + 2) // 2] = den[..., 0::2]
    r1[..., : (n + 1) // 2] = den[..., 1::2]
    sign = np.sign(den[..., 0])
    ok = (sign != 0) & (np.sign(r1[..., 0]) == sign)
    for _ in range(n - 1):
        piv = np.where(r1[..., 0] == 0, 1.0, r1[..., 0])
        r2 = np.zeros_like(r0)
        r2[..., :-1] = r0[..., 1:] - (r0[..., :1] / piv[..., None]) * r1[..., 1:]
        ok &= np.sign(r2[..., 0]) == sign
        r0, r1 = r1, r2
    return ok


def schur_stable(A) -> tuple[np.ndarray, np.ndarray]:
    """Batched: (stable, spectral radius) of closed-loop matrices A (..., N, N)."""
    rho = np.max(np.abs(np.linalg.eigvals(A)), axis=-1)
    return rho < 1.0 - SCHUR_MARGIN, rho


# ---------------------------------------------------------------------------
# H-infinity, continuous time
# ---------------------------------------------------------------------------
def _mag2_x_asc(p_desc: np.ndarray) -> np.ndarray:
    """|p(jw)|^2 as an ascending polynomial in x = w^2 (batched)."""
    p = np.asarray(p_desc, float)[..., ::-1]          # ascending in s
    n = p.shape[-1]
    sgn_e = np.array([(-1.0) ** m for m in range((n + 1) // 2)])
    sgn_o = np.array([(-1.0) ** m for m in range(n // 2)])
    E = p[..., 0::2] * sgn_e                            # Re p(jw) = E(x)
    O = p[..., 1::2] * sgn_o                            # Im p(jw) = w O(x)
    e2 = _bmul_asc(E, E)
    if O.shape[-1] == 0:
        return e2
    o2 = _bmul_asc(O, O)
    xo2 = np.concatenate([np.zeros(o2.shape[:-1] + (1,)), o2], axis=-1)
    return _bsub_asc(e2, -xo2)                          # E^2 + x O^2


def _freq_scale(den: np.ndarray) -> float:
    """A typical frequency of den (geometric mean of |roots|), rad/s, for scaling."""
    d = np.atleast_2d(den)
    d = d.reshape(-1, d.shape[-1])
    lead = np.abs(d[:, 0]); last = np.abs(d[:, -1])
    n = d.shape[-1] - 1
    ok = (lead > 0) & (last > 0)
    if n < 1 or not ok.any():
        return 1.0
    w = np.exp(np.median(np.log(last[ok] / lead[ok])) / n)
    return float(w) if np.isfinite(w) and w > 0 else 1.0


def _scale_s(p: np.ndarray, w0: float) -> np.ndarray:
    """Coefficients of p(w0 s~) (descending)."""
    n = p.shape[-1] - 1
    return p * w0 ** np.arange(n, -1, -1, dtype=float)


def _bpolyval_desc(p: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Batched Horner: descending coefficients p (B, n) at points x (B, m) (complex allowed)."""
    out = np.zeros(x.shape, dtype=np.result_type(p, x))
    for k in range(p.shape[-1]):
        out = out * x + p[:, k:k + 1]
    return out


def _refine_peaks(mag, cand: np.ndarray, lo: np.ndarray, hi: np.ndarray, *, per_decade: int = 8,
                  top: int = 2, iters: int = 32):
    """Batched safeguard of a peak search: the largest of ``mag`` over the
    candidates (the stationary points from eq 9; NaN = none) and over a
    log-spaced grid on [lo, hi] per row, whose ``top`` best local maxima are
    refined by golden-section search in log frequency.  ``mag(points)`` maps
    (B, m) points to (B, m) magnitudes.  Returns (value, point).

    The roots of eq 9 are exact in exact arithmetic; for high-order loops
    with poles close to the stability boundary the root finding can lose
    precision, so every candidate is re-evaluated from the transfer function
    itself and the grid + refinement guards against a missed peak.
    """
    B = cand.shape[0]
    decades = np.log10(hi / lo)
    m = int(max(16, np.ceil(np.max(decades) * per_decade)))
    u = np.linspace(0.0, 1.0, m)[None, :]
    grid = lo[:, None] * (hi / lo)[:, None] ** u
    gv = mag(grid)
    cv = np.where(np.isnan(cand), -np.inf, mag(np.nan_to_num(cand)))
    best_v = np.max(cv, axis=1) if cand.shape[1] else np.full(B, -np.inf)
    best_p = cand[np.arange(B), np.argmax(cv, axis=1)] if cand.shape[1] else np.full(B, np.nan)
    k = np.argmax(gv, axis=1)
    take = gv[np.arange(B), k] > best_v
    best_v = np.where(take, gv[np.arange(B), k], best_v)
    best_p = np.where(take, grid[np.arange(B), k], best_p)
    # local maxima of the grid, best first
    padded = np.concatenate([np.full((B, 1), -np.inf), gv, np.full((B, 1), -np.inf)], axis=1)
    is_max = (padded[:, 1:-1] >= padded[:, :-2]) & (padded[:, 1:-1] >= padded[:, 2:])
    score = np.where(is_max, gv, -np.inf)
    order = np.argsort(-score, axis=1)[:, :top]                  # (B, K), refined together
    rows = np.arange(B)[:, None]
    valid = np.isfinite(score[rows, order])
    gr = 0.5 * (math.sqrt(5.0) - 1.0)
    lg = np.log(grid)
    a = lg[rows, np.maximum(order - 1, 0)]
    b = lg[rows, np.minimum(order + 1, m - 1)]
    c = b - gr * (b - a); d = a + gr * (b - a)
    fc = mag(np.exp(c)); fd = mag(np.exp(d))
    for _ in range(iters):
        left = fc >= fd                             # the maximum lies in [a, d]
        b = np.where(left, d, b); a = np.where(left, a, c)
        c_new = b - gr * (b - a); d_new = a + gr * (b - a)
        c, d = np.where(left, c_new, d), np.where(left, c, d_new)
        fnew = mag(np.exp(np.where(left, c, d)))
        fc, fd = np.where(left, fnew, fd), np.where(left, fc, fnew)
    x = np.where(fc >= fd, c, d)
    v = np.where(valid, np.maximum(fc, fd), -np.inf)
    j = np.argmax(v, axis=1)
    v, x = v[np.arange(B), j], x[np.arange(B), j]
    take = v > best_v
    best_v = np.where(take, v, best_v)
    best_p = np.where(take, np.exp(x), best_p)
    return best_v, best_p


def hinf_exact(num, den, *, w0: float | None = None):
    """Exact sup_w |num(jw)/den(jw)| for stable, proper H (batched); eqs 7-10.

    Returns ``(peak, w_peak)`` (w_peak = inf when the supremum is the
    high-frequency limit).  ``den`` must be Hurwitz (not checked here).
    """
    num = np.asarray(num, float); den = np.asarray(den, float)
    shape = np.broadcast_shapes(num.shape[:-1], den.shape[:-1])
    num = np.broadcast_to(num, shape + num.shape[-1:]).reshape(-1, num.shape[-1])
    den = np.broadcast_to(den, shape + den.shape[-1:]).reshape(-1, den.shape[-1])
    w0 = _freq_scale(den) if w0 is None else w0
    ns, ds = _scale_s(num, w0), _scale_s(den, w0)
    beta = _mag2_x_asc(ns)                       # in x~ = (w/w0)^2
    alpha = _mag2_x_asc(ds)
    beta /= np.max(np.abs(alpha), axis=1, keepdims=True)
    alpha = alpha / np.max(np.abs(alpha), axis=1, keepdims=True)
    q = _bsub_asc(_bmul_asc(alpha, _bder_asc(beta)), _bmul_asc(beta, _bder_asc(alpha)))    # eq 9
    roots = _real_roots_asc(q, 0.0, np.inf)
    cand = np.concatenate([np.zeros((q.shape[0], 1)), roots], axis=1)
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        g = _bpolyval_asc(beta, np.nan_to_num(cand)) / _bpolyval_asc(alpha, np.nan_to_num(cand))
    g = np.where(np.isnan(cand), -np.inf, g)
    # x -> infinity
    db = beta.shape[-1] - 1; da = alpha.shape[-1] - 1
    bl = beta[..., -1]; al = alpha[..., -1]
    if db < da:
        ginf = np.zeros(q.shape[0])
    else:
        ginf = np.where(al != 0, bl / np.where(al == 0, 1, al), np.inf)
    # every candidate re-evaluated from the transfer function, plus the grid safeguard
    wc = np.sqrt(np.maximum(cand, 0.0)) * w0
    wc = np.where(np.isnan(cand), np.nan, wc)

    def mag(w):
        return np.abs(_bpolyval_desc(ns, 1j * w / w0) / _bpolyval_desc(ds, 1j * w / w0))

    B = q.shape[0]
    peak, wpk = _refine_peaks(mag, wc, np.full(B, w0 * 1e-6), np.full(B, w0 * 1e6))
    ginf = np.sqrt(np.maximum(ginf, 0.0))
    use_inf = ginf > peak
    peak = np.where(use_inf, ginf, peak)
    wpk = np.where(use_inf, np.inf, wpk)
    return peak.reshape(shape), wpk.reshape(shape)


def hinf_grid(num, den, w) -> tuple[float, float]:
    """max |H(jw)| over a frequency grid (one system): (peak, w at the peak)."""
    h = np.abs(np.polyval(num, 1j * np.asarray(w)) / np.polyval(den, 1j * np.asarray(w)))
    k = int(np.argmax(h))
    return float(h[k]), float(w[k])


def hinf_statespace(num, den, *, rtol: float = 1e-10) -> tuple[float, float]:
    """H-inf norm of one stable proper SISO system from a state-space realisation.

    Boyd-Balakrishnan / Bruinsma-Steinbuch: with a lower bound g_lb, the
    Hamiltonian of gamma = (1 + 2 rtol) g_lb has imaginary eigenvalues j w_i
    exactly where |H(jw)| = gamma; |H| at their midpoints raises g_lb; stop
    when there are none.  Frequency-scaled and balanced for conditioning.
    """
    from scipy.linalg import matrix_balance
    from scipy.signal import tf2ss

    num = np.trim_zeros(np.asarray(num, float), "f"); den = np.asarray(den, float)
    w0 = _freq_scale(den)
    A, B, C, D = tf2ss(num * w0 ** np.arange(num.size - 1, -1, -1, dtype=float), _scale_s(den, w0))
    if A.size == 0:
        return float(abs(D[0, 0])), 0.0
    _, (sc, _) = matrix_balance(A, separate=True, permute=False)
    A = A * sc[None, :] / sc[:, None]
    B = B / sc[:, None]
    C = C * sc[None, :]
    d = float(D[0, 0])
    n = A.shape[0]

    def mag(w):
        return abs((C @ np.linalg.solve(1j * w * np.eye(n) - A, B))[0, 0] + d)

    poles = np.linalg.eigvals(A)
    trial = [0.0] + [abs(p) for p in poles]
    g_lb, w_pk = abs(d), math.inf
    for w in trial:
        m = mag(w)
        if m > g_lb:
            g_lb, w_pk = m, w
    for _ in range(100):
        gam = (1.0 + 2.0 * rtol) * g_lb
        r = gam ** 2 - d * d
        Ah = A + (B * d / r) @ C
        H = np.block([[Ah, B @ B.T / r], [-C.T @ C * (1 + d * d / r), -Ah.T]])
        ev = np.linalg.eigvals(H)
        tol = 1e-8 * max(1.0, np.max(np.abs(ev)))
        ws = np.sort(np.abs(ev[(np.abs(ev.real) < tol)].imag))
        ws = np.unique(np.round(ws, 12))
        if ws.size == 0:
            break
        if ws.size == 1:
            mids = ws
        else:
            mids = 0.5 * (ws[:-1] + ws[1:])
        improved = False
        for w in mids:
            m = mag(w)
            if m > g_lb * (1 + rtol):
                g_lb, w_pk, improved = m, w, True
        if not improved:
            break
    return float(g_lb), float(w_pk * w0)


def _on_stable(fn, stable, num, den):
    """Apply a batched peak function to the stable rows only: (value, where) with inf/nan elsewhere."""
    stable = np.asarray(stable, bool)
    shape = stable.shape
    num = np.broadcast_to(num, shape + np.shape(num)[-1:])
    den = np.broadcast_to(den, shape + np.shape(den)[-1:])
    val = np.full(shape, np.inf)
    at = np.full(shape, np.nan)
    if stable.any():
        v, w = fn(num[stable], den[stable])
        val[stable], at[stable] = v, w
    return val, at


def robust_constraint(plant: TF, kp, ki, kd, d: float):
    """Batched || P C xi / (1 + P C) ||_inf (eq 6) and the nominal stability (Step 1).

    Returns ``(value, stable, w_peak)``; value is inf where the nominal loop is unstable.
    """
    char, lnum = loop_polys(plant, kp, ki, kd)
    stable = routh_hurwitz(char)
    num = float(d) * lnum
    den = _bmul_asc(char[..., ::-1], np.array([10.0, 0.1, 1.0]))[..., ::-1]
    val, wpk = _on_stable(hinf_exact, stable, num, den)
    return val, stable, wpk


def sensitivity_peak(plant: TF, kp, ki, kd):
    """Batched ||1/(1 + P C)||_inf (continuous), inf where unstable."""
    char, _ = loop_polys(plant, kp, ki, kd)
    stable = routh_hurwitz(char)
    num = np.append(plant.den, 0.0)                 # s m(s)
    val, wpk = _on_stable(hinf_exact, stable, np.broadcast_to(num, char.shape), char)
    return val, wpk


# ---------------------------------------------------------------------------
# the sampled loop
# ---------------------------------------------------------------------------
def sampled_loop(sp: SampledPlant, kp, ki, kd, *, setpoint_weight: float = 1.0):
    """Batched closed loop of the sampled plant with picdrive's law (linear part).

    Law (control_law.py, no saturation): ``u = kp (b r - y) + I + ki Ts e +
    kd (y_prev - y)/Ts``, ``I <- I + ki Ts e``, ``y_prev <- y``.  State
    ``[plant (n), I, y_prev]``; returns ``(Acl, Bcl, Cy)`` with shapes
    (..., N, N), (..., N), (N,), so that ``X[k+1] = Acl X[k] + Bcl r`` and
    the measured speed is ``Cy X[k]``.
    """
    kp, ki, kd = np.broadcast_arrays(np.asarray(kp, float), np.asarray(ki, float), np.asarray(kd, float))
    ts = sp.ts
    n = sp.n
    N = n + 2
    Ad, Bd, Cd = sp.Ad, sp.Bd[:, 0], sp.Cd[0]
    shape = kp.shape
    A = np.zeros(shape + (N, N))
    ky = kp + ki * ts + kd / ts                         # gain on -y
    A[..., :n, :n] = Ad - (ky[..., None, None] * np.outer(Bd, Cd))
    A[..., :n, n] = Bd
    A[..., :n, n + 1] = (kd / ts)[..., None] * Bd
    A[..., n, :n] = -(ki * ts)[..., None] * Cd
    A[..., n, n] = 1.0
    A[..., n + 1, :n] = Cd
    Bc = np.zeros(shape + (N,))
    Bc[..., :n] = (kp * setpoint_weight + ki * ts)[..., None] * Bd
    Bc[..., n] = ki * ts
    Cy = np.zeros(N); Cy[:n] = Cd
    return A, Bc, Cy


def sampled_loop_polys(sp: SampledPlant, kp, ki, kd):
    """Batched (char, lnum, snum) in z of the sampled feedback loop.

    Feedback part of the law: ``C(z) = [kp z (z-1) + ki Ts z^2 + (kd/Ts)(z-1)^2] / (z (z-1))``;
    plant ``P(z) = np(z)/dp(z)``; ``char = z (z-1) dp + Cn np``,
    T = Cn np / char, S = z (z-1) dp / char.  (Derivative on measurement
    changes only the reference path, not T or S.)
    """
    ptf = sp.tf_z
    kp, ki, kd = np.broadcast_arrays(np.asarray(kp, float), np.asarray(ki, float), np.asarray(kd, float))
    ts = sp.ts
    cn = (kp[..., None] * np.array([1.0, -1.0, 0.0]) + (ki * ts)[..., None] * np.array([1.0, 0.0, 0.0])
          + (kd / ts)[..., None] * np.array([1.0, -2.0, 1.0]))          # descending, degree 2
    lnum = _bmul_asc(cn[..., ::-1], ptf.num[::-1])[..., ::-1]
    snum = np.polymul([1.0, -1.0, 0.0], ptf.den)
    size = max(lnum.shape[-1], snum.size)
    lnum = np.pad(lnum, [(0, 0)] * (lnum.ndim - 1) + [(size - lnum.shape[-1], 0)])
    snum = np.pad(snum, (size - snum.size, 0))
    char = lnum + snum
    return char, lnum, np.broadcast_to(snum, char.shape)


def j3_discrete(Acl, Bcl, Cy, ts: float, *, stable=None):
    """Batched Ts * sum_k e[k]^2 for a unit step of r from rest (discrete H2 cost).

    e[k] = 1 - Cy X[k], X[0] = 0.  With X_ss = (I - Acl)^-1 Bcl (Cy X_ss = 1
    by integral action), e[k] = -Cy A^k (-X_ss), so J = Ts X_ss^T W X_ss with
    W = A^T W A + Cy^T Cy (solved in Kronecker form).  inf where unstable
    (``stable``, if given, saves the eigenvalue computation).
    """
    Acl = np.asarray(Acl, float)
    shape = Acl.shape[:-2]
    N = Acl.shape[-1]
    if stable is None:
        stable, _ = schur_stable(Acl)
    eye = np.eye(N)
    Ause = np.where(stable[..., None, None], Acl, 0.5 * eye)
    AT = np.swapaxes(Ause, -1, -2)
    kron = np.eye(N * N) - np.einsum("...ij,...kl->...ikjl", AT, AT).reshape(shape + (N * N, N * N))
    Q = np.outer(Cy, Cy).reshape(-1)
    rhs = np.broadcast_to(Q, shape + (N * N,))[..., None]
    Bcl = np.broadcast_to(np.asarray(Bcl, float), shape + (N,))[..., None]
    try:
        W = np.linalg.solve(kron, rhs)[..., 0].reshape(shape + (N, N))
        xss = np.linalg.solve(eye - Ause, Bcl)[..., 0]
    except np.linalg.LinAlgError:             # a (numerically) marginal row: solve row by row
        W = np.full(shape + (N, N), np.nan)
        xss = np.full(shape + (N,), np.nan)
        for idx in np.ndindex(*shape):
            try:
                W[idx] = np.linalg.solve(kron[idx], rhs[idx])[:, 0].reshape(N, N)
                xss[idx] = np.linalg.solve(eye - Ause[idx], Bcl[idx])[:, 0]
            except np.linalg.LinAlgError:
                pass
    j = ts * np.einsum("...i,...ij,...j->...", xss, W, xss)
    return np.where(stable & np.isfinite(j), j, np.inf)


@functools.lru_cache(maxsize=None)
def _bilinear_matrix(n: int) -> np.ndarray:
    """M with (p(z) at z = (1+w)/(1-w)) * (1-w)^n = p_desc @ M for degree-n p (descending).

    Row j (coefficient of z^(n-j)) holds (1+w)^(n-j) (1-w)^j in descending powers of w.
    """
    M = np.zeros((n + 1, n + 1))
    for j in range(n + 1):
        M[j] = np.polymul(np.poly1d([1.0, 1.0]) ** (n - j), np.poly1d([-1.0, 1.0]) ** j).coeffs[-(n + 1):] \
            if n > 0 else [1.0]
    return M


def hinf_exact_z(num, den):
    """Exact max over the unit circle of |num(z)/den(z)| (batched, den Schur-stable).

    The bilinear map z = (1 + w)/(1 - w) takes the unit circle onto the
    imaginary axis (w = j tan(theta/2)) and a Schur-stable den onto a Hurwitz
    one, so the peak is :func:`hinf_exact` of the mapped pair (eqs 7-10 in w).
    (Working in c = cos theta instead loses all precision for features far
    below the Nyquist frequency, such as the 3.16 rad/s resonance of xi.)
    Returns ``(peak, theta_peak)`` (theta in rad per sample, 0..pi).
    """
    num = np.asarray(num, float); den = np.asarray(den, float)
    n = max(num.shape[-1], den.shape[-1]) - 1
    num = np.pad(num, [(0, 0)] * (num.ndim - 1) + [(n + 1 - num.shape[-1], 0)])
    den = np.pad(den, [(0, 0)] * (den.ndim - 1) + [(n + 1 - den.shape[-1], 0)])
    M = _bilinear_matrix(n)
    shape = np.broadcast_shapes(num.shape[:-1], den.shape[:-1])
    num = np.broadcast_to(num, shape + (n + 1,)).reshape(-1, n + 1)
    den = np.broadcast_to(den, shape + (n + 1,)).reshape(-1, n + 1)
    nw, dw = num @ M, den @ M
    # stationary points of eq 9 in the w plane (nu = tan(theta/2)), then theta
    w0 = _freq_scale(dw)
    beta = _mag2_x_asc(_scale_s(nw, w0)); alpha = _mag2_x_asc(_scale_s(dw, w0))
    sc = np.max(np.abs(alpha), axis=1, keepdims=True)
    beta, alpha = beta / sc, alpha / sc
    q = _bsub_asc(_bmul_asc(alpha, _bder_asc(beta)), _bmul_asc(beta, _bder_asc(alpha)))
    roots = _real_roots_asc(q, 0.0, np.inf)
    th = 2.0 * np.arctan(np.sqrt(np.maximum(roots, 0.0)) * w0)
    th = np.where(np.isnan(roots), np.nan, th)
    B = num.shape[0]
    th = np.concatenate([th, np.zeros((B, 1)), np.full((B, 1), math.pi)], axis=1)   # theta = 0 and pi

    def mag(t):
        z = np.exp(1j * t)
        return np.abs(_bpolyval_desc(num, z) / _bpolyval_desc(den, z))

    peak, tpk = _refine_peaks(mag, th, np.full(B, 1e-7), np.full(B, math.pi))
    return peak.reshape(shape), tpk.reshape(shape)


def xi_tustin(d: float, ts: float) -> TF:
    """xi(s) = d/(s^2 + 0.1 s + 10) by the Tustin map prewarped at its resonance sqrt(10) rad/s."""
    wr = math.sqrt(10.0)
    k = wr / math.tan(wr * ts / 2.0)
    zm1 = np.array([1.0, -1.0]); zp1 = np.array([1.0, 1.0])
    den = k * k * np.polymul(zm1, zm1) + 0.1 * k * np.polymul(zm1, zp1) + 10.0 * np.polymul(zp1, zp1)
    return TF(float(d) * np.polymul(zp1, zp1), den)


def robust_constraint_z(sp: SampledPlant, kp, ki, kd, d: float, *, polys=None, stable=None):
    """Batched || T(z) xi_d(z) ||_inf of the sampled loop (eq 6 for the firmware's loop).

    Returns ``(value, schur_stable, w_peak rad/s)``; inf where unstable.
    ``polys`` (from :func:`sampled_loop_polys`) and ``stable`` may be passed in.
    """
    char, lnum, _ = sampled_loop_polys(sp, kp, ki, kd) if polys is None else polys
    if stable is None:
        stable = schur_char(char)
    xi = xi_tustin(d, sp.ts)
    num = _bmul_asc(lnum[..., ::-1], xi.num[::-1])[..., ::-1]
    den = _bmul_asc(char[..., ::-1], xi.den[::-1])[..., ::-1]
    val, th = _on_stable(hinf_exact_z, stable, num, den)
    return val, stable, th / sp.ts


def sensitivity_peak_z(sp: SampledPlant, kp, ki, kd, *, polys=None, stable=None):
    """Batched ||S(z)||_inf of the sampled loop; inf where unstable. Returns (value, w_peak rad/s)."""
    char, _, snum = sampled_loop_polys(sp, kp, ki, kd) if polys is None else polys
    if stable is None:
        stable = schur_char(char)
    val, th = _on_stable(hinf_exact_z, stable, snum, char)
    return val, th / sp.ts


def schur_char(char: np.ndarray) -> np.ndarray:
    """Batched: all roots of the descending polynomial strictly inside the unit circle."""
    c = np.asarray(char, float)
    shape = c.shape[:-1]
    c2 = c.reshape(-1, c.shape[-1])
    m = c2.shape[-1] - 1
    comp = np.zeros((c2.shape[0], m, m))
    comp[:, 0, :] = -c2[:, 1:] / c2[:, :1]
    if m > 1:
        comp[:, 1:, :-1] = np.eye(m - 1)
    rho = np.max(np.abs(np.linalg.eigvals(comp)), axis=-1)
    return (rho < 1.0 - SCHUR_MARGIN).reshape(shape)

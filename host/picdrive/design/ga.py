"""Genetic algorithm with decimal coding (Passino & Yurkovich 1998; Duy et al. 2008, section 4).

Coding (2008 section 4.1, Table 1).  A chromosome is a string of decimal
digits (genes), one block per trait (gain).  In each block the first gene
is the sign (0-4 negative, 5-9 positive) and the next ``digits`` genes are
the magnitude, most significant first; the trait's *decimal constant* c
says how many digits stand left of the decimal point::

    value = sign * 0.d1 d2 ... dn * 10**c

so the genes 7 4 6 9 9 7 decode to 4.6997 with c = 1, 0.46997 with c = 0,
0.046997 with c = -1, 0.0046997 with c = -2 (Table 1).  The decimal
constant of a trait is the smallest c with 10**c above the largest |bound|.

Search domain D (Step 2): a box [lo, hi] per trait.  The coding reaches
values outside it (|value| up to 10**c, either sign); such a trait is
clipped to the box and the clipped value is written back into the
chromosome (repair), so the population always lies in D.

One generation (a simple GA, Chen et al. 1995 / Passino & Yurkovich):

1. evaluate the cost of every chromosome (a batched call);
2. fitness: 1/cost for a feasible chromosome (constraint met, cost finite),
   0 otherwise.  Eq 17 prints F = -E when feasible and 0 otherwise; with
   E = J3 > 0 that would rank every infeasible chromosome *above* every
   feasible one, so picdrive uses a positive decreasing function of E
   instead, which keeps the paper's intent ("a lower quality index gets a
   larger fitness");
3. elitism: the best ``elite`` chromosomes pass unchanged;
4. roulette-wheel (fitness-proportional) selection of the mating pool
   (uniform if nothing is feasible);
5. single-point crossover of consecutive pairs with probability
   ``p_crossover`` (cross site uniform over the whole string);
6. mutation: every gene is replaced by a random digit with probability
   ``p_mutation``.

The initial population is drawn uniformly from D and encoded (the paper:
"randomly generating a population of 200 chromosomes").  Everything random
comes from one ``numpy.random.Generator`` seeded with ``seed``: the same
seed gives the same run.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

__all__ = ["decimal_constant", "decode", "encode", "GAResult", "run_ga"]


def decimal_constant(bound: float) -> int:
    """Smallest c with 10**c > |bound| (the digits left of the decimal point)."""
    m = abs(float(bound))
    if m == 0:
        return 0
    return int(math.floor(math.log10(m))) + 1


def decode(genes, decimal_constants, digits: int) -> np.ndarray:
    """Chromosomes (..., n_traits * (1 + digits)) of digits 0-9 -> trait values (..., n_traits).

    No clipping here: this is the coding of Table 1.
    """
    g = np.asarray(genes, dtype=np.int64)
    dc = np.asarray(decimal_constants, dtype=float)
    nt = dc.size
    g = g.reshape(g.shape[:-1] + (nt, 1 + digits))
    sign = np.where(g[..., 0] >= 5, 1.0, -1.0)
    weights = 10.0 ** -np.arange(1, digits + 1, dtype=float)
    mag = np.sum(g[..., 1:] * weights, axis=-1)
    return sign * mag * 10.0 ** dc


def encode(values, decimal_constants, digits: int, rng: np.random.Generator | None = None) -> np.ndarray:
    """Trait values -> chromosomes (truncated to ``digits`` digits).

    The sign gene is 5-9 for a value >= 0 and 0-4 for a negative one (a
    random digit of that half when ``rng`` is given, else 9 or 0).
    """
    v = np.asarray(values, dtype=float)
    dc = np.asarray(decimal_constants, dtype=float)
    m = np.abs(v) / 10.0 ** dc
    if np.any(m >= 1.0):
        raise ValueError("a value is too large for its decimal constant")
    ints = np.floor(m * 10.0 ** digits + 1e-9).astype(np.int64)
    ints = np.minimum(ints, 10 ** digits - 1)
    dig = np.stack([(ints // 10 ** (digits - 1 - k)) % 10 for k in range(digits)], axis=-1)
    if rng is None:
        sg = np.where(v >= 0, 9, 0)
    else:
        sg = np.where(v >= 0, rng.integers(5, 10, size=v.shape), rng.integers(0, 5, size=v.shape))
    out = np.concatenate([sg[..., None], dig], axis=-1)
    return out.reshape(v.shape[:-1] + (-1,)).astype(np.int8)


@dataclass
class GAResult:
    best: np.ndarray                 # best trait values found (n_traits,)
    best_cost: float
    best_feasible: bool
    history_best: list[float]        # best cost of each generation (after evaluation)
    history_feasible: list[float]    # feasible fraction of each generation
    n_evaluations: int
    wall_time_s: float
    population: np.ndarray = field(repr=False)     # final population (decoded)
    decimal_constants: list[int] = field(default_factory=list)

    def to_dict(self) -> dict:
        return {"best": self.best.tolist(), "best_cost": self.best_cost, "best_feasible": self.best_feasible,
                "history_best": self.history_best, "history_feasible": self.history_feasible,
                "n_evaluations": self.n_evaluations, "wall_time_s": self.wall_time_s,
                "decimal_constants": self.decimal_constants}


def run_ga(cost: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]], lo, hi, *,
           population: int = 200, generations: int = 20, digits: int = 7,
           p_crossover: float = 0.8, p_mutation: float = 0.05, elite: int = 1,
           seed: int | None = None, progress: bool = True, desc: str = "GA") -> GAResult:
    """Minimise ``cost`` over the box [lo, hi] with the decimal-coded GA.

    ``cost(values)`` takes (pop, n_traits) trait values and returns
    ``(cost, feasible)``, two arrays of length pop.  ``generations``
    generations are bred after the initial population, so ``cost`` is called
    ``generations + 1`` times.
    """
    lo = np.asarray(lo, dtype=float); hi = np.asarray(hi, dtype=float)
    if lo.shape != hi.shape or lo.ndim != 1:
        raise ValueError("lo and hi must be 1-D arrays of the same length")
    if np.any(~(hi > lo)):
        raise ValueError(f"every upper bound must exceed its lower bound: lo={lo.tolist()}, hi={hi.tolist()}")
    if population < 2 or generations < 0:
        raise ValueError("population must be >= 2 and generations >= 0")
    if not 0 <= elite < population:
        raise ValueError("elite must be in [0, population)")
    t0 = time.perf_counter()
    rng = np.random.default_rng(seed)
    dc = np.array([decimal_constant(max(abs(a), abs(b))) for a, b in zip(lo, hi)])
    nt = lo.size
    L = nt * (1 + digits)

    def repair(genes):
        raw = decode(genes, dc, digits)
        vals = np.clip(raw, lo, hi)
        bad = np.any(vals != raw, axis=-1)
        if bad.any():
            genes[bad] = encode(vals[bad], dc, digits, rng)
            vals[bad] = np.clip(decode(genes[bad], dc, digits), lo, hi)
        return vals

    genes = encode(rng.uniform(lo, hi, size=(population, nt)), dc, digits, rng)
    vals = repair(genes)
    hist_best, hist_feas = [], []
    best_v, best_c, best_ok = None, math.inf, False
    n_eval = 0
    try:
        from tqdm import tqdm
        bar = tqdm(total=generations + 1, desc=desc, disable=not progress, leave=False, unit="gen")
    except ImportError:                                 # pragma: no cover - tqdm is a dependency
        bar = None
    for gen in range(generations + 1):
        c, ok = cost(vals)
        c = np.asarray(c, dtype=float); ok = np.asarray(ok, dtype=bool) & np.isfinite(c) & (c > 0)
        n_eval += population
        fit = np.where(ok, 1.0 / np.where(ok, c, 1.0), 0.0)
        order = np.argsort(-fit, kind="stable")
        if ok.any():
            k = order[0]
            if c[k] < best_c:
                best_v, best_c, best_ok = vals[k].copy(), float(c[k]), True
            hist_best.append(float(np.min(c[ok])))
        else:
            hist_best.append(math.inf)
            if best_v is None:
                best_v = vals[0].copy()
        hist_feas.append(float(ok.mean()))
        if bar is not None:
            bar.update(1)
            bar.set_postfix(best=f"{best_c:.4g}", feasible=f"{ok.mean():.0%}")
        if gen == generations:
            break
        # --- breed the next generation
        elite_genes = genes[order[:elite]].copy()
        if fit.sum() > 0:
            prob = fit / fit.sum()
            pick = rng.choice(population, size=population, p=prob)
        else:
            pick = rng.integers(0, population, size=population)
        pool = genes[pick].copy()
        for i in range(0, population - 1, 2):
            if rng.random() < p_crossover:
                site = int(rng.integers(1, L))
                a = pool[i, site:].copy()
                pool[i, site:] = pool[i + 1, site:]
                pool[i + 1, site:] = a
        mut = rng.random(pool.shape) < p_mutation
        pool[mut] = rng.integers(0, 10, size=int(mut.sum()))
        pool[:elite] = elite_genes
        genes = pool
        vals = repair(genes)
    if bar is not None:
        bar.close()
    return GAResult(best=np.asarray(best_v, float), best_cost=best_c, best_feasible=best_ok,
                    history_best=hist_best, history_feasible=hist_feas, n_evaluations=n_eval,
                    wall_time_s=time.perf_counter() - t0, population=vals,
                    decimal_constants=[int(x) for x in dc])

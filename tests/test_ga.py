"""Decimal-coded GA (2008 section 4, Table 1; Passino & Yurkovich)."""
import numpy as np
import pytest

from picdrive.design.ga import decimal_constant, decode, encode, run_ga


@pytest.mark.parametrize("dc,value", [(-2, 0.0046997), (-1, 0.046997), (0, 0.46997), (1, 4.6997)])
def test_table1_decoding(dc, value):
    # k_i = 746997: sign gene 7 (positive), digits 4 6 9 9 7
    assert decode([7, 4, 6, 9, 9, 7], [dc], 5)[0] == pytest.approx(value, rel=1e-12)


def test_sign_gene_and_roundtrip():
    assert decode([4, 4, 6, 9, 9, 7], [1], 5)[0] == pytest.approx(-4.6997)
    assert decode([0, 1, 0, 0, 0, 0], [3], 5)[0] == pytest.approx(-100.0)
    assert decode([5, 0, 0, 0, 0, 0], [3], 5)[0] == 0.0
    rng = np.random.default_rng(0)
    v = np.array([[180.1755, 4.6997, 0.0353], [-12.5, 0.0, 0.099]])
    dc = [decimal_constant(200), decimal_constant(10), decimal_constant(0.1)]
    assert dc == [3, 2, 0]
    g = encode(v, dc, 7, rng)
    assert g.shape == (2, 24) and g.min() >= 0 and g.max() <= 9
    err = np.abs(decode(g, dc, 7) - v)
    assert np.all(err <= 10.0 ** (np.array(dc) - 7) * 1.0001)       # truncation to 7 digits
    assert decimal_constant(4.7) == 1 and decimal_constant(0.05) == -1


def _sphere(target):
    def cost(v):
        c = np.sum(((v - target) / (np.abs(target) + 1)) ** 2, axis=1) + 1e-12
        return c, np.ones(len(v), bool)
    return cost


def test_seeded_determinism_and_bounds():
    lo, hi = np.array([0.0, -5.0, 0.0]), np.array([200.0, 10.0, 0.1])
    cost = _sphere(np.array([150.0, 2.0, 0.05]))
    a = run_ga(cost, lo, hi, seed=7, progress=False, population=50, generations=10)
    b = run_ga(cost, lo, hi, seed=7, progress=False, population=50, generations=10)
    c = run_ga(cost, lo, hi, seed=8, progress=False, population=50, generations=10)
    np.testing.assert_array_equal(a.best, b.best)
    assert a.history_best == b.history_best
    assert not np.array_equal(a.population, c.population)
    assert np.all(a.population >= lo) and np.all(a.population <= hi)
    assert np.all(a.best >= lo) and np.all(a.best <= hi)
    assert a.n_evaluations == 50 * 11


def test_improves_over_generations_and_elitism():
    lo, hi = np.zeros(3), np.array([200.0, 10.0, 0.1])
    target = np.array([123.4, 6.7, 0.0321])
    r = run_ga(_sphere(target), lo, hi, seed=3, progress=False)
    h = np.array(r.history_best)
    assert np.all(np.diff(h) <= 0)                       # elitism: the best never gets worse
    assert h[-1] < 0.2 * h[0]
    assert r.best_cost == pytest.approx(h[-1])
    np.testing.assert_allclose(r.best, target, rtol=0.1)


def test_infeasible_are_never_chosen_as_best():
    lo, hi = np.zeros(2), np.ones(2)

    def cost(v):          # cheaper towards (1, 1), but feasible only where x0 + x1 <= 1
        return 3.0 - v.sum(axis=1), v.sum(axis=1) <= 1.0
    r = run_ga(cost, lo, hi, seed=1, progress=False, population=60, generations=15)
    assert r.best_feasible and r.best.sum() <= 1.0
    assert r.best.sum() > 0.95


def test_bad_arguments():
    with pytest.raises(ValueError, match="upper bound"):
        run_ga(_sphere(np.zeros(1)), [1.0], [0.0], progress=False)
    with pytest.raises(ValueError, match="too large"):
        encode([[150.0]], [2], 5)

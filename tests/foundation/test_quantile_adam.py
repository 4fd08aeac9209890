"""QuantileAdam (foundation/quantile_adam.py) against Dr.Jit's uniform Adam and a closed form in numpy."""

from __future__ import annotations

import numpy as np
import pytest

import drjit as dr
import mitsuba as mi

from foundation.errors import UsageError
from foundation.optim_state import load_optimizer_state, optimizer_state
from foundation.quantile_adam import QuantileAdam


def _grads(n: int, steps: int, seed: int = 0) -> list[np.ndarray]:
    """Gradients with a few large outliers (the silhouettes' share of a morph's gradient): 2 % of the coordinates
    100× the rest."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(steps):
        g = rng.normal(size=n).astype(np.float32) + 0.3
        g[: n // 50] *= 100.0
        out.append(g)
    return out


def _run(opt, grads: list[np.ndarray], x0: np.ndarray) -> np.ndarray:
    opt["x"] = mi.Float(x0)
    for g in grads:
        x = opt["x"]
        dr.backward(dr.sum(x * mi.Float(g)))  # d/dx = g
        opt.step()
    return np.array(opt["x"])


def _reference(grads: list[np.ndarray], x0: np.ndarray, lr: float, q: float, b1: float = 0.9, b2: float = 0.999,
               eps: float = 1e-8) -> np.ndarray:
    """Adam's moments and debiasing, one scale √quantile(v), the normalised step clipped to ±1."""
    x, m, v = x0.astype(np.float64), np.zeros_like(x0, np.float64), np.zeros_like(x0, np.float64)
    for t, g in enumerate(grads, 1):
        m = b1 * m + (1 - b1) * g
        v = b2 * v + (1 - b2) * g.astype(np.float64) ** 2
        scale = lr * np.sqrt(1 - b2**t) / (1 - b1**t)
        x = x - scale * np.clip(m / (np.sqrt(np.quantile(v, q)) + eps), -1.0, 1.0)
    return x


def test_quantile_one_is_drjit_uniform_adam_bit_for_bit():
    grads, x0 = _grads(500, 6), np.linspace(-1, 1, 500).astype(np.float32)
    a = _run(QuantileAdam(lr=0.01, quantile=1.0), grads, x0)
    b = _run(mi.ad.Adam(lr=0.01, uniform=True), grads, x0)
    np.testing.assert_array_equal(a, b)


def test_quantile_step_matches_the_closed_form_and_moves_the_bulk_further():
    grads, x0 = _grads(500, 6), np.linspace(-1, 1, 500).astype(np.float32)
    got = _run(QuantileAdam(lr=0.01, quantile=0.9), grads, x0)
    want = _reference(grads, x0, 0.01, 0.9)
    np.testing.assert_allclose(got, want, rtol=0, atol=2e-6)  # float32 arithmetic against float64
    # the mutation the test must catch: the maximum instead of the quantile (Dr.Jit's uniform Adam)
    assert np.abs(_reference(grads, x0, 0.01, 1.0) - want).max() > 1e-3
    uni = _run(mi.ad.Adam(lr=0.01, uniform=True), grads, x0)
    bulk = slice(500 // 50, None)  # the coordinates without outliers: the uniform scale starves them
    assert np.abs(got - x0)[bulk].mean() > 20 * np.abs(uni - x0)[bulk].mean()
    # no coordinate steps further than the learning rate times Adam's debiasing factor allows
    steps = np.abs(got - x0)
    bound = sum(0.01 * np.sqrt(1 - 0.999**t) / (1 - 0.9**t) for t in range(1, 7))
    assert steps.max() <= bound * (1 + 1e-5)


def test_quantile_adam_resumes_exactly_and_refuses_bad_quantiles():
    grads, x0 = _grads(200, 5, seed=3), np.zeros(200, np.float32)
    whole = _run(QuantileAdam(lr=0.02, quantile=0.8), grads, x0)
    first = QuantileAdam(lr=0.02, quantile=0.8)
    _run(first, grads[:3], x0)
    saved, mid = optimizer_state(first), np.array(first["x"])
    again = QuantileAdam(lr=0.02, quantile=0.8)
    again["x"] = mi.Float(mid)
    load_optimizer_state(again, saved)
    for g in grads[3:]:
        dr.backward(dr.sum(again["x"] * mi.Float(g)))
        again.step()
    np.testing.assert_array_equal(np.array(again["x"]), whole)
    for bad in (0.0, -0.5, 1.5, float("nan")):
        with pytest.raises(UsageError, match="quantile"):
            QuantileAdam(lr=0.01, quantile=bad)

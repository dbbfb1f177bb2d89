"""The aggregates every report shares: the interquartile mean with its bootstrap CI and the area under a curve."""

from __future__ import annotations

import numpy as np
import pytest

from convoy.stats import curve_area, iqm_ci, ratio_ci


def test_the_interquartile_mean_trims_an_outlier_seed_and_its_ci_covers_it() -> None:
    seeds = [10.0, 11.0, 12.0, 13.0, 14.0, 15.0, 16.0, 500.0]  # one seed far off
    out = iqm_ci(seeds)
    assert out["iqm"] == pytest.approx(13.5) and out["n"] == 8  # the middle half: 12, 13, 14, 15
    assert out["low"] < out["iqm"] < out["high"] and out["iqm"] < np.mean(seeds) / 5  # the mean: 73.9
    assert iqm_ci(seeds) == out  # a fixed bootstrap seed: a regenerated report reads the same
    assert iqm_ci([3.0]) == {"iqm": 3.0, "low": 3.0, "high": 3.0, "n": 1}
    assert iqm_ci([])["iqm"] is None


def test_the_area_under_a_greedy_curve_is_its_return_averaged_over_the_run() -> None:
    steps = np.array([0, 100, 200, 400])
    assert curve_area(steps, np.array([5.0, 5.0, 5.0, 5.0])) == pytest.approx(5.0)
    early, late = np.array([0.0, 10.0, 10.0, 10.0]), np.array([0.0, 0.0, 0.0, 10.0])
    assert curve_area(steps, early) == pytest.approx(8.75) and curve_area(steps, late) == pytest.approx(2.5)
    assert curve_area(np.array([7]), np.array([4.0])) == 4.0 and curve_area(np.zeros(0), np.zeros(0)) is None


def test_the_ratio_of_two_groups_means_has_a_ci_around_it_that_narrows_with_seeds() -> None:
    """Told ÷ own: the CI holds the ratio, excludes 1 for groups far apart, and is reproducible (fixed seed)."""
    rng = np.random.default_rng(1)
    told, own = (135 + 5 * rng.standard_normal(10)).tolist(), (100 + 5 * rng.standard_normal(10)).tolist()
    r = ratio_ci(told, own)
    assert r["ratio"] == pytest.approx(np.mean(told) / np.mean(own))
    assert 1.0 < r["low"] < r["ratio"] < r["high"]
    assert ratio_ci(told, own) == r
    wide = ratio_ci(told[:3], own[:3])
    assert wide["high"] - wide["low"] > r["high"] - r["low"]
    same = ratio_ci(own, own)
    assert same["low"] < 1.0 < same["high"]
    assert ratio_ci([2.0], [1.0]) == {"ratio": 2.0, "low": 2.0, "high": 2.0}

"""The model-predictive references (``envs.treadmill.planner``): deterministic, told only what their level allows, and
the 16-bit word they hear round-trips a car's cell and heading."""

import numpy as np
import pytest

from convoy.envs.treadmill import TreadmillConfig
from convoy.envs.treadmill.engine import TreadmillEngine
from convoy.envs.treadmill.planner import (
    LEVELS,
    START,
    TUNED,
    PlannerParams,
    decode_word,
    encode_word,
    from_vector,
    level_actions,
    planner_returns,
    to_vector,
)


@pytest.mark.parametrize("level", LEVELS)
def test_a_planner_is_deterministic_on_fixed_seeds(level: str) -> None:
    cfg = TreadmillConfig()
    a = planner_returns(cfg, level, TUNED[level], 6, seed=3)
    b = planner_returns(cfg, level, TUNED[level], 6, seed=3)
    np.testing.assert_array_equal(a, b)
    assert a.shape == (6,)


def test_the_private_planner_reads_only_the_observation() -> None:
    """Moving a car the agents cannot see (or cars they see, in an engine the policy is not given) changes nothing:
    the private and 16-bit levels act on the observation alone."""
    cfg = TreadmillConfig()
    e = TreadmillEngine(cfg, 16)
    obs = e.reset(5)
    for level in ("private", "team16"):
        before = level_actions(level, e, obs, TUNED[level])
        e.x[:] = 0  # the engine's state, which only the team and full levels may read
        after = level_actions(level, e, obs, TUNED[level])
        np.testing.assert_array_equal(before, after)
        e.reset(5)


def test_the_word_round_trips_a_sensed_cars_cell_and_heading() -> None:
    cfg = TreadmillConfig()
    e = TreadmillEngine(cfg, 64)
    obs = e.reset(0)
    word = encode_word(obs, cfg)
    assert word.dtype == np.uint16
    seen, x, y, heading = decode_word(word, cfg)
    assert seen.any() and not seen.all()
    near, near_dist, _ = e.nearest()
    cell = max(cfg.length - 1, cfg.width - 1) / 63.0
    for b, i in zip(*np.nonzero(seen), strict=True):
        cars = near[b, i][np.isfinite(near_dist[b, i])]
        gap = np.hypot(e.x[b, cars] - x[b, i], e.y[b, cars] - y[b, i])
        j = int(np.argmin(gap))
        assert gap[j] <= cell  # to the code's precision
        assert e.heading[b, cars[j]] == heading[b, i]
    assert (word[~seen] == 0).all()


def test_parameters_round_trip_through_their_label_and_the_search_space() -> None:
    p = PlannerParams(horizon=5, danger=17.25, w_blind=0.5)
    assert PlannerParams.from_label(p.label()) == p
    q = from_vector(to_vector(START))
    assert PlannerParams.from_label(q.label()) == q
    assert abs(q.danger - START.danger) < 1e-3

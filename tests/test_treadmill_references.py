"""The treadmill's reason to exist, as properties of its default rules (fixed seeds, 500 episodes each).

Open loop must not pay (the first version's "floor it" beat every learner) and information must: the
full-information driver beats its private-observation twin by ≥ 30 % with the CIs apart.
"""

import pytest

from envs.treadmill import TreadmillConfig
from envs.treadmill.references import CONSTANTS, best_constant, evaluate_references


@pytest.fixture(scope="module")
def references():
    return evaluate_references(TreadmillConfig(), episodes=500, seed=0)


def test_no_open_loop_policy_is_competitive(references) -> None:
    scripted = references["scripted"].ci95()[0]
    for name in CONSTANTS:
        assert references[name].ci95()[0] <= 0.5 * scripted, name
    assert references[best_constant(references)].ci95()[0] > references["random"].ci95()[0]  # a real baseline


def test_information_pays(references) -> None:
    full_mean, full_ci = references["full-information"].ci95()
    own_mean, own_ci = references["scripted"].ci95()
    assert full_mean >= 1.3 * own_mean
    assert full_mean - full_ci > own_mean + own_ci


def test_one_crash_ends_the_episode_for_every_agent(references) -> None:
    r = references["scripted"]
    assert r.terminated.any()
    assert (r.lengths[r.terminated] < TreadmillConfig().max_steps).all()

"""The treadmill's reason to exist, as properties of its default rules (fixed seeds, 500 episodes each).

Open loop must not pay (the first version's "floor it" beat every learner) and information must: the
full-information driver beats its private-observation twin by ≥ 30 % with the CIs apart.
"""

import pytest

from convoy.envs.treadmill import TreadmillConfig
from convoy.envs.treadmill.references import CONSTANTS, best_constant, evaluate_references, who_sees_the_threat


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


def test_who_sees_the_threat_splits_every_close_call_and_grows_with_what_agents_observe() -> None:
    """Messages can only add what a teammate observes and the threatened agent does not; observing more cars
    (observe_k 3) puts more of the close calls there, a 360° sensor puts them with the agent itself."""
    one = who_sees_the_threat(TreadmillConfig(), steps=100, envs=64)
    assert sum(one.values()) == pytest.approx(1.0) and min(one.values()) > 0
    three = who_sees_the_threat(TreadmillConfig(observe_k=3), steps=100, envs=64)
    assert three["only_teammate"] > one["only_teammate"] + 0.1
    all_round = who_sees_the_threat(TreadmillConfig(sensor_fov=360), steps=100, envs=64)
    assert all_round["own"] > one["own"] + 0.2

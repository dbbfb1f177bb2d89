"""The model-predictive references (``envs.treadmill.planner``): deterministic, told only what their level allows, and
the 16-bit word they hear says where the speaker is, or where a chaser is."""

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
    heard_known,
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


def test_a_word_says_where_its_speaker_is_unless_it_sees_a_car_faster_than_any_agent() -> None:
    for cfg in (TreadmillConfig(), TreadmillConfig(adversary_speed=5, adversary_stealth=True)):
        e = TreadmillEngine(cfg, 64)
        obs = e.reset(0)
        reports = chasers = 0
        for _ in range(40):
            word = encode_word(obs, cfg)
            assert word.dtype == np.uint16
            seen, sure, x, y, heading = decode_word(word, cfg)
            assert seen.all()  # every agent says something: where it is, or where the chaser is
            cell = np.hypot((cfg.length - 1) / 63.0, (cfg.width - 1) / 31.0) / 2 + 1e-9
            me = ~sure
            assert (np.hypot(e.x[:, : cfg.n_agents] - x, e.y[:, : cfg.n_agents] - y)[me] <= cell).all()
            assert (e.heading[:, : cfg.n_agents] == heading)[me].all()
            chaser = np.hypot(e.x[:, cfg.n_agents :][:, :1] - x, e.y[:, cfg.n_agents :][:, :1] - y)  # one adversary
            assert (chaser[sure] <= cell).all()
            fast = np.broadcast_to(e.speed[:, cfg.n_agents :].max(axis=1)[:, None] > cfg.max_speed, sure.shape)
            assert fast[sure].all()
            reports, chasers = reports + seen.sum(), chasers + sure.sum()
            obs = e.step(level_actions("private", e, obs, TUNED["private"])).obs
        assert (chasers > 0) == (cfg.adversary_top > cfg.max_speed)


def test_words_from_every_teammate_identify_the_cars_an_agent_senses() -> None:
    """Told where every teammate is, a listener knows which car it senses is the adversary (its sensor cannot)."""
    cfg = TreadmillConfig()
    e = TreadmillEngine(cfg, 64)
    obs = e.reset(1)
    right = wrong = 0
    for _ in range(30):
        cars = heard_known(obs, cfg, TUNED["team16"])
        near, near_dist, _ = e.nearest()
        k = cfg.observe_k
        sensed = np.isfinite(near_dist)
        truth = near >= cfg.n_agents  # [B, N, k]
        told = cars.adversary[..., :k] > 0.5
        right, wrong = right + (told == truth)[sensed].sum(), wrong + (told != truth)[sensed].sum()
        obs = e.step(level_actions("private", e, obs, TUNED["private"])).obs
    assert right / (right + wrong) > 0.97  # cars closer than the words' cells can be mistaken


def test_parameters_round_trip_through_their_label_and_the_search_space() -> None:
    p = PlannerParams(horizon=5, danger=17.25, w_blind=0.5)
    assert PlannerParams.from_label(p.label()) == p
    q = from_vector(to_vector(START))
    assert PlannerParams.from_label(q.label()) == q
    assert abs(q.danger - START.danger) < 1e-3


def test_a_planner_predicts_a_charger_in_its_line_and_steps_out_of_its_way() -> None:
    """A chaser too fast to steer (``adversary_steer_speed``) drives on in a line: a planner that knows of one coming
    up its lane from behind steers out of it; one driving on in a lane of its own changes nothing."""
    from convoy.envs.treadmill.planner import Known, plan_actions

    cfg = TreadmillConfig(adversary_speed=7, adversary_steer_speed=3, adversary_stealth=True)
    p = TUNED["full"]

    def act(charger_y: float, known: bool = True) -> int:
        cars = Known(
            known=np.full((1, 1, 1), known), x=np.array([[[40.0]]]), y=np.array([[[charger_y]]]),
            heading=np.zeros((1, 1, 1), np.int64), speed=np.array([[[7.0]]]), adversary=np.ones((1, 1, 1)),
            unseen=np.zeros((1, 1)),
        )  # fmt: skip
        return int(plan_actions(cfg, p, np.array([[50.0]]), np.array([[50.0]]), np.zeros((1, 1), np.int64),
                                np.array([[2.0]]), cars)[0, 0])  # fmt: skip

    steer = lambda a: a // 3 - 1  # noqa: E731  (−1, 0, +1: the action's steering)
    assert steer(act(50.0)) != 0  # in its lane, 10 cells back at 7 a step: out of the way
    assert act(80.0) == act(80.0, known=False)  # 30 cells to the side, driving on: as if there were none

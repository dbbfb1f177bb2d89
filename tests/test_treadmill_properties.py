"""Property tests of the treadmill physics (hypothesis): geometry, crashes, rewards, batching."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from convoy.envs.batched import env_seeds
from convoy.envs.treadmill import TreadmillConfig, TreadmillEngine, distance
from convoy.envs.treadmill.config import DX, DY, FULL_FEATURES, N_HEADINGS, OWN_FEATURES, SIGHTING_FEATURES
from convoy.envs.treadmill.engine import _in_sight

KEEP = 4  # steer 0, accelerate 0
FAST = settings(max_examples=60, deadline=None)


def place(engine: TreadmillEngine, x, y, heading, speed) -> None:
    """Put env 0's cars at given cells with given headings and speeds."""
    engine.x[0], engine.y[0] = x, y
    engine.heading[0], engine.speed[0] = heading, speed


def observe_placed(cfg: TreadmillConfig, x, y, heading, speed) -> tuple[np.ndarray, np.ndarray]:
    """One env of ``cfg`` with its cars placed: (observations, closest-car distances) of that state."""
    e = TreadmillEngine(cfg, 1)
    e.reset(0)
    place(e, x, y, heading, speed)
    return e.observe(np.array([0]))


def two_cars(length: int = 40, width: int = 20, max_speed: int = 3) -> TreadmillEngine:
    cfg = TreadmillConfig(n_agents=2, n_adversaries=0, length=length, width=width, max_speed=max_speed)
    e = TreadmillEngine(cfg, autoreset=False)  # a finished episode keeps its last state to look at
    e.reset(0)
    return e


@FAST
@given(st.integers(0, 39), st.integers(2, 17), st.integers(0, 3), st.booleans())
def test_agents_leaving_the_window_crash(x: int, y: int, speed: int, forward: bool) -> None:
    e = two_cars()
    other = 35 if x < 20 else 5
    place(e, [x, other], [y, 2 if y > 10 else 18], [0 if forward else 4, 0], [speed, 1])
    r = e.step(np.array([[KEEP, KEEP]]))
    moved = x + (speed if forward else -speed) - e.cfg.treadmill_speed
    leaves = not 0 <= moved < e.cfg.length
    assert e.x[0, 0] == moved
    assert bool(r.info["crashed"][0, 0]) == leaves == bool(r.terminated[0])
    if leaves:
        assert r.reward[0, 0] == -e.cfg.crash_penalty


def test_adversaries_leaving_the_window_enter_again_at_an_edge() -> None:
    # a constant belt: the cars placed below leave the window this step whatever the adversaries' random actions
    cfg = TreadmillConfig(n_agents=1, n_adversaries=2, length=40, width=20, aggression=0.0, treadmill_speed_max=1)
    e = TreadmillEngine(cfg, 64)
    e.reset(0)
    e.x[:, 0], e.y[:, 0], e.speed[:, 0] = 20, 10, 1
    e.x[:, 1], e.y[:, 1], e.heading[:, 1], e.speed[:, 1] = 0, 3, 4, 2  # out the back this step
    e.x[:, 2], e.y[:, 2], e.heading[:, 2], e.speed[:, 2] = 39, 17, 0, 3  # out the front this step
    r = e.step(np.full((64, 1), KEEP))
    adv = np.s_[:, 1:]
    assert not r.terminated.any()
    assert np.isin(e.x[adv], [0, cfg.length - 1]).all() and (e.heading[adv] == 0).all()
    back = e.x[adv] == 0
    assert (e.speed[adv][back] == cfg.max_speed).all() and (e.speed[adv][~back] == 0).all()
    assert 0.2 < back.mean() < 0.8 and len(np.unique(e.y[adv])) > 5  # both edges, many lanes


@FAST
@given(
    st.integers(5, 33),
    st.sampled_from([1, 2, 3, 5, 6, 7]),  # headings with a lateral component
    st.integers(1, 3),
    st.booleans(),
)
def test_leaving_the_road_sideways_crashes(x: int, heading: int, speed: int, near_edge: bool) -> None:
    e = two_cars()
    width = e.cfg.width
    # put the car close enough to the edge it heads for that this step takes it off the road
    slack = 0 if near_edge else speed - 1
    y = width - speed + slack if DY[heading] > 0 else speed - 1 - slack
    leaves = not 0 <= y + DY[heading] * speed < width
    place(e, [x, 35 if x < 20 else 5], [y, width // 2], [heading, 0], [speed, 1])
    r = e.step(np.array([[KEEP, KEEP]]))
    assert bool(r.info["crashed"][0, 0]) == leaves
    assert bool(r.terminated[0]) == leaves
    if leaves:
        assert r.reward[0, 0] == -e.cfg.crash_penalty


@FAST
@given(
    st.integers(6, 33),
    st.integers(4, 15),
    st.integers(0, 7),
    st.integers(0, 7),
    st.integers(1, 3),
    st.integers(1, 3),
)
def test_cars_driving_into_the_same_cell_collide(qx, qy, h1, h2, v1, v2) -> None:
    e = two_cars()
    starts = [(qx - v * DX[h], qy - v * DY[h]) for h, v in ((h1, v1), (h2, v2))]
    if starts[0] == starts[1]:
        return  # both would start on one cell: not a situation the env can be in
    place(e, [s[0] for s in starts], [s[1] for s in starts], [h1, h2], [v1, v2])
    r = e.step(np.array([[KEEP, KEEP]]))
    assert r.info["crashed"][0].all() and r.terminated[0]
    assert (r.reward[0] == -e.cfg.crash_penalty).all()


@FAST
@given(st.integers(5, 33), st.integers(2, 17), st.integers(0, 7))
def test_swapping_cells_is_a_collision(x: int, y: int, heading: int) -> None:
    e = two_cars()
    place(e, [x, x + DX[heading]], [y, y + DY[heading]], [heading, (heading + 4) % 8], [1, 1])
    r = e.step(np.array([[KEEP, KEEP]]))
    assert r.info["crashed"][0].all()


@FAST
@given(st.integers(5, 33), st.integers(2, 17), st.sampled_from([1, 3, 5, 7]))
def test_diagonal_paths_crossing_collide(x: int, y: int, heading: int) -> None:
    e = two_cars()
    mirrored = {1: 3, 3: 1, 5: 7, 7: 5}[heading]  # same lateral direction, opposite longitudinal one
    place(e, [x, x + DX[heading]], [y, y], [heading, mirrored], [1, 1])
    r = e.step(np.array([[KEEP, KEEP]]))
    assert r.info["crashed"][0].all()  # they end on different cells but crossed on the way


@FAST
@given(st.integers(5, 33), st.integers(2, 10), st.integers(0, 7), st.integers(1, 3), st.integers(2, 8))
def test_parallel_cars_never_collide(x: int, y: int, heading: int, speed: int, gap: int) -> None:
    e = two_cars(max_speed=3)
    place(e, [x, x], [y, y + gap], [heading, heading], [speed, speed])
    if any(not 0 <= yy + DY[heading] * speed < e.cfg.width for yy in (y, y + gap)):
        return  # would leave the road: another rule
    r = e.step(np.array([[KEEP, KEEP]]))
    assert not r.info["crashed"][0].any()


@pytest.mark.slow
@FAST
@given(
    st.integers(0, 2**31),
    st.integers(1, 6),
    st.integers(0, 3),
    st.integers(1, 4),
    st.integers(20, 60),
)
def test_rewards_in_unit_interval_except_crash_penalty(seed, n_agents, n_adv, max_speed, length) -> None:
    if n_agents + n_adv < 2:
        n_adv = 1
    cfg = TreadmillConfig(
        n_agents=n_agents, n_adversaries=n_adv, length=length, width=20, max_speed=max_speed, spawn_gap=2, max_steps=30
    )
    e = TreadmillEngine(cfg, num_envs=8)
    e.reset(seed)
    rng = np.random.default_rng(seed)
    for _ in range(40):
        r = e.step(rng.integers(0, 9, (8, n_agents)))
        crashed = r.info["crashed"]
        assert np.all(r.reward[crashed] == -cfg.crash_penalty)
        assert np.all((r.reward[~crashed] >= 0) & (r.reward[~crashed] <= 1))
        assert np.all(np.abs(r.obs) <= 1) and np.all(np.abs(r.final_obs) <= 1)


@pytest.mark.slow
@settings(max_examples=25, deadline=None)
@given(
    st.lists(st.integers(0, 2**40), min_size=1, max_size=6),
    st.integers(1, 5),
    st.integers(0, 2),
    st.integers(1, 3),
    st.integers(0, 2**31),
    st.booleans(),
)
def test_batch_equals_envs_stepped_one_by_one(seeds, n_agents, n_adv, observe_k, action_seed, v3) -> None:
    if n_agents + n_adv < 2:
        n_adv = 1
    observe_k = min(observe_k, n_agents + n_adv - 1)
    road: dict[str, int | float | bool] = {"length": 30, "width": 12, "spawn_gap": 3, "max_steps": 15}
    if v3:  # the v3 rules' own randomness (spawn headings, a varying belt) and a stealthy adversary
        road |= {"spawn_heading_spread": 4, "treadmill_speed_max": 2, "treadmill_switch_prob": 0.3}
        road |= {"adversary_stealth": True, "adversary_speed": 5, "adversary_steer_speed": 3}
    cfg = TreadmillConfig(n_agents=n_agents, n_adversaries=n_adv, observe_k=observe_k, aggression=0.5, **road)
    b = len(seeds)
    batch = TreadmillEngine(cfg, b)
    singles = [TreadmillEngine(cfg, 1) for _ in range(b)]
    obs = batch.reset(np.array(seeds))
    for i, s in enumerate(singles):
        assert np.array_equal(s.reset(np.array(seeds[i : i + 1]))[0], obs[i])
    rng = np.random.default_rng(action_seed)
    for _ in range(40):  # several episodes: auto-reset included
        acts = rng.integers(0, 9, (b, n_agents))
        rb = batch.step(acts)
        for i, s in enumerate(singles):
            rs = s.step(acts[i : i + 1])
            for field in ("obs", "reward", "terminated", "truncated", "final_obs"):
                assert np.array_equal(getattr(rs, field)[0], getattr(rb, field)[i]), field
            for arr in ("x", "y", "heading", "speed", "t", "belt"):
                assert np.array_equal(getattr(s, arr)[0], getattr(batch, arr)[i]), arr


def test_int_seed_expands_to_disjoint_per_env_seeds() -> None:
    cfg = TreadmillConfig()
    batch = TreadmillEngine(cfg, 4)
    single = TreadmillEngine(cfg, 1)
    assert np.array_equal(batch.reset(100)[2], single.reset(env_seeds(100, 4)[2:3])[0])
    assert not set(env_seeds(100, 64).tolist()) & set(env_seeds(101, 64).tolist())  # two actors share no env
    assert np.array_equal(env_seeds(7, 3), env_seeds(7, 9)[:3])


def test_same_seed_same_episode_and_different_seed_differs() -> None:
    cfg = TreadmillConfig()
    a, b, c = (TreadmillEngine(cfg, 16) for _ in range(3))
    a.reset(7), b.reset(7), c.reset(8)
    acts = np.random.default_rng(0).integers(0, 9, (50, 16, cfg.n_agents))
    for t in range(50):
        ra, rb = a.step(acts[t]), b.step(acts[t])
        c.step(acts[t])
        assert np.array_equal(ra.obs, rb.obs) and np.array_equal(ra.reward, rb.reward)
    assert not np.array_equal(a.x, c.x)


def test_spawned_agents_are_apart_in_the_middle_and_adversaries_enter_at_an_edge() -> None:
    cfg = TreadmillConfig(n_agents=8, n_adversaries=3, spawn_heading_spread=0)  # spreads: the test below
    e = TreadmillEngine(cfg, 256)
    e.reset(3)
    n = cfg.n_agents
    dx = np.abs(e.x[:, :n, None] - e.x[:, None, :n])
    dy = np.abs(e.y[:, :n, None] - e.y[:, None, :n])
    cheb = np.maximum(dx, dy) + np.eye(n, dtype=np.int64) * 10**6
    assert cheb.min() >= cfg.spawn_gap
    assert (e.x[:, :n] >= cfg.length // 4).all() and (e.x[:, :n] < 3 * cfg.length // 4).all()
    assert np.isin(e.x[:, n:], [0, cfg.length - 1]).all()
    assert (e.heading == 0).all() and (e.speed[:, :n] == cfg.initial_speed).all()


def test_observation_encodes_the_closest_car_in_sight() -> None:
    e = two_cars(length=100, width=100)
    place(e, [60, 65], [50, 52], [0, 2], [1, 3])  # the other car is 5 cells ahead, 2 to the left
    obs, closest = e.observe(np.array([0]))
    own, near = obs[0, 0, :OWN_FEATURES], obs[0, 0, OWN_FEATURES:]
    r = e.cfg.sensor_range
    assert own[1] == 1.0 and own[9] == pytest.approx(1 / 3)  # heading 0, speed 1 of 3
    assert own[OWN_FEATURES - 1] == pytest.approx(2 * 60 / 99 - 1)  # longitudinal position on the window
    assert near[0] == 1.0 and near[1] == pytest.approx(5 / r) and near[2] == pytest.approx(2 / r)
    assert near[3 + 2] == 1.0 and near[11] == pytest.approx(1.0)  # heading 2, full speed
    assert closest[0, 0] == pytest.approx(np.hypot(5, 2))


@pytest.mark.parametrize(
    ("other", "fov", "seen"), [((55, 50), 240, False), ((55, 50), 360, True), ((61, 71), 360, False)]
)
def test_sensor_sees_within_its_range_and_field_of_view(other, fov, seen) -> None:
    cfg = TreadmillConfig(n_agents=2, n_adversaries=0, sensor_range=20, sensor_fov=fov)
    # 5 behind: in the blind spot; 21 away: out of range
    obs, closest = observe_placed(cfg, [60, other[0]], [50, other[1]], [0, 0], [1, 1])
    near = obs[0, 0, OWN_FEATURES:]
    assert bool(near[0]) == seen
    if not seen:
        assert (near == 0).all()
    assert closest[0, 0] == pytest.approx(np.hypot(other[0] - 60, other[1] - 50))  # the reward still counts it


@FAST
@given(st.sampled_from([90.0, 200.0, 240.0, 360.0]), st.floats(2.0, 90.0), st.integers(0, 2**31 - 1))
def test_the_sight_lookup_is_the_sight_rule(fov: float, sensor_range: float, seed: int) -> None:
    """``visible`` reads a table inside the window's reach and computes the rule beyond it: both are the rule."""
    e = TreadmillEngine(TreadmillConfig(sensor_fov=fov, sensor_range=sensor_range))
    rs = np.random.default_rng(seed)
    heading = rs.integers(0, N_HEADINGS, (32, 3))
    for reach in (60, 100, 300):  # well inside, at the edge of and past the table
        rel_x, rel_y = rs.integers(-reach, reach + 1, (2, 32, 3, 4))
        expected = _in_sight(rel_x, rel_y, heading, sensor_range, fov)
        np.testing.assert_array_equal(e.visible(rel_x, rel_y, heading), expected)


def test_each_agent_observes_its_closest_cars_in_sight_ties_by_index() -> None:
    """The sort-key selection of ``nearest`` against a stable argsort of distances, on a crowded small window."""
    cfg = TreadmillConfig(n_agents=6, n_adversaries=3, length=24, width=10, spawn_gap=2, observe_k=4, sensor_range=9)
    e = TreadmillEngine(cfg, 256)
    e.reset(3)
    rs = np.random.default_rng(0)
    for _ in range(20):
        e.step(rs.integers(0, 9, (256, cfg.n_agents)))
        near, near_dist, closest = e.nearest()
        rel_x, rel_y = e.offsets()
        dist = distance(0, 0, rel_x, rel_y) + np.where(np.eye(cfg.n_agents, cfg.n_cars, dtype=bool), np.inf, 0)
        seen = e.visible(rel_x, rel_y, e.heading[:, : cfg.n_agents])
        expected = np.argsort(np.where(seen, dist, np.inf), axis=2, kind="stable")[..., : cfg.observe_k]
        expected_dist = np.take_along_axis(np.where(seen, dist, np.inf), expected, axis=2)
        np.testing.assert_array_equal(near_dist, expected_dist)
        np.testing.assert_array_equal(near, expected)
        np.testing.assert_array_equal(closest, dist.min(axis=2))


def test_full_information_tells_every_position_and_who_is_an_adversary() -> None:
    cfg = TreadmillConfig(n_agents=2, n_adversaries=2, full_information=True)
    obs, _ = observe_placed(cfg, [50, 40, 10, 90], [50, 60, 20, 80], [0, 0, 0, 0], [1, 1, 0, 3])
    assert obs.shape[-1] == cfg.obs_dim
    full = obs[0, 0, -3 * FULL_FEATURES :].reshape(3, FULL_FEATURES)  # agent 0's view of cars 1, 2, 3
    assert full[:, 0] == pytest.approx(np.array([-10, -40, 40]) / 99)
    assert full[:, 1] == pytest.approx(np.array([10, -30, 30]) / 99)
    assert full[:, 2] == pytest.approx([1 / 3, 0, 1]) and full[:, 3].tolist() == [0, 1, 1]


def test_team_observations_append_each_teammates_own_observation() -> None:
    private, team = (
        TreadmillEngine(TreadmillConfig(n_agents=3), 4),
        TreadmillEngine(TreadmillConfig(n_agents=3, team_observations=True), 4),
    )
    mine, with_team = private.reset(7), team.reset(7)
    d = mine.shape[-1]
    assert with_team.shape[-1] == team.cfg.obs_dim == 3 * d
    assert np.array_equal(with_team[..., :d], mine)
    for i, peers in enumerate([(1, 2), (0, 2), (0, 1)]):  # teammates in index order, never the agent itself
        assert np.array_equal(with_team[:, i, d:].reshape(4, 2, d), mine[:, list(peers)])


def test_team_sightings_tell_what_a_teammate_observes_in_the_agents_own_frame() -> None:
    cfg = TreadmillConfig(n_agents=2, n_adversaries=2, team_sightings=True, sensor_range=20.0)
    # agent 1 sees adversary 2, which sits in agent 0's rear blind spot; adversary 3 is out of every sensor
    obs, _ = observe_placed(cfg, [50, 30, 40, 90], [50, 50, 52, 90], [0, 0, 0, 0], [1, 1, 1, 1])
    assert obs.shape[-1] == cfg.obs_dim and obs[0, 0, OWN_FEATURES] == 0  # agent 0 itself sees nothing
    told = obs[0, 0, -3 * SIGHTING_FEATURES :].reshape(3, SIGHTING_FEATURES)  # agent 0: cars 1, 2, 3
    assert told[0].tolist() == pytest.approx([1, -20 / 20, 0, 1 / 3, 0])  # a teammate: it can say where it is
    assert told[1].tolist() == pytest.approx([1, -10 / 20, 2 / 20, 1 / 3, 1])  # seen by agent 1: an adversary
    assert (told[2] == 0).all()  # nobody observes it
    with_headings = cfg.model_copy(update={"sighting_headings": True})
    obs, _ = observe_placed(with_headings, [50, 30, 40, 90], [50, 50, 52, 90], [0, 0, 3, 0], [1, 1, 1, 1])
    width = with_headings.sighting_features
    told = obs[0, 0, -3 * width :].reshape(3, width)
    assert obs.shape[-1] == with_headings.obs_dim and width == SIGHTING_FEATURES + N_HEADINGS
    assert told[1, SIGHTING_FEATURES:].argmax() == 3 and told[0, SIGHTING_FEATURES:].argmax() == 0  # each car's own
    assert (told[2] == 0).all()
    with pytest.raises(ValueError, match="team_sightings=true"):
        TreadmillConfig(sighting_headings=True)


def test_aggressive_adversary_closes_in() -> None:
    cfg = TreadmillConfig(n_agents=1, n_adversaries=1, aggression=1.0)
    e = TreadmillEngine(cfg, 64)
    e.reset(0)
    start = distance(e.x[:, 0], e.y[:, 0], e.x[:, 1], e.y[:, 1])
    for _ in range(5):
        e.step(np.full((64, 1), KEEP))
    end = distance(e.x[:, 0], e.y[:, 0], e.x[:, 1], e.y[:, 1])
    assert (end < start).mean() > 0.9


def test_a_faster_adversary_reaches_its_own_top_speed_and_agents_keep_theirs() -> None:
    cfg = TreadmillConfig(n_agents=2, n_adversaries=1, aggression=1.0, adversary_speed=5)
    e = TreadmillEngine(cfg, 32)
    e.reset(0)
    top_adv = top_agent = 0
    for _ in range(30):
        obs = e.step(np.full((32, 2), 8)).obs  # every agent: turn left and accelerate
        top_adv, top_agent = max(top_adv, e.speed[:, 2].max()), max(top_agent, e.speed[:, :2].max())
        assert np.abs(obs).max() <= 1.0
    assert (top_adv, top_agent) == (5, 3)
    assert cfg.top_speed == 5 and TreadmillConfig().top_speed == TreadmillConfig().max_speed
    with pytest.raises(ValueError, match="adversary_speed"):
        TreadmillConfig(adversary_speed=0)


def test_a_chaser_too_fast_to_steer_keeps_its_heading_until_it_slows_down() -> None:
    cfg = TreadmillConfig(n_agents=2, n_adversaries=1, aggression=1.0, adversary_speed=7, adversary_steer_speed=3)
    e = TreadmillEngine(cfg, 256)
    e.reset(0)
    steered_fast = steered_slow = 0
    for _ in range(60):
        heading, speed = e.heading[:, 2].copy(), e.speed[:, 2].copy()
        e.step(np.full((256, 2), KEEP))
        alive = ~e.last_crashed[:, 2] & (e.x[:, 2] > 0) & (e.x[:, 2] < cfg.length - 1)  # no bounce, no re-entry
        alive &= (e.y[:, 2] > 0) & (e.y[:, 2] < cfg.width - 1)
        turned = (e.heading[:, 2] != heading) & alive
        steered_fast += int((turned & (speed > 3)).sum())
        steered_slow += int((turned & (speed <= 3)).sum())
    assert steered_fast == 0 and steered_slow > 0  # it chases, turning only at 3 cells a step or slower
    free = TreadmillConfig(n_agents=2, n_adversaries=1, aggression=1.0, adversary_speed=7)
    assert TreadmillEngine(free, 1)._steer_cap.tolist() == [7, 7, 7]


def test_treadmill_carries_cars_back() -> None:
    e = two_cars(length=40)
    place(e, [10, 30], [5, 15], [0, 0], [0, 1])
    e.step(np.array([[KEEP, KEEP]]))
    assert e.x[0].tolist() == [9, 30]  # standing still drifts back; treadmill speed holds its place


def test_adversaries_bounce_off_the_edge() -> None:
    cfg = TreadmillConfig(n_agents=1, n_adversaries=1, length=40, width=10, aggression=0.0)
    e = TreadmillEngine(cfg, 1)
    e.reset(0)
    place(e, [0, 20], [5, 9], [0, 2], [1, 2])
    e.step(np.array([[KEEP]]))
    assert 0 <= e.y[0, 1] <= 9


def test_bad_actions_rejected() -> None:
    e = TreadmillEngine(TreadmillConfig(), 2)
    e.reset(0)
    with pytest.raises(ValueError, match="actions"):
        e.step(np.zeros((2, 2), np.int64))
    with pytest.raises(ValueError, match="actions"):
        e.step(np.full((2, 3), 9))


def test_varying_belt_runs_between_its_speeds_and_carries_cars_by_its_speed() -> None:
    cfg = TreadmillConfig(n_agents=1, n_adversaries=1, treadmill_speed_max=2, treadmill_switch_prob=0.1, aggression=0)
    e = TreadmillEngine(cfg, 256, autoreset=False)
    e.reset(0)
    seen, changes = set(), 0
    for _ in range(20):
        e.x[:, 0], e.y[:, 0], e.heading[:, 0], e.speed[:, 0] = 50, 50, 0, 0
        before = e.belt.copy()
        e.step(np.full((256, 1), KEEP))
        assert np.array_equal(e.x[:, 0], 50 - e.belt)  # a car at rest falls back by this step's belt speed
        seen |= set(e.belt.tolist())
        changes += int((e.belt != before).sum())
    assert seen == {1, 2} and changes > 0
    assert (TreadmillEngine(TreadmillConfig(), 8).belt == 1).all()  # unset: the belt's speed is constant


def test_spawn_headings_spread_around_forward() -> None:
    e = TreadmillEngine(TreadmillConfig(n_agents=4, spawn_heading_spread=4), 256)
    e.reset(0)
    assert set(e.heading[:, :4].ravel().tolist()) == set(range(8))
    e = TreadmillEngine(TreadmillConfig(n_agents=4, spawn_heading_spread=1), 256)
    e.reset(0)
    assert set(e.heading[:, :4].ravel().tolist()) == {7, 0, 1}
    e = TreadmillEngine(TreadmillConfig(n_agents=4, spawn_heading_spread=0), 16)
    e.reset(0)
    assert (e.heading == 0).all()


def test_a_stealthy_adversary_is_seen_by_teammates_but_not_by_the_agent_it_chases() -> None:
    kw = dict(n_agents=2, n_adversaries=1, sensor_fov=360.0, sensor_range=40.0)
    x, y, heading, speed = [50, 60, 45], [50, 50, 50], [0, 0, 0], [1, 1, 1]  # the adversary is closest to agent 0
    obs, _ = observe_placed(TreadmillConfig(**kw, adversary_stealth=True), x, y, heading, speed)
    seen_dx = obs[0, :, OWN_FEATURES + 1] * 40.0
    assert seen_dx[0] == pytest.approx(10.0)  # agent 0 sees only agent 1, not its chaser 5 cells behind
    assert seen_dx[1] == pytest.approx(-10.0)  # agent 1 sees agent 0 (10 behind) — and the chaser, 15 behind
    e = TreadmillEngine(TreadmillConfig(**kw, adversary_stealth=True, observe_k=2), 1)
    e.reset(0)
    place(e, x, y, heading, speed)
    near, near_dist, _ = e.nearest()
    assert 2 not in near[0, 0][np.isfinite(near_dist[0, 0])] and 2 in near[0, 1][np.isfinite(near_dist[0, 1])]
    obs, _ = observe_placed(TreadmillConfig(**kw), x, y, heading, speed)
    assert obs[0, 0, OWN_FEATURES + 1] * 40.0 == pytest.approx(-5.0)  # without stealth agent 0 sees it

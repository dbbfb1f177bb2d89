"""Property tests of the treadmill physics (hypothesis): geometry, crashes, rewards, batching."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from envs.batched import env_seeds
from envs.treadmill import TreadmillConfig, TreadmillEngine, torus_delta, torus_distance
from envs.treadmill.engine import DX, DY

KEEP = 4  # steer 0, accelerate 0
FAST = settings(max_examples=60, deadline=None)


def place(engine: TreadmillEngine, x, y, heading, speed) -> None:
    """Put env 0's cars at given cells with given headings and speeds."""
    engine.x[0], engine.y[0] = x, y
    engine.heading[0], engine.speed[0] = heading, speed


def two_cars(length: int = 40, width: int = 20, max_speed: int = 3) -> TreadmillEngine:
    e = TreadmillEngine(TreadmillConfig(n_agents=2, n_adversaries=0, length=length, width=width, max_speed=max_speed))
    e.reset(0)
    return e


@given(st.integers(8, 1000), st.integers(-5000, 5000), st.integers(-5000, 5000))
def test_torus_delta_bounded_and_distance_symmetric(length: int, a: int, b: int) -> None:
    d = torus_delta(np.array(a), np.array(b), length)
    assert abs(int(d)) <= length / 2
    assert (a + int(d) - b) % length == 0  # it is an offset that really leads from a to b
    assert torus_distance(a, 0, b, 3, length) == torus_distance(b, 3, a, 0, length)
    assert torus_distance(a, 0, b, 0, length) <= length / 2


@FAST
@given(
    st.integers(0, 39),
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
    place(e, [x, (x + 20) % 40], [y, width // 2], [heading, 0], [speed, 1])
    r = e.step(np.array([[KEEP, KEEP]]))
    assert bool(r.info["crashed"][0, 0]) == leaves
    assert bool(r.terminated[0]) == leaves
    if leaves:
        assert r.reward[0, 0] == -e.cfg.crash_penalty


@FAST
@given(
    st.integers(0, 39),
    st.integers(4, 15),
    st.integers(0, 7),
    st.integers(0, 7),
    st.integers(1, 3),
    st.integers(1, 3),
)
def test_cars_driving_into_the_same_cell_collide(qx, qy, h1, h2, v1, v2) -> None:
    e = two_cars()
    starts = [(qx - v * DX[h], qy - v * DY[h]) for h, v in ((h1, v1), (h2, v2))]
    if (starts[0][0] - starts[1][0]) % 40 == 0 and starts[0][1] == starts[1][1]:
        return  # both would start on one cell: not a situation the env can be in
    place(e, [s[0] % 40 for s in starts], [s[1] for s in starts], [h1, h2], [v1, v2])
    r = e.step(np.array([[KEEP, KEEP]]))
    assert r.info["crashed"][0].all() and r.terminated[0]
    assert (r.reward[0] == -e.cfg.crash_penalty).all()


@FAST
@given(st.integers(0, 39), st.integers(2, 17), st.integers(0, 7))
def test_swapping_cells_is_a_collision(x: int, y: int, heading: int) -> None:
    e = two_cars()
    place(e, [x, (x + DX[heading]) % 40], [y, y + DY[heading]], [heading, (heading + 4) % 8], [1, 1])
    r = e.step(np.array([[KEEP, KEEP]]))
    assert r.info["crashed"][0].all()


@FAST
@given(st.integers(0, 39), st.integers(2, 17), st.sampled_from([1, 3, 5, 7]))
def test_diagonal_paths_crossing_collide(x: int, y: int, heading: int) -> None:
    e = two_cars()
    mirrored = {1: 3, 3: 1, 5: 7, 7: 5}[heading]  # same lateral direction, opposite longitudinal one
    place(e, [x, (x + DX[heading]) % 40], [y, y], [heading, mirrored], [1, 1])
    r = e.step(np.array([[KEEP, KEEP]]))
    assert r.info["crashed"][0].all()  # they end on different cells but crossed on the way


@FAST
@given(st.integers(0, 39), st.integers(2, 10), st.integers(0, 7), st.integers(1, 3), st.integers(2, 8))
def test_parallel_cars_never_collide(x: int, y: int, heading: int, speed: int, gap: int) -> None:
    e = two_cars(max_speed=3)
    place(e, [x, x], [y, y + gap], [heading, heading], [speed, speed])
    if any(not 0 <= yy + DY[heading] * speed < e.cfg.width for yy in (y, y + gap)):
        return  # would leave the road: another rule
    r = e.step(np.array([[KEEP, KEEP]]))
    assert not r.info["crashed"][0].any()


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


@settings(max_examples=25, deadline=None)
@given(
    st.lists(st.integers(0, 2**40), min_size=1, max_size=6),
    st.integers(1, 5),
    st.integers(0, 2),
    st.integers(1, 3),
    st.integers(0, 2**31),
)
def test_batch_equals_envs_stepped_one_by_one(seeds, n_agents, n_adv, observe_k, action_seed) -> None:
    if n_agents + n_adv < 2:
        n_adv = 1
    observe_k = min(observe_k, n_agents + n_adv - 1)
    cfg = TreadmillConfig(
        n_agents=n_agents,
        n_adversaries=n_adv,
        length=30,
        width=12,
        spawn_gap=3,
        max_steps=15,
        observe_k=observe_k,
        aggression=0.5,
    )
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
            for arr in ("x", "y", "heading", "speed", "t"):
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


def test_spawned_cars_are_apart_and_facing_forward() -> None:
    cfg = TreadmillConfig(n_agents=8, n_adversaries=3)
    e = TreadmillEngine(cfg, 256)
    e.reset(3)
    dx = np.abs(torus_delta(e.x[:, :, None], e.x[:, None, :], cfg.length))
    dy = np.abs(e.y[:, :, None] - e.y[:, None, :])
    cheb = np.maximum(dx, dy) + np.eye(cfg.n_cars, dtype=np.int64) * 10**6
    assert cheb.min() >= cfg.spawn_gap
    assert (e.heading == 0).all() and (e.speed == cfg.initial_speed).all()


def test_observation_encodes_the_closest_car() -> None:
    e = two_cars(length=100, width=100)
    place(e, [98, 3], [50, 52], [0, 2], [1, 3])  # the other car is 5 cells ahead across the wrap, 2 to the left
    obs, closest = e._observe(np.array([0]))
    own, near = obs[0, 0, :12], obs[0, 0, 12:]
    assert own[1] == 1.0 and own[9] == pytest.approx(1 / 3)  # heading 0, speed 1 of 3
    assert near[0] == pytest.approx(5 / 50) and near[1] == pytest.approx(2 / 99)
    assert near[2 + 2] == 1.0 and near[10] == pytest.approx(1.0)  # heading 2, full speed
    assert closest[0, 0] == pytest.approx(np.hypot(5, 2))


def test_aggressive_adversary_closes_in() -> None:
    cfg = TreadmillConfig(n_agents=1, n_adversaries=1, aggression=1.0)
    e = TreadmillEngine(cfg, 64)
    e.reset(0)
    start = torus_distance(e.x[:, 0], e.y[:, 0], e.x[:, 1], e.y[:, 1], cfg.length)
    for _ in range(5):
        e.step(np.full((64, 1), KEEP))
    end = torus_distance(e.x[:, 0], e.y[:, 0], e.x[:, 1], e.y[:, 1], cfg.length)
    assert (end < start).mean() > 0.9


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

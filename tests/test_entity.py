"""The entity encoder (``encoder=entity``, ``algos/entity.py``): the treadmill's layout read from the env, tokens
that say what the engine saw, Q-values blind to slot order and to empty slots, a population member equal to the
single run, Algorithm 1's gradients through heard messages, and checkpoints that rebuild it."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

from convoy.algos.algorithm import Progress
from convoy.algos.entity import EntityEncoder, token_features
from convoy.algos.nets import run_state
from convoy.algos.registry import make_algorithm
from convoy.config import job_config, resolve_algo
from convoy.envs import make_batched
from convoy.envs.batched import ENTITY_SOURCES, EnvSpec
from convoy.envs.layout import entity_layout
from convoy.envs.treadmill.config import N_HEADINGS, NEIGHBOUR_FEATURES, OWN_FEATURES
from convoy.envs.treadmill.drivers import encode16
from convoy.transition import Transition, from_columns
from convoy.validation import ConfigError
from tests.transitions import batch, run_of

SIGHTINGS = {"team_sightings": True}
SEEDS = [3, 7, 11]


def env_obs(params: dict[str, Any], envs: int = 8, steps: int = 30, seed: int = 0) -> tuple[Any, list[np.ndarray]]:
    """A treadmill batch and its observations over ``steps`` random steps."""
    env = make_batched("treadmill", envs, **params)
    g = np.random.default_rng(seed)
    obs = [env.reset(seed)]
    for _ in range(steps):
        obs.append(env.step(g.integers(0, 9, size=(envs, env.spec.n_agents))).obs)
    return env, obs


def build(name: str, spec: EnvSpec, share: bool = True, seed: int | list[int] = 0, **hp: Any):
    params = {"encoder": "entity", "entity_width": 16, "hidden": (32, 32), "share_params": share, "batch_size": 16,
              "learning_starts": 0, "replay_capacity": 500, "lr": 1e-3, "target_update": 20, **hp}  # fmt: skip
    return make_algorithm(name, spec, resolve_algo(name, "treadmill", params), device="cpu", seed=seed)


def permuted(obs: np.ndarray, spec: EnvSpec, g: np.random.Generator) -> np.ndarray:
    """``obs [..., N, D]`` with each agent's slots of every car block in a random order of their own."""
    assert spec.layout is not None
    out = obs.copy()
    for block in spec.layout.cars:
        cols = slice(block.start, block.start + block.count * block.width)
        slots = out[..., cols].reshape(*obs.shape[:-1], block.count, block.width)
        order = np.argsort(g.random(slots.shape[:-1]), axis=-1)
        out[..., cols] = np.take_along_axis(slots, order[..., None], axis=-2).reshape(*obs.shape[:-1], -1)
    return out


@pytest.mark.parametrize(
    "params",
    [
        {},
        SIGHTINGS,
        {**SIGHTINGS, "observe_k": 1, "n_agents": 2},
        {**SIGHTINGS, "adversary_stealth": True},
        {**SIGHTINGS, "sighting_headings": True, "adversary_speed": 7, "adversary_steer_speed": 3},
    ],
    ids=["default", "sightings", "one-slot", "stealth", "sighting-headings"],
)
def test_tokens_say_what_the_engine_saw(params: dict[str, Any]) -> None:
    """The layout lives beside the engine (``envs/layout.py``): every token must match the engine's own state —
    present where a car is seen or told, its offset, heading and speed, the adversary flag where the block gives
    one — so a change to the observation that the layout misses fails here."""
    env, _ = env_obs(params, steps=20)
    layout = entity_layout(env.spec)
    enc = EntityEncoder(layout, env.spec.obs_dim, 1, 0, 8, False)
    cfg, n = env.cfg, env.cfg.n_agents
    obs = torch.as_tensor(env.step(np.zeros((env.num_envs, n), np.int64)).obs)
    tokens = enc.tokens(obs).transpose(-3, -2).numpy()  # [B, N, T, F]
    near, near_dist, _ = env.nearest()
    rel_x, rel_y = env.offsets()
    r, k, h = cfg.sensor_range, cfg.observe_k, N_HEADINGS
    sensor, told = tokens[..., :k, :], tokens[..., k:, :]
    seen = np.isfinite(near_dist)
    np.testing.assert_array_equal(sensor[..., 0], seen)

    def of_seen(a: np.ndarray) -> np.ndarray:  # a per-car array [B, C] at each agent's slots [B, N, k]
        return np.take_along_axis(np.broadcast_to(a[:, None], rel_x.shape), near, 2)

    np.testing.assert_allclose(sensor[..., 1], np.where(seen, np.take_along_axis(rel_x, near, 2) / r, 0), atol=1e-6)
    np.testing.assert_allclose(sensor[..., 2], np.where(seen, np.take_along_axis(rel_y, near, 2) / r, 0), atol=1e-6)
    np.testing.assert_allclose(sensor[..., 3] * cfg.top_speed, np.where(seen, of_seen(env.speed), 0), atol=1e-5)
    np.testing.assert_array_equal(sensor[..., 4 : 4 + h].argmax(-1)[seen], of_seen(env.heading)[seen])
    flags = sensor[..., 4 + h :]  # heading known, adversary, adversary known, source one-hot
    np.testing.assert_array_equal(flags[..., 0], seen)  # the sensor gives a heading
    assert not flags[..., 1:3].any(), "the sensor does not say which car is an adversary"
    np.testing.assert_array_equal(flags[..., 3 + ENTITY_SOURCES.index("sensor")], seen)
    assert tokens.shape[-1] == token_features(layout) and not sensor[~seen].any(), "an empty slot is zeros"
    if not cfg.team_sightings:
        assert told.shape[-2] == 0
        return
    others = np.array([[j for j in range(cfg.n_cars) if j != i] for i in range(n)])
    known = env.team_observed(near, near_dist)[:, others] | (others < n)
    me = np.arange(n)[:, None]
    np.testing.assert_array_equal(told[..., 0], known)
    for col, rel in ((1, rel_x), (2, rel_y)):  # a teammate may be out of sensor range: clipped to ±1 like every feature
        want = np.where(known, np.clip(rel[:, me, others] / r, -1, 1), 0)
        np.testing.assert_allclose(told[..., col], want, atol=1e-6)
    if cfg.sighting_headings:  # the told car's own heading, as a sensor slot gives it
        np.testing.assert_array_equal(told[..., 4 : 4 + h].argmax(-1)[known], env.heading[:, others][known])
        np.testing.assert_array_equal(told[..., 4 + h], known)  # heading known
    else:
        assert not told[..., 4 : 4 + h + 1].any(), "a sighting gives no heading"
    np.testing.assert_array_equal(told[..., 5 + h], known & (others >= n))  # adversary
    np.testing.assert_array_equal(told[..., 6 + h], known)  # adversary known
    np.testing.assert_array_equal(told[..., 7 + h + ENTITY_SOURCES.index("told")], known)


@pytest.mark.parametrize("params", [{}, SIGHTINGS], ids=["words", "words-and-sightings"])
def test_the_words_teammates_say_are_their_16_bit_codes_read_as_entities(params: dict[str, Any]) -> None:
    """``team_words``: each agent hears every teammate's ``encode16`` word (the team16 references' code) as 16 bits,
    teammates in index order, at the columns the layout names; the entity encoder reads each word as an entity, so
    the order of the words changes no Q-value, and a word changes what the network computes."""
    env, obs = env_obs({**params, "team_words": True, "adversary_speed": 7}, steps=20)
    layout = entity_layout(env.spec)
    cfg, n = env.cfg, env.cfg.n_agents
    assert layout.words is not None and (layout.words.count, layout.words.bits) == (n - 1, 16)
    words = layout.words
    x = np.concatenate(obs)  # [M, N, D]
    private = x[..., : OWN_FEATURES + cfg.observe_k * NEIGHBOUR_FEATURES]
    said = encode16(private, cfg).astype(np.int64)  # [M, N]: what each agent says
    heard = x[..., words.start : words.start + words.count * words.bits].reshape(*x.shape[:-1], n - 1, 16)
    value = (heard.astype(np.int64) << np.arange(16)).sum(-1)  # [M, N, N−1]
    others = np.array([[j for j in range(n) if j != i] for i in range(n)])
    np.testing.assert_array_equal(value, said[:, others])
    assert (said >> 15).any(), "some agent should see a car"
    algo = build("idqn", env.spec)
    swapped = heard[..., ::-1, :].reshape(*x.shape[:-1], -1)
    y = x.copy()
    y[..., words.start : words.start + words.count * words.bits] = swapped
    assert not np.array_equal(x, y)
    silent = x.copy()
    silent[..., words.start :] = 0
    with torch.no_grad():
        q = algo.greedy_q(torch.as_tensor(x)[None], None)[0]
        torch.testing.assert_close(algo.greedy_q(torch.as_tensor(y)[None], None)[0], q, rtol=0, atol=1e-5)
        assert (algo.greedy_q(torch.as_tensor(silent)[None], None)[0] - q).abs().max() > 1e-4


def test_an_env_without_a_layout_or_with_blocks_it_cannot_read_is_a_config_error() -> None:
    toy = EnvSpec(name="toy", agent_ids=("a", "b"), obs_dims=(6, 6), n_actions=(5, 5), max_steps=10)
    with pytest.raises(ConfigError, match="encoder=mlp") as info:
        build("idqn", toy)
    assert info.value.field == "encoder" and "layout" in str(info.value)
    spec = make_batched("treadmill", 1, team_observations=True).spec
    with pytest.raises(ConfigError, match="team_observations") as info:
        build("ma-mesn", spec)
    assert info.value.field == "encoder"
    build("idqn", spec, encoder="mlp")  # the flat MLP reads any observation
    for env, params in (("referential", {}), ("treadmill", {"team_observations": True})):  # a job: before it starts
        with pytest.raises(ConfigError, match="encoder=mlp") as info:
            job_config(algo="ma-bon", env=env, env_params=params, algo_params={"encoder": "entity"})
        assert info.value.field == "algo_params.encoder"
    job_config(algo="ma-bon", env="treadmill", env_params=SIGHTINGS, algo_params={"encoder": "entity"})


@pytest.mark.parametrize("context", [False, True], ids=["alone", "in-context"])
@pytest.mark.parametrize("share", [True, False], ids=["shared", "per-agent"])
@pytest.mark.parametrize("name", ["idqn", "ma-mesn", "ma-bon"])
def test_q_values_ignore_the_order_of_slots(name: str, share: bool, context: bool) -> None:
    """Permuting each agent's sensor slots and its told sightings leaves every Q-value unchanged (``entity_context``
    too: every car reads the same own features)."""
    env, obs = env_obs(SIGHTINGS)
    algo = build(name, env.spec, share, entity_context=context)
    x = torch.as_tensor(np.concatenate(obs))[None]  # one run's [R = 1, M, N, D]
    y = torch.as_tensor(permuted(np.concatenate(obs), env.spec, np.random.default_rng(1)))[None]
    assert not torch.equal(x, y)
    flat = build(name, env.spec, share, encoder="mlp")
    with torch.no_grad():
        q, _, _ = algo.greedy_q(x, None)
        torch.testing.assert_close(algo.greedy_q(y, None)[0], q, rtol=0, atol=1e-5)
        assert (flat.greedy_q(y, None)[0] - flat.greedy_q(x, None)[0]).abs().max() > 1e-3, "the flat MLP is not"


@pytest.mark.parametrize("context", [False, True], ids=["alone", "in-context"])
def test_an_empty_slot_contributes_nothing(context: bool) -> None:
    """A slot whose present flag is 0 is read as absent whatever else it holds: Q-values with garbage in the empty
    slots equal those with the zeros the env writes there, exactly."""
    env, obs = env_obs(SIGHTINGS)
    algo = build("idqn", env.spec, entity_context=context)
    x = torch.as_tensor(np.concatenate(obs))[None]  # one run's [R = 1, M, N, D]
    assert env.spec.layout is not None
    garbage = x.clone()
    g = torch.Generator().manual_seed(0)
    for block in env.spec.layout.cars:
        for s in range(block.count):
            cols = slice(block.start + s * block.width, block.start + (s + 1) * block.width)
            empty = x[..., block.start + s * block.width + block.present] == 0  # [M, N]
            noise = torch.rand(*x.shape[:-1], block.width, generator=g) * 2 - 1
            noise[..., block.present] = 0
            garbage[..., cols] = torch.where(empty[..., None], noise, x[..., cols])
    assert not torch.equal(garbage, x), "the observations should hold empty slots"
    q = algo.online["q"]
    with torch.no_grad():
        torch.testing.assert_close(q(algo.features(garbage)), q(algo.features(x)), rtol=0, atol=0)


@pytest.mark.parametrize("context", [False, True], ids=["alone", "in-context"])
@pytest.mark.parametrize("share", [True, False], ids=["shared", "per-agent"])
def test_shapes_with_and_without_the_run_axis_and_a_member_is_the_single_run(share: bool, context: bool) -> None:
    """R = 1 and R = 3 populations give ``[R, B, N, A]`` (a single run is R = 1), and run k's Q-values are the
    single run of seed k's (the same initial weights, the encoder stacked like any GroupLinear)."""
    env, obs = env_obs(SIGHTINGS, envs=4, steps=2)
    x = torch.as_tensor(obs[-1])
    single = build("idqn", env.spec, share, seed=SEEDS[1], entity_context=context)
    assert single.greedy_q(x[None], None)[0].shape == (1, 4, 3, 9)
    for seeds in ([SEEDS[1]], SEEDS):
        pop = build("idqn", env.spec, share, seed=seeds, entity_context=context)
        q = pop.greedy_q(x.expand(len(seeds), *x.shape), None)[0]
        assert q.shape == (len(seeds), 4, 3, 9)
        k = seeds.index(SEEDS[1])
        torch.testing.assert_close(q[k], single.greedy_q(x[None], None)[0][0], rtol=0, atol=1e-6)


def test_in_context_each_car_is_read_beside_the_agents_own_motion() -> None:
    """``entity_context``: φ reads every car's token with the agent's own features, so a car's embedding changes
    with the agent's heading; read alone it does not. The own features come from the observation's first columns,
    the ones ``ρ`` reads."""
    env, obs = env_obs(SIGHTINGS, envs=4, steps=3)
    layout = entity_layout(env.spec)
    x = torch.as_tensor(obs[-1])  # [B, N, D]
    turned = x.clone()
    turned[..., 1 : 1 + N_HEADINGS] = turned[..., 1 : 1 + N_HEADINGS].roll(1, dims=-1)  # own heading one-hot
    for context in (False, True):
        torch.manual_seed(0)
        enc = EntityEncoder(layout, env.spec.obs_dim, 1, 0, 8, False, context=context)
        with torch.no_grad():
            cars = [enc.cars(v) for v in (x, turned)]
        assert torch.equal(enc.tokens(x), enc.tokens(turned))  # the cars' tokens are the same
        assert bool((cars[0] != cars[1]).any()) == context


@pytest.mark.parametrize("encoder", ["entity", "mlp"])
@pytest.mark.parametrize("name", ["idqn", "ma-mesn", "ma-bon"])
def test_a_dueling_head_gives_q_as_the_value_plus_the_centred_advantage(name: str, encoder: str) -> None:
    """``dueling``: each Q network's last layer gives V and one A per action; its Q-values are V + A − mean A (so
    their mean over actions is V), the run axis and a population member behave as without it, slot order still
    changes nothing, and message networks keep their plain outputs."""
    from convoy.algos.entity import Dueling

    env, obs = env_obs(SIGHTINGS, envs=4, steps=2)
    x = torch.as_tensor(np.concatenate(obs))
    algo = build(name, env.spec, seed=SEEDS, dueling=True, encoder=encoder)
    key = "q" if name == "idqn" else "policy"
    net = algo.online[key]
    assert isinstance(net[-1], Dueling)
    others = [m for k, module in algo.online.items() if k != key for m in module.modules()]  # message, encoder
    assert not any(isinstance(m, Dueling) for m in others)
    with torch.no_grad():
        q, _, _ = algo.greedy_q(x.expand(len(SEEDS), *x.shape), None)
        assert q.shape == (len(SEEDS), len(x), 3, 9)
        heads: list[torch.Tensor] = []
        hook = net[0].register_forward_hook(lambda m, i, o: heads.append(o))
        algo.greedy_q(x.expand(len(SEEDS), *x.shape), None)
        hook.remove()
        (raw,) = heads
        assert raw.shape[-1] == 10
        torch.testing.assert_close(q.mean(dim=-1), raw[..., 0], rtol=0, atol=1e-5)
        torch.testing.assert_close(q - q.mean(dim=-1, keepdim=True), raw[..., 1:] - raw[..., 1:].mean(-1, True))
        single = build(name, env.spec, seed=SEEDS[1], dueling=True, encoder=encoder)
        torch.testing.assert_close(q[1], single.greedy_q(x[None], None)[0][0], rtol=0, atol=1e-6)
        if encoder == "entity":
            y = torch.as_tensor(permuted(np.concatenate(obs), env.spec, np.random.default_rng(1)))
            torch.testing.assert_close(algo.greedy_q(y.expand(len(SEEDS), *y.shape), None)[0], q, rtol=0, atol=1e-5)


def env_chunk(env: Any, runs: int, g: np.random.Generator, steps: int = 8) -> Transition[np.ndarray]:
    """``steps`` random-action transitions of the treadmill, ``[T, R, B, …]`` (the env's B split into R runs)."""
    b, n = env.num_envs, env.spec.n_agents
    obs = env.reset(int(g.integers(1 << 30)))
    rows: list[dict[str, np.ndarray]] = []
    for _ in range(steps):
        action = g.integers(0, 9, size=(b, n))
        res = env.step(action)
        done = {"terminated": res.terminated, "truncated": res.truncated, "episode": np.zeros(b, np.int64)}
        rows.append({"obs": obs, "next_obs": res.final_obs, "action": action, "reward": res.reward, **done})
        obs = res.obs
    return from_columns({k: np.stack([r[k].reshape(runs, b // runs, *r[k].shape[1:]) for r in rows]) for k in rows[0]})


@pytest.mark.parametrize("share", [True, False], ids=["shared", "per-agent"])
@pytest.mark.parametrize("name", ["idqn", "ma-mesn"])
def test_a_population_member_trains_as_the_single_run_of_its_seed(name: str, share: bool) -> None:
    """As ``tests/test_population.py`` for the flat MLPs: the same batches, the same updates, weights equal to
    float32 rounding (message algorithms over fewer updates: a hard bit flips on rounding, see there)."""
    env = make_batched("treadmill", 4 * len(SEEDS), **SIGHTINGS)
    hp = {"gumbel_noise": 1.0} if name == "ma-mesn" else {}  # sampled messages: the noise streams must match too
    pop = build(name, env.spec, share, seed=SEEDS, **hp)
    singles = [build(name, env.spec, share, seed=s, **hp) for s in SEEDS]
    g = np.random.default_rng(0)
    for _ in range(3):
        c = env_chunk(env, len(SEEDS), g)
        pop.observe(c)
        for k, single in enumerate(singles):
            single.observe(run_of(c, k))
    for agent in (pop, *singles):
        agent.progress = Progress(100, 1, 1000, training=True)
    for _ in range(40 if name == "ma-mesn" else 150):
        pop.update()
        for single in singles:
            single.update()
    gap = max(float((run_state(a.online, 0)[p] - w).abs().max())
              for k, a in enumerate(singles) for p, w in run_state(pop.online, k).items())  # fmt: skip
    # batched and single matmuls sum in different orders, by CPU (1.3e-5 seen after 40 updates); a wrong batch or
    # seed moves weights by 1e-2 and more
    assert gap < 1e-4


def test_mesn_listener_loss_reaches_the_other_agents_message_networks_through_heard_entities() -> None:
    """Algorithm 1's gradient flow with entity encoders: agent i's TD loss trains its own policy f″_i and, straight
    through the messages it hears (each an entity), every other agent's message network f′_j — not its own."""
    env, obs = env_obs(SIGHTINGS, envs=16, steps=1)
    algo = build("ma-mesn", env.spec, share=False)
    g = np.random.default_rng(0)
    m, n = 16, env.spec.n_agents
    rows = batch(  # one run's: [R = 1, M, …]
        obs=torch.as_tensor(obs[0])[None],
        next_obs=torch.as_tensor(obs[1])[None],
        action=torch.as_tensor(g.integers(0, 9, size=(1, m, n))),
        reward=torch.as_tensor(g.normal(size=(1, m, n)), dtype=torch.float32),
        terminated=torch.zeros(1, m, dtype=torch.bool),
    )
    heard_in = algo.online["policy"][0].heard.layers[0]
    for i in range(n):
        algo.updater.optimizer.zero_grad(set_to_none=True)
        algo.agent_losses(rows)[0, i].backward()
        message = sum(
            p.grad[0].abs().flatten(1).sum(1) for p in algo.online["message"].parameters() if p.grad is not None
        )
        policy = algo.online["policy"][1].layers[0].weight.grad[0].abs().sum(dim=(1, 2))
        assert heard_in.weight.grad is not None and heard_in.weight.grad[0, i].abs().sum() > 0, "ψ_i reads m_−i"
        for j in range(n):
            assert (policy[j] > 0) == (j == i), f"agent {i}'s loss and agent {j}'s policy network"
            assert (message[j] > 0) == (j != i), f"agent {i}'s loss and agent {j}'s message network"


@pytest.mark.parametrize(
    ("name", "params"), [("ma-mesn", SIGHTINGS), ("idqn", {"team_words": True})], ids=["sightings", "words"]
)
def test_a_checkpoint_rebuilds_the_entity_networks(name: str, params: dict[str, Any], tmp_path: Path) -> None:
    """A checkpoint records the job (encoder=entity) and the env's spec with its layout, car slots and words alike:
    loading rebuilds the same networks and acts as the saved agent did."""
    from convoy.algos.checkpoint import load_checkpoint, save_checkpoint

    env, obs = env_obs(params, envs=4, steps=2)
    job = job_config(algo=name, env="treadmill", env_params=params, seed=5, device="cpu",
                     algo_params={"encoder": "entity", "entity_width": 16, "hidden": (32,)})  # fmt: skip
    agent = make_algorithm(name, env.spec, job.algo_config(), device="cpu", seed=5)
    with torch.no_grad():  # weights a fresh network of the same seed does not have
        for w in agent.online.parameters():
            w.add_(torch.randn_like(w))
    save_checkpoint(tmp_path / "c.pt", agent, job, {"env_steps": 0, "episodes": 0, "updates": 0})
    loaded, _, _ = load_checkpoint(tmp_path / "c.pt", device="cpu")
    assert type(loaded) is type(agent)
    assert loaded.spec.layout == env.spec.layout is not None and getattr(loaded.cfg, "encoder", None) == "entity"
    x = torch.as_tensor(obs[-1])[None]  # one run's
    with torch.no_grad():
        torch.testing.assert_close(loaded.greedy_q(x, None)[0], agent.greedy_q(x, None)[0], rtol=0, atol=0)

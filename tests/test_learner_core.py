"""Mechanics shared by every algorithm: gradient routing, target networks, double Q, SER, replay, checkpoints."""

from __future__ import annotations

import math
import warnings
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from convoy.algos.algorithm import NetworkAgent, epsilon_at
from convoy.algos.checkpoint import CheckpointError, load_checkpoint, save_checkpoint
from convoy.algos.dqn_ser import age_weights
from convoy.algos.listening import Source
from convoy.algos.registry import make_algorithm
from convoy.algos.replay import JointReplay
from convoy.algos.streams import RunStreams
from convoy.algos.updater import td_target
from convoy.config import ALGORITHMS, IMSConfig, MeSNConfig, job_config, resolve_algo
from convoy.envs import make_batched
from convoy.envs.batched import EnvSpec
from convoy.transition import TRANSITION, Transition, from_columns
from convoy.transition import schema as declared_schema
from convoy.validation import ConfigError
from tests.conftest import single_update
from tests.transitions import filled

SPEC = EnvSpec(name="toy", agent_ids=("a", "b", "c"), obs_dims=(5, 5, 5), n_actions=(4, 4, 4), max_steps=10)


def random_batch(spec: EnvSpec, m: int = 32, seed: int = 0) -> Transition[torch.Tensor]:
    g = np.random.default_rng(seed)
    n, d = spec.n_agents, spec.obs_dim
    return Transition(  # one run's: [R = 1, M, …]
        obs=torch.as_tensor(g.normal(size=(1, m, n, d)), dtype=torch.float32),
        next_obs=torch.as_tensor(g.normal(size=(1, m, n, d)), dtype=torch.float32),
        action=torch.as_tensor(g.integers(0, spec.max_actions, size=(1, m, n))),
        reward=torch.as_tensor(g.normal(size=(1, m, n)), dtype=torch.float32),
        terminated=torch.as_tensor(g.random((1, m)) < 0.2),
        truncated=torch.zeros(1, m, dtype=torch.bool),
        episode=torch.zeros(1, m, dtype=torch.long),
    )


def fill(algo, spec: EnvSpec, rows: int = 256) -> None:
    b = random_batch(spec, rows)
    algo.observe(b.map(lambda v: v.numpy()[:, None]))  # a chunk [T = 1, R = 1, B, …]


def build(name: str, spec: EnvSpec = SPEC, **params):
    params = {"hidden": (32,), "learning_starts": 0, "batch_size": 16, **params}
    torch.manual_seed(0)
    return make_algorithm(name, spec, resolve_algo(name, "referential", params), device="cpu", seed=0)


def test_mesn_td_loss_of_agent_i_reaches_other_message_nets_and_only_its_own_policy() -> None:
    algo = build("ma-mesn", share_params=False)
    batch = random_batch(SPEC)
    for i in range(SPEC.n_agents):
        algo.updater.optimizer.zero_grad(set_to_none=True)
        algo.agent_losses(batch)[0, i].backward()
        policy_grad = algo.online["policy"].layers[0].weight.grad[0].abs().sum(dim=(1, 2))  # per agent
        message_grad = algo.online["message"].layers[0].weight.grad[0].abs().sum(dim=(1, 2))
        for j in range(SPEC.n_agents):
            if j == i:
                assert policy_grad[j] > 0, "agent i's loss must train its own policy network f″_i"
                assert message_grad[j] == 0, "agent i's own message is not an input of its own Q"
            else:
                assert policy_grad[j] == 0, f"agent {i}'s loss leaked into agent {j}'s policy network"
                assert message_grad[j] > 0, f"agent {i}'s loss must reach agent {j}'s message network f′_{j}"


@pytest.mark.parametrize("name", ["ma-mesn", "ma-bon"])  # the -mm variants speak as these do
def test_channel_control_cuts_or_randomises_what_listeners_hear_in_training_and_acting(name: str) -> None:
    """The controls of a communication claim: with the channel cut, listeners hear zeros whatever was sent, no
    TD loss reaches a message network (the twin has the same networks and nothing to learn through them), and
    its greedy Q-values ignore the messages; with noise they hear fresh random bits at every call."""
    batch = random_batch(SPEC)
    cut = build(name, share_params=False, channel_control="cut")
    _, sent, heard = cut.speak(cut.online, batch.obs, train=True)
    assert sent.abs().sum() > 0 and not heard.any()
    cut.updater.optimizer.zero_grad(set_to_none=True)
    cut.agent_losses(batch).sum().backward()
    message = [p.grad for n, p in cut.online.named_parameters() if n.startswith(("message", "encoder"))]
    assert message and all(g is None or not g.any() for g in message)
    noisy = build(name, share_params=False, channel_control="noise")
    first, second = (noisy.speak(noisy.online, batch.obs, train=False)[2] for _ in range(2))
    assert ((first == 0) | (first == 1)).all() and 0.3 < float(first.mean()) < 0.7 and (first != second).any()
    with pytest.raises(ConfigError, match="channel_control"):
        resolve_algo("ims", "referential", {"channel_control": "cut"})


@pytest.mark.parametrize("name", ["ma-mesn", "ma-bon"])  # the -mm variants add to this loss
def test_speakers_that_do_not_learn_keep_their_weights_while_the_listeners_learn(name: str) -> None:
    """``speakers_learn=False``: Q-learning updates the listeners only; the message networks (MA-BoN: and the
    encoders that feed them) keep the weights they started with — a protocol a demonstration start taught cannot
    drift — while the same update with speakers learning moves them."""

    def speaker_and_listener(algo) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
        named = [(n, p.detach().clone()) for n, p in algo.online.named_parameters()]
        return ([p for n, p in named if n.startswith(("message", "encoder"))],
                [p for n, p in named if n.startswith("policy")])  # fmt: skip

    for learn in (False, True):
        algo = build(name, share_params=False, speakers_learn=learn)
        fill(algo, SPEC)
        before = speaker_and_listener(algo)
        for _ in range(3):
            single_update(algo)
        after = speaker_and_listener(algo)
        speakers_moved = any(not torch.equal(a, b) for a, b in zip(before[0], after[0], strict=True))
        assert before[0] and speakers_moved == learn, (name, learn)
        assert any(not torch.equal(a, b) for a, b in zip(before[1], after[1], strict=True))  # listeners learn


def test_mesn_message_nets_get_summed_gradients_of_all_agents() -> None:
    algo = build("ma-mesn", share_params=False)
    batch = random_batch(SPEC)
    grads = []
    for i in range(SPEC.n_agents):
        algo.streams["noise"].load(0, 1)  # same Gumbel noise in every pass (the agent's own stream)
        algo.updater.optimizer.zero_grad(set_to_none=True)
        algo.agent_losses(batch)[0, i].backward()
        grads.append(algo.online["message"].layers[0].weight.grad.clone())
    algo.streams["noise"].load(0, 1)
    algo.updater.optimizer.zero_grad(set_to_none=True)
    algo.agent_losses(batch).sum().backward()
    torch.testing.assert_close(algo.online["message"].layers[0].weight.grad, sum(grads), rtol=1e-4, atol=1e-6)


@pytest.mark.parametrize("name", ["idqn", "dqn-ser", "ma-mesn"])
def test_target_networks_stay_frozen_between_syncs(name: str) -> None:
    algo = build(name, target_update=5)
    fill(algo, SPEC)
    before = {k: v.clone() for k, v in algo.target.state_dict().items()}
    for _ in range(4):
        algo.update()
    for k, v in algo.target.state_dict().items():
        assert torch.equal(v, before[k]), f"target {k} moved before the sync"
    assert any(not torch.equal(v, before[k]) for k, v in algo.online.state_dict().items())
    algo.update()  # the 5th update syncs
    for k, v in algo.target.state_dict().items():
        assert torch.equal(v, algo.online.state_dict()[k])


def test_double_q_uses_online_argmax_and_target_value() -> None:
    online = torch.tensor([[[5.0, 1.0, 0.0]]])  # online prefers action 0
    target = torch.tensor([[[2.0, 9.0, 0.0]]])  # target would prefer action 1
    mask = torch.tensor([[True, True, True]])
    r, term = torch.tensor([[1.0]]), torch.tensor([False])
    assert td_target(r, term, 0.5, target, online, mask).item() == pytest.approx(1.0 + 0.5 * 2.0)
    assert td_target(r, term, 0.5, target, None, mask).item() == pytest.approx(1.0 + 0.5 * 9.0)
    assert td_target(r, torch.tensor([True]), 0.5, target, online, mask).item() == pytest.approx(1.0)
    # an action the agent does not have is never the argmax
    masked = torch.tensor([[False, True, True]])
    assert td_target(r, term, 0.5, target, online, masked).item() == pytest.approx(1.0 + 0.5 * 9.0)


def test_ser_weights_decay_linearly_with_sample_age() -> None:
    w = age_weights(torch.tensor([150, 100, 50, 0]), episodes=150, horizon=100)
    torch.testing.assert_close(w, torch.tensor([1.0, 0.5, 0.0, 0.0]))


def test_ser_fingerprint_is_stored_and_fed_to_the_network() -> None:
    algo = build("dqn-ser", fingerprint=True)
    algo.progress.env_steps, algo.progress.total_steps = 50, 100
    out = algo.act(np.zeros((2, 3, 5), np.float32), 0.1)
    assert out.extras["fingerprint"].shape == (2, 2)
    assert out.extras["fingerprint"][0, 1] == pytest.approx(0.5)
    assert algo.online["q"].layers[0].in_features == 5 + 2  # obs + fingerprint (referential: no sharing)


def test_epsilon_decays_over_the_shorter_of_20_percent_and_100k_steps() -> None:
    cfg = resolve_algo("idqn", "referential")  # the paper's schedule; the treadmill decays over the whole run
    tm = resolve_algo("idqn", "treadmill")
    assert epsilon_at(tm, 500_000, 1_000_000) == pytest.approx((1.0 + 0.01) / 2)
    assert epsilon_at(cfg, 0, 1_000) == pytest.approx(1.0)
    assert epsilon_at(cfg, 100, 1_000) == pytest.approx((1.0 + 0.05) / 2)
    assert epsilon_at(cfg, 200, 1_000) == pytest.approx(0.05)
    assert epsilon_at(cfg, 50_000, 10_000_000) == pytest.approx((1.0 + 0.05) / 2)  # 100k cap
    assert epsilon_at(cfg, 10_000_000, 10_000_000) == pytest.approx(0.05)


def test_heterogeneous_agents_only_take_their_own_actions() -> None:
    spec = EnvSpec(name="het", agent_ids=("s", "l"), obs_dims=(3, 8), n_actions=(1, 5), max_steps=5)
    algo = build("ma-mesn", spec)
    acts = algo.act(np.random.default_rng(0).normal(size=(500, 2, 8)).astype(np.float32), 1.0).actions
    assert acts[:, 0].max() == 0 and set(np.unique(acts[:, 1])) == set(range(5))
    greedy = algo.act(np.random.default_rng(1).normal(size=(100, 2, 8)).astype(np.float32), 0.0).actions
    assert (greedy[:, 0] == 0).all()


def test_replay_is_a_bounded_ring() -> None:
    buf = JointReplay(10)
    declared = sum(np.dtype(f.dtype).itemsize for f in TRANSITION.values())  # zeros [R, M] each: one item a row
    for start in range(0, 25, 5):
        buf.add(filled((1, 5), x=np.arange(start, start + 5)[None, :, None], y=np.zeros((1, 5, 2, 3))))
    assert len(buf) == 10 and buf.nbytes == 10 * 8 + 10 * 6 * 8 + 10 * declared
    assert set(buf.sample(200, RunStreams([0], "replay")).extras["x"][0, :, 0].tolist()) == set(range(15, 25))
    buf.add(filled((1, 30), x=np.arange(100, 130)[None, :, None], y=np.zeros((1, 30, 2, 3))))  # more than capacity
    assert set(buf.sample(200, RunStreams([0], "replay")).extras["x"][0, :, 0].tolist()) == set(range(120, 130))
    with pytest.raises(ValueError, match="fields"):
        buf.add(filled((1, 1), x=np.zeros((1, 1, 1))))
    with pytest.raises(ValueError, match="leading shape"):
        buf.add(filled((5,), x=np.zeros((5, 1)), y=np.zeros((5, 2, 3))))


def test_checkpoint_reload_gives_identical_actions(tmp_path) -> None:
    job = job_config(algo="ma-mesn", env="referential", algo_params={"hidden": (32,), "learning_starts": 0})
    env = make_batched("referential", 8)
    algo = make_algorithm("ma-mesn", env.spec, job.algo_config(), device="cpu")
    fill(algo, env.spec)
    for _ in range(5):
        algo.update()
    path = save_checkpoint(tmp_path / "c.pt", algo, job, {"env_steps": 123})
    again, job2, counters = load_checkpoint(path, device="cpu")
    obs = env.reset(seed=3)
    np.testing.assert_array_equal(algo.act(obs, 0.0).actions, again.act(obs, 0.0).actions)
    np.testing.assert_array_equal(algo.act(obs, 0.0).messages, again.act(obs, 0.0).messages)
    assert job2 == job and counters["env_steps"] == 123 and again.updates == 5


@pytest.mark.parametrize("name", [n for n in ALGORITHMS if n != "codbc"])  # CoDBC: same base class, needs a teacher
def test_initial_weights_are_a_function_of_the_seed_alone(name: str) -> None:
    """A caller that never seeds torch (a benchmark's first run in a process) still gets the same network for the
    same seed, and building one does not move the caller's own torch stream."""
    cfg = resolve_algo(name, "referential", {"hidden": (32,)})

    def weights(seed: int, global_seed: int) -> dict[str, torch.Tensor]:
        torch.manual_seed(global_seed)
        return make_algorithm(name, SPEC, cfg, device="cpu", seed=seed).online.state_dict()

    a, b, other = weights(3, 1), weights(3, 2), weights(4, 1)
    assert a.keys() == b.keys()
    for k in a:
        torch.testing.assert_close(a[k], b[k], rtol=0, atol=0, msg=f"{name}: {k} depends on torch's global RNG")
    assert any(not torch.equal(a[k], other[k]) for k in a), f"{name}: seeds 3 and 4 built identical networks"
    torch.manual_seed(5)
    make_algorithm(name, SPEC, cfg, device="cpu", seed=3)
    drawn = torch.rand(4)
    torch.manual_seed(5)
    torch.testing.assert_close(drawn, torch.rand(4), rtol=0, atol=0, msg="building an algorithm moved torch's RNG")


def test_bad_checkpoints_give_clear_errors(tmp_path) -> None:
    with pytest.raises(CheckpointError, match="no such file"):
        load_checkpoint(tmp_path / "missing.pt")
    (tmp_path / "junk.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(CheckpointError, match="corrupt"):
        load_checkpoint(tmp_path / "junk.pt")
    torch.save({"hello": 1}, tmp_path / "foreign.pt")
    with pytest.raises(CheckpointError, match="not a Convoy checkpoint"):
        load_checkpoint(tmp_path / "foreign.pt")


@pytest.mark.parametrize(
    ("values", "field"),
    [
        ({"algo": "ppo"}, "algo"),
        ({"algo": "ims", "algo_params": {"comm_iterations": 0}}, "comm_iterations"),
        ({"algo_params": {"batch_size": 128, "replay_capacity": 64}}, "batch_size"),
        ({"algo_params": {"learning_rate": 0.1}}, "learning_rate"),
        ({"algo_params": {"hidden": [64, 0]}}, "hidden"),
        ({"steps": 10, "num_envs": 4096}, "steps"),  # less than one batched step
        ({"env": "highway"}, "env"),
        ({"env_params": {"n_agents": 0}}, "n_agents"),
        ({"steps": 0}, "steps"),
        ({"env": "referential", "hierarchical": True}, "hierarchical"),
        ({"runtime": {"actor_nice": 20}}, "runtime.actor_nice"),
    ],
)
def test_impossible_job_configs_name_the_field(values: dict, field: str) -> None:
    with pytest.raises(ConfigError) as info:
        job_config(**values)
    assert info.value.field == field, str(info.value)


@pytest.mark.parametrize(
    ("values", "field", "limit"),
    [
        ({"algo_params": {"hidden": [1_000_000_000]}}, "algo_params.hidden", "max-layer-width"),  # ~100 GB
        ({"algo_params": {"hidden": [16_000, 16_000]}}, "algo_params.hidden", "max-hidden-weights"),  # 256 M weights
        ({"num_envs": 65_536, "env_params": {"n_agents": 32}}, "num_envs", "max-agent-envs"),  # 2.2 M cars
    ],
)
def test_resource_limits_name_the_field_the_limit_and_the_flag(values: dict, field: str, limit: str) -> None:
    from convoy.config import ResourceLimits

    job = job_config(**values)  # a valid config; whether a machine should allocate it is the limits' question
    with pytest.raises(ConfigError) as info:
        ResourceLimits().check(job, "convoy serve")
    assert info.value.field == field and f"convoy serve --{limit} N" in str(info.value), str(info.value)
    ResourceLimits(**{limit.replace("-", "_"): 10**10}).check(job, "convoy serve")  # raised: accepted


def mesn_defaults(env: str) -> MeSNConfig:
    cfg = resolve_algo("ma-mesn", env)
    assert isinstance(cfg, MeSNConfig)
    return cfg


def ims_defaults(env: str) -> IMSConfig:
    cfg = resolve_algo("ims", env)
    assert isinstance(cfg, IMSConfig)
    return cfg


def test_env_defaults_fill_only_what_the_user_left_open() -> None:
    assert resolve_algo("ma-mesn", "treadmill").hidden == (256, 256)
    assert resolve_algo("ma-mesn", "treadmill").lr == 1e-4 and resolve_algo("ma-mesn", "referential").lr == 5e-4
    assert resolve_algo("ma-mesn", "treadmill", {"lr": 3e-4}).lr == 3e-4  # a value the user sets always wins
    assert mesn_defaults("treadmill").message_bits == 16
    assert mesn_defaults("predator-prey").message_bits == 8
    assert mesn_defaults("speaker-listener").message_bits == 2
    assert mesn_defaults("speaker-listener").gumbel_noise == 0.0  # appendix B.2: a plain softmax
    assert mesn_defaults("treadmill").gumbel_noise == 0.0  # deterministic bits (docs/algorithms.md)
    assert mesn_defaults("predator-prey").gumbel_noise == 1.0
    assert ims_defaults("treadmill").comm_iterations == 5
    assert ims_defaults("predator-prey").comm_iterations == 3
    assert resolve_algo("ma-mesn", "treadmill", {"hidden": 64}).hidden == (64,)
    assert resolve_algo("dial", "treadmill").hidden == (384, 256)  # 1.5× the first layer, as the paper's 6144
    assert resolve_algo("dial", "treadmill", {"hidden": 64}).hidden == (64,)


def test_message_bits_are_hard_forward_and_differentiable_backward() -> None:
    from convoy.algos.nets import message_bits

    logits = torch.tensor([[0.3, -0.2, 2.0, -2.0, -0.1, 0.1]], requires_grad=True)  # 3 bits as (off, on) pairs
    exe = message_bits(logits, 3, train=False)
    assert exe.tolist() == [[0.0, 0.0, 1.0]]  # argmax of each pair
    det = message_bits(logits, 3, train=True, noise=0.0)
    assert torch.equal(det.detach(), exe)  # deterministic straight-through: forward = the argmax
    det.sum().backward()
    assert logits.grad is not None and logits.grad.abs().sum() > 0  # the soft path carries a gradient
    torch.manual_seed(0)
    samples = torch.stack([message_bits(logits, 3, train=True).detach() for _ in range(400)])
    assert set(samples.unique().tolist()) <= {0.0, 1.0}
    assert 0.2 < samples[:, 0, 0].mean() < 0.8  # an unsure bit is sampled both ways (Gumbel noise)


def test_channel_information_counts_codewords_not_bits() -> None:
    """The positive-signalling estimate scores a message by its codewords: 16 copies of one split carry ln 2 nats,
    16 independent splits far more, and a message that ignores the observation none."""
    from convoy.algos.nets import channel_information

    gen = torch.Generator().manual_seed(0)
    split = torch.where(torch.rand(512, 1, 1, generator=gen) < 0.5, -20.0, 20.0)
    copies = channel_information(split.expand(512, 1, 16))
    independent = channel_information(torch.where(torch.rand(512, 1, 16, generator=gen) < 0.5, -20.0, 20.0))
    constant = channel_information(torch.full((512, 1, 16), 20.0))
    assert copies.item() == pytest.approx(np.log(2), abs=0.02)
    assert independent.item() > 5.5  # ≈ ln 512, the most a batch of 512 can show
    assert constant.item() == pytest.approx(0.0, abs=1e-6)


@pytest.mark.parametrize("name", ["idqn", "ma-mesn"])
def test_a_non_finite_loss_never_reaches_the_weights(name: str) -> None:
    """The skip is decided on the device: the weights, Adam's moments and its step count stay as they were, the
    update counts (the host cannot know it was skipped) and the run fails when figures that counted
    ``MAX_NONFINITE_IN_A_ROW`` in a row are read, whenever that is."""
    from convoy.algos.updater import MAX_NONFINITE_IN_A_ROW

    algo = build(name)
    b = random_batch(SPEC, 256)
    b.reward[:] = float("nan")
    algo.observe(b.map(lambda v: v.numpy()[:, None]))
    before = {k: v.clone() for k, v in algo.online.state_dict().items()}
    stats = single_update(algo)
    assert np.isnan(stats["loss"]) and np.isnan(stats["grad_norm"]) and algo.updater.skipped_updates == 1
    assert algo.updates == 1
    assert all(torch.equal(before[k], v) for k, v in algo.online.state_dict().items())
    state = algo.updater.optimizer.state_dict()["state"]
    assert all(not st["exp_avg"].any() and not st["exp_avg_sq"].any() and st["step"] == 0 for st in state.values())
    unread = [algo.update() for _ in range(MAX_NONFINITE_IN_A_ROW - 2)]  # nothing read: nothing fails yet
    last = algo.update()
    assert math.isnan(unread[-1].read()[0]["loss"])  # read one short of the limit: skipped, not failed
    with pytest.raises(FloatingPointError, match=f"{MAX_NONFINITE_IN_A_ROW} updates in a row had a non-finite loss"):
        last.read()


def test_chunks_with_impossible_values_are_refused_with_their_reason() -> None:
    from convoy.learner.service import chunk_problem

    schema = {**declared_schema(3, 5), "mu": ("<f4", (3,))}

    def chunk(**change: float) -> Transition[np.ndarray]:
        arrays = {k: np.zeros((2, 4, *shape), dtype=np.dtype(dtype)) for k, (dtype, shape) in schema.items()}
        for name, value in change.items():
            arrays[name][1, 2] = value
        return from_columns(arrays)

    n_actions = (4, 4, 2)  # heterogeneous: agent 2 has two actions
    assert chunk_problem(chunk(), schema, n_actions) is None
    assert chunk_problem(chunk(action=3), schema, n_actions) == "action-range"  # agent 2 has no action 3
    assert chunk_problem(chunk(action=-1), schema, n_actions) == "action-range"
    assert chunk_problem(chunk(action=99), schema, n_actions) == "action-range"
    assert chunk_problem(chunk(reward=float("nan")), schema, n_actions) == "non-finite"
    assert chunk_problem(chunk(obs=float("inf")), schema, n_actions) == "non-finite"
    assert chunk_problem(chunk(obs=1e30), schema, n_actions) == "non-finite"
    assert chunk_problem(chunk(mu=2.0), schema, n_actions) == "out-of-range"
    bad_dtype = replace(chunk(), reward=np.zeros((2, 4, 3), dtype=np.float64))
    assert chunk_problem(bad_dtype, schema, n_actions) == "schema"
    assert chunk_problem(replace(chunk(), extras={}), schema, n_actions) == "schema"
    # MA-MeSN-MM's history travels as float16: its check must not overflow the bound into a warning per chunk
    half = {**declared_schema(3, 5), "history": ("<f2", (3, 4))}
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for value, problem in ((60000.0, None), (np.inf, "non-finite")):
            history = np.full((2, 4, 3, 4), value, np.float16)
            assert chunk_problem(replace(chunk(), extras={"history": history}), half, n_actions) == problem


def test_replay_is_saved_beside_the_checkpoint_and_restored_exactly(tmp_path) -> None:
    from convoy.algos.checkpoint import load_replay, save_replay

    algo = build("idqn")
    fill(algo, SPEC, rows=300)
    path = tmp_path / "replay.npz"
    assert save_replay(path, algo, env_steps=300, max_bytes=1 << 30) > 0
    fresh = build("idqn")
    assert load_replay(path, fresh, env_steps=300) == 300
    a, b = algo.replay.sample(64, RunStreams([1], "replay")), fresh.replay.sample(64, RunStreams([1], "replay"))
    assert all(torch.equal(v, b.columns()[k]) for k, v in a.columns().items())
    assert load_replay(path, build("idqn"), env_steps=200) == 0  # saved at another step than the checkpoint's
    said: list[str] = []
    assert save_replay(path, algo, env_steps=300, max_bytes=1_000, say=said.append) == 0 and not path.exists()
    assert len(said) == 1 and "raise it with --runtime replay_checkpoint_mb=N" in said[0]  # over the bound: says so
    path.write_bytes(b"not a zip")
    assert load_replay(path, build("idqn"), env_steps=300) == 0  # unreadable: refilled from actors instead


def test_a_learner_killed_between_its_replay_and_its_checkpoint_resumes_with_the_replay_before(tmp_path) -> None:
    """The replay is written before the checkpoint: a kill in between leaves a checkpoint of the step before,
    whose replay must still be there (it was lost, and the resume started from an empty buffer)."""
    from convoy.algos.checkpoint import load_replay, save_replay

    algo = build("idqn")
    fill(algo, SPEC, rows=200)
    path = tmp_path / "replay.npz"
    save_replay(path, algo, env_steps=200, max_bytes=1 << 30)  # with the checkpoint at 200
    fill(algo, SPEC, rows=100)
    save_replay(path, algo, env_steps=300, max_bytes=1 << 30)  # then killed before the checkpoint at 300
    assert load_replay(path, build("idqn"), env_steps=200) == 200
    assert load_replay(path, build("idqn"), env_steps=300) == 300


def test_skipped_updates_reach_the_metric_rows_and_persistent_ones_end_the_run(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The trainer's path, not the algorithm alone: a loss that is sometimes non-finite is skipped and counted in
    ``metrics.jsonl``; one that always is ends the run with the cause instead of training on."""
    import json

    from convoy.algos.idqn import IndependentDQN
    from convoy.algos.updater import Loss
    from convoy.config import job_config
    from convoy.services.training import run_inprocess

    real = IndependentDQN.loss
    calls = {"n": 0, "every": 3}

    def sometimes_nan(self: IndependentDQN, batch: Transition[torch.Tensor]) -> Loss:
        calls["n"] += 1
        out = real(self, batch)
        return out._replace(agents=out.agents * float("nan")) if calls["n"] % calls["every"] == 0 else out

    monkeypatch.setattr(IndependentDQN, "loss", sometimes_nan)
    params = {"hidden": [32], "learning_starts": 64, "batch_size": 32}
    job = job_config(algo="idqn", env="referential", steps=3000, num_envs=8, log_every=500, eval_episodes=8,
                     algo_params=params)  # fmt: skip
    result = run_inprocess(job, out_dir=tmp_path / "some", progress=False)
    rows = [json.loads(line) for line in (tmp_path / "some" / "metrics.jsonl").read_text().splitlines()]
    skipped = max(r.get("skipped_updates", 0) for r in rows)
    assert skipped > 0 and result.updates > 0, rows[-1]
    assert all(math.isfinite(r["loss"]) for r in rows if "loss" in r and r["updates"] > 0)
    calls["every"] = 1
    monkeypatch.setattr("convoy.algos.updater.MAX_NONFINITE_IN_A_ROW", 5)  # fewer attempts than this short run makes
    with pytest.raises(FloatingPointError, match="non-finite loss"):
        run_inprocess(job, out_dir=tmp_path / "always", progress=False)


@pytest.mark.parametrize("heard", ["noise", "predicted"])
def test_the_greedy_curve_hears_what_eval_messages_says(heard: Source) -> None:
    """eval_messages=predicted/noise: every curve point is played as `convoy eval --messages` plays it."""
    from convoy.algos.agent import make_agent
    from convoy.analysis.evaluation import evaluate_policy
    from convoy.learner.runlog import Evaluator

    job = job_config(algo="ma-mesn-mm", env="referential", steps=64, eval_episodes=64, eval_messages=heard,
                     algo_params={"hidden": [16]})  # fmt: skip
    env = make_batched("referential", 64)
    algo = make_agent(job, env.spec)
    evaluator = Evaluator(job, lambda n: make_batched("referential", n))
    curve = evaluator.returns(algo)
    probe = evaluate_policy(algo, env, 64, seed=evaluator.seed, messages=heard)
    sent = evaluate_policy(algo, env, 64, seed=evaluator.seed)
    assert np.array_equal(curve, probe.returns)
    assert heard == "predicted" or not np.array_equal(curve, sent.returns)  # noise changes what they do
    evaluator.close()


def test_eval_messages_the_algorithm_cannot_hear_are_refused() -> None:
    with pytest.raises(ConfigError) as err:
        job_config(algo="ma-mesn", eval_messages="predicted")
    assert err.value.field == "eval_messages" and "ma-mesn-mm" in str(err.value)
    with pytest.raises(ConfigError, match="no message channel"):
        job_config(algo="idqn", eval_messages="noise")
    assert job_config(algo="idqn", eval_messages="predicted").eval_messages == "predicted"  # decentralised already


def test_a_populations_chunks_name_runs_it_has(tmp_path: Path) -> None:
    """A population's chunk is ``[T, R·B, …]`` with one run index per finished episode: a chunk whose envs do not
    split into the job's runs, or whose returns name a run the job does not have, is refused with its reason and
    nothing reaches the replay or the runs' counts; a good one reaches each run's own counts."""
    from convoy.algos.agent import make_agent
    from convoy.config import job_config
    from convoy.envs import make_batched
    from convoy.learner.service import Learner
    from convoy.protocol import wire
    from convoy.protocol.session import ZenohSettings

    job = job_config(algo="idqn", env="referential", steps=1000, seeds=[0, 1], num_envs=4,
                     algo_params={"hidden": [16], "learning_starts": 10_000})  # fmt: skip
    learner = Learner("pop", job, tmp_path, ZenohSettings())
    algo = make_agent(job, make_batched("referential", 1).spec)
    assert isinstance(algo, NetworkAgent)
    core = learner._core(algo, {})
    g = np.random.default_rng(0)
    n = algo.spec.n_agents

    def chunk(envs: int, returns: list[float], runs: list[int]) -> wire.Message:
        arrays: dict[str, np.ndarray] = {"obs": g.normal(size=(2, envs, n, algo.obs_dim)).astype(np.float32),
                  "next_obs": g.normal(size=(2, envs, n, algo.obs_dim)).astype(np.float32),
                  "action": np.zeros((2, envs, n), np.int64), "reward": np.zeros((2, envs, n), np.float32),
                  "terminated": np.zeros((2, envs), bool), "truncated": np.zeros((2, envs), bool),
                  "episode": np.zeros((2, envs), np.int64)}  # fmt: skip
        return wire.Message("chunk", "a", 0, 0.0, wire.chunk_body(from_columns(arrays), "a", 0, envs, returns, runs))

    def take(msg: wire.Message) -> str | None:
        return learner._take(core, wire.chunk_transitions(msg.body), msg.body)

    assert take(chunk(7, [], [])) == "schema"  # 7 envs do not split into 2 runs
    assert take(chunk(8, [1.0], [2])) == "out-of-range"  # the job has runs 0 and 1
    assert take(chunk(8, [1.0], [-1])) == "out-of-range"
    assert len(algo.replay) == 0 and core.env_steps == 0 and np.asarray(core.episodes).tolist() == [0, 0]
    assert take(chunk(8, [1.0, 2.0, 3.0], [1, 1, 0])) is None
    assert len(algo.replay) == 2 * 4 and core.env_steps == 2 * 4 and np.asarray(core.episodes).tolist() == [1, 2]
    core.close()

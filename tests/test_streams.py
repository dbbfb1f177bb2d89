"""Per-run random streams on the device (``algos.streams``) and what draws from them.

Run k of R streams draws exactly what the single stream of its seed draws, whatever R and the other runs; the
numbers pass the usual sanity checks (uniform moments and bins, normal moments and tails, integers covering their
range, no correlation between neighbouring runs, counters or indices); a draw for all runs costs the same ops at
any R; greedy acting draws nothing; and checkpoints carry the counters, so a resumed run is the uninterrupted one.
"""

from __future__ import annotations

import io
import warnings
from typing import Any

import numpy as np
import pytest
import torch

from convoy.algos.algorithm import NetworkAgent, Progress
from convoy.algos.registry import make_algorithm
from convoy.algos.replay import JointReplay
from convoy.algos.streams import STREAMS, RunStreams, hash32, legacy_counter
from convoy.config import resolve_algo
from convoy.envs.batched import EnvSpec
from convoy.transition import Transition, from_columns
from tests.test_update_device import Dispatches
from tests.transitions import filled

SEEDS = [3, 7, 11, 0, 12345]
SPEC = EnvSpec(name="toy", agent_ids=("a", "b", "c"), obs_dims=(6, 6, 6), n_actions=(5, 3, 5), max_steps=10)


def draws(s: RunStreams, high: torch.Tensor | int) -> list[torch.Tensor]:
    """One of each kind of draw, in order."""
    return [s.uniform((4, 5)), s.normal(7), s.bits(3), s.integers(high, 6), s.uniform(2, torch.float64)]


def test_run_k_of_r_streams_draws_what_the_stream_of_its_seed_draws_alone() -> None:
    pop = RunStreams(SEEDS, "noise")
    singles = [RunStreams([s], "noise") for s in SEEDS]
    highs = torch.tensor([[2], [9], [1], [1000], [2**30]])
    for _ in range(3):
        together = draws(pop, highs)
        for k, single in enumerate(singles):
            alone = draws(single, highs[k : k + 1])
            for a, b in zip(together, alone, strict=True):
                assert torch.equal(a[k], b[0])
    # a run that uses none of a draw keeps its counter: its next draw is what its single stream draws next
    pop.bits(4, advance=torch.tensor([1, 0, 1, 0, 1]))
    for k in (0, 2, 4):
        singles[k].bits(4)
    assert pop.counters.tolist() == [16, 15, 16, 15, 16]  # 3 × 5 draws, then this one
    next_draw = pop.uniform(3)
    for k, single in enumerate(singles):
        assert torch.equal(next_draw[k], single.uniform(3)[0])


def test_draws_are_a_function_of_seed_purpose_and_counter_alone() -> None:
    a, b = RunStreams(SEEDS, "replay"), RunStreams(SEEDS, "replay")
    assert all(torch.equal(x, y) for x, y in zip(draws(a, 10), draws(b, 10), strict=True))
    counters = a.counters
    a.uniform(3)
    assert a.counters is counters and counters.tolist() == [6] * len(SEEDS)  # advanced in place, one per draw
    other = RunStreams(SEEDS, "explore").bits(1000)
    again = RunStreams(SEEDS, "replay").bits(1000)
    assert (other != again).float().mean() > 0.99  # another purpose: another stream
    keys = {int(k) for k in RunStreams(range(10_000), "noise").keys}
    assert len(keys) == 10_000  # distinct seeds, distinct keys (a bijection below 2^32)
    assert [hash32(x) for x in (0, 1, 2)] == hash32(torch.arange(3)).tolist()  # host and device hash alike
    a.load(2, 99)
    resumed = RunStreams([SEEDS[2]], "replay")
    resumed.load(0, 99)
    assert a.state(2) == 99 and torch.equal(a.bits(2)[2], resumed.bits(2)[0])


def test_a_compiled_draw_is_the_eager_one_and_warns_of_no_cache() -> None:
    """A captured update draws inside the graph: the same numbers, without dynamo's warning that it ignores
    ``index_words``' cache (printed once in every compiled job's log)."""
    compiled, eager = RunStreams(SEEDS, "noise"), RunStreams(SEEDS, "noise")
    draw = torch.compile(lambda: compiled.uniform((3, 4)), fullgraph=True, backend="eager")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert torch.equal(draw(), eager.uniform((3, 4)))
    assert torch.equal(compiled.counters, eager.counters)


def test_uniforms_fill_their_bins_with_the_right_moments() -> None:
    n = 200_000
    u = RunStreams([0, 1, 2], "noise").uniform(n).double()
    assert float(u.min()) >= 0.0 and float(u.max()) < 1.0
    assert torch.allclose(u.mean(1), torch.full((3,), 0.5, dtype=torch.float64), atol=5 * (1 / 12 / n) ** 0.5)
    assert torch.allclose(u.var(1), torch.full((3,), 1 / 12, dtype=torch.float64), atol=0.002)
    for row in u:
        counts = torch.histc(row, bins=64, min=0.0, max=1.0)
        chi2 = float(((counts - n / 64) ** 2 / (n / 64)).sum())
        assert chi2 < 110, chi2  # 63 degrees of freedom: P(χ² > 110) ≈ 2e-4
    for dtype in (torch.float16, torch.bfloat16, torch.float64):
        low = RunStreams([0], "noise").uniform(10_000, dtype)
        assert low.dtype == dtype and float(low.min()) >= 0 and float(low.max()) < 1.0


def test_normals_have_the_right_moments_and_tails() -> None:
    n = 200_001  # odd: the last Box–Muller pair gives one value
    z = RunStreams([0, 1], "noise").normal(n).double()
    assert z.shape == (2, n)
    assert float(z.mean(1).abs().max()) < 5 / n**0.5
    assert float((z.std(1) - 1).abs().max()) < 0.01
    tail = (z.abs() > 2).double().mean(1)
    assert float((tail - 0.0455).abs().max()) < 0.003


def test_integers_cover_their_range_uniformly_per_run() -> None:
    n = 70_000
    high = torch.tensor([[7], [1], [5]])
    i = RunStreams([0, 1, 2], "replay").integers(high, n)
    for row, h in zip(i, high.flatten().tolist(), strict=True):
        counts = torch.bincount(row, minlength=h).double()
        assert len(counts) == h and int(row.min()) == 0
        chi2 = float(((counts - n / h) ** 2 / (n / h)).sum())
        assert chi2 < 30, chi2  # ≤ 6 degrees of freedom: P(χ² > 30) < 5e-5
    big = RunStreams([0], "replay").integers(2**31 - 1, 100_000).double()  # the largest high: no overflow
    assert float(big.min()) >= 0 and float(big.max()) < 2**31 - 1
    assert float(big.mean()) / 2**31 == pytest.approx(0.5, abs=0.01)


def test_no_correlation_between_neighbouring_runs_counters_or_indices() -> None:
    s = RunStreams(range(500), "explore")  # neighbouring seeds
    u = torch.stack([s.uniform(40) for _ in range(50)], dim=1).double()  # [run, counter, index]

    def corr(a: torch.Tensor, b: torch.Tensor) -> float:
        a, b = a.flatten() - a.mean(), b.flatten() - b.mean()
        return float((a * b).mean() / (a.std() * b.std()))

    for a, b in ((u[:-1], u[1:]), (u[:, :-1], u[:, 1:]), (u[:, :, :-1], u[:, :, 1:])):
        assert abs(corr(a, b)) < 5 / a.numel() ** 0.5


def config(name: str, **extra: Any) -> Any:
    hp = {"hidden": (16,), "batch_size": 8, "learning_starts": 0, "replay_capacity": 200, **extra}
    if name == "dial":
        hp.update(replay=True, unroll=4)
    if name == "ma-mesn":
        hp["gumbel_noise"] = 1.0
    return resolve_algo(name, "treadmill", hp)


def chunk(g: np.random.Generator, runs: int | None, t: int = 4, b: int = 4) -> Transition[np.ndarray]:
    n, d = SPEC.n_agents, SPEC.obs_dim
    lead = (t, b) if runs is None else (t, runs, b)
    return from_columns(
        {
            "msg_in": (g.random((*lead, n, (n - 1) * 16)) < 0.5).astype(np.float32),
            "mu": g.uniform(0.2, 1.0, size=(*lead, n)).astype(np.float32),
            "obs": g.normal(size=(*lead, n, d)).astype(np.float32),
            "next_obs": g.normal(size=(*lead, n, d)).astype(np.float32),
            "action": g.integers(0, 3, size=(*lead, n)),
            "reward": g.normal(size=(*lead, n)).astype(np.float32),
            "terminated": g.random(lead) < 0.1,
            "truncated": np.zeros(lead, bool),
            "episode": g.integers(0, 10, size=lead),
        }
    )


@pytest.mark.parametrize("name", ["idqn", "dial"])
def test_a_sample_and_a_noise_draw_cost_the_same_ops_for_1_and_20_runs(name: str) -> None:
    """Kernels per update independent of the population size: one batched draw, one gather per field."""
    ops = []
    for runs in (1, 20):
        agent = make_algorithm(name, SPEC, config(name), device="cpu", seed=list(range(runs)))
        agent.observe(chunk(np.random.default_rng(0), runs))
        x = torch.zeros(runs, 8, 3, 4)
        agent.sample(), agent.rand_like(x), agent.rand_like(x, normal=True)  # warm: first-call set-up aside
        with Dispatches() as counted:
            agent.sample()
            agent.rand_like(x)
            agent.rand_like(x, normal=True)
        ops.append(counted.ops)
    assert ops[0] == ops[1]


def test_greedy_acting_draws_nothing_and_each_run_draws_only_where_it_explores() -> None:
    pop = make_algorithm("idqn", SPEC, config("idqn"), device="cpu", seed=SEEDS[:3])
    single = make_algorithm("idqn", SPEC, config("idqn"), device="cpu", seed=SEEDS[0])
    obs = np.random.default_rng(0).normal(size=(3, 4, SPEC.n_agents, SPEC.obs_dim)).astype(np.float32)
    explore = pop.streams["explore"]
    pop.act(obs, 0.0)
    single.act(obs[0], 0.0)
    assert explore.counters.tolist() == [0, 0, 0] and single.streams["explore"].state(0) == 0
    pop.act(obs, np.array([0.0, 0.5, 1.0]))
    assert explore.counters.tolist() == [0, 1, 1]
    pop.act(obs, np.array([[0.0, 0.0, 0.0, 0.2], [0.0] * 4, [1.0] * 4]))  # one env of run 0 explores
    assert explore.counters.tolist() == [1, 1, 2]
    acted = pop.act(obs, 1.0).actions
    assert (acted < np.asarray(SPEC.n_actions)).all() and (acted >= 0).all()
    for agent_actions in acted.reshape(-1, SPEC.n_agents).T:
        assert len(np.unique(agent_actions)) > 1


def test_ez_greedy_holds_each_random_action_for_a_zeta_drawn_length_run_by_run() -> None:
    """εz-greedy (``eps_hold_max`` > 1): at ε = 1 every agent repeats a random action for runs whose lengths follow
    P(n) ∝ n^−μ on 1 … n_max; greedy acting neither draws nor moves a hold; and run k of a population acts
    exactly as the single run of its seed (each run's holds come from its own stream)."""
    hp = {"eps_hold_max": 8, "eps_hold_mu": 1.5}
    pop = make_algorithm("idqn", SPEC, config("idqn", **hp), device="cpu", seed=SEEDS[:3])
    singles = [make_algorithm("idqn", SPEC, config("idqn", **hp), device="cpu", seed=s) for s in SEEDS[:3]]
    obs = np.zeros((3, 64, SPEC.n_agents, SPEC.obs_dim), dtype=np.float32)
    acted = []
    for t in range(300):
        eps = 1.0 if t % 50 else 0.0  # a greedy act now and then: draws nothing, holds nothing
        together = pop.act(obs, eps).actions
        for k, single in enumerate(singles):
            np.testing.assert_array_equal(together[k], single.act(obs[k], eps).actions)
        if eps:
            acted.append(together)
    assert pop.hold is not None and pop.streams["explore"].counters.tolist() == [294] * 3
    # lengths of the runs of one action (a run that ends on a new hold of the same action joins the next: counted
    # on agent b, 3 actions, against the model of it)
    runs_of = [np.diff(np.flatnonzero(np.diff(np.r_[-1, seq, -1]))) for seq in np.array(acted)[:, :, :, 1].reshape(
        len(acted), -1).T]  # fmt: skip
    lengths = np.concatenate([r[1:-1] for r in runs_of])
    p = np.arange(1, 9) ** -1.5
    p /= p.sum()
    mean_hold = (np.arange(1, 9) * p).sum()
    same = 1 / 3  # a new hold picks the previous action again
    assert lengths.mean() == pytest.approx(mean_hold / (1 - same), rel=0.08)
    assert lengths.max() > 8  # holds of the same action join
    plain = make_algorithm("idqn", SPEC, config("idqn"), device="cpu", seed=SEEDS[0])
    seq = np.array([plain.act(obs[0], 1.0).actions[:, 1] for _ in range(300)])
    assert (seq[1:] == seq[:-1]).mean() == pytest.approx(1 / 3, abs=0.03)  # one step at a time: no holds


def continue_training(agent: NetworkAgent, g: np.random.Generator, steps: int) -> list[np.ndarray]:
    """Act, observe and update ``steps`` times: what a run goes on doing after a resume."""
    acted = []
    for _ in range(steps):
        obs = g.normal(size=(agent.runs, 4, SPEC.n_agents, SPEC.obs_dim)).astype(np.float32)
        acted.append(agent.act(obs, 0.3).actions)
        agent.observe(chunk(g, agent.runs))
        agent.update()
    return acted


def assert_same_weights(a: NetworkAgent, b: NetworkAgent) -> None:
    for n, w in a.online.state_dict().items():
        assert torch.equal(w, b.online.state_dict()[n]), n


def saved(state: dict[str, Any]) -> dict[str, Any]:
    """``state`` written and read back as a checkpoint is (no tensor shared with the live agent)."""
    buf = io.BytesIO()
    torch.save(state, buf)
    buf.seek(0)
    return dict(torch.load(buf, weights_only=False))


@pytest.mark.parametrize("name", ["idqn", "ma-mesn", "dial"])
def test_a_resumed_run_is_the_uninterrupted_run(name: str) -> None:
    """A single run from its state_dict and replay, a population from its members' states and its replay: the
    stream counters come back, so they go on drawing (and training) exactly as without the interruption."""
    torch.set_num_threads(1)
    for seed in (SEEDS[1], SEEDS[:3]):
        runs = None if isinstance(seed, int) else len(seed)
        agent = make_algorithm(name, SPEC, config(name), device="cpu", seed=seed)
        agent.progress = Progress(100, 1, 1000, training=True)
        continue_training(agent, np.random.default_rng(1), 3)
        resumed = make_algorithm(name, SPEC, config(name), device="cpu", seed=seed)
        resumed.progress = agent.progress
        if runs is None:
            resumed.load_state_dict(saved(agent.state_dict()))
        else:
            for k in range(runs):
                resumed.load_member_state(k, saved(agent.member(k).state_dict()))
        resumed.replay.load_state_dict(saved(agent.replay.state_dict()))
        for name_, stream in agent.streams.items():
            assert torch.equal(resumed.streams[name_].counters, stream.counters), name_
        going_on = [continue_training(x, np.random.default_rng(2), 3) for x in (agent, resumed)]
        for a, b in zip(*going_on, strict=True):
            np.testing.assert_array_equal(a, b)
        assert_same_weights(agent, resumed)


@pytest.mark.parametrize("name", ["idqn", "dial"])
def test_a_checkpoint_of_the_old_generators_loads_and_resumes_alike_every_time(name: str) -> None:
    """A state with numpy/torch generator states ("rng", "torch_rng", DIAL's "dru_rng") and no counters: the
    streams start at ``legacy_counter(seed, updates)``, the same at every load."""
    agent = make_algorithm(name, SPEC, config(name), device="cpu", seed=SEEDS[1])
    state = agent.state_dict()
    old = {k: v for k, v in state.items() if k != "streams"}
    old.update(updates=17, rng=np.random.default_rng(SEEDS[1]).bit_generator.state,
               torch_rng=torch.Generator().manual_seed(SEEDS[1]).get_state())  # fmt: skip
    if name == "dial":
        old["dru_rng"] = old["torch_rng"]
    want = legacy_counter(SEEDS[1], 17)
    loaded = []
    for _ in range(2):
        fresh = make_algorithm(name, SPEC, config(name), device="cpu", seed=SEEDS[1])
        fresh.load_state_dict(old)
        assert fresh.updater.stream_state(0) == {"seed": SEEDS[1], **dict.fromkeys(STREAMS, want)}
        loaded.append(fresh.rand_like(torch.zeros(5)))
    assert torch.equal(*loaded)
    pop = make_algorithm(name, SPEC, config(name), device="cpu", seed=SEEDS[:3])
    pop.load_member_state(1, old)
    assert pop.updater.stream_state(1) == {"seed": SEEDS[1], **dict.fromkeys(STREAMS, want)}
    assert pop.updater.stream_state(0) == {"seed": SEEDS[0], **dict.fromkeys(STREAMS, 0)}


def test_replay_samples_on_its_device_with_one_draw_for_every_run() -> None:
    buf, single = JointReplay(50, runs=3), JointReplay(50)
    g = np.random.default_rng(0)
    rows = filled((3, 30), x=g.normal(size=(3, 30, 2)).astype(np.float32), action=g.integers(0, 9, size=(3, 30)))
    valid = g.random((3, 30)) < 0.6
    buf.add(rows, valid)
    single.add(rows.map(lambda v: v[1:2, valid[1]]))
    streams = RunStreams([4, 5, 6], "replay")
    got = buf.sample(16, streams)
    x = got.extras["x"]
    assert x.device == buf.device and x.shape == (3, 16, 2) and got.action.dtype == torch.int64
    assert streams.counters.tolist() == [1, 1, 1]
    alone = single.sample(16, RunStreams([5], "replay")).columns()
    assert all(torch.equal(got.columns()[f][1], alone[f][0]) for f in alone)
    with pytest.raises(ValueError, match="one per run"):
        buf.sample(4, RunStreams([0], "replay"))
    saved = single.state_dict()
    assert isinstance(saved["data"]["x"], np.ndarray) and saved["data"]["x"].shape == (1, int(valid[1].sum()), 2)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_cuda_draws_and_replay_equal_the_cpus() -> None:
    """The hash is integer arithmetic: words, uniforms and integers are bit for bit the CPU's on CUDA; a replay on
    CUDA (inserts staged through pinned memory, non-blocking) holds and samples what the CPU's does."""
    cpu, gpu = RunStreams(SEEDS, "replay"), RunStreams(SEEDS, "replay", "cuda")
    high = torch.tensor([[3], [50], [1], [7], [1000]])
    for i, (a, b) in enumerate(zip(draws(cpu, high), draws(gpu, high.cuda()), strict=True)):
        if i == 1:  # the normals: CUDA's log and cos may round differently
            torch.testing.assert_close(a, b.cpu())
        else:
            assert torch.equal(a, b.cpu())
    g = np.random.default_rng(0)
    buffers = [JointReplay(40, runs=3, device=d) for d in ("cpu", "cuda")]
    for _ in range(5):
        rows = filled((3, 11), x=g.normal(size=(3, 11, 2)).astype(np.float32), terminated=g.random((3, 11)) < 0.5)
        valid = g.random((3, 11)) < 0.8
        for buf in buffers:
            buf.add(rows, valid)
    drawn = [buf.sample(64, RunStreams([1, 2, 3], "replay", buf.device)).columns() for buf in buffers]
    assert drawn[1]["x"].is_cuda and all(torch.equal(drawn[0][k], drawn[1][k].cpu()) for k in drawn[0])
    states = [buf.state_dict() for buf in buffers]
    assert all(np.array_equal(states[0]["data"][k], states[1]["data"][k]) for k in states[0]["data"])

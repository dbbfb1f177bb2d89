"""Population training: run k of a population is the single run of its seed.

Member k and a single run of seed k start from identical weights, draw identical replay batches, exploration and
message noise, and stay equal up to float32 rounding. Why a tolerance and not bit equality: a population evaluates
its runs with batched kernels (``baddbmm`` over runs where a single run calls ``addmm``) and clips each run's
gradient with its own norm computed per run, so sums are taken in another order; and it steps Adam with masked
``torch._foreach_*`` ops where a single run calls torch's fused kernel (the same arithmetic, but ATen's ``sqrt``
and the kernel's round differently in about one element in five). Measured on these sizes (torch 2.13, CPU) the
weights then differ by ≤ 2.2e-6 after 300 updates (4.3e-7 with the fused kernel on both sides). A hard message bit,
though, is a threshold: once the rounding moves one logit-plus-noise across 0 (for message algorithms after
~150-250 updates here) the two runs take different discrete messages and drift apart as any two chaotic
trajectories do. So algorithms with messages are compared over 50 updates (weights then differ by ≤ 7.5e-7), the
others over 300, both to 1e-5; the noise streams themselves are compared exactly.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from convoy.algos.algorithm import NetworkAgent, Progress
from convoy.algos.checkpoint import save_checkpoint
from convoy.algos.nets import GroupLinear, run_state, stack_runs
from convoy.algos.registry import algorithm_class, make_algorithm
from convoy.config import ALGORITHMS, AlgoConfig, job_config, resolve_algo
from convoy.envs.batched import EnvSpec
from convoy.transition import Transition, from_columns
from tests.conftest import population_update, single_update
from tests.transitions import run_of

SPEC = EnvSpec(name="toy", agent_ids=("a", "b", "c"), obs_dims=(6, 6, 6), n_actions=(5, 5, 5), max_steps=10)
SEEDS = [3, 7, 11]
POPULATION_ALGOS = list(ALGORITHMS)  # every algorithm: a single run is a population of one
T, B = 8, 4
WINDOW = 4  # the -mm variants' observation window


def config(name: str, share: bool, teacher: Path | None = None, **extra: object):
    hp = {"hidden": (32, 32), "batch_size": 16, "learning_starts": 0, "replay_capacity": 500, "lr": 1e-3,
          "target_update": 20, "share_params": share}  # fmt: skip
    if name == "dial":  # replayed sequences, so batches can be compared; targets sync by each run's episodes
        hp.update(replay=True, unroll=4, target_update_episodes=3)
    if name == "codbc":  # clones an (untrained) MA-MeSN of the same env shape
        hp.update(teacher=str(teacher), teacher_fraction=0.5)
    if name.endswith("-mm"):
        hp.update(memory_window=WINDOW, memory_hidden=16)
    if name == "dqn-ser":
        hp.update(fingerprint=True, ser_horizon=8)  # ages matter within the test's episodes
    if algorithm_class(name).uses_messages and name != "dial":
        hp["gumbel_noise"] = 1.0  # the paper's sampled messages: the noise streams must match too
    if name in ("ma-mesn", "ma-bon"):
        hp["signalling_coef"] = 0.05  # a per-run auxiliary term
    return resolve_algo(name, "treadmill", {**hp, **extra})


def chunk(g: np.random.Generator, runs: int) -> Transition[np.ndarray]:
    """Random joint transitions ``[T, R, B, …]`` (the data need not come from an env to test the updates)."""
    n, d = SPEC.n_agents, SPEC.obs_dim
    return from_columns(
        {
            "fingerprint": g.random((T, runs, B, 2)).astype(np.float32),
            "history": g.normal(size=(T, runs, B, WINDOW, n, d + 1)).astype(np.float16),  # the memory module's input
            "msg_in": (g.random((T, runs, B, n, (n - 1) * 16)) < 0.5).astype(np.float32),  # DIAL's heard messages
            "mu": g.uniform(0.2, 1.0, size=(T, runs, B, n)).astype(np.float32),  # and behaviour probabilities
            "obs": g.normal(size=(T, runs, B, n, d)).astype(np.float32),
            "next_obs": g.normal(size=(T, runs, B, n, d)).astype(np.float32),
            "action": g.integers(0, SPEC.max_actions, size=(T, runs, B, n)),
            "reward": g.normal(size=(T, runs, B, n)).astype(np.float32),
            "terminated": g.random((T, runs, B)) < 0.1,
            "truncated": np.zeros((T, runs, B), bool),
            "episode": g.integers(0, 10, size=(T, runs, B)),
        }
    )


def feed(pop, singles, g: np.random.Generator, chunks: int = 4) -> None:
    """The same random chunks into the population and, run k's share, into single run k."""
    for _ in range(chunks):
        c = chunk(g, len(singles))
        pop.observe(c)
        for k, single in enumerate(singles):
            single.observe(run_of(c, k))


def trained_side_by_side(cfg: AlgoConfig, rng_seed: int, updates: int) -> tuple[NetworkAgent, list[NetworkAgent]]:
    """An independent-DQN population of ``cfg`` and its single runs, fed the same chunks and updated ``updates``
    times each."""
    pop = make_algorithm("idqn", SPEC, cfg, device="cpu", seed=SEEDS)
    singles = [make_algorithm("idqn", SPEC, cfg, device="cpu", seed=s) for s in SEEDS]
    feed(pop, singles, np.random.default_rng(rng_seed))
    for _ in range(updates):
        pop.update()
        for single in singles:
            single.update()
    return pop, singles


def save_teacher(path: Path) -> Path:
    job = job_config(algo="ma-mesn", env="treadmill", algo_params={"hidden": (16,)}, device="cpu", seed=5)
    agent = make_algorithm("ma-mesn", SPEC, job.algo_config(), device="cpu", seed=5)
    return save_checkpoint(path, agent, job, {"env_steps": 0, "episodes": 0, "updates": 0})


def max_weight_gap(pop, singles) -> float:
    return max(
        float((run_state(a.online, 0)[n] - w).abs().max())
        for k, a in enumerate(singles)
        for n, w in run_state(pop.online, k).items()
    )


@pytest.mark.parametrize("share", [False, True], ids=["per-agent", "shared"])
@pytest.mark.parametrize("name", POPULATION_ALGOS)
def test_member_k_is_the_single_run_of_seed_k(name: str, share: bool, tmp_path: Path) -> None:
    torch.set_num_threads(1)
    teacher = save_teacher(tmp_path / "teacher.pt") if name == "codbc" else None
    cfg = config(name, share, teacher)
    pop = make_algorithm(name, SPEC, cfg, device="cpu", seed=SEEDS)
    singles = [make_algorithm(name, SPEC, cfg, device="cpu", seed=s) for s in SEEDS]
    # identical initial weights, bit for bit
    for k, single in enumerate(singles):
        for n, w in run_state(single.online, 0).items():
            assert torch.equal(run_state(pop.online, k)[n], w), f"{name}: run {k}'s initial {n}"
    # the same data in, the same first batch out
    # each run its own episode clock (stabilised experience replay weighs samples by their age in episodes)
    # (CoDBC's teacher drives a share of the envs while training data is collected)
    pop.progress = Progress(500, np.array([12, 9, 15]), 1000, training=True)
    for single, episodes in zip(singles, (12, 9, 15), strict=True):
        single.progress = Progress(500, episodes, 1000, training=True)
    g = np.random.default_rng(0)
    feed(pop, singles, g)
    first = pop.sample()
    for k, single in enumerate(singles):
        for f, v in single.sample().columns().items():
            assert torch.equal(first.columns()[f][k], v[0]), f"{name}: run {k}'s first batch differs in {f}"
    # the same exploration: ε-greedy actions from each run's own stream
    obs = g.normal(size=(len(SEEDS), B, SPEC.n_agents, SPEC.obs_dim)).astype(np.float32)
    acted = pop.act(obs, np.array([0.0, 0.3, 1.0])).actions
    for k, (single, eps) in enumerate(zip(singles, (0.0, 0.3, 1.0), strict=True)):
        np.testing.assert_array_equal(acted[k], single.act(obs[k], eps).actions)
    # the same message noise, exactly
    x = torch.zeros(len(SEEDS), 5, 4)
    noise = pop.rand_like(x)
    for k, single in enumerate(singles):
        assert torch.equal(noise[k], single.rand_like(x[k : k + 1])[0])
    # updates: equal up to float32 rounding (module docstring)
    updates = 50 if algorithm_class(name).uses_messages else 300
    for _ in range(updates):
        rows = population_update(pop)
        single_rows = [single_update(s) for s in singles]
    assert max_weight_gap(pop, singles) < 1e-5
    for row, single_row in zip(rows, single_rows, strict=True):
        assert row.keys() == single_row.keys()
        assert row["loss"] == pytest.approx(single_row["loss"], rel=1e-4)
    # a run as a single-run agent: its weights, counters and optimizer state
    member = pop.member(1)
    assert member.updates == singles[1].updates == updates
    for n, w in member.online.state_dict().items():
        torch.testing.assert_close(w, singles[1].online.state_dict()[n], rtol=0, atol=1e-5)
    moments = member.updater.optimizer.state_dict()["state"][0]["exp_avg"]
    torch.testing.assert_close(
        moments, singles[1].updater.optimizer.state_dict()["state"][0]["exp_avg"], rtol=0, atol=1e-5
    )


def test_each_run_clips_its_own_gradient_and_a_nonfinite_run_is_left_alone() -> None:
    """A huge loss in one run neither shrinks another run's step (per-run clipping) nor, when not finite, moves
    its own weights or optimizer state, while the other runs step as usual."""
    cfg = config("idqn", False, huber=False)  # the squared TD error: a huge reward makes a huge gradient
    pop = make_algorithm("idqn", SPEC, cfg, device="cpu", seed=SEEDS)
    single = make_algorithm("idqn", SPEC, cfg, device="cpu", seed=SEEDS[0])
    g = np.random.default_rng(0)
    c = chunk(g, len(SEEDS))
    c.reward[:, 1] *= 1e6  # run 1: enormous TD errors, clipped hard
    c.reward[:, 2] = np.nan  # run 2: not finite
    pop.observe(c)
    single.observe(run_of(c, 0))
    before = run_state(pop.online, 2)
    rows = population_update(pop)
    single_row = single_update(single)
    assert rows[0]["grad_norm"] == pytest.approx(single_row["grad_norm"], rel=1e-5)
    assert rows[1]["grad_norm"] > 1e3 * cfg.grad_clip
    assert np.isnan(rows[2]["loss"]) and pop.updater.skipped_updates == 1
    for n, w in run_state(pop.online, 2).items():
        assert torch.equal(w, before[n]), "the non-finite run's weights moved"
    assert not pop.updater.optimizer.state_dict()["state"][0]["exp_avg"][2].any(), "its Adam moments moved"
    for n, w in run_state(pop.online, 0).items():
        torch.testing.assert_close(w, run_state(single.online, 0)[n], rtol=0, atol=1e-6)


def test_a_run_gone_non_finite_keeps_its_weights_and_adam_state_while_the_others_step() -> None:
    """Mid-training (Adam's moments no longer zero) a run whose batches turn non-finite stays exactly where it was
    — weights, target, moments and step count — for as long as that lasts, while the other runs go on as their
    single runs do; its figures read NaN and its streak counts on the device. Once its data is finite again it
    steps on from where it stopped, as its single run that took those updates off."""
    torch.set_num_threads(1)
    cfg = config("idqn", False, policy_ema=0.5, target_tau=0.5)  # Polyak target and average: masked too
    pop, singles = trained_side_by_side(cfg, 2, 5)
    sample = pop.sample

    def run_2_not_finite() -> Transition[torch.Tensor]:
        batch = sample()
        batch.reward[2] = float("nan")
        return batch

    def run_2() -> dict[str, torch.Tensor]:
        modules = {m: getattr(pop, m) for m in ("online", "target", "average")}
        nets = {f"{m}.{k}": v for m, module in modules.items() for k, v in run_state(module, 2).items()}
        state = pop.updater.optimizer.state_dict()["state"]
        return {**nets, **{f"adam.{i}.{k}": v[2].clone() for i, st in state.items() for k, v in st.items()}}

    before = run_2()
    assert float(before["adam.0.step"]) == 5 and before["adam.0.exp_avg"].any()
    pop.sample = run_2_not_finite  # type: ignore[method-assign]
    for _ in range(4):
        rows = population_update(pop)
        singles[0].update()
        singles[1].update()
        singles[2].sample()  # the single run draws its batches as run 2 did, and takes no step
    after = run_2()
    assert all(torch.equal(after[k], v) for k, v in before.items()), "run 2 moved"
    assert np.isnan(rows[2]["loss"]) and np.isnan(rows[2]["grad_norm"]) and np.isfinite(rows[0]["loss"])
    assert pop.updater._nonfinite_in_a_row.tolist() == [0, 0, 4] and pop.updater.skipped_updates == 4
    pop.sample = sample  # type: ignore[method-assign]
    for _ in range(5):
        pop.update()
        for single in singles:
            single.update()
    assert max_weight_gap(pop, singles) < 1e-5
    assert pop.updater._nonfinite_in_a_row.tolist() == [0, 0, 0]
    member = pop.member(2)
    assert (
        member.updater.optimizer.state_dict()["state"][0]["step"]
        == singles[2].updater.optimizer.state_dict()["state"][0]["step"]
    )


@pytest.mark.parametrize("share", [False, True], ids=["per-agent", "shared"])
def test_a_layer_normalised_population_stays_its_single_runs(share: bool) -> None:
    """LayerNorm normalises each row over its own units, so stacking runs must not mix one run's rows into
    another's statistics."""
    torch.set_num_threads(1)
    pop, singles = trained_side_by_side(config("idqn", share, layer_norm=True, target_tau=0.01), 1, 100)
    assert max_weight_gap(pop, singles) < 1e-5


def test_stack_runs_refuses_a_layer_without_a_run_axis() -> None:
    plain = torch.nn.ModuleDict({"layer": torch.nn.Linear(3, 4)})
    with pytest.raises(NotImplementedError, match="no run axis"):
        stack_runs([plain, plain])
    layers = [GroupLinear(2, 3, 4) for _ in range(3)]
    stacked = stack_runs(layers)
    x = torch.randn(3, 5, 2, 3)
    for k, layer in enumerate(layers):
        torch.testing.assert_close(stacked(x)[k], layer(x[k]))


SMALL_TREADMILL = ["--set", "n_agents=2", "--set", "length=30", "--set", "width=12", "--set", "max_steps=60"]


@pytest.mark.parametrize(
    "what, seeds",
    [(["--env", "referential", "--steps", "1200"], [0, 1, 2, 3, 4]),
     (["--env", "treadmill", "--hierarchical", "--steps", "2000", *SMALL_TREADMILL], [0, 1, 2])],
    ids=["idqn", "hierarchical"],
)  # fmt: skip
def test_a_population_run_writes_each_seed_as_its_single_run(what: list[str], seeds: list[int], tmp_path: Path) -> None:
    """``convoy train --inprocess --seeds`` = one run folder per seed with what a single run of that seed writes
    (the same metric rows, curve and summary, up to float32 rounding; only timings differ)."""
    from convoy.cli.main import main

    common = ["train", "--inprocess", "--algo", "idqn", *what, "--num-envs", "8", "--eval-every", "400",
              "--eval-episodes", "20", "--log-every", "400", "--no-progress",
              "--hp", "hidden=32", "--hp", "learning_starts=100"]  # fmt: skip
    assert main([*common, "--seeds", *map(str, seeds), "--out", str(tmp_path / "pop")]) == 0
    timing = {"wall_s", "env_steps_per_s", "updates_per_s", "out_dir"}
    for s in seeds:
        assert main([*common, "--seed", str(s), "--out", str(tmp_path / f"single-{s}")]) == 0
        run = tmp_path / "pop" / f"seed-{s}"
        assert {"checkpoint.pt", "best.pt", "summary.json", "metrics.jsonl", "curve.png"} <= {
            p.name for p in run.iterdir()
        }
        got = json.loads((run / "summary.json").read_text())
        want = json.loads((tmp_path / f"single-{s}" / "summary.json").read_text())
        assert got.keys() == want.keys()
        for key in want.keys() - timing:
            same = got[key] == want[key] if isinstance(want[key], dict) else got[key] == pytest.approx(want[key])
            assert same, f"seed {s}: {key} {got[key]} vs {want[key]}"
        rows = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
        single_rows = [
            json.loads(line) for line in (tmp_path / f"single-{s}" / "metrics.jsonl").read_text().splitlines()
        ]
        assert [r["env_steps"] for r in rows] == [r["env_steps"] for r in single_rows]
        assert [r.get("eval_return") for r in rows] == pytest.approx([r.get("eval_return") for r in single_rows])


def test_population_flags_say_what_is_wrong(capsys: pytest.CaptureFixture[str]) -> None:
    from convoy.cli.main import main

    base = ["train", "--algo", "idqn", "--env", "referential", "--steps", "100"]
    for extra, words in (
        (["--inprocess", "--seeds", "0", "0"], "distinct"),
        (["--inprocess", "--seeds", "0", "1", "--seed", "2"], "not both"),
        (
            ["--inprocess", "--seeds", "0", "1", "--env", "treadmill", "--hierarchical", "--algo", "dial"],
            "one seed per process",
        ),
    ):
        assert main([*base, *extra]) == 2
        err = " ".join(capsys.readouterr().err.split())
        assert "seeds" in err and words in err, err


@pytest.mark.parametrize("name", ["idqn", "dial"])
def test_runs_of_a_population_may_differ_in_lr_gamma_and_target_period(name: str) -> None:
    """A small grid in one population: run k follows its own learning rate (``RunAdam``), discount and target
    period, as the single run with that config does (up to float rounding: a population's RunAdam orders Adam's
    arithmetic differently from torch's fused kernel, which a single run's calls); shapes and the update's
    structure must agree.

    Tolerance 2e-4, measured (torch 2.13 CPU, MKL): on this machine the gap after the loop is 3.9e-5 (DIAL) and
    4.3e-7 (IDQN) with RunAdam's masked foreach step; with the per-parameter step before it, 6.7e-8 and 3.5e-7,
    the same with 1 or 2 threads, ATEN_CPU_CAPABILITY avx512/avx2/none, MKL_ENABLE_INSTRUCTIONS AVX2/SSE4_2,
    MKL_CBWR=COMPATIBLE and mkldnn off (≤ 7.5e-8 / 5.4e-7). Another machine's rounding, though, is not a small
    shift of these: moving every population weight by ±1 ulp before the loop (12 draws) gives gaps up to 3.9e-5
    (DIAL, median 7e-6: the very 3.9e-5 seen on a 2-core x86-64 machine, and now here) and 1.2e-5 (IDQN, median
    3e-6), as a rounding difference takes another argmax or Adam step somewhere. A run given a wrong config is
    far off: gamma 0.9 for 0.95 gives 1.2e-3 (DIAL) / 1.2e-2 (IDQN), lr 3.3e-4 for 3e-4 3.0e-3 (DIAL). 2e-4
    is 5× the worst measured rounding gap and 6× below the smallest wrong-config gap."""
    torch.set_num_threads(1)
    grid = [(1e-3, 0.9, 10), (3e-4, 0.95, 25), (2e-3, 0.99, 5)]
    cfgs = [config(name, False, lr=lr, gamma=g, target_update=c) for lr, g, c in grid]
    pop = make_algorithm(name, SPEC, cfgs[0], device="cpu", seed=SEEDS, run_configs=cfgs)
    singles = [make_algorithm(name, SPEC, c, device="cpu", seed=s) for c, s in zip(cfgs, SEEDS, strict=True)]
    feed(pop, singles, np.random.default_rng(1))
    for _ in range(200 if name == "idqn" else 50):  # DIAL's messages: see the module docstring
        pop.update()
        for single in singles:
            single.update()
    assert max_weight_gap(pop, singles) < 2e-4  # measured: see the docstring
    for k, single in enumerate(singles):  # each run's target synced at its own period
        for n, w in run_state(pop.target, k).items():
            torch.testing.assert_close(w, run_state(single.target, 0)[n], rtol=0, atol=2e-4)
    assert pop.member(1).cfg == cfgs[1]
    wider = config(name, False, hidden=(64, 32))
    with pytest.raises(ValueError, match="hidden"):
        make_algorithm(name, SPEC, cfgs[0], device="cpu", seed=SEEDS, run_configs=[cfgs[0], cfgs[1], wider])


def test_lr_end_anneals_each_runs_learning_rate_over_the_run() -> None:
    """``lr_end``: the learning rate falls linearly from ``lr`` to ``lr_end`` as env steps go from 0 to the run's
    total, per run of a population (a run without ``lr_end`` keeps its ``lr``), and member k still follows the
    single run of its config while the schedule moves."""
    from convoy.algos.updater import RunAdam, lr_at

    torch.set_num_threads(1)
    cfgs = [
        config("idqn", False, lr=1e-3, lr_end=0.0),
        config("idqn", False, lr=1e-3),
        config("idqn", False, lr=2e-3, lr_end=1e-3),
    ]
    pop = make_algorithm("idqn", SPEC, cfgs[0], device="cpu", seed=SEEDS, run_configs=cfgs)
    singles = [make_algorithm("idqn", SPEC, c, device="cpu", seed=s) for c, s in zip(cfgs, SEEDS, strict=True)]
    feed(pop, singles, np.random.default_rng(1))
    total = 1000
    for i in range(200):
        for agent in (pop, *singles):
            agent.progress = Progress(env_steps=5 * i, total_steps=total, training=True)
            agent.update()
    at = 5 * 199 / total
    want = [1e-3 * (1 - at), 1e-3, 2e-3 - at * 1e-3]
    assert isinstance(pop.updater.optimizer, RunAdam)
    np.testing.assert_allclose(pop.updater.optimizer.lrs.numpy(), want, rtol=1e-6)
    for single, lr in zip(singles, want, strict=True):  # a single run's: one rate, on the device
        assert float(single.updater.optimizer.lrs) == pytest.approx(lr, rel=1e-6)
    assert max_weight_gap(pop, singles) < 1e-5
    assert lr_at(cfgs[0], 2 * total, total) == 0.0 and lr_at(cfgs[1], total, total) == 1e-3  # held past the end


@pytest.mark.parametrize("name", ["idqn", "ma-mesn"])
def test_policy_ema_evaluates_the_average_of_the_online_weights(name: str, tmp_path: Path) -> None:
    """``policy_ema`` τ: after each update avg ← (1 − τ)·avg + τ·online; training acts with the online weights,
    evaluation (``progress.training`` off) and a loaded checkpoint with the average, per run of a population."""
    from convoy.algos.checkpoint import load_checkpoint

    torch.set_num_threads(1)
    tau = 0.1
    cfg = config(name, False, policy_ema=tau)
    pop = make_algorithm(name, SPEC, cfg, device="cpu", seed=SEEDS)
    single = make_algorithm(name, SPEC, cfg, device="cpu", seed=SEEDS[1])
    g = np.random.default_rng(0)
    for _ in range(4):
        c = chunk(g, len(SEEDS))
        pop.observe(c)
        single.observe(run_of(c, 1))
    want = {n: w.clone() for n, w in single.online.state_dict().items()}
    for agent in (pop, single):
        agent.progress = Progress(100, 1, 1000, training=True)
    for _ in range(30):
        pop.update()
        single.update()
        for n, w in single.online.state_dict().items():
            want[n] = (1 - tau) * want[n] + tau * w
    assert single.average is not None and single.evaluated is single.average
    for n, w in single.average.state_dict().items():
        torch.testing.assert_close(w, want[n], rtol=0, atol=1e-6)
    member = pop.member(1)
    for n, w in member.evaluated.state_dict().items():
        torch.testing.assert_close(w, want[n], rtol=0, atol=1e-5)
    # acting: online in training, the average out of it (the online net lent back afterwards)
    obs = g.normal(size=(64, SPEC.n_agents, SPEC.obs_dim)).astype(np.float32)
    online_acts = single.act(obs).actions
    single.progress = Progress(100, 1, 1000, training=False)
    averaged_acts = single.act(obs).actions
    assert (online_acts != averaged_acts).any(), "the average should act differently from the online weights"
    assert single.online is not single.average
    plain = make_algorithm(name, SPEC, config(name, False), device="cpu", seed=SEEDS[1])
    plain.load_policy_state(single.average.state_dict())
    np.testing.assert_array_equal(plain.act(obs).actions, averaged_acts)
    # a checkpoint keeps the average and acts with it once loaded
    job = job_config(algo=name, env="treadmill", algo_params=cfg.model_dump(), device="cpu", seed=SEEDS[1])
    save_checkpoint(tmp_path / "c.pt", single, job, {"env_steps": 100, "episodes": 1, "updates": 30})
    loaded, _, _ = load_checkpoint(tmp_path / "c.pt", device="cpu")
    np.testing.assert_array_equal(loaded.act(obs).actions, averaged_acts)


def test_a_jobs_seeds_make_a_population_of_single_runs() -> None:
    """``seeds`` in the one config model (CLI, files, the learner and actors read it): one seed is the single run
    of that seed; a population's members are single runs of their seeds writing DIR/seed-N; the resource limits
    count every run's envs and weights."""
    from convoy.config import ResourceLimits, job_config
    from convoy.validation import ConfigError

    one = job_config(algo="idqn", env="referential", seeds=[7])
    assert one.seed == 7 and one.seeds == [] and one.runs is None and one.member_dirs("out") == [Path("out")]
    pop = job_config(algo="idqn", env="referential", seeds=[4, 2, 9], num_envs=8)
    assert pop.seed == 4 and pop.runs == 3 and pop.run_seeds() == [4, 2, 9]
    assert [(m.seed, m.seeds, m.num_envs) for m in pop.members()] == [(4, [], 8), (2, [], 8), (9, [], 8)]
    assert pop.member_dirs("out") == [Path("out/seed-4"), Path("out/seed-2"), Path("out/seed-9")]
    assert job_config(**pop.model_dump()) == pop  # a saved config reads back as itself
    limits = ResourceLimits(max_agent_envs=3 * 8 * pop.agents_per_env())  # room for three runs of 8 envs
    limits.check(pop, "test")
    with pytest.raises(ConfigError, match="3 runs"):
        limits.check(job_config(**{**pop.model_dump(), "num_envs": 9}), "test")
    hierarchical_dial = {"seeds": [1, 2], "env": "treadmill", "hierarchical": True, "algo": "dial"}
    for bad, words in (({"seeds": [1, 1]}, "distinct"), ({"seeds": [1, 2], "seed": 3}, "not both"),
                       (hierarchical_dial, "one seed per process")):  # fmt: skip
        with pytest.raises(ConfigError, match=words) as info:
            job_config(**{"algo": "idqn", "env": "referential", **bad})
        assert info.value.field == "seeds"


def test_a_population_resumes_at_the_last_step_all_its_runs_saved(tmp_path: Path) -> None:
    """A crash between two runs' checkpoint writes leaves them a step apart: each run keeps the checkpoint before
    its last, and the population resumes where every run has one (here the step before the last)."""
    import shutil

    from convoy.algos.checkpoint import PREVIOUS_CHECKPOINT, read_checkpoint
    from convoy.algos.registry import make_algorithm
    from convoy.cli.main import main
    from convoy.config import job_config
    from convoy.envs import make_batched
    from convoy.learner.resume import restore_population

    cfg = tmp_path / "job.json"
    cfg.write_text(json.dumps({"algo": "idqn", "env": "referential", "steps": 3000, "num_envs": 8,
                               "checkpoint_every": 1000, "eval_episodes": 4, "seeds": [0, 1],
                               "algo_params": {"hidden": [16], "learning_starts": 100}}))  # fmt: skip
    out = tmp_path / "pop"
    assert main(["train", "--inprocess", "--config", str(cfg), "--out", str(out), "--no-progress"]) == 0
    last = read_checkpoint(out / "seed-1" / "checkpoint.pt")["counters"]["env_steps"]
    before = read_checkpoint(out / "seed-1" / PREVIOUS_CHECKPOINT)["counters"]["env_steps"]
    assert before < last
    shutil.copy(out / "seed-1" / PREVIOUS_CHECKPOINT, out / "seed-1" / "checkpoint.pt")  # seed 1 never wrote its last
    job = job_config(**json.loads(cfg.read_text()))
    agent = make_algorithm("idqn", make_batched("referential", 1).spec, job.algo_config(), "cpu", [0, 1])
    counters = restore_population(agent, job.members(), job.member_dirs(out), out / "replay.npz", strict=True)
    assert counters is not None
    assert [c["env_steps"] for c in counters] == [before, before]

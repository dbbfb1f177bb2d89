"""Replay memory follows a run's steps, not ``replay_capacity``: a run allocates the rows it can store (its budget and
less than one more chunk) and grows only if more come (a resumed run past its budget), up to the capacity, where the
ring wraps as before. A ring that has not wrapped holds its rows at 0 … size − 1 and samples ``[0, size)`` whatever
its allocation, so every run that fits trains bit for bit as with all of the capacity allocated up front."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

from convoy.actors.stepping import EnvStepper
from convoy.algos.agent import make_agent, max_env_steps
from convoy.algos.checkpoint import replay_buffers
from convoy.algos.replay import JointReplay
from convoy.algos.streams import RunStreams
from convoy.config import JobConfig, job_config
from convoy.learner.inprocess import Trainer
from convoy.learner.population import PopulationTrainer
from convoy.learner.resume import restore
from convoy.services.training import make_env

SMALL = {"n_agents": 2, "max_steps": 50}
HP: dict[str, Any] = {"hidden": [16], "learning_starts": 32, "batch_size": 16, "replay_ratio": 2.0,
                      "target_update": 20}  # fmt: skip
TIMING = ("wall_s", "env_steps_per_s", "updates_per_s")


def rows(g: np.random.Generator, m: int, runs: int = 1) -> dict[str, np.ndarray]:
    lead = (runs, m)
    return {"x": g.normal(size=(*lead, 3)).astype(np.float32), "k": g.integers(0, 9, size=lead)}


@pytest.mark.parametrize("runs", [1, 3], ids=["single", "population"])
def test_a_reserved_ring_holds_and_samples_what_a_fully_allocated_one_does(runs: int) -> None:
    """Through growth (a reserve of 5) and past the capacity (50 rows, 137 inserted): equal contents and draws."""
    full, short = JointReplay(50, runs=runs), JointReplay(50, runs=runs)
    short.reserve(5)
    g = np.random.default_rng(0)
    streams = [RunStreams(range(runs), "replay") for _ in range(2)]
    for m in (3, 1, 7, 2, 11, 4, 30, 9, 25, 45):
        batch = rows(g, m, runs)
        valid = None if runs == 1 else g.random((runs, m)) < 0.7  # the runs' own rows (a meta level's)
        for buf in (full, short):
            buf.add(batch, valid)
        assert short.allocated <= 50 and full.allocated == 50
        draws = [b.sample(8, s) for b, s in zip((full, short), streams, strict=True)]
        for k in draws[0]:
            assert torch.equal(draws[0][k], draws[1][k])
        a, b = full.state_dict(), short.state_dict()
        np.testing.assert_array_equal(a["size"], b["size"])
        np.testing.assert_array_equal(a["next"], b["next"])
        for k in a["data"]:
            np.testing.assert_array_equal(a["data"][k], b["data"][k])
    assert short.allocated == 50  # wrapped: all of the capacity


def test_a_reserve_allocates_only_that_and_the_capacity_still_bounds_it() -> None:
    buf = JointReplay(100)
    buf.reserve(10)
    buf.add({"x": np.zeros((1, 4, 2), np.float32)})
    assert buf.allocated == 10 and buf.nbytes == 10 * 2 * 4
    buf.add({"x": np.zeros((1, 8, 2), np.float32)})  # past the reserve: grown by half at least
    assert buf.allocated == 15 and len(buf) == 12
    buf.reserve(1_000)  # more than the capacity: the capacity
    assert buf.allocated == 100
    with pytest.raises(ValueError, match="rows"):
        buf.reserve(0)


def small_job(algo: str, **extra: Any) -> JobConfig:
    hp = {**HP, **extra.pop("algo_params", {})}
    if algo == "dial":
        hp.update(replay=True, unroll=4)
    values = {"steps": 480, "num_envs": 4, "eval_every": 0, "eval_episodes": 0, "device": "cpu", "seed": 3}
    return job_config(algo=algo, env="treadmill", env_params=SMALL, algo_params=hp, **{**values, **extra})


def train(job: JobConfig, reserve: int | None) -> tuple[Any, list[dict[str, Any]]]:
    """Train ``job`` in one process; ``reserve``: replay rows to allocate instead of the job's (None: the job's)."""
    torch.set_num_threads(1)
    env = make_env(job, job.num_envs * (job.runs or 1))
    try:
        agent = make_agent(job, env.spec)
        if reserve is not None:
            agent.reserve_replay(reserve)
        if job.runs:
            results = PopulationTrainer(job.members(), env, agent, progress=False).run()
        else:
            results = [Trainer(job, env, agent, progress=False).run()]
    finally:
        env.close()
    return agent, [{k: v for k, v in r.items() if k not in TIMING} for res in results for r in res.rows]


def assert_same_state(a: Any, b: Any, where: str = "state") -> None:
    if isinstance(a, torch.Tensor):
        assert torch.equal(a, b), where
    elif isinstance(a, np.ndarray):
        np.testing.assert_array_equal(a, b, err_msg=where)
    elif isinstance(a, dict):
        assert a.keys() == b.keys(), where
        for k in a:
            assert_same_state(a[k], b[k], f"{where}.{k}")
    elif isinstance(a, list | tuple):
        assert len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            assert_same_state(x, y, f"{where}[{i}]")
    else:
        assert a == b or (a != a and b != b), f"{where}: {a!r} != {b!r}"  # NaN figures equal NaN


@pytest.mark.parametrize(
    ("algo", "extra"),
    [("idqn", {}), ("idqn", {"algo_params": {"n_step": 2}}), ("ma-mesn", {}), ("dial", {}),
     ("idqn", {"hierarchical": True}), ("idqn", {"seeds": [3, 4]})],
    ids=["idqn", "idqn-n-step", "ma-mesn", "dial-replay", "hierarchical", "population"],
)  # fmt: skip
def test_a_run_that_fits_trains_bit_identically_with_replay_sized_to_its_steps(algo: str, extra: dict) -> None:
    """The default (rows for the run's steps) against an explicit 1 M capacity allocated whole (what every run did
    before) and against a 1-row reserve that grows as rows come: the same weights, optimizer state and metric
    rows, exactly."""
    params = {**HP, **extra.get("algo_params", {}), "replay_capacity": 1_000_000}
    whole, whole_rows = train(small_job(algo, **{**extra, "algo_params": params}), reserve=10**9)
    default_job = small_job(algo, **extra)
    default, default_rows = train(default_job, reserve=None)
    grown, grown_rows = train(default_job, reserve=1)
    assert default.updates > 0
    for other, other_rows in ((default, default_rows), (grown, grown_rows)):
        assert_same_state(whole_rows, other_rows, "rows")
        for k in range(len(default_job.seeds) or 1):  # a population's state is its runs'
            a, b = (whole.member(k), other.member(k)) if default_job.runs else (whole, other)
            assert_same_state(a.state_dict(), b.state_dict())
    need = max_env_steps(default_job, default.chunk_len)
    for name, buf in replay_buffers(default).items():
        big = replay_buffers(whole)[name]
        assert buf.capacity == big.capacity and big.allocated == big.capacity
        assert 0 < len(buf) <= buf.allocated <= need * (default.n_agents if "controller" in name else 1)
        assert buf.nbytes < big.nbytes / 100


def one_chunk(job: JobConfig) -> Any:
    """The job's agent with one chunk of its env's transitions in its replay."""
    env = make_env(job)
    try:
        agent = make_agent(job, env.spec)
        stepper = EnvStepper(env, agent, job.seed)
        while stepper.chunk_steps < agent.chunk_len:
            stepper.step(1.0)
        agent.observe(stepper.take_chunk())
    finally:
        env.close()
    return agent


@pytest.mark.parametrize("algo", ["idqn", "ma-mesn", "dial", "h-idqn"])
def test_replay_memory_at_defaults_is_what_the_runs_steps_need(algo: str) -> None:
    """A default treadmill job of 20 k steps: ≤ 1.1 × the bytes of the rows its steps make (was 1 M rows, 1.2 GB)."""
    hier = algo.startswith("h-")
    job = job_config(algo=algo.removeprefix("h-"), env="treadmill", steps=20_000, hierarchical=hier, device="cpu",
                     algo_params={"replay": True} if algo == "dial" else {})  # fmt: skip
    agent = one_chunk(job)
    for name, buf in replay_buffers(agent).items():
        if not len(buf):
            continue  # a meta level with no option ended yet
        per_step = agent.n_agents if name.startswith("controller") else 1  # the controller: a row per agent
        unroll = int(job.algo_config().unroll) if algo == "dial" else 1  # type: ignore[attr-defined]
        need_rows = -(-job.steps * per_step // unroll)
        row_bytes = buf.nbytes // buf.allocated
        print(f"{algo} {name}: {buf.nbytes / 2**20:.1f} MiB for {need_rows:,} rows (capacity {buf.capacity:,})")
        assert buf.nbytes <= 1.1 * need_rows * row_bytes
        assert buf.allocated < buf.capacity


def test_a_run_resumed_past_its_budget_gets_replay_for_its_new_one(tmp_path: Path) -> None:
    """The saved rows come back into a replay allocated for the new budget, and the run goes on past the old
    allocation to its new end."""
    first = small_job("idqn", runtime={"keep_replay": True}, checkpoint_every=10**6)
    env = make_env(first)
    try:
        agent = make_agent(first, env.spec)
        Trainer(first, env, agent, out_dir=tmp_path, progress=False).run()
    finally:
        env.close()
    saved = replay_buffers(agent)["replay"]
    old = saved.allocated
    assert len(saved) == first.steps and old < 2 * first.steps
    longer = first.model_copy(update={"steps": 3 * first.steps})
    env = make_env(longer)
    try:
        resumed = make_agent(longer, env.spec)
        replay = replay_buffers(resumed)["replay"]
        restored = restore(resumed, longer, tmp_path, strict=True)
        assert restored is not None
        (counters,) = restored  # one dict per run
        assert counters["replay_rows"] == first.steps == len(replay)
        assert replay.allocated == max_env_steps(longer, resumed.chunk_len) > old
        Trainer(longer, env, resumed, out_dir=tmp_path, progress=False, counters=counters).run()
    finally:
        env.close()
    assert len(replay) == longer.steps <= replay.allocated


def test_a_single_runs_replay_file_from_before_the_run_axis_loads_as_run_0() -> None:
    """Replay files written before a single run was a run of one hold rows ``[rows, …]`` and 0-dim pointers."""
    buf = JointReplay(10)
    buf.load_state_dict({"data": {"x": np.arange(6, dtype=np.float32)[:, None]}, "next": np.array(6), "size": 6})
    assert len(buf) == 6 and buf.state_dict()["next"].tolist() == [6]
    np.testing.assert_array_equal(buf.state_dict()["data"]["x"][0, :, 0], np.arange(6))

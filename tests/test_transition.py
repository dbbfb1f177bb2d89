"""The declared transition (``convoy.transition``): every algorithm's acting loop records it, in its dtypes and
shapes, whatever extras the algorithm adds; the wire and the learner hold chunks to it."""

from __future__ import annotations

import re
from dataclasses import fields, replace
from pathlib import Path

import numpy as np
import pytest
import torch

from convoy.actors.stepping import EnvStepper
from convoy.algos.agent import make_agent
from convoy.algos.replay import JointReplay
from convoy.algos.streams import RunStreams
from convoy.config import ALGORITHMS, job_config
from convoy.envs import make_batched
from convoy.learner.service import transition_schema
from convoy.transition import TRANSITION, Transition, from_columns, record, schema

SMALL = {"n_agents": 2, "n_adversaries": 1, "length": 30, "width": 12, "max_steps": 20}


# CoDBC acts as independent DQN does; the hierarchical wrapper around two of them
CASES = [(n, False) for n in ALGORITHMS if n != "codbc"] + [("idqn", True), ("ma-mesn", True)]


@pytest.mark.parametrize(("name", "hierarchical"), CASES)
def test_every_algorithm_records_the_declared_transition(name: str, hierarchical: bool) -> None:
    job = job_config(algo=name, env="treadmill", env_params=SMALL, hierarchical=hierarchical,
                     algo_params={"hidden": [8]}, device="cpu")  # fmt: skip
    env = make_batched("treadmill", 3, **SMALL)
    algo = make_agent(job, env.spec)
    stepper = EnvStepper(env, algo, seed=0)
    for _ in range(2):
        stepper.step(1.0)
    chunk = stepper.take_chunk()
    declared = schema(env.spec.n_agents, env.spec.obs_dim)
    assert {k: (v.dtype.str, v.shape[3:]) for k, v in chunk.columns().items() if k in TRANSITION} == declared
    assert all(v.shape[:3] == (2, 1, 3) for v in chunk.columns().values())  # [T, R, B]
    assert {k: v for k, v in transition_schema(job, algo).items() if k in TRANSITION} == declared


def test_record_casts_to_the_declared_dtypes_and_keeps_extras_apart() -> None:
    b, n, d = 4, 2, 3
    extras = {"mu": np.ones((b, n), np.float32)}
    got = record(np.zeros((b, n, d)), np.zeros((b, n), np.int32), np.zeros((b, n)), np.zeros((b, n, d)),
                 np.zeros(b, bool), np.zeros(b, bool), np.zeros(b, np.int32), extras)  # fmt: skip
    assert {k: v.dtype.str for k, v in got.columns().items()} == {
        **{k: f.dtype for k, f in TRANSITION.items()},
        "mu": "<f4",
    }
    assert got.extras == extras
    with pytest.raises(ValueError, match="reward"):
        record(got.obs, got.action, got.reward, got.next_obs, got.terminated, got.truncated, got.episode,
               extras={"reward": got.reward})  # fmt: skip


def test_the_declaration_is_the_dataclass() -> None:
    """One source: the declared fields are the transition's attributes, in order, and a map of names without one of
    them is no transition."""
    assert tuple(TRANSITION) == tuple(f.name for f in fields(Transition) if f.name != "extras")
    with pytest.raises(KeyError, match="truncated"):
        from_columns({k: np.zeros(1) for k in TRANSITION if k != "truncated"})


def test_the_replay_holds_rows_to_the_declared_transition() -> None:
    b, n, d = 4, 2, 3
    rows = record(np.zeros((b, n, d)), np.zeros((b, n)), np.zeros((b, n)), np.zeros((b, n, d)), np.zeros(b, bool),
                  np.zeros(b, bool), np.zeros(b), {"fingerprint": np.zeros((b, 2), np.float32)})  # fmt: skip
    rows = rows.map(lambda v: v[None])  # one run's
    replay = JointReplay(16, declared=schema(n, d))
    replay.add(rows)  # the declared fields and an extra
    assert len(replay) == b
    with pytest.raises(ValueError, match=r"'obs' is <f8 \(2, 3\) per row; the declared transition holds <f4"):
        replay.add(replace(rows, obs=rows.obs.astype(np.float64)))
    with pytest.raises(ValueError, match="'next_obs' is <f4 \\(2, 4\\)"):
        replay.add(replace(rows, next_obs=np.zeros((1, b, n, 4), np.float32)))
    assert len(replay) == b  # nothing refused was written


def test_a_typed_transition_round_trips_through_the_replay_and_its_file() -> None:
    """What the replay stores it samples as the same transition, on its device, each field where it was; its state
    (a replay file's) loads into a fresh replay that samples the same rows."""
    g = np.random.default_rng(0)
    b, n, d = 5, 2, 3
    rows = record(g.normal(size=(b, n, d)), g.integers(0, 4, (b, n)), g.normal(size=(b, n)), g.normal(size=(b, n, d)),
                  g.random(b) < 0.5, g.random(b) < 0.5, np.arange(b), {"fingerprint": g.random((b, 2))})  # fmt: skip
    rows = rows.map(lambda v: v[None])  # one run's [R = 1, M, …]
    replay = JointReplay(16, declared=schema(n, d))
    replay.add(rows)
    got = replay.sample(32, RunStreams([0], "replay"))
    assert isinstance(got, Transition) and set(got.extras) == {"fingerprint"}
    picked = got.episode[0].numpy()  # each row's index: the episode stamps are 0 … b − 1
    for name, mine in rows.columns().items():
        theirs = got.columns()[name]
        assert theirs.dtype == torch.from_numpy(mine).dtype and theirs.shape[2:] == mine.shape[2:], name
        np.testing.assert_array_equal(theirs[0].numpy(), mine[0][picked], err_msg=name)
    fresh = JointReplay(16, declared=schema(n, d))
    fresh.load_state_dict(replay.state_dict())
    again = fresh.sample(32, RunStreams([0], "replay"))
    assert all(torch.equal(v, got.columns()[k]) for k, v in again.columns().items())


# Where transition fields may be read by name: the wire codec (a chunk's body is a msgpack map) and the declaration
NAMED_AT = {Path("protocol/wire.py"), Path("convoy/transition.py")}
PRODUCT = ("convoy", "algos", "protocol", "learner", "actors", "api", "services", "cli", "envs", "analysis")


def test_no_product_code_reads_a_transition_field_by_name() -> None:
    """Outside the wire codec a transition's fields are attributes (``batch.obs``), never ``batch["obs"]``: a
    typo is then an error the type checker finds, not a ``KeyError`` at run time."""
    root = Path(__file__).resolve().parent.parent
    names = "|".join(TRANSITION)
    by_name = re.compile(rf"""(\[\s*|\.get\(\s*|\bpop\(\s*)["']({names})["']""")
    found = [
        f"{path.relative_to(root)}:{i}: {line.strip()}"
        for folder in PRODUCT
        for path in sorted((root / folder).rglob("*.py"))
        if path.relative_to(root) not in NAMED_AT
        for i, line in enumerate(path.read_text().splitlines(), 1)
        if by_name.search(line)
    ]
    assert not found, "transition fields read by name:\n" + "\n".join(found)

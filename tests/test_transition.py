"""The declared transition (``convoy.transition``): every algorithm's acting loop records it, in its dtypes and
shapes, whatever extras the algorithm adds; the wire and the learner hold chunks to it."""

from __future__ import annotations

import numpy as np
import pytest

from convoy.actors.stepping import EnvStepper
from convoy.algos.agent import make_agent
from convoy.algos.replay import JointReplay
from convoy.config import ALGORITHMS, job_config
from convoy.envs import make_batched
from convoy.learner.service import transition_schema
from convoy.transition import TRANSITION, record, schema

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
    assert {k: (v.dtype.str, v.shape[3:]) for k, v in chunk.items() if k in TRANSITION} == declared  # [T, R, B]
    assert all(v.shape[:3] == (2, 1, 3) for v in chunk.values())
    assert {k: v for k, v in transition_schema(job, algo).items() if k in TRANSITION} == declared


def test_record_casts_to_the_declared_dtypes_and_keeps_extras_apart() -> None:
    b, n, d = 4, 2, 3
    extras = {"mu": np.ones((b, n), np.float32)}
    got = record(np.zeros((b, n, d)), np.zeros((b, n), np.int32), np.zeros((b, n)), np.zeros((b, n, d)),
                 np.zeros(b, bool), np.zeros(b, bool), np.zeros(b, np.int32), extras)  # fmt: skip
    assert {k: v.dtype.str for k, v in got.items()} == {**{k: f.dtype for k, f in TRANSITION.items()}, "mu": "<f4"}
    with pytest.raises(ValueError, match="reward"):
        record(**{k: got[k] for k in TRANSITION}, extras={"reward": got["reward"]})


def test_the_replay_holds_rows_to_the_declared_transition() -> None:
    b, n, d = 4, 2, 3
    rows = record(np.zeros((b, n, d)), np.zeros((b, n)), np.zeros((b, n)), np.zeros((b, n, d)), np.zeros(b, bool),
                  np.zeros(b, bool), np.zeros(b), {"fingerprint": np.zeros((b, 2), np.float32)})  # fmt: skip
    rows = {k: v[None] for k, v in rows.items()}  # one run's
    replay = JointReplay(16, declared=schema(n, d))
    replay.add(rows)  # the declared fields and an extra
    assert len(replay) == b
    with pytest.raises(ValueError, match="'truncated'"):
        replay.add({k: v for k, v in rows.items() if k != "truncated"})
    with pytest.raises(ValueError, match=r"'obs' is <f8 \(2, 3\) per row; the declared transition holds <f4"):
        replay.add({**rows, "obs": rows["obs"].astype(np.float64)})
    with pytest.raises(ValueError, match="'next_obs' is <f4 \\(2, 4\\)"):
        replay.add({**rows, "next_obs": np.zeros((1, b, n, 4), np.float32)})
    assert len(replay) == b  # nothing refused was written

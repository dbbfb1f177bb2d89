"""Prioritized replay (``priority_alpha`` > 0; ``algos/replay.py``, ``algos/idqn.py``): rows drawn in proportion to
their priorities with importance weights, new rows at the largest priority, the update's |TD error| written back,
priorities kept in replay files (and hostile ones refused), and a population's run k the single run of its seed.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from convoy.algos.algorithm import PRIORITY_FLOOR, Progress
from convoy.algos.checkpoint import load_replay, save_replay
from convoy.algos.idqn import IndependentDQN
from convoy.algos.registry import make_algorithm
from convoy.algos.replay import BLOCK, JointReplay
from convoy.algos.streams import RunStreams
from convoy.config import resolve_algo
from convoy.transition import TRANSITION, Transition, from_columns
from tests.test_population import SEEDS, SPEC, feed, max_weight_gap

ROWS = 2 * BLOCK + 500  # three blocks, the last one partly filled


def rows(runs: int, m: int, start: int = 0) -> Transition[np.ndarray]:
    """``m`` rows per run whose ``episode`` field is the row's number, so a draw shows which rows it took."""
    cols = {k: np.zeros((runs, m, *(2 if d == "N" else 3 for d in f.shape)), f.dtype) for k, f in TRANSITION.items()}
    cols["episode"][:] = np.arange(start, start + m)
    return from_columns(cols)


def test_rows_are_drawn_in_proportion_to_their_priorities_with_importance_weights() -> None:
    replay = JointReplay(4 * BLOCK, runs=2, prioritized=True)
    replay.add(rows(2, ROWS))
    every = torch.arange(ROWS).expand(2, ROWS)
    priority = torch.stack([1.0 + (torch.arange(ROWS) % 10).float(), 10.0 - (torch.arange(ROWS) % 10).float()])
    replay.set_priorities(every, priority)
    streams = RunStreams([0, 1], "replay")
    counts = torch.zeros(2, ROWS)
    for _ in range(100):
        batch, idx, weight = replay.sample_prioritized(512, streams, beta=0.6)
        assert torch.equal(batch.episode, idx)  # the rows drawn are the rows gathered
        counts.scatter_add_(1, idx, torch.ones_like(idx, dtype=torch.float32))
        p = priority.gather(1, idx) / priority.sum(dim=1, keepdim=True)
        expected = (ROWS * p) ** -0.6
        torch.testing.assert_close(weight, expected / expected.amax(dim=1, keepdim=True))
    share = torch.stack([counts[:, torch.arange(ROWS) % 10 == c].sum(dim=1) for c in range(10)], dim=1)
    share = share / share.sum(dim=1, keepdim=True)
    want = torch.stack([priority[:, torch.arange(ROWS) % 10 == c].sum(dim=1) for c in range(10)], dim=1)
    torch.testing.assert_close(share, want / want.sum(dim=1, keepdim=True), atol=0.005, rtol=0.0)
    assert counts[:, ROWS - 1].sum() > 0  # the last, partly filled block is reached


def test_new_rows_get_the_largest_priority_and_a_nonfinite_one_changes_nothing() -> None:
    replay = JointReplay(4 * BLOCK, runs=2, prioritized=True)
    replay.add(rows(2, 100))
    replay.set_priorities(torch.tensor([[3], [4]]), torch.tensor([[7.0], [0.5]]))
    replay.add(rows(2, 10, start=100))
    held = replay._priority[:, :110]
    assert held[0, 100:].eq(7.0).all() and held[1, 100:].eq(1.0).all()  # run 1's largest is still the first rows' 1
    before = replay._priority.clone()
    replay.set_priorities(torch.tensor([[5, 6], [5, 6]]), torch.tensor([[float("nan"), 2.0], [float("inf"), 3.0]]))
    assert replay._priority[0, 5] == before[0, 5] and replay._priority[1, 5] == before[1, 5]
    assert replay._priority[0, 6] == 2.0 and replay._priority[1, 6] == 3.0
    torch.testing.assert_close(replay._block_sum, replay._priority.view(2, -1, BLOCK).sum(dim=2))
    with pytest.raises(ValueError, match="no priorities"):
        JointReplay(100).sample_prioritized(4, RunStreams([0], "replay"), 0.4)


class Holder:
    def __init__(self, replay: JointReplay) -> None:
        self.replay = replay


def test_priorities_live_in_the_replay_file_and_hostile_ones_are_refused(tmp_path: Path) -> None:
    saved = JointReplay(4 * BLOCK, runs=2, prioritized=True)
    saved.add(rows(2, 300))
    saved.set_priorities(torch.tensor([[1, 2], [3, 4]]), torch.tensor([[9.0, 0.25], [0.5, 6.0]]))
    path = tmp_path / "replay.npz"
    assert save_replay(path, Holder(saved), 300, 1 << 30) > 0
    loaded = Holder(JointReplay(4 * BLOCK, runs=2, prioritized=True))
    assert load_replay(path, loaded, 300) == 300
    assert torch.equal(loaded.replay._priority[:, :300], saved._priority[:, :300])
    assert torch.equal(loaded.replay._max_priority, saved._max_priority)
    # a file of uniform replay loads with every row at priority 1
    plain = JointReplay(4 * BLOCK, runs=2)
    plain.add(rows(2, 300))
    save_replay(path, Holder(plain), 300, 1 << 30)
    assert load_replay(path, loaded, 300) == 300
    assert loaded.replay._priority[:, :300].eq(1.0).all() and loaded.replay._priority[:, 300:].eq(0.0).all()
    # a negative priority would make the draw's sums lie: the file is refused and the buffer starts empty
    state = saved.state_dict()
    state["priority"][0, 5] = -1.0
    with pytest.raises(ValueError, match="finite and ≥ 0"):
        JointReplay(4 * BLOCK, runs=2, prioritized=True).load_state_dict(state)


def config(name: str = "idqn", **extra: object):
    hp = {"hidden": (32, 32), "batch_size": 16, "learning_starts": 0, "replay_capacity": 500, "lr": 1e-3,
          "target_update": 20, "share_params": True, "priority_alpha": 0.6, "priority_beta": 0.4, **extra}  # fmt: skip
    return resolve_algo(name, "treadmill", hp)


def test_an_update_weighs_by_importance_and_writes_each_rows_td_error_back() -> None:
    agent = make_algorithm("idqn", SPEC, config(), device="cpu", seed=5)
    assert isinstance(agent, IndependentDQN)
    agent.progress = Progress(500, 1, 1000, training=True)  # halfway: β = 0.7
    feed(agent, [agent], np.random.default_rng(4))
    batch = agent.sample()
    drawn = agent._drawn
    assert drawn is not None
    w = batch.extras["is_weight"]
    err, delta = agent.td_losses(batch)
    torch.testing.assert_close(agent.loss(batch).agents, (err * w.unsqueeze(-1)).mean(dim=-2))
    agent.streams["replay"].load(0, agent.streams["replay"].state(0) - 1)  # the same draw again
    agent.update()
    assert agent._drawn is not None and torch.equal(agent._drawn, drawn)
    torch.testing.assert_close(agent.replay._priority.gather(1, drawn), (delta + PRIORITY_FLOOR) ** 0.6)


@pytest.mark.parametrize("name", ["idqn", "dqn-ser"])
def test_member_k_of_a_prioritized_population_is_the_single_run_of_seed_k(name: str) -> None:
    torch.set_num_threads(1)
    cfg = config(name)
    pop = make_algorithm(name, SPEC, cfg, device="cpu", seed=SEEDS)
    singles = [make_algorithm(name, SPEC, cfg, device="cpu", seed=s) for s in SEEDS]
    for agent in [pop, *singles]:
        agent.progress = Progress(100, 3, 1000, training=True)
    g = np.random.default_rng(0)
    feed(pop, singles, g)
    for _ in range(60):
        pop.update()
        for single in singles:
            single.update()
    feed(pop, singles, g, chunks=1)  # new rows come in at each run's own largest priority
    for _ in range(40):
        pop.update()
        for single in singles:
            single.update()
    assert max_weight_gap(pop, singles) < 1e-5
    for k, single in enumerate(singles):
        torch.testing.assert_close(pop.replay._priority[k], single.replay._priority[0], atol=1e-5, rtol=1e-5)


def test_uniform_replay_keeps_no_priorities() -> None:
    agent = make_algorithm("idqn", SPEC, config(priority_alpha=0.0), device="cpu", seed=0)
    feed(agent, [agent], np.random.default_rng(1), chunks=1)
    assert "is_weight" not in agent.sample().extras and agent._drawn is None
    assert not agent.replay.prioritized

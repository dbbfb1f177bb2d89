"""Learner updates per second: each algorithm's ``update()`` beside a plain PyTorch DQN update of the same sizes.

For every algorithm, ms per ``update()`` of Convoy's learner, and of a reference written the way a textbook (or
CleanRL) writes a DQN update: an ``nn.Sequential`` of ``nn.Linear``/``nn.ReLU`` with the algorithm's widths (the
agent's observation and one-hot id in, the treadmill's actions out), ``torch.optim.Adam`` at the algorithm's
learning rate, a batch sampled from a replay of the same rows (batch × agents; DIAL: batch × unroll × agents), a
double-Q target from a target network with the advantage-learning gap Convoy's configs use, the Huber TD loss
summed over agents, and the gradient clipped to the algorithm's norm. For independent DQN that is the same update,
so the ratio is what Convoy's code costs beyond plain PyTorch; for the others it is also what the algorithm adds
(messages, more networks, DIAL's unroll) over a DQN of that size.

The two run interleaved on one thread (Convoy, reference, Convoy, reference, ...; median of ``--repeats``), so
drift on a shared machine hits both alike. Sizes: the paper's treadmill networks (hidden 4096 → 12, batch 64; for
every algorithm, though DIAL's own is 6144 → 12) and (256, 256) with batch 128, the treadmill default of all but
DIAL and IMS; N = 3 agents + 1 adversary. Convoy's replay is filled with random play through each algorithm's own
acting path (``EnvStepper``); DIAL uses its replay variant (``replay=true``, unroll 8), so an update samples like
the others.

Run from the repository root: ``python benchmarks/updates.py`` (~3 min); ``--quick`` for a smoke run of seconds;
``--algos`` to choose; ``--json`` to save the figures.
"""

from __future__ import annotations

import argparse
import itertools
import os
import statistics
import sys
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import torch  # noqa: E402
import torch.nn.functional as F  # noqa: E402
from torch import Tensor, nn  # noqa: E402

from benchmarks.report import cpu_model, write_json  # noqa: E402
from convoy.actors.stepping import EnvStepper  # noqa: E402
from convoy.algos.registry import make_algorithm  # noqa: E402
from convoy.config import PAPER_TREADMILL_HIDDEN, resolve_algo  # noqa: E402
from convoy.envs import make_batched  # noqa: E402
from convoy.output import markdown_table  # noqa: E402

ALGOS = ("idqn", "dqn-ser", "dial", "ims", "ma-mesn", "ma-bon", "ma-mesn-mm", "ma-bon-mm")
SIZES = {"paper (4096, 12), batch 64": (PAPER_TREADMILL_HIDDEN, 64), "default (256, 256), batch 128": ((256, 256), 128)}
QUICK_SIZES = {"quick (64, 32), batch 32": ((64, 32), 32)}
PLAY_STEPS = 64  # random env steps × 16 envs: the replay the updates sample from
DIAL_UNROLL = 8


def filled(
    name: str, seeds: int | list[int] = 0, device: str = "cpu", play_steps: int = PLAY_STEPS, **params: Any
) -> Any:
    """``name`` on the treadmill (3 agents + 1 adversary, 16 envs a run; a population when ``seeds`` is a list) on
    ``device``, its replay filled with ``play_steps`` steps of random play, ``params`` over the treadmill's."""
    runs = len(seeds) if isinstance(seeds, list) else 1
    env = make_batched("treadmill", 16 * runs, n_agents=3, n_adversaries=1)
    params = {"learning_starts": 0, "replay_capacity": 4096, **params}
    if name == "dial":  # its replayed sequences: on-policy DIAL has one batch per episode, nothing to time over
        params.update(replay=True, unroll=DIAL_UNROLL)
    algo = make_algorithm(name, env.spec, resolve_algo(name, "treadmill", params), device=device, seed=seeds)
    stepper = EnvStepper(env, algo, 0)
    for _ in range(play_steps):
        stepper.step(1.0)
    algo.observe(stepper.take_chunk())
    env.close()
    return algo


def ms_per_call(step: Any, seconds: float) -> float:
    """Mean ms of ``step()`` calls over ``seconds`` (at least 3, after 3 untimed ones)."""
    for _ in range(3):
        step()
    n, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds or n < 3:
        step()
        n += 1
    return (time.perf_counter() - t0) / n * 1e3


class ReferenceDQN:
    """A double DQN update in plain PyTorch: ``nn.Sequential``, ``torch.optim.Adam``, Huber TD, clipped gradients.

    One row is one agent's transition (observation with the agent's one-hot id appended); a sampled batch holds
    ``samples`` joint transitions of ``agents`` rows each, and the loss is each agent's mean Huber error, summed,
    as Convoy's learners minimise it."""

    def __init__(
        self,
        obs_dim: int,
        hidden: tuple[int, ...],
        n_actions: int,
        agents: int,
        samples: int,
        cfg: Any,
        replay_rows: int = 4096,
    ) -> None:
        def net() -> nn.Sequential:
            sizes, layers = [obs_dim + agents, *hidden], []
            for a, b in itertools.pairwise(sizes):
                layers += [nn.Linear(a, b), nn.ReLU()]
            return nn.Sequential(*layers, nn.Linear(sizes[-1], n_actions))

        self.agents, self.samples = agents, samples
        self.gamma, self.gap, self.clip = cfg.gamma, cfg.advantage_learning, cfg.grad_clip
        self.q, self.target = net(), net()
        self.target.load_state_dict(self.q.state_dict())
        self.opt = torch.optim.Adam(self.q.parameters(), lr=cfg.lr)
        g = torch.Generator().manual_seed(0)
        self.replay = {
            "obs": torch.randn(replay_rows, agents, obs_dim, generator=g),
            "next_obs": torch.randn(replay_rows, agents, obs_dim, generator=g),
            "action": torch.randint(0, n_actions, (replay_rows, agents), generator=g),
            "reward": torch.rand(replay_rows, agents, generator=g),
            "terminated": torch.rand(replay_rows, generator=g) < 0.02,
        }
        self.eye = torch.eye(agents)

    def sample(self) -> dict[str, Tensor]:
        idx = torch.randint(0, len(self.replay["obs"]), (self.samples,))
        return {k: v[idx] for k, v in self.replay.items()}

    def rows(self, obs: Tensor) -> Tensor:
        """``[M, N, D]`` → ``[M·N, D + N]``: every agent's observation with its one-hot id."""
        ids = self.eye.expand(obs.shape[0], -1, -1)
        return torch.cat([obs, ids], dim=-1).reshape(-1, obs.shape[-1] + self.agents)

    def loss(self, batch: dict[str, Tensor]) -> Tensor:
        obs, next_obs = self.rows(batch["obs"]), self.rows(batch["next_obs"])
        action = batch["action"].reshape(-1, 1)
        with torch.no_grad():
            best = self.q(next_obs).argmax(dim=1, keepdim=True)
            cont = (~batch["terminated"]).float().repeat_interleave(self.agents)
            y = batch["reward"].reshape(-1) + self.gamma * cont * self.target(next_obs).gather(1, best).squeeze(1)
            if self.gap:
                q_t = self.target(obs)
                y = y - self.gap * (q_t.max(dim=1).values - q_t.gather(1, action).squeeze(1))
        q = self.q(obs).gather(1, action).squeeze(1)
        err = F.smooth_l1_loss(q, y, reduction="none").reshape(-1, self.agents)
        return err.mean(dim=0).sum()

    def update(self) -> None:
        loss = self.loss(self.sample())
        self.opt.zero_grad(set_to_none=True)
        loss.backward()
        nn.utils.clip_grad_norm_(self.q.parameters(), self.clip)
        self.opt.step()


def reference_for(algo: Any, hidden: tuple[int, ...]) -> ReferenceDQN:
    """The reference update at ``algo``'s sizes: its observation, actions, agents, batch rows and hyperparameters."""
    cfg = algo.cfg
    samples = cfg.batch_size * (int(cfg.unroll) if algo.name == "dial" else 1)
    return ReferenceDQN(algo.obs_dim, hidden, algo.n_act, algo.n_agents, samples, cfg)


def interleaved(convoy: Any, reference: Any, seconds: float, repeats: int) -> tuple[float, float]:
    """Median ms per call of each, measured in turns."""
    a, b = [], []
    for _ in range(repeats):
        a.append(ms_per_call(convoy, seconds))
        b.append(ms_per_call(reference, seconds))
    return statistics.median(a), statistics.median(b)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--algos", nargs="+", default=list(ALGOS), choices=ALGOS, help="algorithms (default: all)")
    p.add_argument("--seconds", type=float, default=1.0, help="timed updates per measurement, s (default 1)")
    p.add_argument("--repeats", type=int, default=3, help="measurements each way; the median counts (default 3)")
    p.add_argument("--quick", action="store_true", help="smoke run: small networks, short measurements")
    p.add_argument("--json", metavar="PATH", help="also write every figure as JSON")
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    if args.quick:
        args.seconds, args.repeats = 0.2, 1
    sizes = QUICK_SIZES if args.quick else SIZES
    print(f"{cpu_model()}, 1 torch thread, load average {os.getloadavg()[0]:.1f} at start.\n")
    figures: dict[str, Any] = {}
    for size_name, (hidden, batch) in sizes.items():
        rows, out = [], {}
        for name in args.algos:
            algo = filled(name, hidden=hidden, batch_size=batch)
            ref = reference_for(algo, hidden)
            convoy_ms, ref_ms = interleaved(algo.update, ref.update, args.seconds, args.repeats)
            out[name] = {
                "rows_per_update": ref.samples * ref.agents,
                "convoy_ms": convoy_ms,
                "reference_ms": ref_ms,
                "convoy_updates_per_s": 1e3 / convoy_ms,
                "convoy_over_reference": convoy_ms / ref_ms,
            }
            rows.append([name, f"{ref.samples * ref.agents:,}", f"{convoy_ms:.2f}", f"{1e3 / convoy_ms:.1f}",
                         f"{ref_ms:.2f}", f"{convoy_ms / ref_ms:.2f}"])  # fmt: skip
        figures[size_name] = out
        print(f"### {size_name}\n")
        header = ["algorithm", "rows/update", "Convoy ms/update", "Convoy updates/s", "reference ms/update",
                  "Convoy ÷ reference"]  # fmt: skip
        print(markdown_table(header, rows, [False, True, True, True, True, True]) + "\n", flush=True)
    if args.json:
        write_json(args.json, figures)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Learner updates per second: Convoy's update beside a plain PyTorch one, and the fused MLP node on and off.

Two questions, measured in the same run on the same thread:

1. **Is the fused MLP node worth keeping?** Every algorithm's networks are ``GroupMLP``s, which by default run a
   forward pass through ``learner.fused_mlp`` (one autograd node per MLP). With ``GroupMLP.fused = False`` the same
   weights run layer by layer through autograd. Per algorithm and network size, ms per ``update()`` both ways,
   interleaved (on, off, on, off, ...) so that drift on a shared machine hits both alike; the ratio is plain ÷ fused.
   The rule (issue "a house a newcomer can live in"): keep the node only where it is ≥ 1.3× at the paper's sizes.
2. **How far is Convoy's independent DQN from a textbook one?** The reference is CleanRL's shape: an
   ``nn.Sequential`` of the same widths, ``torch.optim.Adam``, a double-Q Huber TD loss with a target network and
   gradient clipping, on a batch of the same rows (batch × agents, shared weights); the ratio is reference ÷ Convoy.

Sizes: the paper's treadmill networks (hidden 4096 → 12, batch 64) and Convoy's treadmill defaults (256, 256;
batch 128), N = 3 agents + 1 adversary. The replay is filled with random play through each algorithm's own acting
path (``EnvStepper``); DIAL uses its replay variant (``replay=true``), so an update samples like the others.

Run from the repository root: ``python benchmarks/updates.py`` (~3 min); ``--quick`` for a smoke run of seconds;
``--algos`` to choose; ``--json`` to save the figures.
"""

from __future__ import annotations

import argparse
import itertools
import json
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
from torch import nn  # noqa: E402

from benchmarks.report import cpu_model, markdown_table  # noqa: E402
from convoy.actors.stepping import EnvStepper  # noqa: E402
from convoy.algos.nets import GroupMLP  # noqa: E402
from convoy.algos.registry import make_algorithm  # noqa: E402
from convoy.config import PAPER_TREADMILL_HIDDEN, resolve_algo  # noqa: E402
from convoy.envs import make_batched  # noqa: E402

ALGOS = ("idqn", "dqn-ser", "dial", "ims", "ma-mesn", "ma-bon", "ma-mesn-mm", "ma-bon-mm")
SIZES = {"paper (4096, 12), batch 64": (PAPER_TREADMILL_HIDDEN, 64), "default (256, 256), batch 128": ((256, 256), 128)}
QUICK_SIZES = {"quick (64, 32), batch 32": ((64, 32), 32)}
PLAY_STEPS = 64  # random env steps × 16 envs: the replay the updates sample from


def filled(name: str, hidden: tuple[int, ...], batch: int) -> Any:
    """Algorithm ``name`` on the treadmill (3 agents + 1 adversary) with a replay of random play."""
    env = make_batched("treadmill", 16, n_agents=3, n_adversaries=1)
    params: dict[str, Any] = {"hidden": hidden, "batch_size": batch, "learning_starts": 0, "replay_capacity": 4096}
    if name == "dial":
        params.update(replay=True, unroll=8)
    algo = make_algorithm(name, env.spec, resolve_algo(name, "treadmill", params), device="cpu", seed=0)
    stepper = EnvStepper(env, algo, 0)
    for _ in range(PLAY_STEPS):
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


def fused_vs_plain(algo: Any, seconds: float, repeats: int) -> tuple[float, float]:
    """Median ms per update with the fused node and without, interleaved."""
    fused, plain = [], []
    try:
        for _ in range(repeats):
            GroupMLP.fused = True
            fused.append(ms_per_call(algo.update, seconds))
            GroupMLP.fused = False
            plain.append(ms_per_call(algo.update, seconds))
    finally:
        GroupMLP.fused = True
    return statistics.median(fused), statistics.median(plain)


class ReferenceDQN:
    """CleanRL-style double DQN update on ``rows`` observations: nn.Sequential, Adam, Huber TD, clipped gradients."""

    def __init__(self, obs_dim: int, hidden: tuple[int, ...], n_actions: int, rows: int, lr: float) -> None:
        def net() -> nn.Sequential:
            sizes, layers = [obs_dim, *hidden], []
            for a, b in itertools.pairwise(sizes):
                layers += [nn.Linear(a, b), nn.ReLU()]
            return nn.Sequential(*layers, nn.Linear(sizes[-1], n_actions))

        self.q, self.target = net(), net()
        self.target.load_state_dict(self.q.state_dict())
        self.opt = torch.optim.Adam(self.q.parameters(), lr=lr)
        g = torch.Generator().manual_seed(0)
        self.obs, self.next_obs = torch.randn(rows, obs_dim, generator=g), torch.randn(rows, obs_dim, generator=g)
        self.action = torch.randint(0, n_actions, (rows,), generator=g)
        self.reward, self.done = torch.rand(rows, generator=g), torch.zeros(rows)

    def update(self) -> None:
        with torch.no_grad():
            best = self.q(self.next_obs).argmax(dim=1, keepdim=True)
            y = self.reward + 0.95 * (1 - self.done) * self.target(self.next_obs).gather(1, best).squeeze(1)
        q = self.q(self.obs).gather(1, self.action[:, None]).squeeze(1)
        loss = F.smooth_l1_loss(q, y)
        self.opt.zero_grad(set_to_none=True)
        loss.backward()
        nn.utils.clip_grad_norm_(self.q.parameters(), 10.0)
        self.opt.step()


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
            algo = filled(name, hidden, batch)
            fused, plain = fused_vs_plain(algo, args.seconds, args.repeats)
            out[name] = {"fused_ms": fused, "plain_ms": plain, "plain_over_fused": plain / fused}
            rows.append([name, f"{fused:.2f}", f"{plain:.2f}", f"{plain / fused:.2f}"])
        idqn = filled("idqn", hidden, batch)
        spec = idqn.spec
        ref = ReferenceDQN(idqn.obs_dim + spec.n_agents, hidden, spec.n_actions[0], batch * spec.n_agents, 1e-4)
        ref_ms = statistics.median(ms_per_call(ref.update, args.seconds) for _ in range(args.repeats))
        convoy_ms = out["idqn"]["fused_ms"] if "idqn" in out else fused_vs_plain(idqn, args.seconds, args.repeats)[0]
        out["reference_dqn"] = {"ms": ref_ms, "convoy_idqn_ms": convoy_ms, "reference_over_convoy": ref_ms / convoy_ms}
        figures[size_name] = out
        print(f"### {size_name}\n")
        print(markdown_table(["algorithm", "fused ms/update", "plain ms/update", "plain ÷ fused"], rows,
                             [False, True, True, True]))  # fmt: skip
        kept = [r[0] for r in rows if float(r[3]) >= 1.3]
        print(f"\nfused ≥ 1.3× faster for: {', '.join(kept) or 'none'}")
        print(
            f"independent DQN: Convoy {convoy_ms:.2f} ms/update, plain nn.Sequential + Adam reference {ref_ms:.2f} "
            f"ms/update → reference ÷ Convoy = {ref_ms / convoy_ms:.2f}\n",
            flush=True,
        )
    if args.json:
        Path(args.json).write_text(json.dumps(figures, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Environment throughput on one CPU core: the treadmill engine against highway-env and MPE2, measured in one run.

What is measured. Agent-steps per second: one agent-step is one agent receiving one action and returning one
observation and reward, so a step of B envs with N agents each counts B × N. Env-steps per second counts each env
advancing one step (B per batched call). The treadmill engine (``envs.treadmill.TreadmillEngine``) is timed at
B ∈ {1, 64, 1024} envs × N ∈ {2, 4, 8, 16} agents, each env with one adversary car. In the same run and on the
same core the script times

* highway-env ``highway-fast-v0`` with 4 controlled vehicles (``MultiAgentAction`` of ``DiscreteMetaAction``,
  ``MultiAgentObservation`` of ``Kinematics``): the closest off-the-shelf multi-agent driving simulator;
* highway-env ``highway-fast-v0`` as shipped (1 controlled vehicle), for reference;
* MPE2 ``simple_speaker_listener_v4`` (discrete actions, 25-step episodes), the paper's communication task;
* Convoy's own speaker-listener batch (``make_batched("speaker-listener", num_envs=64)``), which loops over MPE2
  envs, to show what the adapter costs;

and prints the ratio of every row's agent-steps/s to highway-env's (4 vehicles) and to MPE2 speaker-listener's.

Why this way.

* One core: the treadmill's claim is that vectorising B envs in numpy beats stepping Python envs one by one, not
  that it uses more cores. BLAS/OpenMP thread pools are capped at 1 before numpy is imported and the process is
  pinned to a single CPU (``os.sched_setaffinity``, where the OS has it).
* Only the environment is timed: actions are drawn beforehand into a small pool (64 entries, cycled), so random
  number generation for the policy is not counted. Episode resets *are* counted, for every env alike (the treadmill
  and the Convoy adapter reset finished envs inside ``step``; highway-env and MPE2 are reset by the loop), because
  a training loop pays for them too.
* Time budgets, not step counts: each measurement runs a few warm-up steps and then steps until at least
  ``--seconds`` (``--baseline-seconds`` for highway-env, which manages only ~30 env-steps/s) have elapsed.
* Noise: the machine may be shared, so every case is measured ``--repeats`` times, in rounds that visit every
  case once (a burst of contention then hits one round of every case rather than all rounds of one). The table
  reports the **median** over repeats, and the best in brackets; ratios and the target check use medians.

Target (from the issue): ≥ 1,000,000 agent-steps/s at B = 1024, N = 4 (highway-env manages ~125).

Run from the repository root: ``python benchmarks/env_throughput.py`` (about a minute with the defaults);
``--quick`` for a smoke test of a few seconds; ``--markdown PATH`` / ``--json PATH`` to also save the figures.
highway-env is in the ``bench`` extra (``pip install -e '.[bench]'``); without it those rows are skipped.
"""

from __future__ import annotations

import os

# Must happen before numpy (or anything importing it) loads, or its thread pools are already sized.
for _var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "NUMEXPR_NUM_THREADS"):
    os.environ[_var] = "1"
os.environ.setdefault("PYGAME_HIDE_SUPPORT_PROMPT", "1")  # highway-env imports pygame

import argparse  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import statistics  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
import warnings  # noqa: E402
from collections.abc import Callable  # noqa: E402
from dataclasses import dataclass, field  # noqa: E402
from importlib import metadata  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402
from report import cpu_model  # noqa: E402 (benchmarks/report.py, next to this script)

from convoy.output import markdown_table as format_table  # noqa: E402

BATCH_SIZES = (1, 64, 1024)
AGENT_COUNTS = (2, 4, 8, 16)
TARGET_B, TARGET_N, TARGET_RATE = 1024, 4, 1_000_000
ACTION_POOL = 64  # pre-drawn action sets, cycled
HIGHWAY_VEHICLES = 4
HIGHWAY_MULTI_AGENT_CONFIG: dict[str, Any] = {
    "controlled_vehicles": HIGHWAY_VEHICLES,
    "action": {"type": "MultiAgentAction", "action_config": {"type": "DiscreteMetaAction"}},
    "observation": {"type": "MultiAgentObservation", "observation_config": {"type": "Kinematics"}},
}
HIGHWAY_KEY = "highway-fast-v0 (4 vehicles)"
MPE_KEY = "mpe2 speaker-listener"


@dataclass
class Case:
    """One thing to time: ``step(i)`` advances it by one (batched) step using pre-drawn action set ``i``."""

    name: str
    num_envs: int
    n_agents: int
    step: Callable[[int], None]
    seconds: float
    warmup: int
    baseline: bool = False
    label: str = ""  # what the table's first column shows (``name`` if empty); B and N have their own columns
    rates: list[float] = field(default_factory=list)  # agent-steps/s, one per repeat
    _calls: int = 0  # keeps cycling the action pool across repeats

    def measure(self) -> float:
        """Warm up, then step until ``seconds`` have passed; records and returns agent-steps/s."""
        for _ in range(self.warmup):
            self._advance()
        clock = time.perf_counter
        calls = 0
        start = clock()
        while True:
            self._advance()
            calls += 1
            elapsed = clock() - start
            if elapsed >= self.seconds:
                break
        rate = self.num_envs * self.n_agents * calls / elapsed
        self.rates.append(rate)
        return rate

    def _advance(self) -> None:
        self.step(self._calls % ACTION_POOL)
        self._calls += 1

    @property
    def median(self) -> float:
        return statistics.median(self.rates)

    @property
    def best(self) -> float:
        return max(self.rates)

    @property
    def env_steps(self) -> float:
        """Median env-steps/s: each of the B envs advancing one step counts once."""
        return self.median / self.n_agents


# --------------------------------------------------------------------------------------------- the cases
def treadmill_case(num_envs: int, n_agents: int, seconds: float, seed: int) -> Case:
    from convoy.envs.treadmill import N_ACTIONS, TreadmillConfig, TreadmillEngine

    engine = TreadmillEngine(TreadmillConfig(n_agents=n_agents, n_adversaries=1), num_envs=num_envs)
    engine.reset(seed)
    rng = np.random.default_rng(seed)
    pool = [rng.integers(0, N_ACTIONS, size=(num_envs, n_agents), dtype=np.int64) for _ in range(ACTION_POOL)]

    def step(i: int) -> None:
        engine.step(pool[i])

    return Case(f"treadmill B={num_envs} N={n_agents}", num_envs, n_agents, step, seconds, warmup=10, label="treadmill")


def highway_case(controlled: int, seconds: float, seed: int) -> Case:
    import gymnasium
    import highway_env  # noqa: F401  (registers the highway-* ids)

    config = HIGHWAY_MULTI_AGENT_CONFIG if controlled > 1 else {}
    env = gymnasium.make("highway-fast-v0", config=config)
    env.reset(seed=seed)
    highway: Any = env.unwrapped  # highway-env's own env class, with its controlled vehicles
    n_agents = len(highway.controlled_vehicles)
    if n_agents != controlled:
        raise RuntimeError(f"highway-env built {n_agents} controlled vehicles, expected {controlled}")
    env.action_space.seed(seed)
    pool = [env.action_space.sample() for _ in range(ACTION_POOL)]  # a tuple of ints per step when multi-agent

    def step(i: int) -> None:
        _, _, terminated, truncated, _ = env.step(pool[i])
        if terminated or truncated:
            env.reset()

    name = HIGHWAY_KEY if controlled > 1 else "highway-fast-v0 (1 vehicle, default)"
    return Case(name, 1, n_agents, step, seconds, warmup=2, baseline=True)


def mpe_case(seconds: float, seed: int) -> Case:
    from mpe2 import simple_speaker_listener_v4

    env = simple_speaker_listener_v4.parallel_env(max_cycles=25, continuous_actions=False)
    env.reset(seed=seed)
    agents = list(env.possible_agents)
    for k, a in enumerate(agents):
        env.action_space(a).seed(seed + k)
    pool = [{a: int(env.action_space(a).sample()) for a in agents} for _ in range(ACTION_POOL)]

    def step(i: int) -> None:
        env.step(pool[i])
        if not env.agents:
            env.reset()

    return Case(MPE_KEY, 1, len(agents), step, seconds, warmup=10, baseline=True)


def adapter_case(num_envs: int, seconds: float, seed: int) -> Case:
    from convoy.envs.registry import make_batched

    batch = make_batched("speaker-listener", num_envs=num_envs)
    batch.reset(seed)
    rng = np.random.default_rng(seed)
    n_actions = np.asarray(batch.spec.n_actions, dtype=np.int64)
    pool = [
        rng.integers(0, n_actions, size=(num_envs, batch.spec.n_agents), dtype=np.int64) for _ in range(ACTION_POOL)
    ]

    def step(i: int) -> None:
        batch.step(pool[i])

    name = f"convoy speaker-listener B={num_envs}"
    label = "Convoy speaker-listener (adapter looping mpe2)"
    return Case(name, num_envs, batch.spec.n_agents, step, seconds, warmup=3, baseline=True, label=label)


# -------------------------------------------------------------------------------------------- reporting
def pin_to_one_core(cpu: int | None) -> int | None:
    """Pin this process to ``cpu`` (default: the lowest allowed); returns the CPU, or None where unsupported."""
    if not hasattr(os, "sched_setaffinity"):
        return None
    allowed = sorted(os.sched_getaffinity(0))
    chosen = allowed[0] if cpu is None else cpu
    if chosen not in allowed:
        raise SystemExit(f"--cpu: CPU {chosen} is not available to this process (allowed: {allowed})")
    os.sched_setaffinity(0, {chosen})
    return chosen


def version(dist: str) -> str:
    try:
        return metadata.version(dist)
    except metadata.PackageNotFoundError:
        return "not installed"


def fmt_rate(x: float) -> str:
    return f"{x:,.0f}" if x >= 100 else f"{x:,.1f}"


def fmt_ratio(x: float | None) -> str:
    if x is None:
        return "—"
    return f"{x:,.0f}×" if x >= 100 else f"{x:,.1f}×" if x >= 1 else f"{x:.2g}×"


def markdown_table(cases: list[Case], refs: dict[str, float | None]) -> str:
    header = [
        "env",
        "B",
        "N",
        "agent-steps/s median (best)",
        "env-steps/s median",
        "× highway-env 4 veh.",
        "× mpe2 spk-lst",
    ]
    right = [False, True, True, True, True, True, True]
    rows = []
    for c in cases:
        ratios = [None if (ref := refs[k]) is None else c.median / ref for k in (HIGHWAY_KEY, MPE_KEY)]
        rows.append(
            [
                c.label or c.name,
                str(c.num_envs),
                str(c.n_agents),
                f"{fmt_rate(c.median)} ({fmt_rate(c.best)})",
                fmt_rate(c.env_steps),
                *map(fmt_ratio, ratios),
            ]
        )
    return format_table(header, rows, right)


def target_line(cases: list[Case]) -> str:
    hit = next((c for c in cases if c.name == f"treadmill B={TARGET_B} N={TARGET_N}"), None)
    goal = f"≥ {TARGET_RATE:,} agent-steps/s at B = {TARGET_B}, N = {TARGET_N}"
    if hit is None:
        return f"Target {goal}: not measured in this run."
    verdict = "MET" if hit.median >= TARGET_RATE else "NOT MET"
    return (
        f"Target {goal}: **{verdict}** (median {fmt_rate(hit.median)}, best {fmt_rate(hit.best)}, "
        f"{hit.median / TARGET_RATE:.2f}× the target)."
    )


# ------------------------------------------------------------------------------------------------- main
def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    p.add_argument("--seconds", type=float, default=1.0, help="time budget per measurement (default 1.0)")
    p.add_argument(
        "--baseline-seconds",
        type=float,
        default=3.0,
        help="time budget per highway-env measurement, which runs only ~30 env-steps/s (default 3.0)",
    )
    p.add_argument("--repeats", type=int, default=3, help="measurements per case; the median is reported (default 3)")
    p.add_argument("--quick", action="store_true", help="smoke test: 0.2 s budgets (1 s for highway-env), 1 repeat")
    p.add_argument("--skip-highway", action="store_true", help="leave out highway-env (it is slow to time)")
    p.add_argument(
        "--batch-sizes", type=int, nargs="+", default=list(BATCH_SIZES), metavar="B", help="treadmill B (1 64 1024)"
    )
    p.add_argument(
        "--agents", type=int, nargs="+", default=list(AGENT_COUNTS), metavar="N", help="treadmill N (2 4 8 16)"
    )
    p.add_argument("--adapter-envs", type=int, default=64, help="B of the Convoy speaker-listener row (0: skip)")
    p.add_argument("--cpu", type=int, default=None, help="CPU to pin to (default: the lowest allowed)")
    p.add_argument("--seed", type=int, default=0, help="seed of the envs and of the pre-drawn actions (default 0)")
    p.add_argument("--markdown", type=Path, metavar="PATH", help="also write the table (Markdown) to PATH")
    p.add_argument("--json", type=Path, metavar="PATH", help="also write every figure as JSON to PATH")
    args = p.parse_args(argv)
    if args.quick:
        args.seconds, args.baseline_seconds, args.repeats = 0.2, 1.0, 1
    if args.seconds <= 0 or args.baseline_seconds <= 0 or args.repeats < 1:
        p.error("--seconds and --baseline-seconds must be > 0 and --repeats ≥ 1")
    return args


def build_cases(args: argparse.Namespace, notes: list[str]) -> list[Case]:
    cases = [treadmill_case(b, n, args.seconds, args.seed) for b in args.batch_sizes for n in args.agents]
    if args.skip_highway:
        notes.append("highway-env skipped (--skip-highway).")
    else:
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # gymnasium's env-checker chatter about highway-env's spaces
                cases.append(highway_case(HIGHWAY_VEHICLES, args.baseline_seconds, args.seed))
                cases.append(highway_case(1, args.baseline_seconds, args.seed))
        except ImportError as exc:
            notes.append(
                f"highway-env skipped: not importable ({exc}); it is in the `bench` extra: pip install -e '.[bench]'."
            )
    try:
        cases.append(mpe_case(args.seconds, args.seed))
        if args.adapter_envs > 0:
            cases.append(adapter_case(args.adapter_envs, args.seconds, args.seed))
    except ImportError as exc:
        notes.append(f"mpe2 skipped: not importable ({exc}).")
    return cases


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    cpu = pin_to_one_core(args.cpu)
    notes: list[str] = []
    began = time.perf_counter()
    cases = build_cases(args, notes)

    for r in range(args.repeats):
        for c in cases:
            print(f"[round {r + 1}/{args.repeats}] {c.name} …", end=" ", file=sys.stderr, flush=True)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                rate = c.measure()
            print(f"{fmt_rate(rate)} agent-steps/s", file=sys.stderr, flush=True)

    by_name = {c.name: c for c in cases}
    refs: dict[str, float | None] = {k: by_name[k].median if k in by_name else None for k in (HIGHWAY_KEY, MPE_KEY)}
    pinned = f"pinned to CPU {cpu}" if cpu is not None else "not pinned (no sched_setaffinity)"
    heading = (
        f"Env throughput on one core ({pinned} of {os.cpu_count()}; {cpu_model()}), "
        f"Python {platform.python_version()}, numpy {version('numpy')}, "
        f"highway-env {version('highway-env')}, mpe2 {version('mpe2')}.  \n"
        f"Median of {args.repeats} × ≥ {args.seconds:g} s per case (≥ {args.baseline_seconds:g} s for highway-env), "
        f"best in brackets; ratios are of medians. Agent-steps/s = B × N × steps/s; resets included."
    )
    table = markdown_table(cases, refs)
    target = target_line(cases)
    text = "\n\n".join([heading, table, target, *notes])
    print(text)
    elapsed = time.perf_counter() - began
    print(f"\n(total {elapsed:.0f} s)", file=sys.stderr)

    if args.markdown:
        args.markdown.parent.mkdir(parents=True, exist_ok=True)
        args.markdown.write_text(text + "\n")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        target_case = by_name.get(f"treadmill B={TARGET_B} N={TARGET_N}")
        payload = {
            "machine": {
                "cpu_model": cpu_model(),
                "pinned_cpu": cpu,
                "cpu_count": os.cpu_count(),
                "python": platform.python_version(),
                "versions": {d: version(d) for d in ("numpy", "highway-env", "mpe2", "gymnasium", "pettingzoo")},
            },
            "settings": {
                "seconds": args.seconds,
                "baseline_seconds": args.baseline_seconds,
                "repeats": args.repeats,
                "seed": args.seed,
                "action_pool": ACTION_POOL,
            },
            "results": [
                {
                    "name": c.name,
                    "baseline": c.baseline,
                    "num_envs": c.num_envs,
                    "n_agents": c.n_agents,
                    "agent_steps_per_s": {"median": c.median, "best": c.best, "all": c.rates},
                    "env_steps_per_s_median": c.env_steps,
                    "ratio_vs_highway_4": None if (highway := refs[HIGHWAY_KEY]) is None else c.median / highway,
                    "ratio_vs_mpe2_speaker_listener": None if (mpe := refs[MPE_KEY]) is None else c.median / mpe,
                }
                for c in cases
            ],
            "target": {
                "num_envs": TARGET_B,
                "n_agents": TARGET_N,
                "agent_steps_per_s": TARGET_RATE,
                "median": None if target_case is None else target_case.median,
                "met": target_case is not None and target_case.median >= TARGET_RATE,
            },
            "elapsed_s": elapsed,
            "notes": notes,
        }
        args.json.write_text(json.dumps(payload, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

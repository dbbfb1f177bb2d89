"""Inference time per env step against the number of agents N, for every algorithm (the paper's section 6.2).

What is measured. For every algorithm in ``algos.registry.ALGORITHMS`` and N ∈ {2, 4, 8, 16, 32, 64} agents on the
treadmill (one adversary, the default 100 × 100 road, which has 625 spawn cells), at the paper's network sizes
(``convoy.config.resolve_algo``: treadmill hidden (4096, 12), 16 message bits, 5 IMS rounds, shared weights), the
wall time of one ``algo.act(obs, 0.0, state)`` call for B = 1 env (``--batch``), i.e. the decision of all N agents
for one env step, including the numpy ↔ torch conversions and ε-greedy bookkeeping an actor pays. Recurrent state
(DIAL's messages from t−1) is carried from call to call as an actor would. The table also gives the parameter count
and the matmul FLOPs of one call (torch's ``FlopCounterMode``; see ``count_flops``), and fits the exponent k of
time ≈ c·N^k by least squares on log-log axes over every N and over the upper half of N (fixed per-call overheads,
a few hundred µs of Python and dispatch, flatten the curve at small N, so the upper half is the better estimate of
the asymptotic order). The same fit on the FLOPs shows the order the architecture implies.

What the paper leads one to expect: MA-BoN ~linear (one broadcast message; only f′'s first layer grows with N, and
linearly), DIAL ~quadratic (each of N agents reads the other N−1 agents' messages, so its input width grows with
(N−1)·bits and N such rows are evaluated), MA-MeSN quadratic-ish for the same reason. With shared weights every
algorithm also appends a one-hot agent id (N columns) to each agent's input, which adds a small N² term everywhere.
The figures are what this machine measures; nothing is asserted.

Device: ``--device`` (default ``cpu``, where ``runtime.actor_device`` puts actors; ``auto``/``cuda`` for a GPU).
``act`` returns numpy actions, so every timed call includes its round trip to the device and back.

Why this way. One thread (``torch.set_num_threads(1)``, ``--threads``) pinned to one core, because an actor runs
per core; warm-up calls first; a time budget per measurement and the median over ``--repeats`` rounds that visit
every case once (a burst of contention on the shared machine hits one round of every case, not every round of one).

Run from the repository root: ``python benchmarks/inference_scaling.py`` (a few minutes); ``--quick`` for a smoke
test of a few seconds (N ∈ {2, 4, 8}, hidden (256, 12)); ``--json``, ``--markdown`` and ``--plot`` (PNG, default
``runs/bench/inference_scaling.png``) save the figures. Algorithms whose module does not import yet are skipped with a
note, so new ones are picked up as they land.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import statistics
import sys
import time
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from scipy import stats

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # run as a script from anywhere
    sys.path.insert(0, str(ROOT))

from benchmarks.report import cpu_model  # noqa: E402
from convoy.algos.algorithm import NetworkAgent  # noqa: E402
from convoy.algos.nets import pick_device  # noqa: E402
from convoy.algos.registry import algorithm_class, make_algorithm  # noqa: E402
from convoy.config import ALGORITHMS, DEVICES, PAPER_TREADMILL_HIDDEN, paper_treadmill_hidden, resolve_algo  # noqa: E402
from convoy.envs.registry import make_batched  # noqa: E402
from convoy.output import markdown_table, pyplot, save_figure  # noqa: E402

ENV = "treadmill"
AGENT_COUNTS = (2, 4, 8, 16, 32, 64)
QUICK_AGENTS = (2, 4, 8)
QUICK_HIDDEN = (256, 12)
OBS_POOL = 16  # distinct observations cycled through, so the policy sees varied inputs
DEFAULT_PLOT = ROOT / "runs" / "bench" / "inference_scaling.png"


# ------------------------------------------------------------------------------------------------- helpers
def count_flops(fn: Callable[[], Any]) -> int:
    """Matmul FLOPs of ``fn()`` as torch's ``FlopCounterMode`` counts them. oneDNN and cuDNN are off while it
    counts: their fused LSTM layer (the memory modules') is one kernel call the counter knows no formula for, and
    counts as 0; without them the same layer runs as the matmuls it is made of, and those are counted."""
    from torch.utils.flop_counter import FlopCounterMode

    with warnings.catch_warnings():  # mkldnn.flags() warns about Intel-GPU TF32 on builds without XPU
        warnings.filterwarnings("ignore", message="TF32 acceleration on top of oneDNN")
        with (
            torch.backends.mkldnn.flags(enabled=False),
            torch.backends.cudnn.flags(enabled=False),
            FlopCounterMode(display=False) as mode,
        ):
            fn()
    return int(mode.get_total_flops())


def importable_algorithms(names: Sequence[str], notes: list[str]) -> list[str]:
    """The registry names whose module imports; the others get a note (they are being written elsewhere)."""
    ok = []
    for name in names:
        try:
            algorithm_class(name)
        except Exception as exc:  # a module in progress can fail in any way at import
            msg = f"{name}: skipped, not importable yet ({type(exc).__name__}: {exc})"
            notes.append(msg)
            print(f"note: {msg}", file=sys.stderr)
        else:
            ok.append(name)
    return ok


def build_algorithm(
    name: str, n_agents: int, num_envs: int, params: dict[str, Any], seed: int, device: torch.device
) -> tuple[Any, Any]:
    """A treadmill batch (N agents + 1 adversary) and algorithm ``name`` at the env's resolved (paper) sizes, its
    networks on ``device``."""
    env = make_batched(ENV, num_envs, n_agents=n_agents, n_adversaries=1)
    cfg = resolve_algo(name, ENV, params)
    algo = make_algorithm(name, env.spec, cfg, device=device, seed=seed)
    return env, algo


def add_device_arg(p: argparse.ArgumentParser, default: str, role: str) -> None:
    """``--device`` with the config's choices (``convoy.config.DEVICES``)."""
    p.add_argument(
        "--device",
        choices=DEVICES,
        default=default,
        help=f"torch device of the networks (default {default}, as {role}; auto = CUDA when present)",
    )


def resolve_device(p: argparse.ArgumentParser, name: str) -> torch.device:
    """The device ``--device`` names, or a usage error that says what to pick instead."""
    if name == "cuda" and not torch.cuda.is_available():
        p.error("--device cuda: torch sees no CUDA device here; use --device auto (CUDA when present) or cpu")
    return pick_device(name)


def synchronize(device: torch.device) -> None:
    """Wait for queued GPU work, so that a clock read after it times the work, not its launch."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def pin_cores(count: int, first: int | None = None) -> list[int] | None:
    """Pin this process to ``count`` CPUs (from ``first``, default the lowest allowed); None where unsupported."""
    if not hasattr(os, "sched_setaffinity"):
        return None
    allowed = sorted(os.sched_getaffinity(0))
    if first is not None and first not in allowed:
        raise SystemExit(f"--cpu: CPU {first} is not available to this process (allowed: {allowed})")
    start = 0 if first is None else allowed.index(first)
    chosen = allowed[start : start + count]
    if len(chosen) < count:
        raise SystemExit(f"--threads {count}: only {len(allowed) - start} CPUs available from CPU {allowed[start]}")
    os.sched_setaffinity(0, set(chosen))
    return chosen


def machine_info(cores: list[int] | None, threads: int, device: torch.device) -> dict[str, Any]:
    return {
        "device": str(device),
        "device_name": torch.cuda.get_device_name(device) if device.type == "cuda" else cpu_model(),
        "cpu_model": cpu_model(),
        "pinned_cpus": cores,
        "cpu_count": os.cpu_count(),
        "torch_threads": threads,
        "python": platform.python_version(),
        "torch": torch.__version__,
        "numpy": np.__version__,
    }


def timed_calls(fn: Callable[[], Any], seconds: float, min_calls: int) -> float:
    """Seconds per call of ``fn``, calling it until ``seconds`` have passed and at least ``min_calls`` times."""
    clock = time.perf_counter
    calls = 0
    start = clock()
    while True:
        fn()
        calls += 1
        elapsed = clock() - start
        if elapsed >= seconds and calls >= min_calls:
            return elapsed / calls


def fmt_count(x: float) -> str:
    """1234567 → 1.23M: parameter and FLOP counts span six orders of magnitude."""
    for unit, scale in (("G", 1e9), ("M", 1e6), ("k", 1e3)):
        if abs(x) >= scale:
            return f"{x / scale:.3g}{unit}"
    return f"{x:.3g}"


def write_outputs(args: argparse.Namespace, text: str, payload: dict[str, Any]) -> None:
    if args.markdown:
        args.markdown.parent.mkdir(parents=True, exist_ok=True)
        args.markdown.write_text(text + "\n")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(payload, indent=2) + "\n")


# ------------------------------------------------------------------------------------------------ the cases
@dataclass
class Case:
    """One (algorithm, N): an algorithm object, a pool of real observations and the carried recurrent state."""

    algo_name: str
    n_agents: int
    batch: int
    algo: NetworkAgent
    obs_pool: list[np.ndarray]
    n_params: int
    flops_per_act: int = 0
    state: Any = None
    seconds_per_act: list[float] = field(default_factory=list)
    _i: int = 0

    def act(self) -> None:
        out = self.algo.act(self.obs_pool[self._i % len(self.obs_pool)], 0.0, self.state)
        self.state = out.state
        self._i += 1

    def measure(self, seconds: float, min_calls: int) -> float:
        t = timed_calls(self.act, seconds, min_calls)
        self.seconds_per_act.append(t)
        return t

    @property
    def median_ms(self) -> float:
        return 1e3 * statistics.median(self.seconds_per_act)

    @property
    def best_ms(self) -> float:
        return 1e3 * min(self.seconds_per_act)


def make_case(
    name: str, n_agents: int, batch: int, params: dict[str, Any], seed: int, warmup: int, device: torch.device
) -> Case:
    """Build the algorithm, record real observations from random play, warm up and count one call's FLOPs."""
    env, algo = build_algorithm(name, n_agents, batch, params, seed, device)
    rng = np.random.default_rng(seed)
    obs = env.reset(seed=seed)
    pool = []
    n_actions = np.asarray(env.spec.n_actions, dtype=np.int64)
    for _ in range(OBS_POOL):
        pool.append(obs)
        obs = env.step(rng.integers(0, n_actions, size=(batch, n_agents))).obs
    env.close()
    case = Case(name, n_agents, batch, algo, pool, algo.n_parameters(), state=algo.initial_state(batch))
    for _ in range(warmup):
        case.act()
    case.flops_per_act = count_flops(case.act)
    return case


# ------------------------------------------------------------------------------------------------- fitting
def log_points(ns: Sequence[float], ys: Sequence[float]) -> tuple[np.ndarray, np.ndarray]:
    """(log N, log y) of the points a fit may use: positive, finite."""
    pts = [(n, y) for n, y in zip(ns, ys, strict=True) if n > 0 and y > 0 and math.isfinite(y)]
    return np.log([n for n, _ in pts]), np.log([y for _, y in pts])


def fit_exponent(ns: Sequence[float], ys: Sequence[float]) -> float | None:
    """Slope k of log y = k log N + log c (least squares); None with fewer than two points or bad values."""
    x, y = log_points(ns, ys)
    if len(set(x.tolist())) < 2:
        return None
    return float(np.polyfit(x, y, 1)[0])


def fit_exponent_ci(ns: Sequence[float], ys: Sequence[float]) -> tuple[float, float] | None:
    """95 % CI of that slope over every measured round (Student-t on the least-squares slope's standard error), so
    a claim "grows quadratically" is judged by the range the timings allow, not by one fitted number."""
    x, y = log_points(ns, ys)
    if len(set(x.tolist())) < 2 or len(x) < 3:
        return None
    fit = stats.linregress(x, y)
    half = float(stats.t.ppf(0.975, len(x) - 2)) * float(fit.stderr)
    return float(fit.slope) - half, float(fit.slope) + half


def upper_half(ns: Sequence[int]) -> list[int]:
    """The larger half of the agent counts (at least two), where fixed per-call overheads matter least."""
    s = sorted(ns)
    return s[min(len(s) // 2, max(len(s) - 2, 0)) :]


def summarise(cases: list[Case], names: list[str], agents: list[int]) -> dict[str, dict[str, Any]]:
    """Per algorithm: times, FLOPs and parameter counts by N, and the fitted exponents."""
    upper = upper_half(agents)
    fits: dict[str, dict[str, Any]] = {}
    for name in names:
        mine = sorted((c for c in cases if c.algo_name == name), key=lambda c: c.n_agents)
        if not mine:
            continue
        ns = [c.n_agents for c in mine]
        ms = [c.median_ms for c in mine]
        fl = [float(c.flops_per_act) for c in mine]
        up = [i for i, c in enumerate(mine) if c.n_agents in upper]
        rounds = [(c.n_agents, 1e3 * t) for c in mine if c.n_agents in upper for t in c.seconds_per_act]
        fits[name] = {
            "agents": ns,
            "ms_per_act": ms,
            "flops_per_act": [c.flops_per_act for c in mine],
            "params": [c.n_params for c in mine],
            "exponent_all": fit_exponent(ns, ms),
            "exponent_upper": fit_exponent([ns[i] for i in up], [ms[i] for i in up]),
            "exponent_upper_ci": fit_exponent_ci([n for n, _ in rounds], [y for _, y in rounds]),
            "upper_agents": [ns[i] for i in up],
            "flops_exponent_all": fit_exponent(ns, fl),
            "flops_exponent_upper": fit_exponent([ns[i] for i in up], [fl[i] for i in up]),
        }
    return fits


# ------------------------------------------------------------------------------------------------ reporting
def fmt_k(k: float | None) -> str:
    return "—" if k is None else f"{k:.2f}"


def fmt_ms(x: float) -> str:
    return f"{x:.3f}" if x < 1 else f"{x:.2f}" if x < 100 else f"{x:.0f}"


def report_table(fits: dict[str, dict[str, Any]], agents: list[int]) -> str:
    upper = upper_half(agents)
    up_label = f"N ≥ {upper[0]}" if upper else "upper"
    header = [
        "algorithm",
        *(f"N={n} ms" for n in agents),
        "k (all N)",
        f"k ({up_label})",
        f"FLOP k ({up_label})",
        f"params N={agents[0]} → {agents[-1]}",
    ]
    right = [False, *([True] * (len(header) - 1))]
    rows = []
    for name, f in fits.items():
        by_n = dict(zip(f["agents"], f["ms_per_act"], strict=True))
        params = dict(zip(f["agents"], f["params"], strict=True))
        rows.append(
            [
                name,
                *(fmt_ms(by_n[n]) if n in by_n else "—" for n in agents),
                fmt_k(f["exponent_all"]),
                fmt_k(f["exponent_upper"]),
                fmt_k(f["flops_exponent_upper"]),
                f"{fmt_count(params.get(agents[0], 0))} → {fmt_count(params.get(agents[-1], 0))}",
            ]
        )
    return markdown_table(header, rows, right)


def plot(fits: dict[str, dict[str, Any]], path: Path, title: str) -> Path:
    """Log-log ms per act against N, with dashed N¹ and N² guides through the plot's middle."""
    plt = pyplot()

    path.parent.mkdir(parents=True, exist_ok=True)
    fig, ax = plt.subplots(figsize=(7, 4.5))
    all_ms = []
    for name, f in fits.items():
        label = f"{name} (k={fmt_k(f['exponent_upper'])})"
        ax.plot(f["agents"], f["ms_per_act"], marker="o", label=label)
        all_ms.extend(f["ms_per_act"])
    ns = sorted({n for f in fits.values() for n in f["agents"]})
    if ns and all_ms:
        mid_n = math.sqrt(ns[0] * ns[-1])
        mid_ms = math.exp(statistics.mean(math.log(m) for m in all_ms))
        xs = np.array([ns[0], ns[-1]], dtype=float)
        for k, style in ((1, ":"), (2, "--")):
            ax.plot(xs, mid_ms * (xs / mid_n) ** k, style, color="grey", lw=1, label=f"∝ N^{k}")
    ax.set_xscale("log", base=2)
    ax.set_yscale("log")
    ax.set_xlabel("agents N")
    ax.set_ylabel("ms per act (one env step, all agents)")
    ax.set_title(title, fontsize=9)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7, loc="upper left")
    save_figure(fig, path)
    return path


# ------------------------------------------------------------------------------------------------------ main
def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    p.add_argument("--agents", type=int, nargs="+", default=list(AGENT_COUNTS), metavar="N", help="agent counts")
    p.add_argument("--algos", nargs="+", default=list(ALGORITHMS), metavar="NAME", help="algorithms (default: all)")
    p.add_argument("--batch", type=int, default=1, help="envs per act call B (default 1)")
    p.add_argument(
        "--hidden", type=int, nargs="+", default=None, metavar="W", help="hidden widths (default: the paper's)"
    )
    p.add_argument("--seconds", type=float, default=0.25, help="time budget per measurement (default 0.25)")
    p.add_argument("--repeats", type=int, default=5, help="measurements per case; the median is reported (default 5)")
    p.add_argument("--warmup", type=int, default=5, help="untimed act calls before measuring (default 5)")
    p.add_argument("--min-calls", type=int, default=3, help="at least this many calls per measurement (default 3)")
    p.add_argument("--threads", type=int, default=1, help="torch intra-op threads, and CPUs pinned (default 1)")
    p.add_argument("--cpu", type=int, default=None, help="first CPU to pin to (default: the lowest allowed)")
    add_device_arg(p, "cpu", "runtime.actor_device: actors act on CPU")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--quick", action="store_true", help="smoke test: N 2 4 8, hidden 256 12, short budgets")
    p.add_argument("--markdown", type=Path, metavar="PATH", help="also write the table (Markdown) to PATH")
    p.add_argument("--json", type=Path, metavar="PATH", help="also write every figure as JSON to PATH")
    p.add_argument("--plot", type=Path, default=DEFAULT_PLOT, metavar="PATH", help=f"PNG (default {DEFAULT_PLOT})")
    args = p.parse_args(argv)
    if args.quick:
        if args.agents == list(AGENT_COUNTS):
            args.agents = list(QUICK_AGENTS)
        args.hidden = args.hidden or list(QUICK_HIDDEN)
        args.seconds, args.repeats, args.warmup, args.min_calls = 0.02, 2, 2, 2
    if args.seconds <= 0 or args.repeats < 1 or args.batch < 1 or args.threads < 1 or min(args.agents) < 1:
        p.error("--seconds must be > 0 and --repeats, --batch, --threads, --agents ≥ 1")
    args.device = resolve_device(p, args.device)
    args.agents = sorted(set(args.agents))
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    cores = pin_cores(args.threads, args.cpu)
    torch.set_num_threads(args.threads)
    began = time.perf_counter()
    notes: list[str] = []
    names = importable_algorithms(args.algos, notes)
    cases: list[Case] = []
    for name in names:
        params: dict[str, Any] = {"hidden": tuple(args.hidden) if args.hidden else paper_treadmill_hidden(name)}
        try:
            for n in args.agents:
                print(f"build {name} N={n} …", file=sys.stderr, flush=True)
                cases.append(make_case(name, n, args.batch, params, args.seed, args.warmup, args.device))
        except Exception as exc:  # an algorithm being written may import but not yet run
            cases = [c for c in cases if c.algo_name != name]
            msg = f"{name}: skipped, failed at N={n} ({type(exc).__name__}: {exc})"
            notes.append(msg)
            print(f"note: {msg}", file=sys.stderr)
    names = [n for n in names if any(c.algo_name == n for c in cases)]

    for r in range(args.repeats):
        for c in cases:
            t = c.measure(args.seconds, args.min_calls)
            print(f"[round {r + 1}/{args.repeats}] {c.algo_name} N={c.n_agents}: {1e3 * t:.3f} ms", file=sys.stderr)

    fits = summarise(cases, names, args.agents)
    hidden = tuple(args.hidden) if args.hidden else PAPER_TREADMILL_HIDDEN
    pinned = f"pinned to CPU {cores}" if cores is not None else "not pinned"
    heading = (
        f"Inference time per env step (one `act` call for B = {args.batch} env, all N agents) on the treadmill "
        f"(N agents + 1 adversary), hidden {hidden}, on {args.device}, {args.threads} torch thread(s) {pinned} of "
        f"{os.cpu_count()} ({cpu_model()}), torch {torch.__version__}.  \n"
        f"Median of {args.repeats} × ≥ {args.seconds:g} s per case, after {args.warmup} warm-up calls. "
        f"k: least-squares slope of log time on log N (time ≈ c·N^k); FLOP k: the same for torch-counted FLOPs."
    )
    table = report_table(fits, args.agents)
    elapsed = time.perf_counter() - began
    plot_path = None
    if fits and args.plot:
        up = upper_half(args.agents)
        title = f"act time vs agents, treadmill, hidden {hidden}, B={args.batch}; k: slope over N ≥ {up[0]}"
        plot_path = plot(fits, args.plot, title)
        notes.append(f"Plot: {plot_path}")
    text = "\n\n".join([heading, table, *notes])
    print(text)
    print(f"\n(total {elapsed:.0f} s)", file=sys.stderr)

    payload = {
        "machine": machine_info(cores, args.threads, args.device),
        "settings": {
            "env": ENV,
            "n_adversaries": 1,
            "agents": args.agents,
            "batch": args.batch,
            "hidden": list(hidden),
            "seconds": args.seconds,
            "repeats": args.repeats,
            "warmup": args.warmup,
            "seed": args.seed,
            "quick": args.quick,
        },
        "results": [
            {
                "algo": c.algo_name,
                "n_agents": c.n_agents,
                "batch": c.batch,
                "ms_per_act": {"median": c.median_ms, "best": c.best_ms, "all": [1e3 * t for t in c.seconds_per_act]},
                "params": c.n_params,
                "flops_per_act": c.flops_per_act,
            }
            for c in cases
        ],
        "fits": fits,
        "plot": None if plot_path is None else str(plot_path),
        "notes": notes,
        "elapsed_s": elapsed,
    }
    write_outputs(args, text, payload)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

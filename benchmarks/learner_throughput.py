"""Learner throughput: updates/s, transitions/s and the fraction of the CPU's matmul peak one ``update()`` reaches.

What is measured. For every algorithm in ``learner.registry.ALGORITHMS`` on the treadmill (N = 3 agents + 1
adversary, ``--agents``) at the paper's network sizes (treadmill hidden (4096, 12), 16 message bits, 5 IMS rounds,
shared weights) and batch size 64 (``--batch-size``, several values allowed):

* the replay is filled with real transitions: a few env steps are played with ε = 1 (random actions, through
  ``algo.act`` so that every extra an algorithm stores — DIAL's received messages and behaviour probabilities, SER's
  episode stamps — is real) and those chunks are observed again and again until the replay holds ``--fill`` rows
  (default: its capacity, 100,000). ``learning_starts`` is 0, so ``can_update()`` holds at once;
* DIAL learns on-policy from whole chunks ``[T = unroll = 32, B, …]``; one update consumes one observed chunk, so a
  chunk is observed (untimed) before every update that needs one. Its B is ``--dial-envs`` (default: the batch
  size), i.e. one DIAL update sees ``batch_size`` sequences of 32 steps — what its replay variant samples — and the
  table's transitions/update says how many steps that is;
* ``update()`` is timed call by call after ``--warmup`` untimed updates: median over ``--repeats`` rounds (each ≥
  ``--seconds``) → updates/s, and transitions/s = transitions per update × updates/s;
* the FLOPs of one update are counted by torch itself (``torch.utils.flop_counter.FlopCounterMode`` around one
  ``update()``: every matmul of the forward passes, the backward pass and the target evaluations, and the fused
  LSTM layers of the memory modules, which torch's own table counts as zero (``benchmarks/flops.py``); elementwise
  work such as ReLU, Gumbel sampling and Adam is not counted, so achieved GFLOP/s is matmul work per second of
  update);
* the peak is torch's own: ``torch.mm`` of two square float32 matrices (``--peak-n``, 2048) with the same thread
  count, measured in the same run, so the fraction of peak compares like with like;
* how far an update is from its own GEMMs: every GEMM one update runs (``mm``, ``addmm``, ``bmm``, ``baddbmm``, and
  the fused LSTM layer calls, whose oneDNN/cuDNN kernels are GEMMs plus gates, with their operands' shapes, strides
  and dtypes, recorded by a ``TorchDispatchMode``) is replayed alone on fresh operands
  of the same layout — *warm* (the same call repeated, operands in cache: the speed the kernels have on these
  shapes) and *cold* (``--flush-mb`` of memory streamed before each call, as inside an update, whose activations
  do not fit the caches) — and the same GEMMs *inside* real updates: each call timed by itself (between device
  synchronisations) while ``update()`` runs, summed per update, median of ``--gemm-repeats`` updates. That sum is
  the update's GEMM time as the update runs it; the rest of ``ms/update`` is the other operators, autograd and
  Python. Where the GEMMs inside the update alone take longer than an update at the target may (its FLOPs ÷ the
  target fraction of the peak), the verdict says so: no change to the other operators reaches the target there,
  only faster GEMMs. Also the aten operator calls per update, and the minor page faults per timed update
  (``getrusage``), which count the fresh activation buffers the allocator had to map. (``torch.profiler`` is not
  used for this: on this torch it inflated the matmuls' self time ~4×.)
* the other side of the roofline: the speed of a streaming read of ``--flush-mb`` MB (``sum``), which is what the
  passes over activations too big for the caches run at.

Device: ``--device`` (default ``auto``, as the learner's ``JobConfig.device``: CUDA when present). Every timed
region is closed by a device synchronisation; on CUDA the peak is ``torch.mm`` on the GPU with torch's default TF32
setting (recorded in the JSON), the "cold" flush streams ``--flush-mb`` through the GPU's L2 instead, and the
streaming read is GPU memory.

Target (from the issue): ≥ 0.5 of the matmul peak at the paper's sizes. It is reported, not asserted.

Run from the repository root: ``python benchmarks/learner_throughput.py`` (a few minutes); ``--quick`` for a smoke
test of a few seconds (hidden (256, 12), small replay and batch); ``--json`` / ``--markdown`` save the figures.
Algorithms whose module does not import yet are skipped with a note.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch.utils._python_dispatch import TorchDispatchMode
from torch.utils._pytree import tree_map

sys.path.insert(0, str(Path(__file__).resolve().parent))  # the sibling script's helpers
from flops import RNN_FLOPS, count_flops, op_flops
from inference_scaling import (
    ENV,
    add_device_arg,
    build_algorithm,
    fmt_count,
    importable_algorithms,
    machine_info,
    pin_cores,
    resolve_device,
    synchronize,
    write_outputs,
)
from report import cpu_model, markdown_table

from convoy.actors.stepping import EnvStepper
from convoy.algos.algorithm import Algorithm, Progress
from convoy.algos.registry import ALGORITHMS
from convoy.config import PAPER_TREADMILL_HIDDEN, paper_treadmill_hidden
from convoy.envs.registry import make_batched
from convoy.learner.runtime import configure_learner

try:
    import resource
except ImportError:  # not on Windows
    resource = None  # type: ignore[assignment]

TARGET_FRACTION = 0.5
DEFAULT_AGENTS = 3
COLLECT_ENVS = 64  # envs played in parallel to gather the real transitions that fill the replay
COLLECT_STEPS = 32  # steps of those envs (2,048 distinct transitions, observed repeatedly)
QUICK_HIDDEN = (256, 12)
GEMM_OPS = frozenset({"mm", "addmm", "bmm", "baddbmm", "mv", "addmv"})


# ------------------------------------------------------------------------------------------------ data
def rusage() -> tuple[int, float]:
    """Minor page faults and kernel seconds so far: a fresh [rows, 4096] activation costs one fault per 4 KiB page
    touched, which on a VM can cost as much as the arithmetic on it."""
    if resource is None:
        return 0, 0.0
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_minflt, r.ru_stime


def collect(algo: Algorithm, env: Any, steps: int, seed: int) -> dict[str, np.ndarray]:
    """``steps`` env steps of random play as one chunk ``[T, B, …]``, with the fields the in-process trainer stores
    plus the algorithm's own extras (the same ``EnvStepper`` the trainer and the actors use)."""
    stepper = EnvStepper(env, algo, seed)
    for _ in range(steps):
        stepper.step(1.0)
    return stepper.take_chunk()


# ------------------------------------------------------------------------------------------------ the cases
@dataclass
class Case:
    """One (algorithm, batch size): a filled learner, the chunk it re-observes, and its timings."""

    algo_name: str
    batch_size: int
    algo: Algorithm
    chunk: dict[str, np.ndarray]
    transitions_per_update: int
    chunk_envs: int
    flops: int = 0
    flops_by_op: dict[str, int] = field(default_factory=dict)
    gemms: dict[str, Any] = field(default_factory=dict)  # see replay_gemms
    gemms_in_update_s: float = 0.0  # see gemms_in_update
    seconds_per_update: list[float] = field(default_factory=list)
    faults_per_update: list[float] = field(default_factory=list)  # minor page faults (fresh buffers touched)
    sys_seconds_per_update: list[float] = field(default_factory=list)  # kernel time, mostly those faults

    def ready(self) -> None:
        """Untimed: give an on-policy learner (DIAL) its next chunk when its queue is empty."""
        if not self.algo.can_update():
            self.algo.observe(self.chunk)
            if not self.algo.can_update():
                raise RuntimeError(f"{self.algo_name}: can_update() is false after observing a chunk")

    def update(self) -> None:
        self.ready()
        self.algo.update()

    def measure(self, seconds: float, min_updates: int) -> float:
        """Mean seconds per update over ≥ ``seconds`` of update time (chunk observation excluded)."""
        clock = time.perf_counter
        spent, calls, faults, sys_s = 0.0, 0, 0, 0.0
        while spent < seconds or calls < min_updates:
            self.ready()
            synchronize(self.algo.device)
            r0, t0 = rusage(), clock()
            self.algo.update()
            synchronize(self.algo.device)
            spent += clock() - t0
            r1 = rusage()
            faults += r1[0] - r0[0]
            sys_s += r1[1] - r0[1]
            calls += 1
        self.seconds_per_update.append(spent / calls)
        self.faults_per_update.append(faults / calls)
        self.sys_seconds_per_update.append(sys_s / calls)
        return spent / calls

    @property
    def median_s(self) -> float:
        return statistics.median(self.seconds_per_update)

    @property
    def updates_per_s(self) -> float:
        return 1.0 / self.median_s

    @property
    def transitions_per_s(self) -> float:
        return self.transitions_per_update * self.updates_per_s

    @property
    def gflops(self) -> float:
        return self.flops * self.updates_per_s / 1e9


def make_case(name: str, batch_size: int, args: argparse.Namespace) -> Case:
    """Build the learner with a small ``learning_starts``, fill its replay with real transitions, warm it up and
    count one update's FLOPs and replay its GEMMs alone."""
    params: dict[str, Any] = {
        "batch_size": batch_size,
        "learning_starts": 0,
        "replay_capacity": max(args.capacity, batch_size),
    }
    params["hidden"] = tuple(args.hidden) if args.hidden else paper_treadmill_hidden(name)
    probe_env, algo = build_algorithm(name, args.agents, 1, params, args.seed, args.device)
    probe_env.close()
    sequential = algo.chunk_len > 1  # DIAL: one update per observed [chunk_len, B] chunk
    envs = (args.dial_envs or batch_size) if sequential else COLLECT_ENVS
    env = make_batched(ENV, envs, n_agents=args.agents, n_adversaries=1)
    chunk = collect(algo, env, algo.chunk_len if sequential else COLLECT_STEPS, args.seed)
    env.close()
    rows = int(np.prod(chunk["terminated"].shape))
    if sequential:
        algo.observe(chunk)
        per_update = rows
    else:
        fill = min(args.fill or algo.cfg.replay_capacity, algo.cfg.replay_capacity)
        while len(algo.replay) < fill:
            algo.observe(chunk)
        per_update = algo.cfg.batch_size
    algo.progress = Progress(env_steps=len(algo.replay), episodes=int(chunk["episode"].max()), total_steps=10**6)
    case = Case(name, batch_size, algo, chunk, per_update, envs)
    for _ in range(args.warmup):
        case.update()
    case.ready()
    case.flops, case.flops_by_op = count_flops(algo.update)
    case.gemms = replay_gemms(record_gemms(case), args.flush_mb, args.gemm_repeats, args.device)
    case.gemms_in_update_s = gemms_in_update(case, args.gemm_repeats)
    return case


@dataclass(frozen=True)
class Layout:
    """A tensor operand of a recorded GEMM, by shape, strides and dtype (the replay makes a fresh one like it)."""

    shape: tuple[int, ...]
    stride: tuple[int, ...]
    dtype: torch.dtype


Recorded = tuple[Any, list[Any]]  # (aten overload, its positional args with every tensor as a Layout)


def record_gemms(case: Case) -> tuple[list[Recorded], int]:
    """Every GEMM of one update — ``GEMM_OPS``, and the fused recurrent layers whose kernels are GEMMs plus gates
    (``flops.RNN_FLOPS``: a CPU ``nn.LSTM`` layer is one oneDNN call) — and the aten op calls."""

    def layout(a: Any) -> Any:
        return Layout(tuple(a.shape), tuple(a.stride()), a.dtype) if isinstance(a, torch.Tensor) else a

    class Recorder(TorchDispatchMode):
        def __init__(self) -> None:
            super().__init__()
            self.gemms: list[Recorded] = []
            self.calls = 0

        def __torch_dispatch__(self, func: Any, types: Any, args: Any = (), kwargs: Any = None) -> Any:
            self.calls += 1
            if is_gemm(func) and not kwargs:
                self.gemms.append((func, tree_map(layout, list(args))))
            return func(*args, **(kwargs or {}))

    case.ready()
    with Recorder() as rec:
        case.algo.update()
    return rec.gemms, rec.calls


def is_gemm(func: Any) -> bool:
    """A matmul (``GEMM_OPS``) or a fused recurrent layer, whose kernel is GEMMs plus gates (``flops.RNN_FLOPS``)."""
    packet = func.overloadpacket
    return packet.__name__ in GEMM_OPS or packet in RNN_FLOPS


class GemmClock(TorchDispatchMode):
    """Times every GEMM call by itself (``is_gemm``, between device synchronisations) while it is active; the
    other operators run untimed. The dispatch costs Python time between operators, never inside a timed call."""

    def __init__(self, device: torch.device) -> None:
        super().__init__()
        self.device = device
        self.seconds = 0.0
        self.calls = 0

    def __torch_dispatch__(self, func: Any, types: Any, args: Any = (), kwargs: Any = None) -> Any:
        if not is_gemm(func):
            return func(*args, **(kwargs or {}))
        synchronize(self.device)
        t0 = time.perf_counter()
        out = func(*args, **(kwargs or {}))
        synchronize(self.device)
        self.seconds += time.perf_counter() - t0
        self.calls += 1
        return out


def gemms_in_update(case: Case, updates: int) -> float:
    """Median seconds per update spent inside its GEMMs, timed call by call during ``updates`` real updates: the
    GEMMs with the caches as the update leaves them, which neither replay reproduces exactly."""
    per_update = []
    for _ in range(updates):
        case.ready()
        with GemmClock(case.algo.device) as clock:
            case.algo.update()
        per_update.append(clock.seconds)
    return statistics.median(per_update)


def gemm_flops(func: Any, args: list[Any]) -> int:
    """2·m·k·n of a GEMM (the last two tensor operands, batched or not); a fused RNN layer's by ``flops.op_flops``."""
    rnn = op_flops(func, args)
    if rnn is not None:
        return rnn
    *_, a, b = [t for t in args if isinstance(t, torch.Tensor)]  # (bias,) a, b
    return 2 * int(np.prod(a.shape)) * (b.shape[-1] if b.dim() > 1 else 1)


def replay_gemms(recorded: tuple[list[Recorded], int], flush_mb: int, repeats: int, device: torch.device) -> dict:
    """The update's GEMMs alone, on fresh operands of the same shapes and strides: seconds warm (each call repeated,
    median) and cold (``flush_mb`` MB streamed before every timed call, median), their FLOPs and the op calls."""
    gemms, calls = recorded
    flush = torch.zeros(max(1, flush_mb) * (1 << 20) // 4, device=device)
    clock = time.perf_counter

    def fresh(a: Any) -> Any:
        if not isinstance(a, Layout):
            return a
        t = torch.empty_strided(a.shape, a.stride, dtype=a.dtype, device=device)
        return t.normal_() if t.is_floating_point() else t.zero_()  # e.g. oneDNN's byte workspace

    def timed(op: Any, operands: list[Any], evict: bool) -> float:
        times = []
        for _ in range(repeats):
            if evict:
                flush.add_(1.0)  # evicts the operands (and everything else) from the caches
            synchronize(device)
            t0 = clock()
            op(*operands)
            synchronize(device)
            times.append(clock() - t0)
        return statistics.median(times)

    warm = cold = 0.0
    flops = 0
    for op, template in gemms:
        operands = tree_map(fresh, template)
        flops += gemm_flops(op, operands)
        op(*operands)
        warm += timed(op, operands, evict=False)
        cold += timed(op, operands, evict=True)
    return {"count": len(gemms), "flops": flops, "warm_s": warm, "cold_s": cold, "op_calls": calls}


# ------------------------------------------------------------------------------------------------ the peak
def matmul_peak(n: int, threads: int, repeats: int, min_seconds: float, device: torch.device) -> dict[str, Any]:
    """torch's own float32 GEMM speed on this device and thread count: ``torch.mm`` of two n × n matrices (on CUDA
    with torch's default TF32 setting, which the learner's matmuls share)."""
    torch.set_num_threads(threads)
    gen = torch.Generator().manual_seed(0)
    a, b = torch.randn(n, n, generator=gen).to(device), torch.randn(n, n, generator=gen).to(device)
    out = torch.empty(n, n, device=device)
    for _ in range(2):
        torch.mm(a, b, out=out)
    rates = []
    for _ in range(repeats):
        clock = time.perf_counter
        synchronize(device)
        calls, start = 0, clock()
        while True:
            torch.mm(a, b, out=out)
            synchronize(device)
            calls += 1
            elapsed = clock() - start
            if elapsed >= min_seconds:
                break
        rates.append(2.0 * n**3 * calls / elapsed / 1e9)
    return {"n": n, "gflops_median": statistics.median(rates), "gflops_best": max(rates), "all": rates}


def read_bandwidth(mb: int, repeats: int, device: torch.device) -> float:
    """GB/s of a streaming read (``sum``) over ``mb`` MB: the other side of the roofline. The paper's thin layers
    (26–58 inputs → 4096 → 12) make an update pass over ``[rows, 4096]`` activations far more often than they fit
    the caches, so this, not the matmul peak, is what the cold GEMMs and the elementwise passes run at."""
    x = torch.ones(max(1, mb) * (1 << 20) // 4, device=device)
    x.sum()
    times = []
    for _ in range(max(3, repeats)):
        synchronize(device)
        start = time.perf_counter()
        x.sum()
        synchronize(device)
        times.append(time.perf_counter() - start)
    return x.numel() * 4 / statistics.median(times) / 1e9


# ------------------------------------------------------------------------------------------------ reporting
def fmt_rate(x: float) -> str:
    return f"{x:,.0f}" if x >= 100 else f"{x:,.1f}" if x >= 10 else f"{x:,.2f}"


def gemm_cell(seconds: float, flops: int, peak: float) -> str:
    return f"{1e3 * seconds:.2f} ({flops / seconds / 1e9 / peak:.2f})" if seconds > 0 else "—"


def report_table(cases: list[Case], peak: float) -> str:
    header = [
        "algorithm",
        "batch",
        "trans./update",
        "ms/update",
        "updates/s",
        "transitions/s",
        "FLOP/update",
        "GFLOP/s",
        "of peak",
        "aten ops/update",
        "GEMMs alone, warm: ms (of peak)",
        "GEMMs alone, cold: ms (of peak)",
        "GEMMs inside the update: ms (of peak)",
        "page faults/update",
    ]
    right = [False, *([True] * 13)]
    rows = []
    for c in cases:
        g = c.gemms
        rows.append(
            [
                c.algo_name,
                f"{c.chunk_envs} seq × {c.algo.chunk_len}" if c.algo.chunk_len > 1 else str(c.batch_size),
                f"{c.transitions_per_update:,}",
                f"{1e3 * c.median_s:.2f}",
                fmt_rate(c.updates_per_s),
                fmt_rate(c.transitions_per_s),
                fmt_count(c.flops),
                fmt_rate(c.gflops),
                f"{c.gflops / peak:.2f}",
                f"{g['op_calls']:,}",
                gemm_cell(g["warm_s"], g["flops"], peak),
                gemm_cell(g["cold_s"], g["flops"], peak),
                gemm_cell(c.gemms_in_update_s, g["flops"], peak),
                f"{statistics.median(c.faults_per_update):,.0f}",
            ]
        )
    return markdown_table(header, rows, right)


def verdict(cases: list[Case], peak: float) -> str:
    if not cases:
        return "No algorithm could be measured."
    hit = [c.algo_name + f" (batch {c.batch_size})" for c in cases if c.gflops / peak >= TARGET_FRACTION]
    best = max(cases, key=lambda c: c.gflops)
    text = (
        f"Target ≥ {TARGET_FRACTION:g} of the matmul peak ({fmt_rate(peak)} GFLOP/s): "
        + (f"**MET** by {', '.join(hit)}." if hit else "**NOT MET** by any algorithm.")
        + f" Best: {best.algo_name} at batch {best.batch_size}, {fmt_rate(best.gflops)} GFLOP/s "
        f"({best.gflops / peak:.2f} of peak)."
    )
    bound = [f"{c.algo_name} (batch {c.batch_size})" for c in cases if gemm_bound(c, peak)]
    if bound:
        text += (
            f" GEMM-bound: for {', '.join(bound)} the GEMMs inside the update alone already take longer than an"
            f" update at {TARGET_FRACTION:g} of the peak may take, so only faster GEMMs (other kernels, another"
            " device) could reach the target there."
        )
    return text


def gemm_bound(case: Case, peak: float) -> bool:
    """Whether the update's GEMMs, as timed inside it, exceed the whole time an update at the target may take (its
    FLOPs ÷ the target fraction of the peak): then no change to the other operators can reach the target."""
    return case.gemms_in_update_s > case.flops / (TARGET_FRACTION * peak * 1e9)


# ------------------------------------------------------------------------------------------------------ main
def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    p.add_argument("--algos", nargs="+", default=list(ALGORITHMS), metavar="NAME", help="algorithms (default: all)")
    p.add_argument("--agents", type=int, default=DEFAULT_AGENTS, help="agents N (+1 adversary; default 3)")
    p.add_argument(
        "--batch-size", type=int, nargs="+", default=[64], metavar="B", help="batch sizes (default 64; try 64 1024)"
    )
    p.add_argument("--dial-envs", type=int, default=None, help="sequences per DIAL update (default: the batch size)")
    p.add_argument(
        "--hidden", type=int, nargs="+", default=None, metavar="W", help="hidden widths (default: the paper's)"
    )
    p.add_argument("--capacity", type=int, default=100_000, help="replay capacity (default 100,000, the config's)")
    p.add_argument("--fill", type=int, default=None, help="rows to fill the replay with (default: its capacity)")
    p.add_argument("--threads", type=int, default=1, help="torch intra-op threads, and CPUs pinned (default 1)")
    p.add_argument("--cpu", type=int, default=None, help="first CPU to pin to (default: the lowest allowed)")
    p.add_argument("--seconds", type=float, default=1.0, help="update time per measurement (default 1.0)")
    p.add_argument("--repeats", type=int, default=3, help="measurements per case; the median is reported (default 3)")
    p.add_argument("--warmup", type=int, default=3, help="untimed updates before measuring (default 3)")
    p.add_argument("--gemm-repeats", type=int, default=9, help="timed calls per GEMM in the replay; median (9)")
    p.add_argument("--flush-mb", type=int, default=64, help="MB streamed before each cold GEMM call (default 64)")
    p.add_argument("--min-updates", type=int, default=2, help="at least this many updates per measurement")
    p.add_argument("--peak-n", type=int, default=2048, help="size of the square matmul that defines the peak")
    add_device_arg(p, "auto", "the learner: JobConfig.device")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--quick", action="store_true", help="smoke test: hidden 256 12, batch 32, small replay")
    p.add_argument("--markdown", type=Path, metavar="PATH", help="also write the table (Markdown) to PATH")
    p.add_argument("--json", type=Path, metavar="PATH", help="also write every figure as JSON to PATH")
    args = p.parse_args(argv)
    if args.quick:
        args.hidden = args.hidden or list(QUICK_HIDDEN)
        if args.batch_size == [64]:
            args.batch_size = [32]
        args.capacity, args.fill = min(args.capacity, 4096), args.fill or 2048
        args.seconds, args.repeats, args.warmup, args.min_updates, args.peak_n = 0.05, 1, 1, 1, 512
        args.gemm_repeats, args.flush_mb = 3, 8
    if (
        args.seconds <= 0
        or args.repeats < 1
        or args.gemm_repeats < 1
        or args.threads < 1
        or args.agents < 1
        or min(args.batch_size) < 1
    ):
        p.error("--seconds must be > 0 and --repeats, --threads, --agents, --batch-size ≥ 1")
    args.device = resolve_device(p, args.device)
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    cores = pin_cores(args.threads, args.cpu)
    configure_learner(args.threads)  # what the learner does: threads + keep big buffers mapped
    began = time.perf_counter()
    notes: list[str] = []
    names = importable_algorithms(args.algos, notes)

    cases: list[Case] = []
    for name in names:
        for bs in args.batch_size:
            print(f"build {name} batch={bs} …", file=sys.stderr, flush=True)
            try:
                cases.append(make_case(name, bs, args))
            except Exception as exc:  # an algorithm being written may import but not yet learn
                msg = f"{name} (batch {bs}): skipped, failed to build or update ({type(exc).__name__}: {exc})"
                notes.append(msg)
                print(f"note: {msg}", file=sys.stderr)

    peak = matmul_peak(args.peak_n, args.threads, max(3, args.repeats), min(args.seconds, 0.5), args.device)
    print(f"peak: torch.mm {args.peak_n}² → {peak['gflops_median']:.1f} GFLOP/s", file=sys.stderr)
    for r in range(args.repeats):
        for c in cases:
            t = c.measure(args.seconds, args.min_updates)
            print(f"[round {r + 1}/{args.repeats}] {c.algo_name} b={c.batch_size}: {1e3 * t:.2f} ms", file=sys.stderr)
    peak_after = matmul_peak(args.peak_n, args.threads, max(3, args.repeats), min(args.seconds, 0.5), args.device)
    peak_rates = peak["all"] + peak_after["all"]  # before and after the updates, so drift shows
    peak_gflops = statistics.median(peak_rates)
    read_gbs = read_bandwidth(args.flush_mb, 9, args.device)

    hidden = tuple(args.hidden) if args.hidden else PAPER_TREADMILL_HIDDEN
    machine = machine_info(cores, args.threads, args.device)
    pinned = f"pinned to CPU {cores}" if cores is not None else "not pinned"
    heading = (
        f"Learner throughput on the treadmill (N = {args.agents} agents + 1 adversary), hidden {hidden}, on "
        f"{args.device} ({machine['device_name']}), {args.threads} torch thread(s) {pinned} of {os.cpu_count()} "
        f"({cpu_model()}), torch {torch.__version__}.  \n"
        f"Median of {args.repeats} × ≥ {args.seconds:g} s of `update()` per case after {args.warmup} warm-up "
        f"updates; replay filled to {args.fill or args.capacity:,} rows. FLOPs: torch's FlopCounterMode over one "
        f"update (matmuls and fused LSTM layers, forward + backward + targets). Peak: torch.mm of "
        f"{args.peak_n}² float32, "
        f"{fmt_rate(peak_gflops)} GFLOP/s (median of {len(peak_rates)}, before and after; best "
        f"{fmt_rate(max(peak_rates))}). GEMMs alone: every GEMM of one update replayed by itself on operands of "
        f"the same shapes and strides, warm (repeated, median of {args.gemm_repeats}) and cold ({args.flush_mb} MB "
        f"streamed before each call), summed, with their fraction of the peak, and the same GEMMs timed call by call "
        f"inside {args.gemm_repeats} real updates (median); memory: a streaming read of "
        f"{args.flush_mb} MB runs at {read_gbs:.1f} GB/s; page faults: minor faults per timed "
        f"update (getrusage). DIAL (on-policy) learns from one chunk of B sequences × unroll steps per update instead "
        f"of a replay sample."
    )
    table = report_table(cases, peak_gflops)
    text = "\n\n".join([heading, table, verdict(cases, peak_gflops), *notes])
    print(text)
    elapsed = time.perf_counter() - began
    print(f"\n(total {elapsed:.0f} s)", file=sys.stderr)

    payload = {
        "machine": machine,
        "settings": {
            "env": ENV,
            "n_agents": args.agents,
            "n_adversaries": 1,
            "batch_sizes": args.batch_size,
            "dial_envs": args.dial_envs,
            "hidden": list(hidden),
            "replay_capacity": args.capacity,
            "fill": args.fill,
            "seconds": args.seconds,
            "repeats": args.repeats,
            "warmup": args.warmup,
            "seed": args.seed,
            "quick": args.quick,
        },
        "peak": {
            "op": "torch.mm float32",
            "device": str(args.device),
            "cuda_tf32": torch.backends.cuda.matmul.allow_tf32 if args.device.type == "cuda" else None,
            "n": args.peak_n,
            "gflops": peak_gflops,
            "gflops_best": max(peak_rates),
            "gflops_before": peak["all"],
            "gflops_after": peak_after["all"],
        },
        "memory_read_gbs": read_gbs,
        "target_fraction": TARGET_FRACTION,
        "results": [
            {
                "algo": c.algo_name,
                "batch_size": c.batch_size,
                "chunk_envs": c.chunk_envs if c.algo.chunk_len > 1 else None,
                "chunk_len": c.algo.chunk_len,
                "transitions_per_update": c.transitions_per_update,
                "params": c.algo.n_parameters(),
                "ms_per_update": {
                    "median": 1e3 * c.median_s,
                    "best": 1e3 * min(c.seconds_per_update),
                    "all": [1e3 * t for t in c.seconds_per_update],
                },
                "page_faults_per_update": statistics.median(c.faults_per_update),
                "sys_ms_per_update": 1e3 * statistics.median(c.sys_seconds_per_update),
                "updates_per_s": c.updates_per_s,
                "transitions_per_s": c.transitions_per_s,
                "flops_per_update": c.flops,
                "flops_by_op": c.flops_by_op,
                "gflops_per_s": c.gflops,
                "fraction_of_peak": c.gflops / peak_gflops,
                "meets_target": c.gflops / peak_gflops >= TARGET_FRACTION,
                "gemms_alone": c.gemms,
                "gemms_in_update_s": c.gemms_in_update_s,
            }
            for c in cases
        ],
        "notes": notes,
        "elapsed_s": elapsed,
    }
    write_outputs(args, text, payload)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

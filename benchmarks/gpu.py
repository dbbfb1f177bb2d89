"""The update on an accelerator: ms per update, eager against captured, at P = 1, 20 and 128 runs, and a
population's aggregate training env-steps/s against one run on one CPU core, measured in the same run.

Per algorithm (independent DQN, MA-MeSN with its Gumbel messages, DIAL with its DRU noise; treadmill defaults, 3
agents + 1 adversary) and population size P: ms per ``update()`` — the replay's sample on the device, loss,
gradients, per-run clip and non-finite guard, Adam, targets — eager, and with ``--hp compile=true`` (one
``torch.compile(fullgraph=True)`` graph; on CUDA also replayed as a CUDA graph), timed over many updates with one
synchronisation per 10, as training runs them (figures are read in batches), after the compile: the median of 5
windows. Beside them, ms per eager ``sample()``: the replay's draw and gather run before the captured step, a floor
under it. Run-updates/s = P × 1000 ÷ ms. Then training: ``convoy train --inprocess`` of P = 20 (and 128)
independent-DQN runs on the device, captured, against one run on one pinned CPU core (1 torch thread), aggregate
env-steps/s = P × steps ÷ wall time (start-up included: users pay it too).

The goals it prints (issue "One code path, on the device"): P = 20 training ≥ 20 × one CPU core's run; a captured
IDQN update ≤ 1 ms at P = 1; P = 128 ≥ 50 k run-updates/s. Compiling dominates the script's time (a graph per
algorithm and P).

Run from the repository root on a machine with a GPU: ``python benchmarks/gpu.py --json docs/figures/gpu.json``.
On an H200 the updates of idqn took a minute and those of MA-MeSN and DIAL at P = 1 and 20 three, mostly compiling;
``--algos`` (none: training only) and ``--train-sizes`` (none: updates only) split it across calls, and every figure
is saved as soon as it is measured. ``--device cpu --quick`` is a smoke run of the same code (a minute on 2 cores).
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import torch  # noqa: E402
from rich.console import Console  # noqa: E402
from rich.table import Table  # noqa: E402

from benchmarks.population import pinned, run_all, train_args  # noqa: E402
from benchmarks.report import cpu_model, write_json  # noqa: E402
from benchmarks.updates import filled  # noqa: E402

ALGOS = ("idqn", "ma-mesn", "dial")
SIZES = (1, 20, 128)
ENVS_PER_RUN = 16
PLAY_STEPS = 32  # random env steps of every run's envs: the replay the updates sample from


def synchronize(device: str) -> None:
    if device.startswith("cuda"):
        torch.cuda.synchronize()


def ms_per_update(agent: Any, device: str, seconds: float, windows: int = 5) -> tuple[float, float]:
    """(ms per update, the median over ``windows`` windows that share ``seconds`` of back-to-back updates; seconds
    the first updates took: the compile). A median, as ``timeit`` repeats: the first window after a compile can
    still share the device and the host with compile workers, GPU clocks and the CUDA-graph pool warming up."""
    t0 = time.perf_counter()
    for _ in range(3):  # the first compiles (captured) or warms the allocator (eager); CUDA graphs record on the 2nd
        agent.update()
    synchronize(device)
    warm_s = time.perf_counter() - t0
    return median_ms(agent.update, device, seconds, windows), warm_s


def median_ms(call: Callable[[], Any], device: str, seconds: float, windows: int = 5) -> float:
    """ms per ``call``: the median over ``windows`` windows that share ``seconds``, each timing calls in blocks of
    10 with one synchronisation per block."""
    per_window = []
    for _ in range(windows):
        n, t0 = 0, time.perf_counter()
        while n == 0 or time.perf_counter() - t0 < seconds / windows:
            for _ in range(10):
                call()
            n += 10
            synchronize(device)
        per_window.append((time.perf_counter() - t0) / n * 1e3)
    return statistics.median(per_window)


def update_figures(algo: str, runs: int, device: str, seconds: float, **params: Any) -> dict[str, float]:
    """ms per update eager and captured, P runs (``params`` over the treadmill's); ms per eager ``sample()`` (the
    replay's draw, outside the captured step); the captured step's CUDA-graph skips (0: it replays as one)."""
    out: dict[str, float] = {}
    for mode, compile in (("eager", False), ("captured", True)):
        torch._dynamo.reset()
        torch._dynamo.utils.counters.clear()
        agent = filled(algo, list(range(runs)), device, PLAY_STEPS, compile=compile, **params)
        ms, warm_s = ms_per_update(agent, device, seconds)
        out[f"{mode}_ms"], out[f"{mode}_warm_s"] = ms, warm_s
        out[f"{mode}_run_updates_per_s"] = runs * 1e3 / ms
    # the replay's draw and gather run eagerly before the captured step (~50 small ops: 0.12 ms of host time at P = 1
    # on a CPU), so they are a floor under the captured figure: timed alone, they say how much of it they are
    out["sample_ms"] = median_ms(agent.sample, device, seconds)
    out["cudagraph_skips"] = float(torch._dynamo.utils.counters["inductor"]["cudagraph_skips"])
    out["speedup"] = out["eager_ms"] / out["captured_ms"]
    return out


def training_figures(sizes: list[int], steps: int, device: str, work: Path, save: Callable[[], None],
                     out: dict[str | int, Any], console: Console) -> None:  # fmt: skip
    """Aggregate env-steps/s of P captured runs on ``device`` and of one run on one pinned CPU core, into ``out``,
    each figure printed and saved as soon as it is measured (a call cut short keeps what it measured)."""
    core = sorted(os.sched_getaffinity(0))[0]
    one = [*train_args("idqn", steps, work / "core"), "--seed", "0", "--device", "cpu", "--threads", "1"]
    t_core = run_all([one], [pinned(core)])
    out.update(cpu_core_steps_per_s=steps / t_core, steps=steps)
    console.print(f"training: one run on one CPU core {steps / t_core:,.0f} env-steps/s ({t_core:.0f} s)")
    save()
    for p in sizes:
        cmd = [*train_args("idqn", steps, work / f"p{p}"), "--seeds", *map(str, range(p)), "--device", device,
               "--hp", "compile=true"]  # fmt: skip
        t = run_all([cmd], [[]])
        out[p] = {"steps_per_s": p * steps / t, "wall_s": t, "ratio": p * t_core / t}
        console.print(f"training: P = {p} on {device} {p * steps / t:,.0f} env-steps/s ({t:.0f} s), "
                      f"{p * t_core / t:.1f}× one CPU core's run")  # fmt: skip
        save()


def recipe(preset: str | None, algo: str) -> dict[str, Any]:
    """The algorithm parameters of ``preset``'s learner (none: the treadmill defaults) under those of
    ``experiments/fig3_centralised.toml``'s mid scale (its batches, learning rate, deterministic messages), the
    compile switch left to the timing."""
    if preset is None:
        return {}
    from convoy.cli.sweep_file import read_file, sweep_body
    from convoy.config import preset_params

    body = sweep_body(read_file(ROOT / "experiments" / "fig3_centralised.toml"), "mid")
    mid = {k: v for k, v in body["base"].get("algo_params", {}).items() if k != "compile"}
    return {**preset_params(preset, algo)[1], **mid, **(body.get("algos") or {}).get(algo, {})}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    device = "cuda" if torch.cuda.is_available() else "cpu"
    p.add_argument("--device", default=device, help="updates' and populations' device (default: cuda if present)")
    p.add_argument("--algos", nargs="*", default=list(ALGOS), choices=ALGOS,
                   help="algorithms whose update is timed (default: all three; none for training only)")  # fmt: skip
    p.add_argument("--sizes", nargs="+", type=int, default=list(SIZES), help="population sizes P (default 1 20 128)")
    p.add_argument("--seconds", type=float, default=2.0, help="timed updates per figure (default %(default)s s)")
    p.add_argument("--train-sizes", nargs="*", type=int, default=[20, 128],
                   help="P trained against one CPU core's run (default 20 128; none to skip)")  # fmt: skip
    p.add_argument("--steps", type=int, default=4000, help="env steps per trained run (default %(default)s)")
    p.add_argument("--preset", choices=["charger"], help="time the updates of a preset's learner recipe (charger: "
                   "entity encoder, 3-step returns, layer norm, Polyak target, policy average; batches of 128 as the "
                   "mid reproduction) instead of the treadmill defaults")  # fmt: skip
    p.add_argument("--quick", action="store_true", help="smoke run: idqn, P = 1 and 2, 0.2 s, 300 steps, P = 2")
    p.add_argument("--json", metavar="PATH", help="also write the figures as JSON")
    args = p.parse_args(argv)
    if args.quick:
        args.algos, args.sizes, args.seconds, args.train_sizes, args.steps = ["idqn"], [1, 2], 0.2, [2], 300
    if args.device == "cpu":
        torch.set_num_threads(1)  # as a learner computes (a job's torch_threads): its updates, not a thread pool's
    console = Console(width=120)
    name = torch.cuda.get_device_name(args.device) if args.device.startswith("cuda") else cpu_model()
    console.print(f"{name}; torch {torch.__version__}; treadmill defaults, {ENVS_PER_RUN} envs per run")
    figures: dict[str, Any] = {"device": name, "torch": torch.__version__, "updates": {}, "training": {}}
    table = Table(title=f"ms per update on {args.device}: eager vs captured")
    columns = ("algo", "P", "eager ms", "captured ms", "×", "captured run-updates/s", "compile s", "graph skips")
    for col in (*columns, "sample ms"):
        table.add_column(col, justify="right")

    def save() -> None:  # as it goes: a call cut short keeps what it measured
        if args.json:
            write_json(args.json, figures)

    for algo in args.algos:
        figures["updates"][algo] = {}
        for size in args.sizes:
            f = update_figures(algo, size, args.device, args.seconds, **recipe(args.preset, algo))
            figures["updates"][algo][size] = f
            console.print(f"{algo} P = {size}: eager {f['eager_ms']:.2f} ms, captured {f['captured_ms']:.2f} ms, "
                          f"eager sample {f['sample_ms']:.2f} ms")  # fmt: skip
            table.add_row(algo, str(size), f"{f['eager_ms']:.2f}", f"{f['captured_ms']:.2f}", f"{f['speedup']:.2f}",
                          f"{f['captured_run_updates_per_s']:,.0f}", f"{f['captured_warm_s']:.0f}",
                          f"{f['cudagraph_skips']:.0f}", f"{f['sample_ms']:.2f}")  # fmt: skip
            save()
    console.print(table)
    if args.train_sizes:
        with tempfile.TemporaryDirectory() as tmp:
            training_figures(args.train_sizes, args.steps, args.device, Path(tmp), save, figures["training"], console)
    goals = []
    idqn = figures["updates"].get("idqn", {})
    if 1 in idqn:
        goals.append(f"captured IDQN update at P = 1: {idqn[1]['captured_ms']:.2f} ms (goal ≤ 1 ms on a GPU)")
    if 128 in idqn:
        goals.append(f"P = 128: {idqn[128]['captured_run_updates_per_s']:,.0f} run-updates/s (goal ≥ 50,000)")
    if 20 in figures["training"]:
        goals.append(f"P = 20 training: {figures['training'][20]['ratio']:.1f}× one CPU core (goal ≥ 20×)")
    for line in goals:
        console.print(line)
    save()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

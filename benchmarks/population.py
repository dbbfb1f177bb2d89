"""Population training beside separate processes: aggregate env-steps/s and ms per update.

For each algorithm at the treadmill defaults and each population size P, the same P runs (seeds 0…P−1, ``--steps``
env steps each) trained two ways, measured in the same run of this script:

* **population** — one ``convoy train --inprocess --seeds 0 … P−1 --threads C`` process (C = the cores this script
  may use): one batched act and one batched update for all runs;
* **separate** — P ``convoy train --inprocess --seed k --threads 1`` processes, C at a time (what a user does today).

Aggregate env-steps/s = P × steps ÷ wall time, from the first process's start to the last one's end (start-up is a
cost users pay too), and the ratio population ÷ separate. Then ms per ``update()`` in this process: a population
of P against P single-run updates (the learner's share of the cost; 1 torch thread and C threads), and how close a
single run's update already comes to one core's matmul peak (what bounds any population's gain on a CPU). With a CUDA
device it also times P = 20 on the GPU against one single-run process on one CPU core, and the GPU update with and
without a CUDA graph.

Run from the repository root: ``python benchmarks/population.py`` (idqn and ma-mesn at P = 1, 2, 5: ~10 min on 2
cores); ``--algos``, ``--sizes``, ``--steps`` to choose; ``--json`` to save the figures.

``--baseline TREE`` instead compares this checkout with another (``git worktree add /tmp/before REV``): the same
P-run population trained by each tree's code, alternating (this, before, before, this, …) ``--repeats`` times each so
that a machine's load falls on both alike, and the median aggregate env-steps/s of each with their ratio.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import torch  # noqa: E402
from rich.console import Console  # noqa: E402
from rich.table import Table  # noqa: E402

from benchmarks import updates  # noqa: E402
from benchmarks.report import cpu_model, write_json  # noqa: E402
from benchmarks.updates import ms_per_call  # noqa: E402

ALGOS = ("idqn", "ma-mesn", "ma-bon", "dial", "ims")
CONVOY = [sys.executable, "-m", "convoy.cli"]


def train_args(algo: str, steps: int, out: Path, eval_episodes: int = 10) -> list[str]:
    """What every run of the comparison trains: the algorithm at the treadmill defaults, the final greedy
    evaluation small (10 episodes; 0 = none, nor its reference policies) and no curve, so that the measurement is
    the training."""
    return [*CONVOY, "train", "--inprocess", "--algo", algo, "--env", "treadmill", "--steps", str(steps),
            "--eval-every", "0", "--eval-episodes", str(eval_episodes), "--no-progress", "--out", str(out)]  # fmt: skip


def run_all(commands: list[list[str]], slots: list[list[str]], code: Path | None = None) -> float:
    """Run ``commands``, as many at a time as there are ``slots`` (a command prefix each: a ``taskset`` pinning
    or nothing), with the ``convoy`` package found in ``code`` if given (``linked_package``); wall seconds for all
    of them."""
    env = {**os.environ, "OMP_NUM_THREADS": "1", **({"PYTHONPATH": str(code)} if code else {})}
    pending, free = list(commands), list(slots)
    running: list[tuple[subprocess.Popen[bytes], list[str]]] = []
    t0 = time.perf_counter()
    while pending or running:
        while pending and free:
            slot = free.pop(0)
            proc = subprocess.Popen(
                [*slot, *pending.pop(0)], env=env, cwd=code, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE
            )  # in ``code``: python -m puts the working folder first on the path
            running.append((proc, slot))
        time.sleep(0.05)
        for proc, slot in list(running):
            if proc.poll() is not None:
                if proc.returncode:
                    err = proc.stderr.read().decode() if proc.stderr is not None else ""
                    raise RuntimeError(f"{proc.args!r} failed:\n{err[-2000:]}")
                running.remove((proc, slot))
                free.append(slot)
    return time.perf_counter() - t0


def linked_package(tree: Path, into: Path) -> Path:
    """A folder whose ``convoy/`` is ``tree``'s code, its folders linked as pyproject's package-dir maps them (as
    ``.ci/typecheck`` does): run from it, ``python -m convoy.cli`` runs that checkout, not the installed one (an
    editable install's finder comes after the path)."""
    import tomllib

    dirs = tomllib.loads((tree / "pyproject.toml").read_text())["tool"]["setuptools"]["package-dir"]
    package = into / "convoy"
    package.mkdir(parents=True)
    for module in (tree / "convoy").glob("*.py"):
        (package / module.name).symlink_to(module.resolve())
    for name, folder in dirs.items():
        if name.count(".") == 1:  # convoy.X is folder X; its subpackages come with it
            (package / name.split(".")[1]).symlink_to((tree / folder).resolve())
    return into


def paired_population(algo: str, p: int, steps: int, threads: int, before: Path, repeats: int, work: Path) -> dict:
    """The same P-run population trained by this checkout's code and by ``before``'s, alternating."""
    seeds = [str(s) for s in range(p)]
    walls: dict[str, list[float]] = {"now": [], "before": []}
    for r in range(repeats):
        for which in ("now", "before") if r % 2 == 0 else ("before", "now"):
            out = work / f"{algo}-{which}-{p}-{r}"
            # no final evaluation: the treadmill's references grew planners since older trees, tens of seconds a run
            cmd = [*train_args(algo, steps, out, eval_episodes=0), "--seeds", *seeds, "--threads", str(threads)]
            walls[which].append(run_all([cmd], [[]], code=before if which == "before" else None))
    now, then = statistics.median(walls["now"]), statistics.median(walls["before"])
    return {"now_steps_per_s": p * steps / now, "before_steps_per_s": p * steps / then, "ratio": then / now,
            "now_wall_s": walls["now"], "before_wall_s": walls["before"]}  # fmt: skip


def compare_trees(args: argparse.Namespace, cores: list[int], console: Console) -> dict[str, Any]:
    """``--baseline``: every algorithm and size, this checkout against the other; a table, the figures."""
    figures: dict[str, Any] = {"cores": len(cores), "cpu": cpu_model(), "steps": args.steps, "repeats": args.repeats,
                               "baseline": str(args.baseline), "algos": {}}  # fmt: skip
    table = Table(title=f"P runs in one population: this checkout vs {args.baseline} (aggregate env-steps/s, median)")
    for col in ("algo", "P", "now", "before", "now ÷ before"):
        table.add_column(col, justify="right")
    with tempfile.TemporaryDirectory() as tmp:
        before = linked_package(Path(args.baseline), Path(tmp) / "before-code")
        for algo in args.algos:
            for size in args.sizes:
                row = paired_population(algo, size, args.steps, len(cores), before, args.repeats, Path(tmp))
                figures["algos"].setdefault(algo, {})[size] = row
                console.print(f"{algo} P = {size}: {row['ratio']:.2f}× {args.baseline}")
                table.add_row(algo, str(size), f"{row['now_steps_per_s']:,.0f}", f"{row['before_steps_per_s']:,.0f}",
                              f"{row['ratio']:.2f}×")  # fmt: skip
                if args.json:
                    write_json(args.json, figures)
    console.print(table)
    return figures


def pinned(core: int) -> list[str]:
    return ["taskset", "-c", str(core)]


def training_throughput(algo: str, p: int, steps: int, cores: list[int], work: Path) -> dict[str, float]:
    """Aggregate env-steps/s of P runs as one population and as separate processes."""
    seeds = [str(s) for s in range(p)]
    c = len(cores)  # the population gets every core as torch threads; separate runs one core each
    pop_cmd = [*train_args(algo, steps, work / f"{algo}-pop{p}"), "--seeds", *seeds, "--threads", str(c)]
    t_pop = run_all([pop_cmd], [[]])
    sep = [[*train_args(algo, steps, work / f"{algo}-{p}-{s}"), "--seed", s, "--threads", "1"] for s in seeds]
    t_sep = run_all(sep, [pinned(core) for core in cores])
    return {
        "population_steps_per_s": p * steps / t_pop,
        "separate_steps_per_s": p * steps / t_sep,
        "ratio": t_sep / t_pop,
        "population_wall_s": t_pop,
        "separate_wall_s": t_sep,
    }


def filled(algo: str, seeds: int | list[int], device: str = "cpu") -> Any:
    """``algo`` at the treadmill defaults (3 agents + 1 adversary) with 2,048 rows of random play per run."""
    return updates.filled(algo, seeds, device, play_steps=128)


def update_cost(algo: str, p: int, threads: int) -> dict[str, float]:
    """ms per population update of P runs beside P single-run updates, with ``threads`` torch threads."""
    torch.set_num_threads(threads)
    single = filled(algo, 0)
    pop = filled(algo, list(range(p)))
    one = ms_per_call(single.update, 2.0)
    many = ms_per_call(pop.update, 2.0)
    return {"single_ms": one, "population_ms": many, "per_run_ms": many / p, "ratio": p * one / many}


def core_peak_gflops() -> float:
    """What one core's float32 matmul reaches at best (a 2048² × 2048² product, 1 thread): the ceiling of any
    update's arithmetic on this CPU."""
    torch.set_num_threads(1)
    a, b = torch.randn(2048, 2048), torch.randn(2048, 2048)
    return 2 * 2048**3 / ms_per_call(lambda: a @ b, 1.0) / 1e6


def update_arithmetic(algo: str, peak_gflops: float) -> dict[str, float]:
    """FLOPs of one single-run update and the share of one core's matmul peak it reaches on 1 thread. A population
    does the same arithmetic per run, so on a CPU the most its update can gain over separate runs is peak ÷ that
    rate: when the single run is near the peak, batching runs has little left to win."""
    from torch.utils.flop_counter import FlopCounterMode

    torch.set_num_threads(1)
    single = filled(algo, 0)
    with FlopCounterMode(display=False) as counter:
        single.update()
    flops = counter.get_total_flops()
    gflops = flops / ms_per_call(single.update, 2.0) / 1e6
    return {"mflop": flops / 1e6, "gflops": gflops, "peak_gflops": peak_gflops, "of_peak": gflops / peak_gflops}


def cuda_figures(algo: str, steps: int, work: Path) -> dict[str, float]:
    """P = 20 on the GPU against one single-run process on one CPU core; GPU update ms at P = 1."""
    seeds = [str(s) for s in range(20)]
    t_gpu = run_all([[*train_args(algo, steps, work / f"{algo}-cuda"), "--seeds", *seeds, "--device", "cuda"]], [[]])
    t_cpu = run_all([[*train_args(algo, steps, work / f"{algo}-core"), "--seed", "0", "--device", "cpu"]], [pinned(0)])
    single = filled(algo, 0, device="cuda")

    def synced() -> None:
        single.update()
        torch.cuda.synchronize()

    return {"gpu_p20_steps_per_s": 20 * steps / t_gpu, "cpu_core_steps_per_s": steps / t_cpu,
            "ratio": 20 * t_cpu / t_gpu, "gpu_update_ms_p1": ms_per_call(synced, 2.0)}  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--algos", nargs="+", default=["idqn", "ma-mesn"], choices=ALGOS)
    p.add_argument("--sizes", nargs="+", type=int, default=[1, 2, 5], help="population sizes P (default 1 2 5)")
    p.add_argument("--steps", type=int, default=6000, help="env steps per run (default %(default)s)")
    p.add_argument("--json", metavar="PATH", help="also write the figures as JSON")
    p.add_argument(
        "--baseline", metavar="TREE", type=Path, help="another checkout (git worktree add TREE REV): its populations"
    )
    p.add_argument("--repeats", type=int, default=3, help="--baseline: trainings per tree (default %(default)s)")
    args = p.parse_args(argv)
    cores = sorted(os.sched_getaffinity(0))
    console = Console()
    if args.baseline:
        paired = compare_trees(args, cores, console)
        if args.json:
            write_json(args.json, paired)
        return 0
    console.print(f"{cpu_model()}, {len(cores)} cores; {args.steps:,} env steps per run, treadmill defaults")
    peak = core_peak_gflops()
    figures: dict[str, Any] = {"cores": len(cores), "cpu": cpu_model(), "steps": args.steps, "algos": {},
                               "core_peak_gflops": peak}  # fmt: skip
    table = Table(title="P runs: one population process vs separate processes (aggregate env-steps/s)")
    for col in ("algo", "P", "population", "separate", "ratio", "update ms: P singles", "population", "ratio"):
        table.add_column(col, justify="right")
    with tempfile.TemporaryDirectory() as tmp:
        for algo in args.algos:
            rows: dict[str | int, dict[str, Any]] = {"arithmetic": update_arithmetic(algo, peak)}
            figures["algos"][algo] = rows
            for size in args.sizes:
                run = training_throughput(algo, size, args.steps, cores, Path(tmp))
                upd = update_cost(algo, size, len(cores))
                rows[size] = {"training": run, "update": upd}
                console.print(f"{algo} P = {size}: {run['ratio']:.2f}× separate processes, update {upd['ratio']:.2f}×")
                if args.json:  # as it goes: a long run that fails later keeps what it measured
                    write_json(args.json, figures)
                table.add_row(
                    algo, str(size), f"{run['population_steps_per_s']:,.0f}", f"{run['separate_steps_per_s']:,.0f}",
                    f"{run['ratio']:.2f}×", f"{size * upd['single_ms']:.1f}", f"{upd['population_ms']:.1f}",
                    f"{upd['ratio']:.2f}×",
                )  # fmt: skip
            if torch.cuda.is_available():
                figures["algos"][algo]["cuda"] = cuda_figures(algo, args.steps, Path(tmp))
    console.print(table)
    for algo, rows in figures["algos"].items():
        a = rows["arithmetic"]
        console.print(
            f"{algo}: one update is {a['mflop']:.0f} MFLOP; a single run does it at {a['gflops']:.0f} GFLOPS on 1 "
            f"thread, {a['of_peak']:.0%} of a core's matmul peak ({peak:.0f}): a population's update can beat P "
            f"single updates by at most {1 / a['of_peak']:.2f}× on this CPU"
        )
        if 5 in rows:
            r = rows[5]["training"]["ratio"]
            console.print(f"{algo}: P = 5 in one process {r:.2f}× the same runs as separate processes (goal ≥ 1.5×)")
        if "cuda" in rows:
            c = rows["cuda"]
            console.print(
                f"{algo} on CUDA: P = 20 {c['ratio']:.1f}× one CPU core's run; update {c['gpu_update_ms_p1']:.2f} ms"
            )
    if args.json:
        write_json(args.json, figures)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

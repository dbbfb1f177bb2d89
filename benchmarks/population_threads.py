"""Can a population's update beat separate processes on a CPU? ms per update of P runs, one process, four ways.

For each algorithm at the treadmill defaults (P = 5 runs, replay filled with random play): P single-run updates
one after another on one torch thread; the population's one batched update on one thread and on two; and the
population split into two shards (⌈P/2⌉ + ⌊P/2⌋ runs) updating at once in two Python threads with one torch
thread each (persistent worker threads, 20 updates per hand-off). Two separate processes would take half the
singles' time: each figure is also given against that.

Run from the repository root: ``python benchmarks/population_threads.py`` (~2 min on 2 cores; ``--algos``).
"""

from __future__ import annotations

import argparse
import queue
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import torch  # noqa: E402

from benchmarks.population import filled  # noqa: E402
from convoy.algos.algorithm import Agent  # noqa: E402


def seconds_per_call(fn: Callable[[], object], seconds: float) -> float:
    fn()
    n, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        fn()
        n += 1
    return (time.perf_counter() - t0) / n


class Worker(threading.Thread):
    """Runs ``n`` updates of its agent per hand-off, in its own thread."""

    def __init__(self, agent: Agent) -> None:
        super().__init__(daemon=True)
        self.agent = agent
        self.todo: queue.Queue[int] = queue.Queue()
        self.done: queue.Queue[int] = queue.Queue()
        self.start()

    def run(self) -> None:
        while True:
            n = self.todo.get()
            for _ in range(n):
                self.agent.update()
            self.done.put(n)


def measure(algo: str, p: int, seconds: float) -> dict[str, float]:
    torch.set_num_threads(1)
    single = seconds_per_call(filled(algo, 0).update, seconds)
    pop = filled(algo, list(range(p)))
    pop1 = seconds_per_call(pop.update, seconds)
    torch.set_num_threads(2)
    pop2 = seconds_per_call(pop.update, seconds)
    torch.set_num_threads(1)
    seeds = list(range(p))
    workers = [Worker(filled(algo, seeds[: (p + 1) // 2])), Worker(filled(algo, seeds[(p + 1) // 2 :]))]

    def sharded() -> None:
        for w in workers:
            w.todo.put(20)
        for w in workers:
            w.done.get()

    shards = seconds_per_call(sharded, seconds) / 20
    return {"singles_ms": p * single * 1e3, "population_1t_ms": pop1 * 1e3, "population_2t_ms": pop2 * 1e3,
            "shards_ms": shards * 1e3, "two_processes_ms": p * single / 2 * 1e3}  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--algos", nargs="+", default=["idqn", "ma-mesn"], help="(default %(default)s)")
    ap.add_argument("--runs", type=int, default=5, help="P (default %(default)s)")
    ap.add_argument("--seconds", type=float, default=5.0, help="timing per figure (default %(default)s)")
    args = ap.parse_args(argv)
    for algo in args.algos:
        f = measure(algo, args.runs, args.seconds)
        two = f["two_processes_ms"]
        print(f"{algo}, P = {args.runs}: {args.runs} single updates {f['singles_ms']:.1f} ms (two processes: "
              f"{two:.1f} ms); population 1 thread {f['population_1t_ms']:.1f} ms, 2 threads "
              f"{f['population_2t_ms']:.1f} ms ({two / f['population_2t_ms']:.2f}× two processes); two shards in two "
              f"threads {f['shards_ms']:.1f} ms ({two / f['shards_ms']:.2f}×)")  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""The treadmill's searched references (issue 31): what a reviewer would try before believing a learner's figure.

On tuning episodes (seed ``TUNING_SEED``) it searches open-loop policies — every constant action, every cycle of
``references.cycle_family`` up to ``--max-period`` (constants, block cycles "a × k then b × m", weaves) and a
cross-entropy search over ``max_steps``-long sequences, shared and per agent, seeded with the best cycles — and tunes
the reactive driver family (``envs.treadmill.drivers``) on a grid, three times: private observation, told what the
teammates observe, told a 16-bit code per teammate. Then it scores each choice on ``--episodes`` other episodes (seed
``SCORING_SEED``, the same episodes for every policy) with 95 % CIs, beside full information and random, and prints
the paired ratios the treadmill is built for:

* best open-loop ÷ tuned private driver (goal ≤ 0.5);
* team driver ÷ tuned private driver (goal ≥ 1.3) and 16-bit team driver ÷ tuned private driver (goal ≥ 1.2), each
  with a paired 95 % CI (same episodes) that must exclude 1.

Run: ``python benchmarks/treadmill_search.py`` (a few minutes on one core); ``--quick`` for a smaller
search; ``--set KEY=VALUE`` changes a rule.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402
from rich.console import Console  # noqa: E402
from rich.table import Table  # noqa: E402

from benchmarks.report import write_json  # noqa: E402
from convoy.cli.args import parse_pairs  # noqa: E402
from convoy.envs.treadmill import TreadmillConfig  # noqa: E402
from convoy.envs.treadmill.config import V2_RULES  # noqa: E402
from convoy.envs.treadmill.references import (  # noqa: E402
    SCORING_SEED,
    driver_grid,
    driver_returns,
    full_information_returns,
    open_loop_search,
    paired_ratio,
    random_returns,
    sequence_returns,
    tune_driver,
)
from convoy.stats import ci95_half  # noqa: E402
from convoy.validation import build_config  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument(
        "--rules", choices=("default", "v2"), default="default", help="rule set: the defaults or the second set"
    )
    p.add_argument("--episodes", type=int, default=500, help="scoring episodes per policy (default %(default)s)")
    p.add_argument(
        "--tune-episodes", type=int, default=300, help="tuning episodes per grid point (default %(default)s)"
    )
    p.add_argument("--max-period", type=int, default=32, help="longest open-loop cycle searched (default %(default)s)")
    p.add_argument("--quick", action="store_true", help="smaller grids and searches (a smoke test)")
    p.add_argument("--set", action="append", metavar="KEY=VALUE", help="treadmill parameter, repeatable")
    p.add_argument("--json", metavar="PATH", help="also write the figures as JSON")
    args = p.parse_args(argv)
    base = V2_RULES if args.rules == "v2" else {}
    cfg = build_config(TreadmillConfig, **(base | parse_pairs(args.set, "--set")))
    console = Console(width=200)
    start = time.perf_counter()

    chosen = open_loop_search(cfg, args.max_period, quick=args.quick)
    returns: dict[str, np.ndarray] = {}
    notes: dict[str, str] = {}
    for name, (seq, tuned) in chosen.items():
        seq = seq[None]  # one sequence: [T] shared or [N, T] per agent
        returns[name] = sequence_returns(cfg, seq, args.episodes, SCORING_SEED)[0]
        notes[name] = f"tuning {tuned:.1f}"
    grid = driver_grid(args.quick)
    params = {}
    for kind in ("private", "team", "team16"):
        params[kind], tuned = tune_driver(cfg, kind, grid, args.tune_episodes)
        returns[f"{kind} driver"] = driver_returns(cfg, kind, params[kind], args.episodes, SCORING_SEED)
        notes[f"{kind} driver"] = f"tuning {tuned:.1f}; {params[kind].label()}"
    returns["full information"] = full_information_returns(cfg, args.episodes, SCORING_SEED)
    returns["random"] = random_returns(cfg, args.episodes, SCORING_SEED)

    table = Table(title=f"treadmill references ({args.rules} rules): {args.episodes} scoring episodes each")
    for col in ("policy", "return per agent (95 % CI)", "chosen on tuning episodes"):
        table.add_column(col, justify="left" if col != "return per agent (95 % CI)" else "right")
    for name, r in returns.items():
        table.add_row(name, f"{r.mean():.1f} ± {ci95_half(r):.1f}", notes.get(name, ""))
    console.print(table)
    private = returns["private driver"]
    open_loop = [n for n in returns if n.startswith("open-loop")]
    best_open = max(open_loop, key=lambda n: returns[n].mean())
    ratios = {
        "best open-loop ÷ private": paired_ratio(returns[best_open], private),
        "team ÷ private": paired_ratio(returns["team driver"], private),
        "team16 ÷ private": paired_ratio(returns["team16 driver"], private),
    }
    goals = {"best open-loop ÷ private": "≤ 0.5", "team ÷ private": "≥ 1.3", "team16 ÷ private": "≥ 1.2"}
    for name, r in ratios.items():
        console.print(
            f"{name}: {r['ratio']:.2f} ± {r['ratio_ci95']:.2f} (goal {goals[name]}); paired difference "
            f"{r['diff']:+.1f} ± {r['diff_ci95']:.1f}" + (f"  [best open-loop: {best_open}]" if "open" in name else "")
        )
    console.print(f"({time.perf_counter() - start:.0f} s)")
    if args.json:
        figures = {
            n: {"mean": float(r.mean()), "ci95": ci95_half(r), "note": notes.get(n, "")} for n, r in returns.items()
        }
        write_json(
            args.json,
            {
                "config": cfg.model_dump(),
                "episodes": args.episodes,
                "policies": figures,
                "ratios": ratios,
                "params": {k: v.label() for k, v in params.items()},
            },
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

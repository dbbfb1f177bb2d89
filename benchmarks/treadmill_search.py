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

Then the model-predictive planner (``envs.treadmill.planner``), at each information level — its own sensor, a 16-bit
word per teammate, its teammates' observations, every car — tuned by the same cross-entropy search (``--planner-*``
flags: the budget, the same for every level, each started from ``planner.START``) and scored on the same episodes:
the strongest policy Convoy has for each level, so the ratios that say what teammates' knowledge is worth are taken
against the private planner (goals: private planner ≥ 1.6 × the tuned private driver; team and 16-bit planners
≥ 1.3 × the private planner, paired CIs excluding 1; best open loop ≤ 0.3 × the private planner).

Run: ``python benchmarks/treadmill_search.py`` (about an hour on one core, most of it the planners' tuning);
``--part planners --json docs/figures/treadmill_search.json`` redoes only the planners and keeps the rest of that
file, ``--part others`` the rest and keeps the planners; ``--quick`` for a smaller search; ``--set KEY=VALUE``
changes a rule.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402
from rich.console import Console  # noqa: E402
from rich.table import Table  # noqa: E402

from benchmarks.report import write_json  # noqa: E402
from convoy.cli.args import parse_pairs  # noqa: E402
from convoy.envs.treadmill import (  # noqa: E402
    TreadmillConfig,
    planner,
)
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
    p.add_argument(
        "--part",
        choices=("all", "planners", "others"),
        default="all",
        help="all: every reference; planners: only the planners, the rest kept from --json's file; others: every "
        "reference but the planners, which keep their parameters from --json's file and are scored again "
        "(default: all)",
    )
    p.add_argument(
        "--planner-iterations",
        type=int,
        default=6,
        help="cross-entropy iterations per level; 0 scores the planners as tuned (planner.tuned_for: on these rules "
        "where a search ran on them, else on the default rules), e.g. on other rules (default %(default)s)",
    )
    p.add_argument("--planner-population", type=int, default=12, help="candidates per iteration (default %(default)s)")
    p.add_argument(
        "--planner-episodes", type=int, default=64, help="tuning episodes per candidate (default %(default)s)"
    )
    p.add_argument(
        "--levels",
        nargs="+",
        choices=planner.LEVELS,
        default=list(planner.LEVELS),
        help="information levels whose planner is tuned; with --part planners the others keep their parameters from "
        "--json's file and are only scored again (default: all)",
    )
    p.add_argument("--workers", type=int, default=1, help="levels tuned in parallel processes (default %(default)s)")
    args = p.parse_args(argv)
    base = V2_RULES if args.rules == "v2" else {}
    cfg = build_config(TreadmillConfig, **(base | parse_pairs(args.set, "--set")))
    console = Console(width=200)
    start = time.perf_counter()
    returns: dict[str, np.ndarray] = {}
    notes: dict[str, str] = {}
    kept: dict = {}
    refs: dict[str, np.ndarray] = {}
    drivers: dict = {}
    if args.part != "all":
        kept = _kept(args.json, cfg, args.episodes)
    if args.part == "planners" and kept:
        refs = kept_references(cfg, kept, args.episodes)
    if args.part != "planners":
        drivers = open_loop_and_drivers(cfg, args, returns, notes)
    if args.part == "others":
        args.levels = []  # every level keeps the kept file's planner (one missing from it is tuned)
    tuned = tune_planners(cfg, args, kept, returns, notes)

    rules = f"{args.rules} rules" + "".join(f", {pair}" for pair in args.set or [])
    table = Table(title=f"treadmill references ({rules}): {args.episodes} scoring episodes each")
    for col in ("policy", "return per agent (95 % CI)", "chosen on tuning episodes"):
        table.add_column(col, justify="left" if col != "return per agent (95 % CI)" else "right")
    for name, r in returns.items():
        table.add_row(name, f"{r.mean():.1f} ± {ci95_half(r):.1f}", notes.get(name, ""))
    console.print(table)
    every = refs | returns
    ratios = {} if args.part == "planners" else driver_ratios(every)
    ratios |= planner_ratios(every)
    for name, r in ratios.items():
        console.print(
            f"{name}: {r['ratio']:.2f} ± {r['ratio_ci95']:.2f} (goal {GOALS[name]}); paired difference "
            f"{r['diff']:+.1f} ± {r['diff_ci95']:.1f}"
        )
    console.print(f"({time.perf_counter() - start:.0f} s)")
    if args.json:
        figures = {
            n: {"mean": float(r.mean()), "ci95": ci95_half(r), "note": notes.get(n, "")} for n, r in returns.items()
        }
        out = kept | {"config": cfg.model_dump(), "episodes": args.episodes}
        out["policies"] = kept.get("policies", {}) | figures
        out["ratios"] = kept.get("ratios", {}) | ratios
        out["episode_returns"] = {n: v.tolist() for n, v in every.items() if n in PAIRED}
        out["planners"] = {level: p.label() for level, p in tuned.items()}
        out["planner_budget"] = planner_budget(args) | {"start": planner.START.label()}
        if args.part != "planners":
            out["params"] = {k: v.label() for k, v in drivers.items()}
        write_json(args.json, out)
    return 0


def _kept(path: str | None, cfg: TreadmillConfig, episodes: int) -> dict:
    """The earlier figures at ``path`` that ``--part planners`` keeps: only if measured on these rules and episodes
    (otherwise the planners are written alone, ratios among themselves)."""
    if not path or not Path(path).is_file():
        return {}
    kept = json.loads(Path(path).read_text())
    same_rules = TreadmillConfig(**kept.get("config", {})) == cfg  # a rule added since keeps its default
    if not same_rules or kept.get("episodes") != episodes:
        print(f"{path}: other rules or scoring episodes; the planners are written alone", flush=True)
        return {}
    return kept


def kept_references(cfg: TreadmillConfig, kept: dict, episodes: int) -> dict[str, np.ndarray]:
    """Per-episode returns of the kept file's tuned private driver and best open-loop policy (a constant on the
    default rules), replayed on the scoring episodes: what the planners' paired ratios need."""
    from convoy.envs.treadmill.references import TUNED

    out = {"private driver": driver_returns(cfg, "private", TUNED["private"], episodes, SCORING_SEED)}
    open_loop = {n: v["mean"] for n, v in kept["policies"].items() if n.startswith("open-loop")}
    best = max(open_loop, key=open_loop.__getitem__, default="")  # none in a file of planners alone
    if "constant-" in best:
        action = int(best.rsplit("-", 1)[1])
        out["best open loop"] = sequence_returns(cfg, np.full((1, cfg.max_steps), action), episodes, SCORING_SEED)[0]
    return out


PAIRED = ("private driver", *(f"{level} planner" for level in planner.LEVELS), "best open loop")
GOALS = {
    "best open-loop ÷ private": "≤ 0.5",
    "team ÷ private": "≥ 1.3",
    "team16 ÷ private": "≥ 1.2",
    "private planner ÷ private driver": "≥ 1.6",
    "team planner ÷ private planner": "≥ 1.3",
    "team16 planner ÷ private planner": "≥ 1.3",
    "full planner ÷ private planner": "",
    "best open loop ÷ private planner": "≤ 0.3",
}


def open_loop_and_drivers(cfg: TreadmillConfig, args, returns: dict, notes: dict) -> dict:
    """The open-loop search and the reactive drivers' grids, each scored on the scoring episodes; returns the
    drivers' chosen parameters by kind."""
    chosen = open_loop_search(cfg, args.max_period, quick=args.quick)
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
    open_loop = [n for n in returns if n.startswith("open-loop")]
    returns["best open loop"] = returns[max(open_loop, key=lambda n: returns[n].mean())]
    return params


def tune_planners(cfg: TreadmillConfig, args, kept: dict, returns: dict, notes: dict) -> dict:
    """Each information level's planner tuned with the same budget from the same start (``--levels``; the others keep
    the kept file's parameters), then scored on the scoring episodes; returns the chosen parameters per level."""
    budget = planner_budget(args)
    todo = [level for level in planner.LEVELS if level in args.levels or level not in kept.get("planners", {})]
    with ProcessPoolExecutor(max_workers=args.workers) as pool:
        jobs = {level: pool.submit(_tune_level, cfg, level, budget, args.episodes) for level in todo}
        tuned = {}
        for level in planner.LEVELS:
            if level in jobs:
                tuned[level], value, scores = jobs[level].result()
                tuning = f"tuning {value:.1f}" if np.isfinite(value) else "as tuned on the default rules"
                notes[f"{level} planner"] = f"{tuning}; {tuned[level].label()}"
            else:
                tuned[level] = planner.PlannerParams.from_label(kept["planners"][level])
                scores = planner.planner_returns(cfg, level, tuned[level], args.episodes, SCORING_SEED)
                notes[f"{level} planner"] = kept["policies"][f"{level} planner"]["note"]
            returns[f"{level} planner"] = scores
    return tuned


def planner_budget(args) -> dict[str, int]:
    """The cross-entropy budget every level gets (``--quick``: a smoke test's)."""
    if args.quick:
        return {"iterations": min(1, args.planner_iterations), "population": 3, "episodes": 2}
    return {
        "iterations": args.planner_iterations,
        "population": args.planner_population,
        "episodes": args.planner_episodes,
    }


def _tune_level(cfg: TreadmillConfig, level: str, budget: dict, episodes: int):
    """One level's tuning and scoring (a worker process: levels tune in parallel with ``--workers``)."""
    start = time.perf_counter()
    log = lambda line: print(f"  {line} ({time.perf_counter() - start:.0f} s)", flush=True)  # noqa: E731
    if budget["iterations"] == 0:  # score the planners as tuned, on these rules or the defaults
        params, value = planner.tuned_for(cfg)[level], float("nan")
    else:
        params, value = planner.tune_planner(cfg, level, start=planner.START, log=log, **budget)
    return params, value, planner.planner_returns(cfg, level, params, episodes, SCORING_SEED)


def driver_ratios(returns: dict[str, np.ndarray]) -> dict[str, dict[str, float]]:
    private = returns["private driver"]
    return {
        "best open-loop ÷ private": paired_ratio(returns["best open loop"], private),
        "team ÷ private": paired_ratio(returns["team driver"], private),
        "team16 ÷ private": paired_ratio(returns["team16 driver"], private),
    }


def planner_ratios(returns: dict[str, np.ndarray]) -> dict[str, dict[str, float]]:
    """Paired ratios against the private planner, the strongest private policy (and it against the driver)."""
    private = returns["private planner"]
    out = {}
    if "private driver" in returns:
        out["private planner ÷ private driver"] = paired_ratio(private, returns["private driver"])
    for level in ("team", "team16", "full"):
        out[f"{level} planner ÷ private planner"] = paired_ratio(returns[f"{level} planner"], private)
    if "best open loop" in returns:
        out["best open loop ÷ private planner"] = paired_ratio(returns["best open loop"], private)
    return out


if __name__ == "__main__":
    raise SystemExit(main())

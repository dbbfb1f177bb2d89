"""Where teammates' knowledge could pay: the planners tuned on the default rules, scored on other rules.

On the default rules a model-predictive planner on its own sensor scores ~90 % of the most an agent can score, and
told its teammates' observations (or every car) it gains nothing measurable (``docs/treadmill.md``). This screen plays
the four planners (``planner.TUNED``, as tuned on the default rules: not re-tuned, so a variant's ratios are only a
first look) on rule variants that take information away from the private agent — a hidden chaser, more chasers, a
narrower or shorter sensor, a more aggressive chaser, slower cars — and prints, per variant, each level's return and
the paired ratios to the private planner. A variant worth a new rule set shows the private planner well below the
ceiling *and* team ÷ private ≥ 1.3 with its CI above 1; it then needs each level re-tuned
(``benchmarks/treadmill_search.py --part planners --set …``).

Resumable: each variant's figures are written to ``--cache DIR/NAME.json`` as it ends, and a variant whose file is
there, or whose figures the ``--json`` file holds for the same episodes, is not played again. Run:
``python benchmarks/treadmill_variants.py --json docs/figures/treadmill_variants.json`` (about 3 minutes a variant on
one core).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.report import write_json  # noqa: E402
from benchmarks.treadmill_search import main as search  # noqa: E402

VARIANTS: dict[str, dict[str, str]] = {
    "the chaser hidden from its target": {"adversary_stealth": "true"},
    "two chasers": {"n_adversaries": "2"},
    "a 180° sensor": {"sensor_fov": "180"},
    "a 30-cell sensor": {"sensor_range": "30"},
    "aggression 0.9": {"aggression": "0.9"},
    "two hidden chasers": {"adversary_stealth": "true", "n_adversaries": "2"},
    "top speed 2, belt 1": {"max_speed": "2", "treadmill_speed_max": "1"},
    "4 agents, 2 chasers": {"n_agents": "4", "n_adversaries": "2"},
    "a chaser faster than the agents (5)": {"adversary_speed": "5"},
    "a hidden chaser faster than the agents (5)": {"adversary_stealth": "true", "adversary_speed": "5"},
}
LEVELS = ("private", "team", "full")  # the 16-bit word is a design of its own, judged where the rules are chosen


def file_name(sets: dict[str, str]) -> str:
    return "_".join(f"{k}-{v}" for k, v in sets.items()) + ".json"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--episodes", type=int, default=200, help="scoring episodes per policy (default %(default)s)")
    p.add_argument("--cache", default="runs/variants", help="folder of each variant's figures (default %(default)s)")
    p.add_argument("--json", metavar="PATH", help="also write every variant's figures as one JSON")
    args = p.parse_args(argv)
    cache = Path(args.cache)
    out: dict[str, dict] = {}
    done = json.loads(Path(args.json).read_text()) if args.json and Path(args.json).is_file() else {}
    for label, sets in VARIANTS.items():
        earlier = done.get("variants", {}).get(label)
        if done.get("episodes") == args.episodes and earlier and earlier["sets"] == sets:
            out[label] = earlier  # measured before: the --json file is a cache too
            print(f"{label}: kept from {args.json}", flush=True)
            continue
        path = cache / file_name(sets)
        kept = json.loads(path.read_text()) if path.is_file() else None
        if kept is None or kept.get("episodes") != args.episodes:
            print(f"{label}: playing the planners on {args.episodes} episodes …", flush=True)
            flags = [f for k, v in sets.items() for f in ("--set", f"{k}={v}")]
            search(["--part", "planners", "--planner-iterations", "0", "--episodes", str(args.episodes), *flags,
                    "--json", str(path)])  # fmt: skip
            kept = json.loads(path.read_text())
        policies, ratios = kept["policies"], kept["ratios"]
        out[label] = {
            "sets": sets,
            "returns": {level: policies[f"{level} planner"] for level in LEVELS},
            "ratios": {level: ratios[f"{level} planner ÷ private planner"] for level in LEVELS if level != "private"},
        }
        r = out[label]["ratios"]
        print(
            f"{label}: private {policies['private planner']['mean']:.1f}; team ÷ private {r['team']['ratio']:.2f} ± "
            f"{r['team']['ratio_ci95']:.2f}, full {r['full']['ratio']:.2f}",
            flush=True,
        )
    if args.json:
        write_json(args.json, {"episodes": args.episodes, "variants": out})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

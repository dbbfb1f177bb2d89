"""The figures the README and docs quote from a benchmark's JSON, rendered into them: one source for each figure.

A rendered block sits between ``<!-- figures:NAME -->`` and ``<!-- /figures -->`` in a Markdown file; NAME says
which renderer fills it, from which JSON in ``docs/figures/`` (written by the benchmark named there) or from every
figure ``convoy reproduce`` wrote to ``docs/reproduction/`` (the JSONs ``docs/reproduction.md`` is rendered from,
verdicts included). After re-running a benchmark or ``convoy reproduce``, ``python benchmarks/doc_figures.py``
rewrites every block; ``--check`` exits 1, naming the stale blocks, when a file does not show what its JSON holds
(``tests/test_doc_figures.py`` runs it).
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from convoy.analysis.verdicts import NOT, REPRODUCED, p_above, significant  # noqa: E402
from convoy.cli.reproduction_page import duration, heading_anchor  # noqa: E402
from convoy.output import markdown_table  # noqa: E402
from convoy.stats import mean_ci, ratio_ci  # noqa: E402

FIGURES = ROOT / "docs" / "figures"
REPRODUCTION = ROOT / "docs" / "reproduction"
FILES = ("README.md", "docs/treadmill.md", "docs/benchmarks.md")
BLOCK = re.compile(r"(<!-- figures:([\w-]+) -->\n)(.*?)(<!-- /figures -->)", re.S)


def _ci(p: dict[str, Any], bold: bool = False) -> str:
    """``−11.2 ± 1.7`` from a ``mean`` and ``ci95`` (a typographic minus, as the docs write it)."""
    text = f"{p['mean']:.1f} ± {p['ci95']:.1f}".replace("-", "−")
    return f"**{text}**" if bold else text


def _signed(x: float) -> str:
    """``+3.5`` or ``−3.5`` (a typographic minus, as the docs write it)."""
    return f"{x:+.1f}".replace("-", "−")


PLANNER_ROWS = (
    ("private planner", "planner, its own sensor"),
    ("team16 planner", "planner, hears a 16-bit word per teammate"),
    ("team planner", "planner, told what its teammates observe"),
    ("full planner", "planner, told every car and who is an adversary"),
)


def references(search: dict[str, Any]) -> str:
    """README: the references a learner is judged against (``benchmarks/treadmill_search.py --json``)."""
    p = search["policies"]
    rows = [
        ["random", _ci(p["random"])],
        ["best open-loop policy found (constants, cycles to period 32, cross-entropy over 200-step sequences)",
         _ci(max((v for k, v in p.items() if k.startswith("open-loop")), key=lambda v: v["mean"]))],
        ["tuned reactive driver, its own sensor (the earlier private reference)", _ci(p["private driver"])],
        *([f"model-predictive {label}", _ci(p[name])] for name, label in PLANNER_ROWS),
    ]  # fmt: skip
    header = [f"policy ({search['episodes']} scoring episodes; tuned on others)", "return per agent (95 % CI)"]
    return markdown_table(header, rows, [False, True])


def _ratio_text(x: dict[str, float]) -> str:
    return f"**{x['ratio']:.2f} ± {x['ratio_ci95']:.2f}** (difference {x['diff']:+.1f} ± {x['diff_ci95']:.1f})"


def _typographic(text: str) -> str:
    return text.replace("-", "−").replace("open−loop", "open-loop").replace("16−bit", "16-bit")


def search_table(search: dict[str, Any]) -> str:
    """docs/treadmill.md: every searched reference with what it was chosen on, and the paired ratios."""
    p, r = search["policies"], search["ratios"]

    def tuning(name: str) -> str:
        return p[name]["note"].split(";")[0]

    cycle = next(k for k in p if k.startswith("open-loop: best cycle"))
    constant = next(k for k in p if k.startswith("open-loop: constant"))
    rows = [
        ["random", _ci(p["random"]), ""],
        [f"best constant (action {constant.rsplit('-', 1)[1]})", _ci(p[constant]), tuning(constant)],
        [f"best cycle {cycle.split('cycle ', 1)[1]}", _ci(p[cycle]), tuning(cycle)],
        ["cross-entropy, one sequence for all agents", _ci(p["open-loop: CEM shared"]),
         tuning("open-loop: CEM shared") + " (it overfits its 16 episodes)"],
        ["cross-entropy, one sequence per agent", _ci(p["open-loop: CEM per agent"]),
         tuning("open-loop: CEM per agent")],
        ["tuned private driver", _ci(p["private driver"]), tuning("private driver")],
        ["team driver", _ci(p["team driver"]), tuning("team driver")],
        ["16-bit team driver", _ci(p["team16 driver"]), tuning("team16 driver")],
        ["full-information driver", _ci(p["full information"]), ""],
        *([f"**{label}**", _ci(p[name], bold=True), tuning(name)] for name, label in PLANNER_ROWS),
    ]  # fmt: skip
    header = [f"policy ({search['episodes']} scoring episodes, seed 0)", "return per agent (95 % CI)",
              "chosen on the tuning episodes"]  # fmt: skip
    table = markdown_table(header, rows, [False, True, False])
    drivers = _typographic(
        "Paired over the same episodes (ratio CI by the delta method, difference by Student's t). The drivers: best "
        f"open loop ÷ private {_ratio_text(r['best open-loop ÷ private'])}; team ÷ private "
        f"{_ratio_text(r['team ÷ private'])}; 16-bit team ÷ private {_ratio_text(r['team16 ÷ private'])}."
    )
    planners = _typographic(
        "The planners, against the private planner, the strongest private policy: team "
        f"{_ratio_text(r['team planner ÷ private planner'])}; 16-bit "
        f"{_ratio_text(r['team16 planner ÷ private planner'])}; full information "
        f"{_ratio_text(r['full planner ÷ private planner'])}; best open loop "
        f"{_ratio_text(r['best open loop ÷ private planner'])}; and the private planner ÷ the tuned private driver "
        f"{_ratio_text(r['private planner ÷ private driver'])}."
    )
    b = search["planner_budget"]
    budget = (
        f"Each planner's tuning: {b['iterations']} cross-entropy iterations × {b['population']} candidates × "
        f"{b['episodes']} tuning episodes (seed 1), every level from the same start (`planner.START`)."
    )
    return f"{table}\n\n{drivers}\n\n{planners}\n\n{budget}"


def reference_line(search: dict[str, Any]) -> str:
    """docs/benchmarks.md: the references in one line."""
    p = search["policies"]
    best = max((v for k, v in p.items() if k.startswith("open-loop")), key=lambda v: v["mean"])
    return (f"References on the same rules ({search['episodes']} scoring episodes): searched open loop "
            f"{best['mean']:.1f}, tuned private driver {p['private driver']['mean']:.1f}; planners: own sensor "
            f"{p['private planner']['mean']:.1f}, 16-bit words {p['team16 planner']['mean']:.1f}, teammates' "
            f"observations {p['team planner']['mean']:.1f}, every car {p['full planner']['mean']:.1f} "
            "per agent.")  # fmt: skip


def _seeds(values: list[float], fmt: str = "{:.1f}") -> str:
    """Each seed's figure for up to five seeds, else their range."""
    if len(values) <= 5:
        return ", ".join(fmt.format(v) for v in values)
    return f"{fmt.format(min(values))}–{fmt.format(max(values))}"


def learners(scores: dict[str, Any]) -> str:
    """docs/benchmarks.md: every scored learner group, last and best policies held out
    (``benchmarks/learner_scores.py``)."""

    def start(g: dict[str, Any]) -> str:
        v = g["start_values"]
        return f"{sum(x['q'] for x in v) / len(v):.1f} / {sum(x['discounted_return'] for x in v) / len(v):.1f}"

    rows = [
        [label, f"{len(g['seeds'])}", f"{g['episodes']}",
         f"{g['last_mean']:.1f} ± {g['last_ci95']:.1f} ({_seeds(g['last'])})",
         f"{g['best_mean']:.1f} ± {g['best_ci95']:.1f}", _seeds(g["last_over_best"], "{:.2f}"), start(g)]
        for label, g in scores["groups"].items()
    ]  # fmt: skip
    header = ["run", "seeds", "held-out episodes", "last policy (each seed)", "best.pt, held out",
              "last ÷ best, per seed", "at the start: max Q / discounted return"]  # fmt: skip
    right = [False, True, True, True, True, False, True]
    return markdown_table(header, rows, right) + "\n\n" + learner_comparisons(scores)


def learner_comparisons(scores: dict[str, Any], headline: bool = False) -> str:
    """docs: the learner comparisons that ask whether teammates' knowledge pays, with Welch's test; the README's
    ``headline`` keeps the studies of ≥ 15 seeds an arm and the latest comparison of arms told different things
    with ≥ 10 seeds an arm (a screen of one learner setting against another is not the README's question, and a
    3-seed screen of told against own does not replace a 10-seed study)."""
    from convoy.envs.treadmill.config import INFORMATION_FIELDS

    groups = scores["groups"]
    chosen = scores["comparisons"]
    if headline:
        seeds = lambda c: min(len(groups[c["a"]]["last"]), len(groups[c["b"]]["last"]))  # noqa: E731
        told = lambda g: {k: v for k, v in g["env_params"].items() if k in INFORMATION_FIELDS}  # noqa: E731
        contrasts = [c for c in chosen if told(groups[c["a"]]) != told(groups[c["b"]])]
        latest = ([c for c in contrasts if seeds(c) >= 10] or contrasts)[-1:]
        chosen = [c for c in chosen if seeds(c) >= 15 and c not in latest] + latest
    rows = [
        [f"{c['a']} vs {c['b']}", f"{groups[c['a']]['last_mean']:.1f} vs {groups[c['b']]['last_mean']:.1f}",
         f"{_signed(c['diff'])} [{_signed(c['diff_low'])}, {_signed(c['diff_high'])}]",
         f"{c['p']:.2f}" if c["p"] >= 0.01 else f"{c['p']:.1e}", _ratio_of(groups[c["a"]], groups[c["b"]])]
        for c in chosen
    ]  # fmt: skip
    header = ["last policies, held out", "mean per agent", "difference (95 % CI)", "Welch p", "ratio (95 % CI)"]
    return markdown_table(header, rows, [False, True, True, True, True])


def _ratio_of(a: dict[str, Any], b: dict[str, Any]) -> str:
    """A ÷ B of two groups' last policies with the seeds' bootstrap CI (``convoy.stats.ratio_ci``)."""
    r = ratio_ci(a["last"], b["last"])
    return f"{r['ratio']:.2f} [{r['low']:.2f}, {r['high']:.2f}]"


def charger_learners(scores: dict[str, Any]) -> str:
    """docs/treadmill.md: every learner group trained on the charger rules, last policies held out, each against the
    planner of its information (the private planner for its own sensor, the team planner told every sighting) on the
    same episodes. A group scored without ``--references`` takes the figure another group on those rules and episodes
    stored: a planner plays the same episodes the same way."""
    from convoy.envs.treadmill.config import CHARGER_RULES, INFORMATION_FIELDS

    def rules(g: dict[str, Any]) -> dict[str, Any]:
        return {k: v for k, v in g["env_params"].items() if k not in INFORMATION_FIELDS}

    chosen = {label: g for label, g in scores["groups"].items() if rules(g) == CHARGER_RULES}
    played: dict[tuple[int, str], float] = {}
    for g in chosen.values():
        for name, value in g.get("references", {}).items():
            played[g["episodes"], name] = value

    def against(g: dict[str, Any]) -> str:
        name = "team-planner" if g["env_params"].get("team_sightings") else "private-planner"
        ref = played.get((g["episodes"], name))
        if ref is None:
            return "—"
        lo, hi = (g["last_mean"] - g["last_ci95"]) / ref, (g["last_mean"] + g["last_ci95"]) / ref
        return f"{g['last_mean'] / ref:.2f} [{lo:.2f}, {hi:.2f}] of {name} ({ref:.1f})"

    rows = [
        [label.removeprefix("charger rules, "), f"{len(g['seeds'])}", f"{g['last_mean']:.1f} ± {g['last_ci95']:.1f}",
         against(g), _seeds(g["last_over_best"], "{:.2f}")]
        for label, g in chosen.items()
    ]  # fmt: skip
    header = ["independent DQN on the charger rules", "seeds", "last policies, held out", "÷ the planner of its "
              "information (95 % CI)", "last ÷ best, per seed"]  # fmt: skip
    return markdown_table(header, rows, [False, True, True, True, False])


def _ratio(search: dict[str, Any], key: str) -> str:
    return f"{search['ratios'][key]['ratio']:.2f} ×"


def _planner_verdict(search: dict[str, Any], key: str, goal: float) -> str:
    """``**1.07 ×** (goal ≥ 1.3: not met)`` for a planner ratio, the verdict from the ratio and its paired CI."""
    x = search["ratios"][key]
    met = x["ratio"] >= goal and x["ratio"] - x["ratio_ci95"] > 1.0
    return f"**{x['ratio']:.2f} ± {x['ratio_ci95']:.2f} ×** (goal ≥ {goal}: {'met' if met else '**not met**'})"


def properties(search: dict[str, Any]) -> str:
    """docs/treadmill.md: the three properties of the rules, with the search's paired ratios — against the
    strongest private policy (the private planner) as well as against the tuned reactive driver."""
    p = search["policies"]
    ceiling = search["config"]["max_steps"]
    return (
        "1. **no open-loop policy is competitive** — the best open-loop policy a search finds (constant\n"
        "   actions, every cycle up to period 32, cross-entropy over whole 200-step sequences) scores\n"
        f"   **{_ratio(search, 'best open loop ÷ private planner')}** the private planner and "
        f"**{_ratio(search, 'best open-loop ÷ private')}** the tuned private driver (goal ≤ 0.3);\n"
        "2. **what teammates observe pays** — *not against the strongest private policy.* The reactive\n"
        f"   drivers, tuned alike, score **{_ratio(search, 'team ÷ private')}** told what their teammates observe "
        f"and **{_ratio(search, 'team16 ÷ private')}**\n"
        "   through a hand-written 16-bit code — but the private driver is weak. A model-predictive\n"
        f"   planner on its own sensor scores {p['private planner']['mean']:.1f} per agent "
        f"({_ratio(search, 'private planner ÷ private driver')} the tuned driver; the most an agent can score is "
        f"{ceiling}), and the same planner,\n"
        "   tuned with the same budget, scores "
        f"{_planner_verdict(search, 'team planner ÷ private planner', 1.3)} that when told what\n"
        f"   its teammates observe, {_planner_verdict(search, 'team16 planner ÷ private planner', 1.3)} through a "
        "16-bit word per teammate, and\n"
        f"   {_ratio(search, 'full planner ÷ private planner')} with every car known. On these rules a\n"
        "   private policy that plans for the cars it cannot see gets all that information is worth to\n"
        "   this planner family, and no told policy can reach 1.3 × it: the most an agent can score is\n"
        f"   {search['config']['max_steps'] / p['private planner']['mean']:.2f} × it;\n"
        "3. **cooperation matters** — one agent's crash ends the episode for every agent."
    )


def figure_scales(records: dict[str, dict[str, Any]]) -> str:
    """``The paper's figures at the quick scale, on these rules``, or, once some ran at a larger scale, which did
    and on what rules (a larger scale's note names the charger rules where it runs on them)."""
    scales: dict[str, list[dict[str, Any]]] = {}
    for r in (records[k] for k in sorted(records)):
        scales.setdefault(r["scale"], []).append(r)
    if set(scales) <= {"quick"}:
        return "The paper's figures at the quick scale, on these rules"
    parts = []
    for scale, held in sorted(scales.items(), key=lambda item: item[0] == "quick"):
        names = " and ".join(r["title"].split(":")[0] for r in held) if scale != "quick" else "the others"
        rules = "the charger rules below" if all("charger rules" in r["note"] for r in held) else "these rules"
        parts.append(f"{names} at the {scale} scale on {rules}")
    return "The paper's figures: " + ",\n".join(parts)


def readme_summary(search: dict[str, Any], scores: dict[str, Any], records: dict[str, dict[str, Any]]) -> str:
    """README: what the treadmill shows, from the reference search, the learners' scores and the scales the
    paper's figures ran at."""
    g = scores["groups"][HEADLINE[1]]
    told = scores["groups"][HEADLINE[0]]
    c = next(c for c in scores["comparisons"] if (c["a"], c["b"]) == HEADLINE)
    p = search["policies"]
    private = p["private planner"]["mean"]
    return (
        "**What it shows.** On the treadmill ([docs/treadmill.md](docs/treadmill.md): cars enter and leave\n"
        "a moving window whose speed changes, sensors have a range and a rear blind spot, chasers come from\n"
        f"behind) a searched open-loop policy scores {_ratio(search, 'best open loop ÷ private planner')} the "
        "strongest private policy Convoy has, a\n"
        f"model-predictive planner on its own sensor ({private:.1f} per agent of at most "
        f"{search['config']['max_steps']}). Told what its teammates observe,\n"
        f"the same planner scores {_ratio(search, 'team planner ÷ private planner')} that "
        f"({_ratio(search, 'team16 planner ÷ private planner')} through a 16-bit word per teammate), told every car "
        f"{_ratio(search, 'full planner ÷ private planner')}:\non these rules what other cars know adds nothing "
        "measurable to a policy that plans for what it cannot see.\n"
        f"Independent DQN on its own observation scores {g['last_mean']:.1f} ± {g['last_ci95']:.1f} per agent "
        f"({g['last_mean'] / private:.2f} × the private planner; "
        f"{g['env_steps'] // 1000} k steps,\nlast policies on {g['episodes']} held-out episodes, "
        f"{len(g['seeds'])} seeds), told every car its teammates see {told['last_mean']:.1f} ± "
        f"{told['last_ci95']:.1f}\n(difference {_signed(c['diff'])}, 95 % CI [{_signed(c['diff_low'])}, "
        f"{_signed(c['diff_high'])}]): the learners are far from what their own information allows\n"
        f"([docs/benchmarks.md](docs/benchmarks.md#treadmill-learners)).\n{figure_scales(records)}: "
        "[docs/reproduction.md](docs/reproduction.md)."
    )


def variants(screen: dict[str, Any]) -> str:
    """docs/treadmill.md: the planners tuned on the default rules, on rule variants
    (``benchmarks/treadmill_variants.py``)."""
    rows = [
        [label, *(_ci(v["returns"][level]) for level in ("private", "team", "full")),
         *(f"{v['ratios'][level]['ratio']:.2f} ± {v['ratios'][level]['ratio_ci95']:.2f}" for level in ("team", "full"))]
        for label, v in screen["variants"].items()
    ]  # fmt: skip
    header = [f"rules ({screen['episodes']} episodes)", "private planner", "team planner", "full planner",
              "team ÷ private", "full ÷ private"]  # fmt: skip
    return markdown_table(header, rows, [False, *[True] * 5])


def causes(ends: dict[str, Any]) -> str:
    """docs/treadmill.md: how episodes end, per policy, and a learner's belief before it leaves the window
    (``benchmarks/treadmill_causes.py``)."""
    edges = ("out the front", "out the back", "off a side")
    cols = ("survived", "adversary", "teammate", *edges)
    lasted = all("steps" in f for f in ends.values())  # figures stored before the benchmark counted steps lack them
    rows = [
        [label, f"{f['return']:.1f} ± {f['ci95']:.1f}", *(f"{f[c]:.0%}" for c in cols),
         "—" if f["max_q_before_leaving"] is None else f"{f['max_q_before_leaving']:.1f}",
         *((f"{f['steps']:.0f}", f"{f['return_per_step']:.3f}") if lasted else ())]
        for label, f in ends.items()
    ]  # fmt: skip
    header = [
        "policy",
        "return",
        "survived 200 steps",
        "caught by the adversary",
        "hit a teammate",
        *edges,
        "max Q at the last act before leaving",
        *(("steps lasted", "return per step") if lasted else ()),
    ]
    return markdown_table(header, rows, [False, *[True] * (len(header) - 1)])


# --- the paper's figures, from `convoy reproduce`'s JSON (docs/reproduction/ID.json) ------------------------------


def _final(r: dict[str, Any], group: str) -> str:
    """A group's return over seeds, as ``convoy reproduce`` summarised it and judged the claims on: its last
    policies on the held-out episodes where it scored them, else its final greedy evaluation."""
    g = next(g for g in r["groups"] if g["group"] == group)
    return _ci(g["held_out"]["last"] if r.get("judged_on") == "held_out" else g["final"])


def _verdict(r: dict[str, Any], claim: str) -> dict[str, Any]:
    """The verdict ``convoy reproduce`` gave ``claim`` (its text in the figure file)."""
    for v in r["verdicts"]:
        if v["claim"] == claim:
            return v
    raise KeyError(f"{r['id']}: no claim {claim!r}; its claims: {', '.join(v['claim'] for v in r['verdicts'])}")


def _p(p: float) -> str:
    return "p < 0.001" if p < 0.001 else f"p = {p:.1g}" if p < 0.01 else f"p = {p:.2f}"


def _short(claim: str) -> str:
    """A claim less its parenthesised gloss (``… its twin with the channel cut (communication helps)``)."""
    return re.sub(r" \([^()]*\)$", "", claim)


def _recovered(v: dict[str, Any]) -> str:
    """``MA-MeSN recovers 51% [45%, 57%] of the told learner's gain … (goal ≥ 50%: met)`` from a fraction's
    verdict."""
    who, what = _short(v["claim"]).split(" recovers ", 1)
    goal = re.search(r"goal ≥ [\d.]+%: (?:not )?met", v["why"])
    return f"{who} recovers {v['ours']}{what.removeprefix('half')}" + (f" ({goal.group(0)})" if goal else "")


def _against_twin(v: dict[str, Any]) -> str:
    """``MA-MeSN − its channel-cut twin +22.5 [19.2, 25.8]`` from a twin claim's verdict (its difference, Welch's
    interval), with the verdict word where it is not *reproduced*."""
    who = v["claim"].split(" ends above ", 1)[0]
    diff = re.search(r"difference (\S+ \[[^\]]+\])", v["ours"])
    word = "" if v["verdict"] == REPRODUCED else f" ({v['verdict']})"
    return f"{who} − its channel-cut twin {diff.group(1) if diff else v['ours']}{word}"


def _outcome(v: dict[str, Any]) -> str:
    """``, p = 0.005: reproduced`` or ``: not reproduced at this budget``, after the two returns compared."""
    if v["verdict"] == REPRODUCED:
        return f", {_p(v['p'])}: reproduced"
    return f": {v['verdict']} at this budget"


def _span(values: set[int]) -> str:
    """``5``, or ``3–5`` when they differ."""
    return f"{min(values)}–{max(values)}" if len(values) > 1 else f"{min(values)}"


def _steps(r: dict[str, Any]) -> str | None:
    """``30 k``: the env steps per run that the figure's note states (``5 seeds × 30 k env steps …``, or
    ``~405–450 k env steps a run``)."""
    m = re.search(r"seeds × ([\d.,]+ [kM]) env steps", r["note"]) or re.search(
        r"(~?[\d.,–]+ [kM]) env steps a run", r["note"]
    )
    return m.group(1) if m else None


def _budget(r: dict[str, Any]) -> str:
    """``5 seeds × 30 k steps``: the seeds the figure's groups have and the env steps its note states."""
    steps = _steps(r)
    return f"{_span({g['final']['n'] for g in r['groups']})} seeds" + (f" × {steps} steps" if steps else "")


def _where(r: dict[str, Any]) -> str:
    """A link to the figure's section of docs/reproduction.md (the anchor that page's headings get)."""
    return f"[docs/reproduction.md](docs/reproduction.md#{heading_anchor(r['title'])})"


def _none_above_random(r: dict[str, Any]) -> bool:
    """Whether no group ends significantly above the random policy on its env (docs/reproduction.md's *above
    random?* column, the same test)."""
    tested = [(g["final"]["values"], (g.get("references") or r["references"] or {}).get("random")) for g in r["groups"]]
    known = [(values, ref) for values, ref in tested if ref is not None]
    return bool(known) and not any(significant(*p_above(values, float(ref))) for values, ref in known)


def reproduction_results(search: dict[str, Any], records: dict[str, dict[str, Any]]) -> str:
    """README: the results table's rows with a JSON behind them: the treadmill search's headline ratio and the
    paper's figures as ``convoy reproduce`` measured and judged them."""
    open_loop = search["ratios"]["best open loop ÷ private planner"]
    team = search["ratios"]["team planner ÷ private planner"]
    rows = [[f"treadmill: best open-loop policy found ÷ private planner (paired, {search['episodes']} episodes)",
             f"{open_loop['ratio']:.2f} ± {open_loop['ratio_ci95']:.2f} (goal ≤ 0.3)",
             "[docs/treadmill.md](docs/treadmill.md)"],
            [f"treadmill: planner told teammates' observations ÷ private planner (paired, {search['episodes']} "
             "episodes)", f"{team['ratio']:.2f} ± {team['ratio_ci95']:.2f} (goal ≥ 1.3)",
             "[docs/treadmill.md](docs/treadmill.md)"]]  # fmt: skip

    fig3 = records["fig3"]
    head = _verdict(fig3, "MA-MeSN ends above independent DQN")
    also = [_against_twin(v) for v in fig3["verdicts"] if "its twin with the channel cut" in v["claim"]]
    also += [_recovered(v) for v in fig3["verdicts"]
             if v["claim"].startswith("MA-") and " recovers " in v["claim"] and "[" in v["ours"]]  # fmt: skip
    also += [f"{_short(v['claim'])}: not reproduced" for v in fig3["verdicts"] if v["verdict"] == NOT]
    held = (fig3.get("held_out_references") if fig3.get("judged_on") == "held_out" else None) or fig3["references"]
    # the strongest policies of the learners' information: the planners where measured, else the tuned driver
    names = {"private-planner": "private planner", "team16-planner": "16-bit planner", "private-driver": "tuned driver"}
    strongest = [f"{name} {held[key]:.0f}" for key, name in names.items() if key in held][:2]
    also += [f"{', '.join(strongest)} on the same episodes"] if strongest else []
    rows.append([f"Fig. 3 at the {fig3['scale']} scale ({_budget(fig3)}): MA-MeSN vs independent DQN",
                 f"{_final(fig3, 'algo=ma-mesn')} vs {_final(fig3, 'algo=idqn')}{_outcome(head)} ({'; '.join(also)})",
                 _where(fig3)])  # fmt: skip

    ordered = [records[k] for k in sorted(records)]
    labels = [r["title"].split(":")[0] for r in ordered]
    figs = [label.removeprefix("Fig. ") for label in labels if label.startswith("Fig. ")]
    tables = [label for label in labels if not label.startswith("Fig. ")]
    seeds = _span({g["final"]["n"] for r in ordered for g in r["groups"]})
    numbers = [re.sub(r"[a-z]+$", "", f) for f in figs]  # 4a, 4b → 4
    scales = sorted({r["scale"] for r in ordered})
    minutes = [r["minutes"] for r in ordered]
    verdicts = []
    for i, (r, label) in enumerate(zip(ordered, labels, strict=True)):
        short = label if i == 0 or not label.startswith("Fig. ") else label.removeprefix("Fig. ")
        word = "not" if r["verdict"] == NOT else r["verdict"]
        at = f" at {_steps(r)} steps" if _steps(r) else ""
        why = f" (no learner above random{at})" if _none_above_random(r) else ""
        verdicts.append(f"{short} {word}{why}")
    rows.append([f"Figs. {numbers[0]}–{numbers[-1]}{''.join(' and ' + t for t in tables)} at the "
                 f"{' and '.join(scales)} scale ({seeds} seeds each, ≤ {duration(60 * max(minutes))} a "
                 f"figure, {duration(60 * sum(minutes))} in all)",
                 " · ".join(verdicts), "[docs/reproduction.md](docs/reproduction.md)"])  # fmt: skip

    fig5 = records["fig5"]
    named = {"ma-mesn-mm": "MA-MeSN-MM", "codbc": "CoDBC", "dqn-ser": "DQN + SER", "idqn": "DQN"}
    held = [f"{v['claim'].replace(' ends above ', ' > ')}, {_p(v['p'])}" for v in fig5["verdicts"]
            if v["verdict"] == REPRODUCED]  # fmt: skip
    rows.append([f"Fig. 5 at the {fig5['scale']} scale, decentralised execution: {' / '.join(named.values())}",
                 " / ".join(_final(fig5, f"algo={k}") for k in named)
                 + (f": {'; '.join(held)}" if held else ": no difference at this budget"), _where(fig5)])  # fmt: skip

    table1 = records["table1"]
    analysis = table1["analysis"]
    returns = {"return_sent": "true messages", "return_shuffled": "shuffled across envs",
               "return_modal": "each sender's modal message", "return_noise": "white noise"}  # fmt: skip
    use = next((v for v in table1["verdicts"] if v.get("headline")), table1["verdicts"][0])  # true vs shuffled
    consistency = analysis["speaker_consistency"]
    shown = [mean_ci(analysis[k]["value"]) for k in returns]
    rows.append([f"Table 1 at the {table1['scale']} scale, MA-MeSN's return with {' / '.join(returns.values())}",
                 " / ".join(_ci(s) for s in shown) + ": "
                 + (f"true messages beat shuffled ones, {_p(use['p'])}" if use["verdict"] == REPRODUCED
                    else "the listeners do not use what the messages say at this budget")
                 + f" (speaker consistency {mean_ci(consistency['value'])['mean']:.2f} vs shuffled "
                 f"{mean_ci(consistency['shuffled'])['mean']:.2f})", _where(table1)])  # fmt: skip

    fig8 = records["fig8"]
    head = _verdict(fig8, "MA-MeSN ends above independent DQN")
    others: dict[str, list[str]] = {}
    for v in fig8["verdicts"]:
        if v is not head and v["claim"].endswith(" ends above independent DQN"):
            others.setdefault(v["verdict"], []).append(v["claim"].removesuffix(" ends above independent DQN"))
    rest = "; ".join(f"{' and '.join(names)} {'not' if verdict == NOT else verdict}"
                     for verdict, names in others.items())  # fmt: skip
    rows.append([f"Fig. 8 at the {fig8['scale']} scale ({_budget(fig8)}): MA-MeSN vs independent DQN on "
                 "speaker-listener",
                 f"{_final(fig8, 'algo=ma-mesn')} vs {_final(fig8, 'algo=idqn')}{_outcome(head)}"
                 + (f"; {rest}" if rest else ""), _where(fig8)])  # fmt: skip
    return markdown_table(["what", "figure", "where"], rows, [False, False, False])


def population_table(bench: dict[str, Any]) -> str:
    """docs/benchmarks.md: population vs separate processes per algorithm and size (``benchmarks/population.py
    --json``), the goal's size (P = 5) in bold."""
    rows = []
    for algo, sizes in bench["algos"].items():
        for size, f in sizes.items():
            train, upd = f["training"], f["update"]
            ratio = f"{train['ratio']:.2f}×"
            rows.append([algo, size, f"{train['population_steps_per_s']:,.0f}", f"{train['separate_steps_per_s']:,.0f}",
                         f"**{ratio}**" if size == "5" else ratio, f"{int(size) * upd['single_ms']:.1f}",
                         f"{upd['population_ms']:.1f}", f"{upd['ratio']:.2f}×"])  # fmt: skip
    header = ["algo", "P", "population env-steps/s", "separate", "ratio", "update ms: P singles", "population", "ratio"]
    return markdown_table(header, rows, [False, True, True, True, True, True, True, True])


def gpu_table(gpu: dict[str, Any]) -> str:
    """docs/benchmarks.md: ms per update eager and captured per algorithm and P (``benchmarks/gpu.py --json``), the
    goals' cells in bold, and what the run did not measure."""
    rows = []
    for algo, sizes in gpu["updates"].items():
        for size, f in sizes.items():
            rate = f"{f['captured_run_updates_per_s']:,.0f}"
            captured = f"{f['captured_ms']:.2f}"
            goal_ms = (algo, size) == ("idqn", "1")
            rows.append([algo, size, f"{f['eager_ms']:.2f}", f"**{captured}**" if goal_ms else captured,
                         f"{f['speedup']:.1f}×", f"**{rate}**" if (algo, size) == ("idqn", "128") else rate,
                         f"{f['captured_warm_s']:.0f}", f"{f['cudagraph_skips']:.0f}",
                         f"{f['sample_ms']:.2f}" if "sample_ms" in f else "–"])  # fmt: skip
    header = ["algo", "P", "eager ms", "captured ms", "×", "captured run-updates/s", "compile s", "CUDA-graph skips",
              "eager sample ms"]  # fmt: skip
    table = markdown_table(header, rows, [False, *[True] * 8])
    missing = "; ".join(f"{what}: {why}" for what, why in gpu.get("not_measured", {}).items())
    return f"{gpu['device']}, torch {gpu['torch']}.\n\n{table}" + (f"\n\nNot measured: {missing}." if missing else "")


def soak_table(soak: dict[str, Any]) -> str:
    """docs/benchmarks.md: what the soak (``benchmarks/soak.py --json``) submitted, kept and used."""

    def growth(f: dict[str, float], unit: str) -> str:
        return f"{f['first']:.0f} → {f['last']:.0f}{unit} (max {f['max']:.0f}): {f['ratio']:.2f}×"

    rows = [
        ["jobs submitted / in the store / completed",
         f"{soak['submitted']} / {soak['present']} / {soak['states'].get('completed', 0)} ({soak['lost']} lost, "
         f"{soak['refused_while_down']} refused while down)", "nothing lost"],
        [f"SQLite `integrity_check` after {soak['kills']} kills", soak["integrity"], "ok"],
        ["service RSS, first → last", growth(soak["rss_mb"], " MB"), "≤ 1.10×"],
        ["service open file descriptors, first → last", growth(soak["fds"], ""), "≤ 1.10×"],
    ]  # fmt: skip
    return markdown_table(["figure", "result", "goal"], rows, [False, False, False])


def engineering_results(population: dict[str, Any], population_all: dict[str, Any], soak: dict[str, Any]) -> str:
    """README: the service's own figures (population training, the soak), from the same JSONs as docs/benchmarks.md."""
    at5 = {algo: sizes["5"]["training"]["ratio"] for algo, sizes in population["algos"].items() if "5" in sizes}
    every5 = [sizes["5"]["training"]["ratio"] for sizes in population_all["algos"].values() if "5" in sizes]
    below = [algo for algo, r in at5.items() if r < 1.5]
    pop = (f"{population['cores']} cores, P = 5: "
           + ", ".join(f"{r:.2f}× ({algo})" for algo, r in at5.items())
           + f" at {population['steps'] // 1000} k steps a run; {min(every5):.2f}–{max(every5):.2f}× over all "
           f"{len(every5)} algorithms at {population_all['steps'] // 1000} k"
           + (f" — below the 1.5× goal for {' and '.join(below)}" if below else ""))  # fmt: skip
    total = soak["states"].get("completed", 0)
    rows = [
        ["population training: 5 seeds in one process vs 5 separate processes, aggregate env-steps/s", pop,
         "[docs/benchmarks.md](docs/benchmarks.md#population-training)"],
        [f"soak: {soak['submitted']} jobs ({soak['submitted'] - soak['alone']} of them in {soak['sweeps']} sweeps) "
         f"over {soak['minutes']:.0f} min, the service killed with `kill -9` {soak['kills']} times",
         f"{soak['lost']} lost, {total} completed, SQLite {soak['integrity']}, RSS {soak['rss_mb']['ratio']:.2f}× and "
         f"open files {soak['fds']['ratio']:.2f}× first to last",
         "[docs/benchmarks.md](docs/benchmarks.md#soak-python-benchmarkssoakpy)"],
    ]  # fmt: skip
    return markdown_table(["what", "figure", "where"], rows, [False, False, False])


# the comparison the README leads with: (learner told teammates' sightings, the same on its own observation)
HEADLINE = (
    "+ team sightings, LayerNorm, τ 0.001, squared TD error, ε over half, lr annealed to 0, averaged policy, 400 k, "
    "20 seeds",
    "own, LayerNorm, τ 0.001, squared TD error, ε over half, lr annealed to 0, averaged policy, 400 k, 20 seeds",
)

SEARCH, SCORES, CAUSES = "treadmill_search.json", "treadmill_learners.json", "treadmill_causes.json"
CHARGER_CAUSES = "treadmill_charger_causes.json"
VARIANTS = "treadmill_variants.json"
POPULATION, POPULATION_ALL, SOAK, GPU = "population.json", "population_all.json", "soak.json", "gpu.json"
REPRODUCED_FIGURES = "reproduction/*.json"  # every figure in REPRODUCTION, by id
RENDERERS: dict[str, tuple[tuple[str, ...], Callable[..., str]]] = {
    "treadmill-references": ((SEARCH,), references),
    "treadmill-search": ((SEARCH,), search_table),
    "treadmill-reference-line": ((SEARCH,), reference_line),
    "treadmill-properties": ((SEARCH,), properties),
    "readme-summary": ((SEARCH, SCORES, REPRODUCED_FIGURES), readme_summary),
    "treadmill-learners": ((SCORES,), learners),
    "treadmill-learner-comparisons": ((SCORES,), learner_comparisons),
    "treadmill-learner-headline": ((SCORES,), lambda scores: learner_comparisons(scores, headline=True)),
    "treadmill-charger-learners": ((SCORES,), charger_learners),
    "treadmill-causes": ((CAUSES,), causes),
    "treadmill-charger-causes": ((CHARGER_CAUSES,), causes),
    "treadmill-variants": ((VARIANTS,), variants),
    "reproduction-results": ((SEARCH, REPRODUCED_FIGURES), reproduction_results),
    "population": ((POPULATION,), population_table),
    "population-all": ((POPULATION_ALL,), population_table),
    "soak": ((SOAK,), soak_table),
    "gpu": ((GPU,), gpu_table),
    "engineering-results": ((POPULATION, POPULATION_ALL, SOAK), engineering_results),
}


def load(source: str) -> Any:
    """A renderer's source: a JSON in FIGURES, or (REPRODUCED_FIGURES) every ``convoy reproduce`` record by id."""
    if source == REPRODUCED_FIGURES:
        records = (json.loads(p.read_text()) for p in sorted(REPRODUCTION.glob("*.json")))
        return {r["id"]: r for r in records}
    return json.loads((FIGURES / source).read_text())


def rendered(text: str) -> str:
    """``text`` with every figures block filled from its JSON."""

    def fill(m: re.Match[str]) -> str:
        name = m.group(2)
        if name not in RENDERERS:
            raise KeyError(f"figures block {name!r}: no renderer; known: {', '.join(RENDERERS)}")
        sources, render = RENDERERS[name]
        data = [load(source) for source in sources]
        return f"{m.group(1)}{render(*data)}\n{m.group(4)}"

    return BLOCK.sub(fill, text)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--check", action="store_true", help="only report stale blocks (exit 1 if any)")
    args = p.parse_args(argv)
    stale = []
    for name in FILES:
        path = ROOT / name
        text = path.read_text()
        new = rendered(text)
        if new != text:
            stale.append(name)
            if not args.check:
                path.write_text(new)
    if args.check and stale:
        print(f"stale figures in {', '.join(stale)}: run python benchmarks/doc_figures.py", file=sys.stderr)
        return 1
    print(("rewrote " + ", ".join(stale)) if stale else "every figures block is current")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

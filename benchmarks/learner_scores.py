"""Trained treadmill learners re-scored on held-out episodes: the figures the docs quote about learners.

Each ``--group LABEL=DIR[,DIR…]`` is a population run or several (``convoy train --seeds …``, one ``DIR/seed-N/`` per
seed; a one-seed run's files sit in ``DIR`` itself). Every seed's last policy (``checkpoint.pt``) and best point of its
greedy curve (``best.pt``, chosen on the training run's own evaluation episodes) are played greedily on ``--episodes``
episodes of seed ``--seed`` — episodes neither was chosen on — and the group gets the mean over seeds with its 95 %
t-CI, each seed's last ÷ best (below 1: the policy fell from its best point). ``--compare A B`` adds Welch's t-test of
A's last policies against B's (seeds are independent runs, so unpaired; both scored on as many episodes) and the ratio
of their means with a bootstrap CI. ``--references private-planner team-planner`` plays those reference policies on the
same episodes and gives each group's last policies as a ratio to them. The JSON (``--json``, default
``docs/figures/treadmill_learners.json``) keeps the groups of earlier calls, so groups can be scored as their runs
finish, each with its own episode count (one seed of episodes for the whole file: the first N episodes of a longer
scoring are the same episodes), and ``--pool LABEL A B`` joins scored groups' seeds from their stored figures (a study
whose populations ran in different sessions); ``python benchmarks/doc_figures.py`` renders it into docs/benchmarks.md.
Why more episodes for a budget's headline: a seed's last ÷ best is a ratio of two 200-episode means, noisy by about
±0.06 — as wide as the gap between holding and falling.

Run: ``python benchmarks/learner_scores.py --group "own, 150 k"=runs/v4/idqn-private`` (~20 s per seed).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402
from scipy import stats  # noqa: E402

from benchmarks.report import write_json  # noqa: E402
from convoy.analysis.evaluation import HELD_OUT_SEED  # noqa: E402
from convoy.stats import ci95_half, ratio_ci  # noqa: E402

DEFAULT_JSON = ROOT / "docs" / "figures" / "treadmill_learners.json"


def seed_dirs(run_dir: Path) -> list[tuple[int, Path]]:
    """``(seed, DIR/seed-N)`` of a population run, in seed order, or ``(seed, DIR)`` of a one-seed run (its files sit
    in DIR itself); a clear error when there are none."""
    found = sorted((int(p.name.split("-", 1)[1]), p) for p in run_dir.glob("seed-*") if p.name[5:].isdigit())
    if not found and (run_dir / "checkpoint.pt").is_file() and (run_dir / "job.json").is_file():
        try:
            found = [(int(json.loads((run_dir / "job.json").read_text())["seed"]), run_dir)]
        except (ValueError, KeyError, TypeError) as e:
            raise SystemExit(f"--group: {run_dir / 'job.json'} names no seed ({e}); is it a convoy train run?") from e
    if not found:
        raise SystemExit(
            f"--group: {run_dir} has no seed-N/ folders and no checkpoint.pt; give the --out of a convoy train run"
        )
    return found


def score(
    path: Path, episodes: int, seed: int, values: bool = False, weights: str = "judged"
) -> tuple[float, tuple[float, float] | None, Any, dict[str, Any]]:
    """One checkpoint's mean greedy return per agent over ``episodes`` episodes of ``seed``, its ``start_values``
    (when ``values``), its job and counters. ``weights``: the ones the run judges (its ``policy_ema`` average when it
    keeps one) or its ``online`` weights (the average lags them by ~1 / ``policy_ema`` updates)."""
    from convoy.analysis.evaluation import SCORING_ENVS, evaluate_policy
    from convoy.services.training import loaded_policy

    with loaded_policy(path, min(episodes, SCORING_ENVS)) as (algo, env, job, counters):
        if weights == "online":
            algo.average = None  # act with the online weights (``NetworkAgent.evaluated``)
        mean = evaluate_policy(algo, env, episodes, seed=seed).mean
        return mean, start_values(algo, env, seed) if values else None, job, counters


def start_values(algo: Any, env: Any, seed: int) -> tuple[float, float]:
    """At every env's first state: the value the learner believes it holds (max_a Q, mean over agents) and the
    discounted return its greedy policy then collects (γ of its own config, up to the episode's end). A Q far below
    the return means the Q-function sees only a few steps ahead: each target sync lets value travel one bootstrap
    (or ``n_step`` steps) further."""
    import torch

    obs, state = env.reset(seed=seed), algo.initial_state(env.num_envs)
    with torch.no_grad():
        q, _, _ = algo.greedy_q(torch.as_tensor(obs, dtype=torch.float32, device=algo.device)[None], state)  # R = 1
    believed = float(q.max(dim=-1).values.mean())
    gamma = float(algo.cfg.gamma)
    collected, weight = np.zeros(env.num_envs), np.ones(env.num_envs)
    while weight.any():
        out = algo.act(obs, 0.0, state)
        result = env.step(out.actions)
        collected += weight * result.reward.mean(axis=-1)
        weight = np.where(result.terminated | result.truncated, 0.0, weight * gamma)
        obs, state = result.obs, algo.reset_state(out.state, result.terminated | result.truncated)
    return believed, float(collected.mean())


def scored_before(groups: dict[str, Any], episodes: int, weights: str = "judged") -> dict[str, dict[str, Any]]:
    """Per seed folder, its figures in an earlier group scored on the same episodes with the same weights (and that
    group's settings): a group that adds seeds to scored ones plays only the new seeds."""
    out: dict[str, dict[str, Any]] = {}
    for g in groups.values():
        same = g["episodes"] == episodes and g.get("weights", "judged") == weights
        if not same or not all(Path(d).is_dir() for d in g["dirs"]):
            continue
        folders = [d for run_dir in g["dirs"] for _, d in seed_dirs(Path(run_dir))]
        if len(folders) != len(g["seeds"]):
            continue  # seeds added to its folders since: score them again
        for i, d in enumerate(folders):
            out[str(d)] = {"last": g["last"][i], "best": g["best"][i], "start": g["start_values"][i], "group": g}
    return out


def score_group(
    run_dirs: list[Path], episodes: int, seed: int, before: dict[str, Any] | None = None, weights: str = "judged"
) -> dict[str, Any]:
    """Every seed's last and best policy held out (or its figures from ``before``), the runs' settings, and the means
    with CIs over seeds."""
    seeds, last, best, values = [], [], [], []
    settings: dict[str, Any] = {}
    before = before or {}
    for s, d in (sd for run_dir in run_dirs for sd in seed_dirs(run_dir)):
        seeds.append(s)
        if str(d) in before:
            known = before[str(d)]
            last.append(known["last"])
            best.append(known["best"])
            values.append(known["start"])
            settings = settings or {
                k: known["group"][k] for k in ("algo", "env_params", "hyper_parameters", "env_steps")
            }
            print(f"  {d}: last {last[-1]:.1f}, best.pt {best[-1]:.1f} (scored before)", flush=True)
            continue
        mean, start, job, counters = score(d / "checkpoint.pt", episodes, seed, values=True, weights=weights)
        assert start is not None
        q, v = start
        last.append(mean)
        values.append({"q": q, "discounted_return": v})
        best.append(score(d / "best.pt", episodes, seed, weights=weights)[0])
        settings = {"algo": job.algo, "env_params": job.env_params,
                    "hyper_parameters": job.algo_params,  # the ones set on the command line; the rest: env defaults
                    "env_steps": counters.get("env_steps", job.steps)}  # fmt: skip
        print(f"  {d}: last {mean:.1f} (start: Q {q:.1f}, discounted return {v:.1f}), best.pt {best[-1]:.1f}",
              flush=True)  # fmt: skip
    out = {"dirs": [str(d) for d in run_dirs], "episodes": episodes, **settings, **figures(seeds, last, best, values)}
    return out | ({"weights": weights} if weights != "judged" else {})


def figures(seeds: list[int], last: list[float], best: list[float], values: list[Any]) -> dict[str, Any]:
    """A group's per-seed figures and their means with 95 % CIs over seeds."""
    x, b = np.asarray(last), np.asarray(best)
    return {
        "seeds": seeds,
        "last": [float(v) for v in last],
        "best": [float(v) for v in best],
        "last_mean": float(x.mean()),
        "last_ci95": ci95_half(x, single=0.0),
        "best_mean": float(b.mean()),
        "best_ci95": ci95_half(b, single=0.0),
        "last_over_best": (x / b).tolist(),
        "start_values": values,  # the last policy's, per seed
    }


SETTINGS = ("algo", "env_params", "hyper_parameters", "env_steps", "weights")  # "weights" only when online


def recipe(group: dict[str, Any]) -> dict[str, Any]:
    """A scored group's settings with its demonstrator resolved to the reference it names (``planner`` is the
    private planner for an own-sensor learner), so that runs started from the same teacher pool."""
    params = group.get("hyper_parameters") or {}
    if not params.get("demonstrator"):
        return group
    from convoy.config import job_config
    from convoy.learner.imitation import job_teacher

    job = job_config(algo=group["algo"], env="treadmill", env_params=group["env_params"], algo_params=params)
    return {**group, "hyper_parameters": {**params, "demonstrator": job_teacher(job)}}


def pool_groups(groups: dict[str, Any], parts: list[str]) -> dict[str, Any]:
    """One group of the seeds of scored ``parts``, from their stored figures alone (no checkpoint is played): a study
    whose arms ran in different sessions, on machines that did not keep each other's runs. The parts must have been
    scored on the same episodes and trained with the same settings, and share no seed."""
    missing = [name for name in parts if name not in groups]
    if missing:
        raise SystemExit(f"--pool: no scored group {missing[0]!r}; scored: {', '.join(groups) or 'none'}")
    first = groups[parts[0]]
    first_recipe = recipe(first)
    for name in parts[1:]:
        g = groups[name]
        if g["episodes"] != first["episodes"]:
            raise SystemExit(f"--pool: {name!r} was scored on {g['episodes']} episodes, {parts[0]!r} on "
                             f"{first['episodes']}; score both with the same --episodes")  # fmt: skip
        g_recipe = recipe(g)
        differ = [k for k in SETTINGS if g_recipe.get(k) != first_recipe.get(k)]
        if differ:
            raise SystemExit(f"--pool: {name!r} and {parts[0]!r} differ in {differ[0]} ({g.get(differ[0])!r} vs "
                             f"{first.get(differ[0])!r}); pool only runs of one recipe")  # fmt: skip
    seeds = [s for name in parts for s in groups[name]["seeds"]]
    twice = sorted({s for s in seeds if seeds.count(s) > 1})
    if twice:
        raise SystemExit(f"--pool: seed {twice[0]} is in more than one part; a seed counts once")

    def joined(key: str) -> list[Any]:
        return [v for name in parts for v in groups[name][key]]

    out = {"dirs": joined("dirs"), "pooled": parts, "episodes": first["episodes"],
           **{k: first[k] for k in SETTINGS if k in first},
           **figures(seeds, joined("last"), joined("best"), joined("start_values"))}  # fmt: skip
    refs = [groups[name].get("references") for name in parts]
    if refs[0] and all(r == refs[0] for r in refs):  # references are deterministic on the same episodes
        out["references"] = refs[0]
        out["last_over_reference"] = against_references(out, refs[0])
    return out


def reference_scores(env_params: dict[str, Any], names: list[str], episodes: int, seed: int) -> dict[str, float]:
    """Each treadmill reference policy's mean return per agent on the very episodes the groups' policies are
    re-scored on (``evaluate_reference``: the same rounds of first episodes)."""
    from convoy.analysis.evaluation import SCORING_ENVS, evaluate_reference
    from convoy.envs import make_batched

    env = make_batched("treadmill", min(episodes, SCORING_ENVS), **env_params)
    try:
        return {name: float(evaluate_reference(env, name, episodes, seed).mean()) for name in names}
    finally:
        env.close()


def against_references(group: dict[str, Any], refs: dict[str, float]) -> dict[str, list[float]]:
    """The group's last policies' mean over seeds ÷ each reference's mean on the same episodes, with the 95 % CI of
    the seeds' mean carried through (the reference plays the same episodes: its episode noise is the learners')."""
    half = group["last_ci95"]
    return {name: [group["last_mean"] / r, (group["last_mean"] - half) / r, (group["last_mean"] + half) / r]
            for name, r in refs.items()}  # fmt: skip


def compare(a: dict[str, Any], b: dict[str, Any]) -> dict[str, float]:
    """Welch's t-test of group a's last policies against group b's, and the difference of means with its 95 % CI."""
    x, y = np.asarray(a["last"]), np.asarray(b["last"])
    test = stats.ttest_ind(x, y, equal_var=False)
    ci = test.confidence_interval(0.95)
    return {"diff": float(x.mean() - y.mean()), "diff_low": float(ci.low), "diff_high": float(ci.high),
            "p": float(test.pvalue)}  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--group", action="append", default=[], metavar="LABEL=DIR[,DIR…]",
                   help="population runs (comma-separated) to score under LABEL, repeatable")  # fmt: skip
    p.add_argument("--pool", nargs="+", action="append", default=[], metavar="LABEL",
                   help="LABEL GROUP GROUP…: a group LABEL of the seeds of groups scored before (this call's or "
                   "earlier calls'), from their stored figures: arms run in other sessions; repeatable")  # fmt: skip
    p.add_argument("--compare", nargs=2, action="append", default=[], metavar=("A", "B"),
                   help="Welch's test of group A's last policies against group B's, repeatable")  # fmt: skip
    p.add_argument("--episodes", type=int, default=200, help="held-out episodes per policy (default %(default)s)")
    p.add_argument(
        "--seed", type=int, default=HELD_OUT_SEED, help="seed of the held-out episodes (default: %(default)s)"
    )
    p.add_argument("--rescore", action="store_true", help="play every seed again, even one an earlier group of "
                   "the file scored on the same episodes (default: reuse its figures)")  # fmt: skip
    p.add_argument("--references", nargs="*", default=[], metavar="NAME",
                   help="treadmill reference policies (convoy env rollout --policy names, e.g. private-planner "
                   "team-planner) played on the same episodes as each --group, each group's last policies given as a "
                   "ratio to them (default: none)")  # fmt: skip
    p.add_argument("--weights", choices=("judged", "online"), default="judged",
                   help="the weights each checkpoint is played with: those its run judges (the policy_ema average "
                   "when the run keeps one) or its online weights (default %(default)s)")  # fmt: skip
    p.add_argument("--json", default=str(DEFAULT_JSON), help="figures file, updated in place (default %(default)s)")
    args = p.parse_args(argv)
    from convoy.envs.treadmill.config import INFORMATION_FIELDS
    from convoy.envs.treadmill.references import REFERENCES

    unknown = [name for name in args.references if name not in REFERENCES]
    if unknown:
        p.error(f"--references: no reference policy {unknown[0]!r}; choose from {', '.join(REFERENCES)}")

    path = Path(args.json)
    data: dict[str, Any] = json.loads(path.read_text()) if path.exists() else {}
    if data and data["seed"] != args.seed:
        raise SystemExit(f"{path} holds scores on episodes of seed {data['seed']}; score with the same --seed, or "
                         "write another --json")  # fmt: skip
    data.setdefault("episodes", args.episodes)  # the count of groups scored before counts were kept per group
    data["seed"] = args.seed
    groups: dict[str, Any] = data.setdefault("groups", {})
    for g in groups.values():
        g.setdefault("episodes", data["episodes"])
    played: dict[str, dict[str, float]] = {}  # references per rule set and episode count, played once
    for spec in args.group:
        label, sep, dirs = spec.rpartition("=")
        if not sep or not label or not dirs:
            raise SystemExit(f"--group {spec!r}: write LABEL=DIR or LABEL=DIR,DIR")
        print(f"{label}: {dirs}", flush=True)
        run_dirs = [Path(d) for d in dirs.split(",")]
        stored = groups.get(label)
        if (
            stored
            and not args.rescore
            and stored["dirs"] == dirs.split(",")
            and stored["episodes"] == args.episodes
            and stored.get("weights", "judged") == args.weights
            and not any(d.exists() for d in run_dirs)
        ):
            # a study across sessions: a group scored where its runs were, named again where they are not
            print(f"  its runs are not here: the figures {path} keeps for it", flush=True)
        else:
            before = {} if args.rescore else scored_before(groups, args.episodes, args.weights)
            groups[label] = score_group(run_dirs, args.episodes, args.seed, before, args.weights)
        g = groups[label]
        print(f"{label}: last {g['last_mean']:.1f} ± {g['last_ci95']:.1f}, best.pt {g['best_mean']:.1f} ± "
              f"{g['best_ci95']:.1f} over {len(g['seeds'])} seeds", flush=True)  # fmt: skip
        if args.references:
            rules = {k: v for k, v in g["env_params"].items() if k not in INFORMATION_FIELDS}  # refs know their own
            key = json.dumps([rules, args.episodes], sort_keys=True)
            if key not in played:
                names = ", ".join(args.references)
                print(f"  the references on the same {args.episodes} episodes: {names}", flush=True)
                played[key] = reference_scores(rules, args.references, args.episodes, args.seed)
            g["references"] = played[key]
            g["last_over_reference"] = against_references(g, played[key])
            for name, (r, lo, hi) in g["last_over_reference"].items():
                print(f"  ÷ {name} ({played[key][name]:.1f}): {r:.2f} [{lo:.2f}, {hi:.2f}]", flush=True)
    for label, *parts in args.pool:
        if len(parts) < 2:
            raise SystemExit(f"--pool {label!r}: name the new group, then two or more scored groups to pool")
        groups[label] = g = pool_groups(groups, parts)
        print(f"{label}: last {g['last_mean']:.1f} ± {g['last_ci95']:.1f}, best.pt {g['best_mean']:.1f} ± "
              f"{g['best_ci95']:.1f} over {len(g['seeds'])} seeds (pooled)", flush=True)  # fmt: skip
    comparisons: list[dict[str, Any]] = data.setdefault("comparisons", [])
    for a, b in args.compare:
        missing = [g for g in (a, b) if g not in groups]
        if missing:
            raise SystemExit(f"--compare: no group {missing[0]!r}; scored: {', '.join(groups) or 'none'}")
        if groups[a]["episodes"] != groups[b]["episodes"]:
            raise SystemExit(f"--compare: {a!r} was scored on {groups[a]['episodes']} episodes, {b!r} on "
                             f"{groups[b]['episodes']}; score both with the same --episodes")  # fmt: skip
        comparisons[:] = [c for c in comparisons if (c["a"], c["b"]) != (a, b)]
        comparisons.append({"a": a, "b": b, **compare(groups[a], groups[b])})
        c = comparisons[-1]
        r = ratio_ci(groups[a]["last"], groups[b]["last"])  # derived from the stored seeds, not stored again
        print(f"{a} − {b}: {c['diff']:+.1f} [{c['diff_low']:+.1f}, {c['diff_high']:+.1f}], Welch p = {c['p']:.2f}; "
              f"ratio {r['ratio']:.2f} [{r['low']:.2f}, {r['high']:.2f}]")  # fmt: skip
    write_json(path, data)
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

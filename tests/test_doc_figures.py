"""Figures quoted in the README and docs are rendered from the benchmarks' JSON (``benchmarks/doc_figures.py``):
the files show what the JSON holds, and a changed figure makes them stale."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any, cast

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

import doc_figures  # noqa: E402

from convoy.cli.reproduction_page import duration  # noqa: E402


def test_every_figures_block_shows_its_json() -> None:
    assert doc_figures.main(["--check"]) == 0


def test_a_changed_figure_makes_its_block_stale(tmp_path: Path, monkeypatch) -> None:
    data = {p.name: json.loads(p.read_text()) for p in doc_figures.FIGURES.glob("*.json")}
    data["treadmill_search.json"]["policies"]["private driver"]["mean"] = 12.345
    group = data["treadmill_learners.json"]["groups"][doc_figures.HEADLINE[1]]
    group["last_mean"] = 23.456
    for name, values in data.items():
        (tmp_path / name).write_text(json.dumps(values))
    monkeypatch.setattr(doc_figures, "FIGURES", tmp_path)
    readme = (ROOT / "README.md").read_text()
    shown = f"12.3 ± {data['treadmill_search.json']['policies']['private driver']['ci95']:.1f}"
    assert shown not in readme and f"{shown} |" in doc_figures.rendered(readme)
    assert "scores 23.5 ±" not in readme and "scores 23.5 ±" in doc_figures.rendered(readme)


def test_a_changed_reproduction_figure_makes_the_readme_results_stale(tmp_path: Path, monkeypatch) -> None:
    records = {p.name: json.loads(p.read_text()) for p in doc_figures.REPRODUCTION.glob("*.json")}
    fig8 = records["fig8.json"]
    idqn = next(g for g in fig8["groups"] if g["group"] == "algo=idqn")["final"]
    stored, idqn["mean"] = idqn["mean"], -15.55
    next(v for v in fig8["verdicts"] if v["claim"] == "MA-MeSN ends above independent DQN")["verdict"] = "partly"
    records["fig6.json"]["verdict"] = "reproduced"
    records["fig5.json"]["minutes"] += 6.2  # the longest figure, and a new total
    for name, values in records.items():
        (tmp_path / name).write_text(json.dumps(values))
    monkeypatch.setattr(doc_figures, "REPRODUCTION", tmp_path)
    readme = (ROOT / "README.md").read_text()
    new = doc_figures.rendered(readme)
    mesn = next(g for g in fig8["groups"] if g["group"] == "algo=ma-mesn")["final"]
    minutes = [r["minutes"] for r in records.values() if "minutes" in r]
    partly = f"{mesn['mean']:.1f} ± {mesn['ci95']:.1f} vs −15.6 ± {idqn['ci95']:.1f}: partly at this budget"
    longest = f"≤ {duration(60 * max(minutes))} a figure, {duration(60 * sum(minutes))} in all"
    for shown in (partly.replace("-", "−"), "· 6 reproduced ·", longest):
        assert shown not in readme and shown in new
    was = f"{stored:.1f} ± {idqn['ci95']:.1f}".replace("-", "−")  # the stored figure's independent DQN
    assert f"vs {was}, p < 0.001: reproduced" in readme and was not in new


def test_fig3_s_row_quotes_the_returns_its_claims_were_judged_on_and_the_recovered_fractions(
    tmp_path: Path, monkeypatch
) -> None:
    """A figure judged on held-out returns shows those, not its final evaluations; a fraction of the told learner's
    gain is quoted with its CI and whether it meets its goal."""
    records = {p.name: json.loads(p.read_text()) for p in doc_figures.REPRODUCTION.glob("*.json")}
    fig3 = records["fig3.json"]
    fig3["judged_on"] = "held_out"
    for i, g in enumerate(fig3["groups"]):
        g["held_out"] = {"last": {"mean": 150.0 + i, "ci95": 1.5, "n": 10, "values": []}}
    fig3["verdicts"].append({"claim": "MA-MeSN recovers half of the told learner's gain over independent DQN",
                             "ours": "51% [45%, 57%]", "verdict": "not comparable", "p": None,
                             "why": "a fraction stated, not a claim of the paper; goal ≥ 50%: not met"})  # fmt: skip
    for name, values in records.items():
        (tmp_path / name).write_text(json.dumps(values))
    monkeypatch.setattr(doc_figures, "REPRODUCTION", tmp_path)
    new = doc_figures.rendered((ROOT / "README.md").read_text())
    mesn, idqn = (
        next(150 + i for i, g in enumerate(fig3["groups"]) if g["group"] == f"algo={a}") for a in ("ma-mesn", "idqn")
    )
    assert f"{mesn:.1f} ± 1.5 vs {idqn:.1f} ± 1.5" in new
    assert (
        "MA-MeSN recovers 51% [45%, 57%] of the told learner's gain over independent DQN (goal ≥ 50%: not met)" in new
    )


def test_the_service_figures_come_from_the_population_and_soak_json(tmp_path: Path, monkeypatch) -> None:
    data = {p.name: json.loads(p.read_text()) for p in doc_figures.FIGURES.glob("*.json")}
    data["population.json"]["algos"]["idqn"]["5"]["training"]["ratio"] = 1.62  # now above the goal
    data["soak.json"]["lost"] = 3
    data["soak.json"]["fds"] = {"first": 25, "last": 31, "max": 33, "ratio": 1.24}
    for name, values in data.items():
        (tmp_path / name).write_text(json.dumps(values))
    monkeypatch.setattr(doc_figures, "FIGURES", tmp_path)
    readme, bench = (ROOT / "README.md").read_text(), (ROOT / "docs" / "benchmarks.md").read_text()
    new_readme, new_bench = doc_figures.rendered(readme), doc_figures.rendered(bench)
    assert "1.62× (idqn)" in new_readme and "below the 1.5× goal for ma-mesn " in new_readme
    assert "3 lost" in new_readme and "open files 1.24×" in new_readme and "3 lost" not in readme
    assert "**1.62×**" in new_bench and "**1.62×**" not in bench
    assert "25 → 31 (max 33): 1.24×" in new_bench


def test_learner_scores_takes_a_one_seed_run_and_names_what_a_folder_lacks(tmp_path: Path) -> None:
    """``convoy train --seeds 20`` writes its files in DIR itself, not DIR/seed-20/: that is one seed; a folder
    with neither is an error naming it."""
    import learner_scores

    one = tmp_path / "one"
    one.mkdir()
    (one / "checkpoint.pt").write_bytes(b"")
    (one / "job.json").write_text(json.dumps({"algo": "idqn", "seed": 20}))
    assert learner_scores.seed_dirs(one) == [(20, one)]
    (tmp_path / "pop" / "seed-3").mkdir(parents=True)
    assert learner_scores.seed_dirs(tmp_path / "pop") == [(3, tmp_path / "pop" / "seed-3")]
    with pytest.raises(SystemExit, match=r"no seed-N/ folders and no checkpoint\.pt"):
        learner_scores.seed_dirs(tmp_path / "pop" / "seed-3")
    (one / "job.json").write_text(json.dumps({"seed": "twenty"}))
    with pytest.raises(SystemExit, match="names no seed"):
        learner_scores.seed_dirs(one)


def test_learner_scores_plays_only_the_seeds_no_earlier_group_scored(tmp_path: Path) -> None:
    """A group that adds a population to two scored ones reuses their seeds' figures (same episodes) and plays
    only the new seeds: here none, so no checkpoint is loaded; another episode count reuses nothing."""
    import learner_scores

    for run, seeds in (("a", (0, 1)), ("b", (5,))):
        for s in seeds:
            (tmp_path / run / f"seed-{s}").mkdir(parents=True)
    dirs = [str(tmp_path / "a"), str(tmp_path / "b")]
    settings = {"algo": "idqn", "env_params": {}, "hyper_parameters": {}, "env_steps": 10}
    earlier = {"ab": {"dirs": dirs, "episodes": 500, "seeds": [0, 1, 5], "last": [10.0, 12.0, 9.0],
                      "best": [11.0, 12.0, 10.0], "start_values": [{}, {}, {}], **settings}}  # fmt: skip
    before = learner_scores.scored_before(earlier, 500)
    group = learner_scores.score_group([Path(d) for d in dirs], 500, 777, before)
    assert group["seeds"] == [0, 1, 5] and group["last"] == [10.0, 12.0, 9.0] and group["algo"] == "idqn"
    assert group["last_over_best"][0] == pytest.approx(10 / 11) and learner_scores.scored_before(earlier, 200) == {}
    assert learner_scores.scored_before(earlier, 500, "online") == {}  # judged weights' figures are not the online's


def test_learner_scores_pools_groups_scored_in_different_sessions(tmp_path: Path) -> None:
    """``--pool LABEL A B`` makes one group of two scored groups' seeds from the JSON alone (their run folders gone),
    with the references they share; groups of other recipes, other episodes or a seed in both are refused."""
    import learner_scores

    settings = {"algo": "idqn", "env_params": {"adversary_speed": 7}, "hyper_parameters": {"n_step": 3},
                "env_steps": 150_000}  # fmt: skip
    refs = {"private-planner": 140.0}

    def group(seeds: list[int], last: list[float], **extra: Any) -> dict[str, Any]:
        return {"dirs": [f"gone-{seeds[0]}"], "episodes": 500, **learner_scores.figures(seeds, last, last, [{}] * len(
                seeds)), "references": refs, **settings, **extra}  # fmt: skip

    path = tmp_path / "scores.json"
    groups = {
        "a": group([0, 1], [100.0, 110.0]),
        "b": group([5, 6, 7], [90.0, 120.0, 105.0]),
        "other recipe": group([8], [1.0], hyper_parameters={"n_step": 1}),
        "overlap": group([1], [3.0]),
        "200": group([9], [4.0], episodes=200),
        "online": group([9], [4.0], weights="online"),
        "planner": group([2], [100.0], hyper_parameters={"n_step": 3, "demonstrator": "planner"}),
        "private-planner": group([3], [100.0], hyper_parameters={"n_step": 3, "demonstrator": "private-planner"}),
        "team-planner": group([4], [100.0], hyper_parameters={"n_step": 3, "demonstrator": "team-planner"}),
    }
    path.write_text(json.dumps({"episodes": 500, "seed": 777, "groups": groups, "comparisons": []}))
    assert learner_scores.main(["--pool", "ab", "a", "b", "--json", str(path)]) == 0
    ab = json.loads(path.read_text())["groups"]["ab"]
    assert ab["seeds"] == [0, 1, 5, 6, 7] and ab["last_mean"] == pytest.approx(105.0) and ab["pooled"] == ["a", "b"]
    assert ab["references"] == refs and ab["last_over_reference"]["private-planner"][0] == pytest.approx(0.75)
    assert ab["hyper_parameters"] == {"n_step": 3} and ab["last_ci95"] > 0
    # `planner` names the private planner for an own-sensor learner: runs started from it either way are one recipe
    assert learner_scores.main(["--pool", "pp", "planner", "private-planner", "--json", str(path)]) == 0
    refused = (
        (["a", "other recipe"], "differ in hyper_parameters"),
        (["a", "overlap"], "seed 1"),
        (["a", "200"], "200 episodes"),
        (["a", "online"], "differ in weights"),
        (["planner", "team-planner"], "differ in hyper_parameters"),
        (["a", "nope"], "no scored group 'nope'"),
        (["a"], "two or more"),
    )
    for parts, error in refused:
        with pytest.raises(SystemExit, match=error):
            learner_scores.main(["--pool", "x", *parts, "--json", str(path)])
    # a --group whose runs are not here keeps its stored figures (same label, folders, episodes), and compares
    assert learner_scores.main(["--group", "a=gone-0", "--group", "b=gone-5", "--compare", "b", "a",
                                "--episodes", "500", "--json", str(path)]) == 0  # fmt: skip
    kept = json.loads(path.read_text())
    assert kept["groups"]["a"] == groups["a"] and kept["comparisons"][-1]["diff"] == pytest.approx(0.0)  # means 105
    with pytest.raises(SystemExit, match="no seed-N/ folders"):  # other episodes: it would have to play them
        learner_scores.main(["--group", "a=gone-0", "--episodes", "200", "--json", str(path)])


def test_references_play_the_episodes_a_learner_is_scored_on(tmp_path: Path) -> None:
    """``evaluate_reference`` plays the very episodes ``evaluate`` gives a learner, rounds included: a Q-network
    made to pick action 4 everywhere scores exactly what the reference ``constant-4`` scores; ``learner_scores``
    gives each group's last policies as a ratio to the references and refuses a name it does not know."""
    import learner_scores
    import numpy as np

    from convoy.algos.registry import make_algorithm
    from convoy.analysis.evaluation import evaluate, evaluate_reference
    from convoy.config import resolve_algo
    from convoy.envs import make_batched

    params = {"length": 60, "width": 60, "max_steps": 30}
    env = make_batched("treadmill", 4, **params)
    algo = make_algorithm("idqn", env.spec, resolve_algo("idqn", "treadmill", {"hidden": (8,)}), device="cpu", seed=0)
    always(algo.online, 4)
    learner = evaluate(env, algo, 6, seed=777)  # two rounds of 4 envs
    assert np.array_equal(evaluate_reference(env, "constant-4", 6, 777), learner)
    assert not np.array_equal(evaluate_reference(env, "constant-1", 6, 777), learner)
    group = {"last_mean": 90.0, "last_ci95": 9.0}
    ratios = learner_scores.against_references(group, {"private-planner": 100.0})
    assert ratios == {"private-planner": [0.9, 0.81, 0.99]}
    with pytest.raises(SystemExit):
        learner_scores.main(["--references", "best-planner", "--json", str(tmp_path / "x.json")])


def test_learner_scores_plays_the_online_weights_or_the_judged_average(tmp_path: Path) -> None:
    """``--weights online`` scores a checkpoint's online weights, not the ``policy_ema`` average its run judges
    (which lags them): an average that always brakes and online weights that always take action 4 score what the
    constant references score."""
    import learner_scores

    from convoy.algos.checkpoint import save_checkpoint
    from convoy.algos.registry import make_algorithm
    from convoy.analysis.evaluation import evaluate_reference
    from convoy.config import job_config
    from convoy.envs import make_batched

    params = {"length": 60, "width": 60, "max_steps": 30}
    job = job_config(algo="idqn", env="treadmill", env_params=params, algo_params={"hidden": (8,), "policy_ema": 0.5})
    env = make_batched("treadmill", 6, **params)  # as many envs as learner_scores plays 6 episodes on
    algo = make_algorithm("idqn", env.spec, job.algo_config(), device="cpu", seed=0)
    always(algo.online, 4)
    always(algo.average, 1)
    path = save_checkpoint(tmp_path / "checkpoint.pt", algo, job, {"env_steps": 0, "episodes": 0, "updates": 0})
    for weights, action in (("judged", 1), ("online", 4)):
        played = learner_scores.score(path, 6, 777, weights=weights)[0]
        assert played == pytest.approx(float(evaluate_reference(env, f"constant-{action}", 6, 777).mean())), weights


def always(nets: Any, action: int) -> None:
    """Make an idqn Q-network (``nets``: its online or averaged weights) pick ``action`` in every state."""
    import torch

    last = cast(Any, nets)["q"].layers[-1]
    with torch.no_grad():
        last.weight.zero_()
        last.bias.zero_()
        last.bias[..., action] = 1.0


def test_the_readme_headline_keeps_the_latest_10_seed_told_against_own_study_not_a_later_screen() -> None:
    scores = json.loads((doc_figures.FIGURES / "treadmill_learners.json").read_text())
    groups = scores["groups"]
    told = [c for c in scores["comparisons"] if "team_sightings" in groups[c["a"]]["env_params"]
            and "team_sightings" not in groups[c["b"]]["env_params"]]  # fmt: skip
    seeds = [min(len(groups[c["a"]]["last"]), len(groups[c["b"]]["last"])) for c in told]
    best = [c for c, n in zip(told, seeds, strict=True) if n >= 10][-1]
    own = [g for g, v in groups.items() if "team_sightings" not in v["env_params"]]
    screen = {**told[-1], "a": own[0], "b": own[1]}  # one own setting against another, compared last
    scores["comparisons"] = [*scores["comparisons"], screen]
    headline = doc_figures.learner_comparisons(scores, headline=True)
    assert f"| {best['a']} vs {best['b']}" in headline and f"| {own[0]} vs {own[1]}" not in headline
    assert min(seeds) < max(seeds)  # a later, smaller told-against-own screen is there and not the headline
    smaller = [c for c, n in zip(told, seeds, strict=True) if c is not best and n < 15]
    assert all(f"| {c['a']} vs {c['b']}" not in headline for c in smaller)

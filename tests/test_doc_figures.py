"""Figures quoted in the README and docs are rendered from the benchmarks' JSON (``benchmarks/doc_figures.py``):
the files show what the JSON holds, and a changed figure makes them stale."""

from __future__ import annotations

import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

import doc_figures  # noqa: E402


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
    next(g for g in fig8["groups"] if g["group"] == "algo=idqn")["final"]["mean"] = -15.55
    next(v for v in fig8["verdicts"] if v["claim"] == "MA-MeSN ends above independent DQN")["verdict"] = "partly"
    records["fig6.json"]["verdict"] = "reproduced"
    records["fig5.json"]["minutes"] += 6.2  # the longest figure: 40.4 min, 108.9 in all
    for name, values in records.items():
        (tmp_path / name).write_text(json.dumps(values))
    monkeypatch.setattr(doc_figures, "REPRODUCTION", tmp_path)
    readme = (ROOT / "README.md").read_text()
    new = doc_figures.rendered(readme)
    for shown in ("−11.2 ± 1.7 vs −15.6 ± 1.0: partly at this budget", "· 6 reproduced ·",
                  "≤ 40 min a figure, 109 min in all"):  # fmt: skip
        assert shown not in readme and shown in new
    assert "vs −17.4 ± 1.0, p < 0.001: reproduced" in readme and "−17.4 ± 1.0" not in new


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

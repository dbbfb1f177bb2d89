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
    assert "12.3 ± 3.9" not in readme and "12.3 ± 3.9 |" in doc_figures.rendered(readme)
    assert "scores 23.5 ±" not in readme and "scores 23.5 ±" in doc_figures.rendered(readme)

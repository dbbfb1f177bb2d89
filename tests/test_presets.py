"""``preset``: named treadmill rules and learner settings a job starts from, under whatever the job sets itself."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from convoy.cli.main import main
from convoy.config import ALGORITHMS, DEMONSTRABLE, PRESET_ALGO_PARAMS, JobConfig
from convoy.envs.treadmill.config import CHARGER_RULES
from convoy.validation import ConfigError, build_config


def test_the_charger_preset_sets_the_rules_and_the_recipe_under_the_jobs_own_settings() -> None:
    job = JobConfig(algo="idqn", preset="charger", env_params={"n_agents": 4}, algo_params={"n_step": 1})
    assert job.env_params == {**CHARGER_RULES, "n_agents": 4}
    assert job.algo_params == {**PRESET_ALGO_PARAMS["charger"], "n_step": 1}  # the job's n_step wins
    assert JobConfig(**job.model_dump()) == job  # a resumed job (its job.json) comes back the same


@pytest.mark.parametrize("algo", [a for a in ALGORITHMS if a != "codbc"])
def test_every_algorithm_takes_the_preset_settings_it_has(algo: str) -> None:
    """DIAL has no entity encoder, learns from sequences (no n-step returns) and updates too rarely for the recipe's
    per-update averaging rates (its own target sync, its online weights judged); the rest take the whole recipe."""
    job = JobConfig(algo=algo, preset="charger")
    fields = ALGORITHMS[algo].config.model_fields
    not_dial = ("n_step", "target_tau", "policy_ema")
    expect = {k: v for k, v in PRESET_ALGO_PARAMS["charger"].items()
              if k in fields and not (algo == "dial" and k in not_dial)}  # fmt: skip
    assert job.algo_params == expect and job.env_params == CHARGER_RULES
    assert "n_step" not in JobConfig(algo="idqn", preset="charger", hierarchical=True).algo_params  # options span steps


@pytest.mark.parametrize("algo", [a for a in ALGORITHMS if a != "codbc"])
def test_charger_demo_starts_from_the_planner_where_the_algorithm_can(algo: str) -> None:
    """A demonstration start and its gentle Q-learning where the learner can take one; else the charger recipe."""
    demo, charger = JobConfig(algo=algo, preset="charger-demo"), JobConfig(algo=algo, preset="charger")
    assert demo.env_params == CHARGER_RULES
    if algo in DEMONSTRABLE:
        start = {"demonstrator": "planner", "eps_start": 0.05, "learning_starts": 20_000}
        assert demo.algo_params == {**charger.algo_params, **start}
    else:
        assert demo.algo_params == charger.algo_params
    assert "demonstrator" not in JobConfig(algo="idqn", preset="charger-demo", hierarchical=True).algo_params
    dqfd = JobConfig(algo=algo, preset="charger-dqfd")  # the same, with DQfD's margin where there is a start
    assert dqfd.algo_params == ({**demo.algo_params, "demo_margin": 1.0} if algo in DEMONSTRABLE else demo.algo_params)


def test_a_preset_off_the_treadmill_or_unknown_is_refused_naming_the_field() -> None:
    with pytest.raises(ConfigError, match="preset: 'charger' sets treadmill rules; drop it or train on the treadmill"):
        build_config(JobConfig, env="speaker-listener", preset="charger")
    choices = r"'charger', 'charger-demo' or 'charger-dqfd' \(got 'chargr'\)"
    with pytest.raises(ConfigError, match=rf"preset: Input should be {choices}"):
        build_config(JobConfig, preset="chargr")


def test_convoy_train_preset_runs_on_the_charger_rules(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    threads = torch.get_num_threads()
    out = tmp_path / "run"
    argv = ["train", "--inprocess", "--algo", "idqn", "--preset", "charger", "--steps", "320", "--num-envs", "16",
            "--eval-episodes", "2", "--no-progress", "--hp", "hidden=32", "--hp", "learning_starts=64",
            "--out", str(out)]  # fmt: skip
    try:
        assert main(argv) == 0
    finally:
        torch.set_num_threads(threads)
    job = json.loads((out / "job.json").read_text())
    assert job["preset"] == "charger" and job["env_params"] == CHARGER_RULES
    assert job["algo_params"]["n_step"] == 3 and job["algo_params"]["encoder"] == "entity"
    assert "adversary_speed" in capsys.readouterr().out  # the run's header names the rules it plays

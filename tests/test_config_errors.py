"""Impossible configurations fail early with a message naming the field and what is allowed."""

import pytest

from convoy.envs import make_batched, make_parallel
from convoy.envs.channel import MessageChannel
from convoy.envs.treadmill import TreadmillParallelEnv
from convoy.validation import ConfigError


@pytest.mark.parametrize(
    ("params", "field", "expect"),
    [
        ({"n_agents": 0}, "n_agents", "1 ≤ n_agents ≤ 1024"),
        ({"length": -5}, "length", "8 ≤ length"),
        ({"width": -1}, "width", "3 ≤ width"),
        ({"n_agents": 700, "n_adversaries": 0}, "n_agents", "1 ≤ n_agents ≤ 325"),
        ({"n_agents": 1, "n_adversaries": 0}, "n_adversaries", "at least 2 cars"),
        ({"observe_k": 4}, "observe_k", "1 ≤ observe_k ≤ n_agents + n_adversaries − 1"),
        ({"treadmill_speed": 5}, "treadmill_speed", "≤ max_speed"),
        ({"aggression": 1.5}, "aggression", "0.0 ≤ aggression ≤ 1.0"),
        ({"crash_penalty": "lots"}, "crash_penalty", "valid number"),
        ({"colour": "red"}, "colour", "known parameters"),
    ],
)
def test_bad_treadmill_config_names_field_and_range(params, field, expect) -> None:
    with pytest.raises(ConfigError) as info:
        make_batched("treadmill", 4, **params)
    assert info.value.field == field
    assert field in str(info.value) and expect in str(info.value)


def test_same_validation_in_every_front_end() -> None:
    with pytest.raises(ConfigError, match="n_agents"):
        TreadmillParallelEnv(n_agents=0)
    with pytest.raises(ConfigError, match="n_agents"):
        make_parallel("treadmill", n_agents=0)


def test_unknown_env_name_lists_the_known_ones() -> None:
    with pytest.raises(ConfigError) as info:
        make_batched("highway", 1)
    assert info.value.field == "env"
    assert "treadmill" in str(info.value) and "predator-prey" in str(info.value)


def test_num_envs_must_be_positive() -> None:
    with pytest.raises(ConfigError, match="num_envs"):
        make_batched("treadmill", 0)


def test_bad_channel_spec() -> None:
    with pytest.raises(ConfigError, match=r"drop.*0.0 ≤ drop ≤ 1.0"):
        MessageChannel.from_spec("drop=2")
    with pytest.raises(ValueError, match="key=value"):
        MessageChannel.from_spec("drop")


def test_the_rest_body_and_the_cli_take_the_job_fields_from_jobconfig() -> None:
    """One definition of each job field: the REST body's defaults, bounds and descriptions are JobConfig's (they
    once disagreed: 100 k vs 200 k default steps, num_envs ≤ 4,096 vs 65,536)."""
    from convoy.api.models import JobSubmit
    from convoy.cli.jobs import submit_body
    from convoy.cli.main import build_parser
    from convoy.config import JobConfig

    shared = set(JobSubmit.model_fields) & set(JobConfig.model_fields) - {"runtime"}  # the body takes a part of it
    assert {"algo", "env", "steps", "num_envs", "seed", "eval_episodes", "eval_every", "log_every"} <= shared
    body, job = JobSubmit.model_json_schema()["properties"], JobConfig.model_json_schema()["properties"]
    for name in shared:
        for key in ("default", "minimum", "maximum", "maxLength", "description"):
            assert body[name].get(key) == job[name].get(key), (name, key)
    cli = submit_body(build_parser().parse_args(["jobs", "submit"]))  # no flags: nothing overrides JobConfig's
    assert JobSubmit(**cli).job_config() == JobSubmit().job_config() == JobConfig()

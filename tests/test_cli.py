"""The ``convoy`` CLI: rollouts with summaries, GIFs and plots; readable errors; complete help."""

import json
import subprocess
import sys

import pytest
from PIL import Image
from PIL.GifImagePlugin import GifImageFile

from convoy.cli.main import build_parser, main
from convoy.envs.treadmill import TreadmillConfig


def test_rollout_writes_gif_summary_and_plot(tmp_path, capsys) -> None:
    gif, summary, plot = tmp_path / "ep.gif", tmp_path / "s.json", tmp_path / "r.png"
    rc = main(
        ["env", "rollout", "--env", "treadmill", "--agents", "3", "--adversaries", "1", "--episodes", "4",
         "--set", "max_steps=40", "--gif", str(gif), "--summary", str(summary), "--plot", str(plot)]
    )  # fmt: skip
    assert rc == 0
    out = capsys.readouterr().out
    assert "mean return" in out and "agent_2" in out
    data = json.loads(summary.read_text())
    assert data["episodes"] == 4 and len(data["episode_returns"]) == 4 and len(data["episode_returns"][0]) == 3
    assert all(1 <= n <= 40 for n in data["episode_lengths"])
    with Image.open(gif) as im:
        assert isinstance(im, GifImageFile) and im.format == "GIF" and im.n_frames == data["episode_lengths"][0] + 1
    assert Image.open(plot).format == "PNG"


def test_scripted_policy_beats_random(tmp_path) -> None:
    figures = {}
    for policy in ("scripted", "random"):
        out = tmp_path / f"{policy}.json"
        assert main(["env", "rollout", "--episodes", "32", "--policy", policy, "--summary", str(out)]) == 0
        figures[policy] = json.loads(out.read_text())["mean_return"]
    assert figures["scripted"] > 3 * figures["random"]


@pytest.mark.parametrize("env", ["referential", "speaker-listener", "predator-prey"])
def test_rollout_runs_every_env(env, capsys) -> None:
    extra = ["--set", "max_steps=30"] if env == "predator-prey" else []
    assert main(["env", "rollout", "--env", env, "--policy", "random", "--episodes", "3", *extra]) == 0
    assert "mean return" in capsys.readouterr().out


@pytest.mark.parametrize(
    ("argv", "needle"),
    [
        (["--agents", "0"], "n_agents"),
        (["--set", "length=-5"], "length"),
        (["--agents", "700", "--adversaries", "0"], "1 ≤ n_agents ≤"),
        (["--env", "highway"], "unknown environment"),
        (["--set", "nonsense"], "KEY=VALUE"),
        (["--env", "referential"], "--policy"),
    ],
)
def test_bad_input_prints_one_line_without_traceback(argv, needle) -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "convoy.cli", "env", "rollout", *argv],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 2
    assert needle in proc.stderr and "Traceback" not in proc.stderr + proc.stdout


def test_help_is_complete(capsys) -> None:
    for argv in (["--help"], ["env", "--help"], ["env", "rollout", "--help"], ["env", "list", "--help"]):
        with pytest.raises(SystemExit) as info:
            build_parser().parse_args(argv)
        assert info.value.code == 0
    text = capsys.readouterr().out
    for flag in ("--env", "--agents", "--adversaries", "--episodes", "--policy", "--seed", "--gif", "--set", "--plot"):
        assert flag in text
    for param in TreadmillConfig.model_fields:  # every treadmill rule is documented where --set is
        assert f"  {param} (default" in text


def test_env_list(capsys) -> None:
    assert main(["env", "list"]) == 0
    out = capsys.readouterr().out
    assert "treadmill" in out and "speaker-listener" in out
    assert main(["env", "list", "--params"]) == 0
    out = capsys.readouterr().out
    assert "n_targets (default 4, 2 ≤ n_targets ≤ 64)" in out and "keep_env_channel (default False)" in out


def test_building_the_cli_imports_no_torch() -> None:
    """Every `convoy` command, and the parent of a distributed job, starts without torch (~1.2 s on 2 cores):
    commands import their heavy modules when they run."""
    import subprocess
    import sys

    code = "import sys, convoy.cli.main as cli; cli.build_parser(); print('torch' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def test_api_fixes_become_convoy_commands_at_the_command_line() -> None:
    """A fix names the requests that help once (``api/remedy.py``): the API says them as routes, the command line
    (``Convoy-Words: cli``) as the convoy command that sends them, a body field as its flag."""
    from convoy.api.remedy import Fix, Step

    cases = [
        (Fix("scale it by resuming: {}", Step("POST /jobs/{id}/resume", "ma-1", {"actors": 4})),
         'scale it by resuming: POST /jobs/ma-1/resume {"actors": 4}',
         "scale it by resuming: `convoy jobs resume ma-1 --actors 4`"),
        (Fix("list the jobs with {}", Step("GET /jobs")), "list the jobs with GET /jobs",
         "list the jobs with `convoy jobs list`"),
        (Fix("check the job's state with {}", Step("GET /jobs/{id}")), "check the job's state with GET /jobs/{id}",
         "check the job's state with `convoy jobs status ID`"),
        (Fix("the whole log: {}", Step("GET /jobs/{id}/logs", "ab-12")).of_job("x"),
         "the whole log: GET /jobs/ab-12/logs", "the whole log: `convoy jobs logs ab-12`"),
        (Fix("list the files with {}", Step("GET /jobs/{id}/checkpoints")).of_job("ab-12"),
         "list the files with GET /jobs/ab-12/checkpoints",
         "list the files with `convoy jobs status ab-12` (its last checkpoint)"),
        (Fix("wait: {}", Step("GET /jobs/{id}/evaluations", "ab-12")), "wait: GET /jobs/ab-12/evaluations",
         "wait: GET /jobs/ab-12/evaluations"),  # no command lists evaluations: the route, in both
        (Fix("a pattern {1,3} is no slot"), "a pattern {1,3} is no slot", "a pattern {1,3} is no slot"),
    ]  # fmt: skip
    for fix, api_text, cli_text in cases:
        assert (fix.say("api"), fix.say("cli")) == (api_text, cli_text)
    with pytest.raises(KeyError):
        Step("GET /nowhere")


def test_every_command_a_fix_names_is_one_the_cli_takes() -> None:
    """Each route a fix may name is a route of the app, and its command (with a body's flags) parses with the CLI's
    own parser into the same request: the words cannot drift from the commands."""
    import shlex

    from fastapi.routing import APIRoute

    from convoy.api.remedy import COMMANDS, Step
    from convoy.api.routes import jobs, metrics, service, sweeps

    routes = {
        f"{m} {r.path.replace('{job_id}', '{id}').replace('{sweep_id}', '{id}')}"
        for module in (jobs, metrics, service, sweeps)
        for r in module.router.routes
        if isinstance(r, APIRoute)
        for m in r.methods or ()
    }
    parser = build_parser()
    for route, command in COMMANDS.items():
        assert route in routes, route
        body = {"actors": 3, "steps": 40_000} if route.startswith("POST") else {}
        said = Step(route, "ab-12", body).say("cli")
        if command is None:
            assert said == route.replace("{id}", "ab-12")
            continue
        argv = shlex.split(said.split("`")[1])
        assert argv[0] == "convoy", said
        args = parser.parse_args(argv[1:])
        assert getattr(args, "id", "ab-12") == "ab-12", said
        assert all(getattr(args, k) == v for k, v in body.items()), said

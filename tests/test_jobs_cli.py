"""``convoy jobs`` against a real ``convoy serve`` on 127.0.0.1: submit → list → watch → logs → status → resume →
watch, the success paths of scale/stop/delete on a job that waits in the queue, and one-line errors (exit 2) for
API errors, an unknown job, a wrong token and a service that is not there."""

from __future__ import annotations

import json
import re
from collections.abc import Iterator
from pathlib import Path

import pytest

from convoy.cli.main import main
from convoy.protocol.session import free_port
from tests.service_fixture import TOKEN, Service

pytestmark = pytest.mark.timeout(240)

SMALL = [
    "--steps", "20000", "--num-envs", "8", "--actors", "1", "--set", "n_agents=2", "--set", "length=30",
    "--set", "width=12", "--set", "max_steps=50", "--hp", "hidden=32", "--hp", "learning_starts=200",
    "--eval-episodes", "4", "--log-every", "1000",
]  # fmt: skip
SUBCOMMANDS = ("submit", "list", "status", "scale", "stop", "resume", "delete", "metrics", "logs", "evaluate", "watch")


@pytest.fixture(scope="module")
def service(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Service]:
    svc = Service(tmp_path_factory.mktemp("jobs-cli") / "svc")
    try:
        yield svc.start()
    finally:
        svc.stop()


@pytest.fixture(autouse=True)
def _wide_terminal(monkeypatch: pytest.MonkeyPatch) -> None:
    """Rich tables at 200 columns, so no cell is wrapped; no token from the environment."""
    monkeypatch.setenv("COLUMNS", "200")
    monkeypatch.delenv("CONVOY_API_TOKEN", raising=False)
    monkeypatch.delenv("CONVOY_API_URL", raising=False)


def jobs(capsys: pytest.CaptureFixture[str], url: str, *argv: str, token: str = TOKEN) -> tuple[int, str, str]:
    """Run ``convoy jobs --url URL --token TOKEN ARGV…`` in this process: (exit code, stdout, stderr)."""
    capsys.readouterr()
    code = main(["jobs", "--url", url, "--token", token, *argv])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def one_line_error(err: str, *parts: str) -> None:
    """stderr is exactly one line ``error: …`` containing ``parts``."""
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("error: "), err
    for part in parts:
        assert part in lines[0], err


@pytest.fixture(scope="module")
def job_id(service: Service) -> str:
    """The small job, submitted through the CLI (capsys is function-scoped, so capture by hand here)."""
    import contextlib
    import io

    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main(["jobs", "--url", service.url, "--token", TOKEN, "submit", *SMALL, "--name", "cli"])
    assert code == 0, err.getvalue()
    match = re.search(r"submitted (\S+): (queued|starting|running)", out.getvalue())
    assert match, out.getvalue()
    return match.group(1)


def test_help_of_every_subcommand(capsys: pytest.CaptureFixture[str]) -> None:
    for argv in (["jobs"], *(["jobs", sub] for sub in SUBCOMMANDS)):
        with pytest.raises(SystemExit) as exc:
            main([*argv, "--help"])
        assert exc.value.code == 0
        text = capsys.readouterr().out
        assert "--url" in text and "--token" in text, argv
    with pytest.raises(SystemExit):
        main(["jobs", "metrics", "--help"])
    assert "--since" in capsys.readouterr().out


def test_submit_and_list(capsys: pytest.CaptureFixture[str], service: Service, job_id: str) -> None:
    assert job_id.startswith("cli-")
    code, out, _ = jobs(capsys, service.url, "list")
    assert code == 0
    assert job_id in out and "ma-mesn/treadmill" in out and "/1" in out
    code, out, _ = jobs(capsys, service.url, "list", "--state", "completed", "--json")
    assert code == 0 and job_id not in out


def test_scale_stop_and_delete_a_queued_job(capsys: pytest.CaptureFixture[str], service: Service, job_id: str) -> None:
    """6 actors need all 8 processes: the job waits behind the small one, is scaled, stopped and deleted unstarted."""
    code, out, err = jobs(capsys, service.url, "submit", *SMALL, "--actors", "6", "--name", "waiter", "--json")
    assert code == 0, err
    waiter = json.loads(out)
    assert waiter["state"] == "queued" and waiter["actors"] == 6
    code, out, err = jobs(capsys, service.url, "scale", waiter["id"], "5")
    assert code == 0 and "5 actors" in out, err
    code, out, err = jobs(capsys, service.url, "stop", waiter["id"])
    assert code == 0 and "stopped" in out, err
    code, out, err = jobs(capsys, service.url, "delete", waiter["id"])
    assert code == 0 and "deleted" in out, err
    code, _, err = jobs(capsys, service.url, "status", waiter["id"])
    assert code == 2
    one_line_error(err, "error: id:", waiter["id"], "—")


def test_watch_until_completed(capsys: pytest.CaptureFixture[str], service: Service, job_id: str) -> None:
    code, out, err = jobs(capsys, service.url, "watch", job_id, "--interval", "0.5", "--timeout", "150")
    assert code == 0, err
    assert re.search(rf"job {job_id} completed: 20,\d{{3}}/20,000 env steps", out), out


def test_metrics_and_logs(capsys: pytest.CaptureFixture[str], service: Service, job_id: str) -> None:
    service.wait(job_id, lambda v: v["state"] == "completed", timeout=240, what="the job to complete")
    code, out, err = jobs(capsys, service.url, "logs", job_id, "--lines", "400")
    assert code == 0, err
    assert f"[h-{job_id}] exited learner-0" in out, out  # the job host's own log, through GET /jobs/{id}/logs
    code, out, err = jobs(capsys, service.url, "metrics", job_id)
    assert code == 0, err
    assert "env_steps" in out and "return" in out and "policy_lag" in out
    assert len(re.findall(r"│\s+\d+\s+│", out)) >= 10, out  # one table row per 1000 env steps
    argv = ("metrics", job_id, "--since", "10000", "--names", "return,loss", "--json")
    code, out, err = jobs(capsys, service.url, *argv)
    assert code == 0, err
    rows = [json.loads(line) for line in out.splitlines()]
    assert rows and all(r["env_steps"] > 10_000 and set(r) <= {"env_steps", "return", "loss"} for r in rows)


def test_status_shows_completed(capsys: pytest.CaptureFixture[str], service: Service, job_id: str) -> None:
    service.wait(job_id, lambda v: v["state"] == "completed", timeout=240, what="the job to complete")
    code, out, err = jobs(capsys, service.url, "status", job_id)
    assert code == 0, err
    assert "completed" in out and "20,000" in out and '"n_agents": 2' in out and "dropped messages" in out
    assert re.search(r"final greedy return\W+[-\d.]+ ± [\d.]+ .*random [-\d.]+", out), out  # the summary's figures


def test_evaluate_waits_for_the_background_evaluation(
    capsys: pytest.CaptureFixture[str], service: Service, job_id: str
) -> None:
    service.wait(job_id, lambda v: v["state"] == "completed", timeout=240, what="the job to complete")
    code, out, err = jobs(capsys, service.url, "evaluate", job_id, "--episodes", "8", "--checkpoint", "best.pt")
    assert code == 0, err
    assert re.search(r"evaluation [0-9a-f]{6} of .*running\ngreedy return [-\d.]+ ± [\d.]+ over 8 episodes", out), out


def test_dropped_messages_read_by_role_and_reason() -> None:
    from convoy.cli.jobs import dropped_text

    dropped = {"learner": {"action-range": 3, "non-finite": 6}, "actors": {"garbage": 1200, "overflow": 0}}
    assert dropped_text(dropped) == "learner: action-range 3, non-finite 6; actors: garbage 1,200"
    assert dropped_text({"learner": {}, "service": {"unusable-metrics": 0}}) == "none"


def test_scale_of_a_completed_job(capsys: pytest.CaptureFixture[str], service: Service, job_id: str) -> None:
    service.wait(job_id, lambda v: v["state"] == "completed", timeout=240, what="the job to complete")
    code, out, err = jobs(capsys, service.url, "scale", job_id, "2")
    assert code == 2 and not out
    one_line_error(err, "completed", f"`convoy jobs resume {job_id} --actors 2`", "—")
    assert "POST /jobs" not in err  # at the command line the fix is a command, not a REST route
    code, _, err = jobs(capsys, service.url, "stop", job_id)
    assert code == 2
    one_line_error(err, "error: state:", "completed")


def test_resume_and_watch_again(capsys: pytest.CaptureFixture[str], service: Service, job_id: str) -> None:
    code, out, err = jobs(capsys, service.url, "resume", job_id, "--steps", "30000", "--actors", "2")
    assert code == 0, err
    assert "queued" in out and "2 actors" in out and "30,000" in out
    code, out, err = jobs(capsys, service.url, "watch", job_id, "--interval", "0.5", "--timeout", "150")
    assert code == 0, err
    assert re.search(rf"job {job_id} completed: 30,\d{{3}}/30,000 env steps", out), out
    # captured output is not a terminal: progress comes as plain lines, whole (never cut to a terminal's width)
    progress = [line for line in out.splitlines() if re.match(rf"{job_id} .*: [\d,]+/30,000 env steps · return ", line)]
    assert len(progress) >= 2 and all(line.endswith(tuple("0123456789–")) for line in progress), out
    code, out, _ = jobs(capsys, service.url, "status", job_id, "--json")
    assert code == 0 and json.loads(out)["actors"] == 2


def test_unknown_job(capsys: pytest.CaptureFixture[str], service: Service) -> None:
    missing = (["status", "no-such-job"], ["watch", "no-such-job"], ["metrics", "no-such-job"], ["logs", "no-such-job"])
    for argv in (*missing, ["stop", "nope"]):
        code, out, err = jobs(capsys, service.url, *argv)
        assert code == 2 and not out, argv
        one_line_error(err, "error: id:", "not found", "— list the jobs with `convoy jobs list`")
        assert "GET /jobs" not in err and err.count("jobs list") == 1, err  # says it once, as a command


def test_the_service_says_its_fixes_in_the_cli_words_the_cli_asks_for(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    """The job service's own refusals, served by the app in this process (no job runs), to `convoy jobs`: the CLI
    asks for its words (``Convoy-Words: cli``) and prints the fix as the service said it — a command, with the flag
    of the body's field — where a plain HTTP client gets the route. Nothing rewrites the text on the way."""
    import threading
    import time

    import httpx
    import uvicorn

    from convoy.api.app import create_app
    from convoy.services.jobservice import JobService
    from convoy.services.store import JobStore
    from tests.service_fixture import AUTH, SMALL_JOB

    store = JobStore(tmp_path / "jobs.sqlite")  # a job that ran and stopped, before the service opens the store
    store.create("ma-1", SMALL_JOB, actors=1, out_dir=str(tmp_path / "jobs" / "ma-1"), state="stopped")
    store.close()
    control = JobService(tmp_path, max_processes=4)
    port = free_port()
    server = uvicorn.Server(uvicorn.Config(create_app(control, TOKEN), port=port, log_level="warning"))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    try:
        t_end = time.monotonic() + 60
        while not server.started and thread.is_alive() and time.monotonic() < t_end:
            time.sleep(0.02)
        url = f"http://127.0.0.1:{port}"
        body = httpx.patch(f"{url}/jobs/ma-1", json={"actors": 2}, headers=AUTH).json()
        assert body["fix"] == 'scale it by resuming: POST /jobs/ma-1/resume {"actors": 2}', body
        code, out, err = jobs(capsys, url, "scale", "ma-1", "2")
        assert code == 2 and not out
        line = "error: state: job 'ma-1' is stopped — scale it by resuming: `convoy jobs resume ma-1 --actors 2`"
        assert err.strip() == line, err
        code, _, err = jobs(capsys, url, "stop", "ma-1")
        assert code == 2 and err.strip().endswith("— check the job's state with `convoy jobs status ma-1`"), err
        code, _, err = jobs(capsys, url, "status", "nope")
        assert code == 2 and err.strip().endswith("— list the jobs with `convoy jobs list`"), err
        code, _, err = jobs(capsys, url, "evaluate", "ma-1", "--checkpoint", "best.pt")
        one_line_error(err, "error: checkpoint:", "no best.pt yet", "— evaluate one it has: `convoy jobs status ma-1`")
        assert code == 2 and "GET /" not in err, err
    finally:
        server.should_exit = True
        thread.join(10)
        control.close()


def test_wrong_and_missing_token(capsys: pytest.CaptureFixture[str], service: Service, job_id: str) -> None:
    code, _, err = jobs(capsys, service.url, "scale", job_id, "1", token="wrong-token")
    assert code == 2
    one_line_error(err, "error: Authorization:", "bearer token", "—", "pass --token TOKEN")  # the CLI's words
    assert "Authorization: Bearer" not in err
    code, _, err = jobs(capsys, service.url, "submit", *SMALL, token="")
    assert code == 2
    one_line_error(err, "error: Authorization:", "CONVOY_API_TOKEN")


def test_api_validation_errors(capsys: pytest.CaptureFixture[str], service: Service) -> None:
    code, _, err = jobs(capsys, service.url, "submit", "--algo", "no-such-algo", "--actors", "1")
    assert code == 2
    one_line_error(err, "error: algo:", "no-such-algo", "—")
    code, _, err = jobs(capsys, service.url, "submit", "--actors", "65")
    assert code == 2
    one_line_error(err, "error: actors:", "—")
    code, _, err = jobs(capsys, service.url, "list", "--state", "done")
    assert code == 2
    one_line_error(err, "error: state:")
    code, _, err = jobs(capsys, service.url, "submit", "--set", "no-equals-sign")
    assert code == 2 and "--set" in err


def test_unreachable_service(capsys: pytest.CaptureFixture[str]) -> None:
    url = f"http://127.0.0.1:{free_port()}"
    for argv in (["list"], ["status", "x"], ["submit", *SMALL], ["watch", "x"]):
        code, out, err = jobs(capsys, url, *argv)
        assert code == 2 and not out, argv
        one_line_error(err, f"error: cannot reach {url} (is `convoy serve` running?)")


def test_url_from_the_environment(
    capsys: pytest.CaptureFixture[str], service: Service, job_id: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("CONVOY_API_URL", service.url)
    monkeypatch.setenv("CONVOY_API_TOKEN", "wrong-token")
    capsys.readouterr()
    assert main(["jobs", "status", job_id]) == 0
    assert job_id in capsys.readouterr().out
    assert main(["jobs", "scale", job_id, "1"]) == 2  # the environment's (wrong) token is used
    one_line_error(capsys.readouterr().err, "error: Authorization:")
    assert main(["jobs", "status", job_id, "--url", "http://127.0.0.1:1"]) == 2  # --url after the subcommand
    one_line_error(capsys.readouterr().err, "cannot reach http://127.0.0.1:1")


def test_watch_of_a_failing_job_rewinds_and_exits_1(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """Scripted answers (no server): running at step 5000, re-queued with its history cut to 3000, then failed."""
    import convoy.cli.jobs as jobs_cmd

    def view(state: str, env_steps: int, error: str | None = None) -> dict[str, object]:
        progress = {"env_steps": env_steps, "fraction": env_steps / 10_000, "return": 1.5, "updates": 7}
        return {"id": "j-1", "state": state, "steps": 10_000, "actors": 2, "actors_alive": 1, "queue_position": None,
                "progress": progress, "error": error}  # fmt: skip

    views = iter([view("running", 5000), view("queued", 3000), view("failed", 3000, "host exited\nwith code 1")])
    pages = iter([
        {"rows": [{"env_steps": 5000, "return": 1.5}], "last_step": 5000},
        {"rows": [], "last_step": 3000},
        {"rows": [], "last_step": 3000},
    ])  # fmt: skip
    sinces: list[object] = []

    def call(self: object, method: str, path: str, **kwargs: object) -> object:
        if path.endswith("/metrics"):
            params = kwargs.get("params")
            sinces.append(params.get("since") if isinstance(params, dict) else None)
            return next(pages)
        return next(views)

    monkeypatch.setattr(jobs_cmd.Api, "call", call)
    capsys.readouterr()
    assert main(["jobs", "watch", "j-1", "--interval", "0.01"]) == 1
    assert sinces == [4999, 5000, 3000]
    one_line_error(capsys.readouterr().err, "job j-1 failed: 3,000/10,000 env steps", "host exited with code 1", "—")

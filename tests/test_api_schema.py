"""Bad input never gives a 5xx: schemathesis against a live ``convoy serve``, plus hand-written error cases.

One real service runs for the whole module on 127.0.0.1 with ``--max-processes 3``. Its first job (the *blocker*,
1 actor = 3 processes) takes the whole budget and its process group is frozen with SIGSTOP right after it starts,
so it holds the budget without using the CPU: every job submitted later — by schemathesis (``POST /jobs`` is fuzzed
too) or by hand — stays ``queued`` and no generated body can start training. Jobs asking for 2 or more actors need
more than 3 processes and are refused with 422 (field ``actors``). The teardown ends the API first (so nothing
queued can start) and then the blocker's process group, by PID.

Case count: schemathesis runs each of the ``N_OPERATIONS`` operations through its examples, coverage and fuzzing
phases; the fuzzing phase alone generates up to ``MAX_EXAMPLES`` cases per operation. Every case the test function
sees is counted per operation, and the module's teardown asserts that the sum is at least ``MIN_CASES`` (1000) and that
every operation was exercised. Every case carries the bearer token, so mutating routes are tested past the auth
check. Every schemathesis check runs (no 5xx, status codes, headers and bodies as documented, invalid data
rejected, valid data accepted) except valid-data acceptance on ``POST /jobs`` (see the test).
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import time
from collections import Counter
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest
import requests
import schemathesis
from hypothesis import HealthCheck, settings
from schemathesis.checks import positive_data_acceptance

from tests.service_fixture import AUTH, SMALL_JOB, Service

pytestmark = pytest.mark.timeout(240)

MAX_EXAMPLES = 100
MIN_CASES = 1000
N_OPERATIONS = 26  # every route in /openapi.json (the dashboard and /static are not in the schema)
CASES: Counter[str] = Counter()


@pytest.fixture(scope="module", autouse=True)
def _case_count() -> Iterator[None]:
    """After the module, whatever order its tests ran in: the generated requests (when they ran) reached MIN_CASES
    and exercised every operation."""
    yield
    if CASES:
        assert len(CASES) == N_OPERATIONS, sorted(CASES)
        assert sum(CASES.values()) >= MIN_CASES, dict(CASES)
        print(f"schemathesis: {sum(CASES.values())} cases over {len(CASES)} operations: {dict(sorted(CASES.items()))}")


def _killpg(pid: int, sig: signal.Signals) -> None:
    with contextlib.suppress(ProcessLookupError, PermissionError):
        os.killpg(pid, sig)


@pytest.fixture(scope="module")
def service(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Service]:
    svc = Service(tmp_path_factory.mktemp("schema") / "svc", max_processes=3)
    frozen: list[int] = []
    try:
        svc.start()
        body = {**SMALL_JOB, "steps": 1_000_000, "actors": 1, "name": "blocker"}
        resp = svc.client.post("/jobs", json=body, headers=AUTH)
        assert resp.status_code == 201, resp.text
        blocker = resp.json()["id"]
        view = svc.wait(blocker, lambda v: v["state"] != "queued", timeout=30, what="the blocker to start")
        assert view["state"] in ("starting", "running"), view
        pids = svc.host_pids()
        assert len(pids) == 1, pids
        frozen = pids
        _killpg(pids[0], signal.SIGSTOP)  # holds the 3-process budget, uses no CPU
        svc.blocker = blocker  # type: ignore[attr-defined]  # this module's fixture tags its service with the job
        yield svc
    finally:
        svc.stop()  # the API first: with it gone no queued job can start; then the blocker's group (SIGKILL)
        for pid in frozen:
            _killpg(pid, signal.SIGKILL)
            _killpg(pid, signal.SIGCONT)


@pytest.fixture(scope="module")
def api_schema(service: Service) -> Any:
    return schemathesis.openapi.from_url(f"{service.url}/openapi.json")


@pytest.fixture(scope="module")
def http() -> Iterator[requests.Session]:
    with requests.Session() as session:
        yield session


def assert_error(resp: httpx.Response, status: int, field: str | None = None) -> dict[str, Any]:
    """The response has ``status`` and the one error shape, naming ``field`` and saying how to fix it."""
    assert resp.status_code == status, f"{resp.status_code} != {status}: {resp.text}"
    body = resp.json()
    assert set(body) == {"field", "problem", "fix"}, body
    assert body["field"] and body["problem"] and body["fix"].strip(), body
    if field is not None:
        assert body["field"] == field, body
    return body


def submit(svc: Service, **extra: Any) -> httpx.Response:
    return svc.client.post("/jobs", json={**SMALL_JOB, "steps": 20_000, "actors": 1, **extra}, headers=AUTH)


@pytest.fixture(scope="module")
def queued_job(service: Service) -> str:
    """A job that stays queued behind the blocker."""
    resp = submit(service, name="waiting")
    assert resp.status_code == 201, resp.text
    job = resp.json()
    assert job["state"] == "queued" and job["queue_position"] >= 1, job
    return job["id"]


# --- generated cases ----------------------------------------------------------------------------------------------


@pytest.fixture(autouse=True)
def _schemathesis_on_pytest_9(request: pytest.FixtureRequest) -> None:
    """schemathesis 4's lazy ``from_fixture`` reads ``node._nodeid``, which pytest 9 no longer has."""
    if not hasattr(request.node, "_nodeid"):
        request.node._nodeid = request.node.nodeid


schema = schemathesis.pytest.from_fixture("api_schema")


@schema.parametrize()
@settings(max_examples=MAX_EXAMPLES, deadline=None, suppress_health_check=list(HealthCheck), print_blob=True)
def test_generated_requests_never_give_a_server_error(
    case: schemathesis.Case, service: Service, http: requests.Session
) -> None:
    if case.operation.path.endswith("/events") and isinstance(case.query, dict):
        case.query.setdefault("timeout", 1)  # a stream: never leave it open for its default 300 s
    CASES[case.operation.label] += 1
    response = case.call(base_url=service.url, session=http, headers=AUTH, timeout=20)
    # Every check but one: POST /jobs refuses with a 422 naming the field some bodies its schema allows — limits
    # across fields (steps ≥ num_envs, network size) and the free-form env/algo params, which no schema states.
    # POST /sweeps likewise: its base is a job body and its grid's values are free-form.
    submits = case.operation.method.upper() == "POST" and case.operation.path in ("/jobs", "/sweeps")
    case.validate_response(response, excluded_checks=[positive_data_acceptance] if submits else None)


# --- hand-written cases -------------------------------------------------------------------------------------------


def test_unknown_algorithm(service: Service) -> None:
    body = assert_error(submit(service, algo="no-such-algo"), 422, "algo")
    assert "no-such-algo" in body["problem"]


def test_the_catalogue_lists_every_parameter_the_errors_point_to(service: Service, capsys) -> None:
    """GET /envs and GET /algos list every env and algorithm with each parameter's default, range and meaning
    (the fields a 422 names are among them, and the 422 says where to look); convoy algos --json is the same."""
    from convoy.cli.main import main

    envs = service.client.get("/envs").json()["envs"]
    algos = service.client.get("/algos").json()["algos"]
    assert {"treadmill", "referential"} <= set(envs) and {"idqn", "ma-mesn", "dial"} <= set(algos)
    assert {"sensor_fov", "team_sightings"} <= set(envs["treadmill"]["params"])
    assert {"gumbel_noise", "message_bits"} <= set(algos["ma-mesn"]["params"])
    lr = algos["idqn"]["params"]["lr"]
    assert lr["range"] and lr["description"] and algos["idqn"]["env_defaults"]["treadmill"]["lr"] == 1e-4
    body = assert_error(submit(service, algo_params={"lr": -1.0}), 422, "lr")
    assert "GET /algos" in body["fix"], body
    assert main(["algos", "--json"]) == 0
    assert json.loads(capsys.readouterr().out) == algos


@pytest.mark.parametrize("actors", [0, -1, -1000])
def test_actors_not_positive(service: Service, actors: int) -> None:
    assert_error(submit(service, actors=actors), 422, "actors")


@pytest.mark.parametrize("actors", [65, 1000, 2**40])
def test_actors_above_the_api_limit(service: Service, actors: int) -> None:
    body = assert_error(submit(service, actors=actors), 422, "actors")
    assert "64" in body["fix"]


def test_actors_above_the_process_budget(service: Service, queued_job: str) -> None:
    body = assert_error(submit(service, actors=2), 422, "actors")
    assert "4 processes" in body["problem"] and "3" in body["problem"]
    assert_error(service.client.patch(f"/jobs/{queued_job}", json={"actors": 5}, headers=AUTH), 422, "actors")


def test_bad_env_and_algo_params(service: Service) -> None:
    assert_error(submit(service, env_params={"n_agents": 0}), 422, "n_agents")
    assert_error(submit(service, env_params={"no_such_param": 1}), 422, "no_such_param")
    assert_error(submit(service, algo_params={"hidden": "wide"}), 422, "hidden")
    assert_error(submit(service, env="no-such-env"), 422, "env")
    assert_error(submit(service, steps=0), 422, "steps")
    assert_error(submit(service, name="bad name/with slash"), 422, "name")


@pytest.mark.parametrize(
    ("extra", "field", "limit"),
    [
        ({"algo_params": {"hidden": [1_000_000_000]}}, "algo_params.hidden", "max-layer-width"),  # wanted ~100 GB
        ({"algo_params": {"hidden": [16_000, 16_000]}}, "algo_params.hidden", "max-hidden-weights"),
        ({"num_envs": 4096, "env_params": {"n_agents": 256}}, "num_envs", "max-agent-envs"),  # 1.05 M cars
    ],
)
def test_jobs_too_large_for_the_machine_are_refused_at_submit(
    service: Service, extra: dict, field: str, limit: str
) -> None:
    """The audit's ``hidden: [1e9]`` was accepted (201) and crash-looped; now 422 names the field, the limit and
    the server flag that changes it, and nothing is queued."""
    before = len(service.client.get("/jobs").json()["jobs"])
    body = assert_error(submit(service, **extra), 422, field)
    assert limit.replace("-", "_") in body["problem"] and f"convoy serve --{limit} N" in body["problem"], body
    assert len(service.client.get("/jobs").json()["jobs"]) == before


class _Touch:
    """A pickled object whose loading (``torch.load(weights_only=False)``) would create a file: hostile."""

    def __init__(self, path: Path) -> None:
        self.path = path

    def __reduce__(self) -> tuple[Any, ...]:
        return (open, (str(self.path), "w"))


def test_a_codbc_job_with_a_teacher_it_cannot_use_is_refused_at_submit(service: Service, tmp_path: Path) -> None:
    """A CoDBC job naming a missing, corrupt, hostile or foreign teacher was accepted (201), and its actors died on
    the teacher and were respawned with back-off for ever (state running, no error). The service reads the file
    where its processes would (without running anything in it) and answers 422 naming the field; nothing is
    queued."""
    import torch

    from convoy.algos.agent import make_agent
    from convoy.algos.checkpoint import save_checkpoint
    from convoy.config import job_config
    from convoy.envs import make_batched

    corrupt, hostile, foreign = tmp_path / "corrupt.pt", tmp_path / "hostile.pt", tmp_path / "foreign.pt"
    corrupt.write_bytes(b"not a checkpoint")
    marker = tmp_path / "pwned"
    torch.save({"kind": "convoy-checkpoint", "format": 1, "state": _Touch(marker)}, hostile)
    other = job_config(algo="idqn", env="referential", algo_params={"hidden": [8]})
    env = make_batched("referential", 1)
    save_checkpoint(foreign, make_agent(other, env.spec, device="cpu"), other, {"env_steps": 0})
    env.close()
    before = len(service.client.get("/jobs").json()["jobs"])
    for teacher, says in (
        (tmp_path / "missing.pt", "no such file"),
        (corrupt, "corrupt or not a Convoy checkpoint"),
        (hostile, "could run code"),
        (foreign, "was trained on"),
    ):
        resp = submit(service, algo="codbc", algo_params={"hidden": [32], "teacher": str(teacher)})
        body = assert_error(resp, 422, "algo_params.teacher")
        assert str(teacher) in body["problem"] and says in body["problem"], body
    assert not marker.exists()
    assert len(service.client.get("/jobs").json()["jobs"]) == before


def test_the_restart_policy_the_errors_name_is_settable_over_rest(service: Service) -> None:
    """A job failed at the 6th actor death told the user to raise runtime.max_restarts, which REST refused (422
    "extra inputs"); the runtime's restart fields are now part of the job body."""
    runtime = {"actor_max_restarts": 500, "max_restarts": 9, "restart_backoff_s": 2.0}
    resp = submit(service, name="policy", runtime=runtime)
    assert resp.status_code == 201, resp.text
    job = resp.json()
    try:
        assert {k: job["config"]["runtime"][k] for k in runtime} == runtime
    finally:
        assert service.client.delete(f"/jobs/{job['id']}", headers=AUTH).status_code == 204
    assert_error(submit(service, runtime={"actor_max_restarts": -1}), 422, "runtime.actor_max_restarts")


def test_fewer_steps_than_one_batched_step_is_refused(service: Service) -> None:
    """The audit's ``steps: 10`` with 4,096 envs trained 32,768 steps."""
    body = assert_error(submit(service, steps=10, num_envs=4096), 422, "steps")
    assert "num_envs" in body["problem"]


@pytest.mark.parametrize("raw", [b"{", b"{'algo': 'x'}", b"not json", b'{"actors": 1,}'])
def test_malformed_json_body(service: Service, raw: bytes) -> None:
    headers = {**AUTH, "Content-Type": "application/json"}
    assert_error(service.client.post("/jobs", content=raw, headers=headers), 400, "body")


@pytest.mark.parametrize("body", [[], "a string", 3, None])
def test_body_that_is_not_an_object(service: Service, body: Any) -> None:
    assert_error(service.client.post("/jobs", json=body, headers=AUTH), 422)


def test_unknown_field_in_body(service: Service, queued_job: str) -> None:
    body = assert_error(submit(service, learning_rate=0.1), 422, "learning_rate")
    assert "extra" in body["problem"].lower() or "not permitted" in body["problem"].lower()
    patch = service.client.patch(f"/jobs/{queued_job}", json={"actors": 1, "replicas": 2}, headers=AUTH)
    assert_error(patch, 422, "replicas")
    resume = service.client.post(f"/jobs/{queued_job}/resume", json={"budget": 5}, headers=AUTH)
    assert_error(resume, 422, "budget")


def test_missing_token(service: Service, queued_job: str) -> None:
    assert_error(service.client.post("/jobs", json={**SMALL_JOB, "actors": 1}), 401, "Authorization")
    assert_error(service.client.patch(f"/jobs/{queued_job}", json={"actors": 1}), 401, "Authorization")
    for path in (f"/jobs/{queued_job}/stop", f"/jobs/{queued_job}/resume", f"/jobs/{queued_job}/evaluate"):
        assert_error(service.client.post(path, json={}), 401, "Authorization")
    assert_error(service.client.delete(f"/jobs/{queued_job}"), 401, "Authorization")
    assert service.client.get(f"/jobs/{queued_job}").json()["state"] == "queued"


@pytest.mark.parametrize(
    "header",
    [
        "Bearer wrong-token",
        "Bearer test-token extra",
        "bearer test-tokenX",
        "Basic dGVzdC10b2tlbg==",
        "test-token",
        "Bearer",
    ],
)
def test_wrong_token(service: Service, queued_job: str, header: str) -> None:
    auth = {"Authorization": header}
    assert_error(service.client.post("/jobs", json={**SMALL_JOB, "actors": 1}, headers=auth), 401, "Authorization")
    assert_error(service.client.patch(f"/jobs/{queued_job}", json={"actors": 1}, headers=auth), 401, "Authorization")


@pytest.mark.parametrize(
    ("method", "path", "body"),
    [
        ("GET", "/jobs/{id}", None),
        ("PATCH", "/jobs/{id}", {"actors": 1}),
        ("POST", "/jobs/{id}/stop", None),
        ("POST", "/jobs/{id}/resume", {}),
        ("DELETE", "/jobs/{id}", None),
        ("GET", "/jobs/{id}/metrics", None),
        ("GET", "/jobs/{id}/events", None),
        ("GET", "/jobs/{id}/checkpoints", None),
        ("GET", "/jobs/{id}/checkpoints/checkpoint.pt", None),
        ("POST", "/jobs/{id}/evaluate", {"episodes": 2}),
        ("GET", "/jobs/{id}/evaluations", None),
        ("GET", "/jobs/{id}/evaluations/abcdef", None),
        ("GET", "/jobs/{id}/logs", None),
    ],
)
def test_unknown_job(service: Service, method: str, path: str, body: Any) -> None:
    url = path.format(id="no-such-job")
    resp = service.client.request(method, url, json=body, headers=AUTH)
    err = assert_error(resp, 404, "id")
    assert "no-such-job" in err["problem"]


@pytest.mark.parametrize("job_id", ["bad id", "a" * 65, "semi;colon", "ünïcode"])
def test_malformed_job_id(service: Service, job_id: str) -> None:
    assert_error(service.client.get(f"/jobs/{job_id}"), 422, "job_id")


def test_body_over_64_kib(service: Service) -> None:
    big = {**SMALL_JOB, "actors": 1, "env_params": {"pad": "x" * (65 * 1024)}}
    body = assert_error(service.client.post("/jobs", json=big, headers=AUTH), 413, "body")
    assert "65536" in body["problem"]
    assert_error(service.client.post("/jobs", content=b"{" + b" " * 70_000 + b"}", headers=AUTH), 413, "body")


def test_chunked_body_over_64_kib(service: Service) -> None:
    def chunks() -> Iterator[bytes]:
        yield b'{"name": "'
        for _ in range(80):
            yield b"x" * 1024
        yield b'"}'

    resp = service.client.post("/jobs", content=chunks(), headers={**AUTH, "Content-Type": "application/json"})
    assert_error(resp, 413, "body")


@pytest.mark.parametrize("state", ["done", "QUEUED", "", "1"])
def test_bad_state_filter(service: Service, state: str) -> None:
    body = assert_error(service.client.get("/jobs", params={"state": state}), 422, "state")
    assert "queued" in body["fix"] or "queued" in body["problem"]


def test_state_filter(service: Service, queued_job: str) -> None:
    jobs = service.client.get("/jobs", params={"state": "queued"}).json()["jobs"]
    assert queued_job in [j["id"] for j in jobs] and all(j["state"] == "queued" for j in jobs)


@pytest.mark.parametrize(("param", "value"), [("since", "ten"), ("since", "1.5"), ("since", "-2"), ("limit", "0")])
def test_bad_metrics_query(service: Service, queued_job: str, param: str, value: str) -> None:
    assert_error(service.client.get(f"/jobs/{queued_job}/metrics", params={param: value}), 422, param)


def test_metrics_of_a_job_without_rows(service: Service, queued_job: str) -> None:
    page = service.client.get(f"/jobs/{queued_job}/metrics", params={"since": 0, "names": "return,loss"}).json()
    assert page == {"job": queued_job, "rows": [], "last_step": None}


def test_checkpoint_download_of_a_missing_file(service: Service, queued_job: str) -> None:
    for name in ("checkpoint.pt", "nothing-here.pt", "job.json", "..pt"):
        resp = service.client.get(f"/jobs/{queued_job}/checkpoints/{name}")
        assert_error(resp, 404, "name")
    assert service.client.get(f"/jobs/{queued_job}/checkpoints").json() == {"job": queued_job, "checkpoints": []}


def test_resume_of_a_queued_job(service: Service, queued_job: str) -> None:
    body = assert_error(service.client.post(f"/jobs/{queued_job}/resume", json={}, headers=AUTH), 409)
    assert "queued" in body["problem"]


def test_stop_resume_and_delete_of_a_job_that_never_ran(service: Service) -> None:
    resp = submit(service, name="cancel-me")
    assert resp.status_code == 201, resp.text
    job = resp.json()["id"]
    assert service.client.post(f"/jobs/{job}/stop", headers=AUTH).json()["state"] == "stopped"
    assert_error(service.client.post(f"/jobs/{job}/stop", headers=AUTH), 409, "state")
    assert_error(service.client.patch(f"/jobs/{job}", json={"actors": 1}, headers=AUTH), 409)
    resume = service.client.post(f"/jobs/{job}/resume", json={"actors": 2}, headers=AUTH)
    assert_error(resume, 422, "actors")  # 4 processes > the budget of 3
    assert_error(service.client.post(f"/jobs/{job}/resume", json={"steps": 0}, headers=AUTH), 422, "steps")
    resume = service.client.post(f"/jobs/{job}/resume", json={"steps": 30_000}, headers=AUTH)
    assert resume.status_code == 200 and resume.json()["state"] == "queued" and resume.json()["steps"] == 30_000
    assert service.client.post(f"/jobs/{job}/stop", headers=AUTH).json()["state"] == "stopped"
    assert service.client.delete(f"/jobs/{job}", headers=AUTH).status_code == 204
    assert_error(service.client.get(f"/jobs/{job}"), 404, "id")


def test_evaluate_without_a_checkpoint(service: Service, queued_job: str) -> None:
    path = f"/jobs/{queued_job}/evaluate"
    assert_error(service.client.post(path, json={"episodes": 2}, headers=AUTH), 422, "checkpoint")
    assert_error(service.client.post(path, json={"episodes": 0}, headers=AUTH), 422, "episodes")
    assert_error(service.client.post(path, json={"messages": "shouted"}, headers=AUTH), 422, "messages")
    assert_error(service.client.post(path, json={"checkpoint": "../x.pt"}, headers=AUTH), 422, "checkpoint")


def test_events_of_a_queued_job_close_after_the_timeout(service: Service, queued_job: str) -> None:
    t0 = time.monotonic()
    resp = service.client.get(f"/jobs/{queued_job}/events", params={"timeout": 1})
    assert resp.status_code == 200 and "event: state" in resp.text and '"queued"' in resp.text
    assert time.monotonic() - t0 < 120  # it closed (a stream that never closed would hit the client's timeout)
    assert_error(service.client.get(f"/jobs/{queued_job}/events", params={"timeout": 0}), 422, "timeout")


def test_events_carry_ids_so_a_browser_resumes_after_the_last_one(service: Service) -> None:
    """``retry:`` first, every event's ``id`` = the last env step sent; ``Last-Event-ID`` resumes after it."""
    from convoy.services.store import JobStore

    job = submit(service, name="sse").json()["id"]  # queued behind the blocker: only the rows written here
    with JobStore(service.data / "jobs.sqlite") as store:
        store.append_metrics(job, [{"env_steps": s, "return": float(s)} for s in (100, 200, 300)])
    first = service.client.get(f"/jobs/{job}/events", params={"timeout": 1}).text
    assert first.startswith("retry: ") and "id: 300\nevent: metrics\ndata: " in first, first
    resumed = service.client.get(f"/jobs/{job}/events", params={"timeout": 1}, headers={"Last-Event-ID": "200"})
    data = [line for line in resumed.text.splitlines() if line.startswith("data: [")]
    assert [r["env_steps"] for r in json.loads(data[0][6:])] == [300], resumed.text
    bad = service.client.get(f"/jobs/{job}/events", headers={"Last-Event-ID": "yesterday"})
    assert_error(bad, 422, "Last-Event-ID")
    assert service.client.delete(f"/jobs/{job}", headers=AUTH).status_code == 204


def test_docs_health_and_prometheus(service: Service) -> None:
    spec = service.client.get("/openapi.json")
    assert spec.status_code == 200 and "/jobs" in spec.json()["paths"]
    assert service.client.get("/docs").status_code == 200
    health = service.client.get("/healthz")
    assert health.status_code == 200 and health.json()["ok"] is True
    prom = service.client.get("/metrics")
    assert prom.status_code == 200 and "convoy_jobs" in prom.text
    assert 'convoy_jobs{state="queued"}' in prom.text


def test_the_blocker_held_the_budget(service: Service) -> None:
    """Nothing generated or submitted here ever started: the only job that left the queue is the blocker."""
    jobs = service.client.get("/jobs").json()["jobs"]
    started = [j["id"] for j in jobs if j["state"] not in ("queued", "stopped")]
    assert started == [service.blocker], started  # type: ignore[attr-defined]  # set by the fixture above
    assert service.host_pids() and len(service.host_pids()) == 1


def test_router_errors_have_the_one_shape(service: Service) -> None:
    assert_error(service.client.get("/no/such/route"), 404, "path")
    assert_error(service.client.delete("/healthz", headers=AUTH), 405, "method")
    assert_error(service.client.put("/jobs", json={}, headers=AUTH), 405, "method")


def test_the_schema_documents_the_error_body_the_server_sends(service: Service) -> None:
    schema = service.client.get("/openapi.json").json()
    assert "HTTPValidationError" not in schema["components"]["schemas"]  # FastAPI's 422 shape, never sent here
    submit_errors = schema["paths"]["/jobs"]["post"]["responses"]
    for status in ("400", "401", "404", "409", "413", "422"):
        assert submit_errors[status]["content"]["application/json"]["schema"] == {
            "$ref": "#/components/schemas/ErrorBody"
        }, status


def test_a_failed_jobs_error_names_its_last_exception() -> None:
    from convoy.protocol.reports import Report
    from convoy.services.jobservice import failure_summary

    records = [
        Report("crashed", "learner-0", "exit code 1"),
        Report("error", "learner-0.5", "OutOfMemoryError: CUDA out of memory. Tried to allocate 104.00 GiB"),
        Report("failed", "learner-0.5", "learner crashed 6 times within 60 s (last: learner-0.5 exit code 1)"),
    ]
    text = failure_summary("x", records)
    assert text.startswith("learner-0.5 failed: learner crashed 6 times")
    assert "cause: learner-0.5: OutOfMemoryError: CUDA out of memory" in text
    assert "convoy jobs logs x" in text
    assert failure_summary("x", []).startswith("its processes reported nothing")


def test_a_refused_jobs_error_is_the_whole_refusal_once() -> None:
    """A refused configuration's verdict carries the refusal itself: the error says it whole, not cut at 300
    characters and then repeated as the cause."""
    from convoy.protocol.reports import Report
    from convoy.services.jobservice import failure_summary

    said = (
        "ConfigError: teacher: checkpoint /data/"
        + "x" * 200
        + ".pt: cannot be read; it is corrupt or not a Convoy checkpoint"
    )
    records = [
        Report("error", "h-x.actor-0", said),
        Report(
            "failed",
            "h-x.actor-0",
            f"h-x.actor-0 refused the job's configuration (exit code 78), so it is not "
            f"restarted: {said}; fix the config (or the file it names) and start the job again",
        ),
    ]
    text = failure_summary("x", records)
    assert text.count(said) == 1 and "cause:" not in text and text.endswith("convoy jobs logs x"), text


def test_a_job_body_takes_a_preset_as_convoy_train_does(service: Service) -> None:
    """``preset`` in POST /jobs (and so in a sweep's base, which Fig. 3's real budget uses): its settings under the
    body's own; one on an env it does not fit, or an unknown name, is refused naming the field."""
    from convoy.api.models import JobSubmit

    job = JobSubmit(algo="idqn", env="treadmill", preset="charger-demo", algo_params={"n_step": 1}).job_config()
    assert job.algo_params["demonstrator"] == "planner" and job.algo_params["n_step"] == 1  # the body's own wins
    assert job.env_params["adversary_stealth"] is True
    body = assert_error(submit(service, env="referential", algo_params={}, env_params={}, preset="charger"), 422)
    assert body["field"] == "preset" and "treadmill" in body["problem"], body
    assert_error(submit(service, preset="chargr"), 422, "preset")

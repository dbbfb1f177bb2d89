"""Many hosts for real: a router, a learner host and two actor hosts, each in its own Linux network namespace with
its own address, joined only by veth links to a bridge in the router's namespace (``.ci/run`` installs iproute2).

One actor host's link is cut for 10 s and restored mid-run: the job must complete with its full step count, its
learner never restarting (nothing acknowledged is lost: the learner's replay and counters live in one process),
and the cut host's actors must deliver again after the link returns. Every namespace, link and process is removed
by name and PID at the end.
"""

from __future__ import annotations

import json
import os
import secrets
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SUBNET = "10.77.{}.{}"
STEPS = 300_000
LISTEN = """
import sys, time, zenoh
from protocol import keys
from protocol.session import ZenohSettings, open_session
session = open_session(ZenohSettings(mode='client', connect=(sys.argv[1],), shared_memory=False))
out = open(sys.argv[2], 'a', buffering=1)
sub = session.declare_subscriber(keys.metrics_all('mh'), lambda s: out.write(f'{time.time()} {s.key_expr}\\n'))
while True:
    time.sleep(1)
"""  # records (time, key) of every metrics message of job mh: who delivered when

pytestmark = [
    pytest.mark.timeout(400),
    pytest.mark.skipif(os.geteuid() != 0 or shutil.which("ip") is None, reason="needs root and iproute2 (ip netns)"),
]


def ip(*args: str) -> None:
    subprocess.run(["ip", *args], check=True, capture_output=True, text=True)


class Hosts:
    """Namespaces ``<tag>-r`` (router, bridge) and ``<tag>-<name>`` for each host, addresses 10.77.N.1 / .2 …"""

    def __init__(self, names: list[str]) -> None:
        self.tag = f"cvy{secrets.token_hex(2)}"
        self.net = secrets.randbelow(200) + 20
        self.names, self.ns, self.addr = names, {}, {}
        self.router_ns = f"{self.tag}-r"
        self.router_addr = SUBNET.format(self.net, 1)

    def up(self) -> None:
        ip("netns", "add", self.router_ns)
        ip("-n", self.router_ns, "link", "set", "lo", "up")
        ip("-n", self.router_ns, "link", "add", "br0", "type", "bridge")
        ip("-n", self.router_ns, "addr", "add", f"{self.router_addr}/24", "dev", "br0")
        ip("-n", self.router_ns, "link", "set", "br0", "up")
        for i, name in enumerate(self.names, start=2):
            ns, addr = f"{self.tag}-{name}", SUBNET.format(self.net, i)
            self.ns[name], self.addr[name] = ns, addr
            ip("netns", "add", ns)
            ip("-n", ns, "link", "set", "lo", "up")
            ip("-n", ns, "link", "add", "eth0", "type", "veth", "peer", "name", f"to-{name}", "netns", self.router_ns)
            ip("-n", ns, "addr", "add", f"{addr}/24", "dev", "eth0")
            ip("-n", ns, "link", "set", "eth0", "up")
            ip("-n", self.router_ns, "link", "set", f"to-{name}", "master", "br0", "up")

    def cut(self, name: str, down: bool) -> None:
        ip("-n", self.router_ns, "link", "set", f"to-{name}", "down" if down else "up")

    def down(self) -> None:
        for ns in [*self.ns.values(), self.router_ns]:  # deleting a namespace removes its veth ends and the bridge
            subprocess.run(["ip", "netns", "del", ns], capture_output=True)


@pytest.fixture
def hosts() -> Iterator[Hosts]:
    h = Hosts(["learner", "a1", "a2"])
    try:
        h.up()
        yield h
    finally:
        h.down()


def test_a_job_across_four_namespaces_survives_a_10s_link_cut(tmp_path: Path, hosts: Hosts) -> None:
    endpoint = f"tcp/{hosts.router_addr}:7447"
    job = ["--job-id", "mh", "--env", "referential", "--steps", str(STEPS), "--num-envs", "32", "--hp", "hidden=64",
           "--hp", "learning_starts=256", "--eval-episodes", "100", "--log-every", "2000"]  # fmt: skip
    net = ["--mode", "client", "--connect", endpoint, "--no-shm"]
    procs: list[subprocess.Popen] = []
    logs = tmp_path / "logs"
    logs.mkdir()
    out = tmp_path / "run"

    def start(ns: str, name: str, args: list[str]) -> subprocess.Popen:
        fh = open(logs / f"{name}.log", "w")  # noqa: SIM115 (closed with the process)
        cmd = ["ip", "netns", "exec", ns, sys.executable, "-m", "services.cli", *args]
        p = subprocess.Popen(cmd, stdout=fh, stderr=subprocess.STDOUT, cwd=ROOT, start_new_session=True)
        procs.append(p)
        return p

    def rows() -> list[dict]:
        path = out / "metrics.jsonl"
        return [json.loads(line) for line in path.read_text().splitlines()] if path.exists() else []

    try:
        start(hosts.router_ns, "router", ["router", "--listen", endpoint])
        heard = tmp_path / "heard.txt"
        listener = ["ip", "netns", "exec", hosts.router_ns, sys.executable, "-c", LISTEN, endpoint, str(heard)]
        procs.append(subprocess.Popen(listener, cwd=ROOT, start_new_session=True, stderr=subprocess.DEVNULL))
        learner = start(hosts.ns["learner"], "learner", ["host", "--name", "learner-host", "--roles", "learner",
                                                          "--out", str(out), *job, *net])  # fmt: skip
        for name in ("a1", "a2"):
            start(hosts.ns[name], name, ["host", "--name", f"{name}-host", "--roles", "actor", "--actors", "1",
                                         *job, *net])  # fmt: skip
        t_end = time.monotonic() + 120
        while not rows() or rows()[-1]["env_steps"] < 6_000:
            assert learner.poll() is None, (logs / "learner.log").read_text()[-3000:]
            assert time.monotonic() < t_end, "no progress before the cut"
            time.sleep(0.5)
        before = rows()[-1]["env_steps"]
        hosts.cut("a1", down=True)
        time.sleep(10.0)
        hosts.cut("a1", down=False)
        restored = time.time()
        assert learner.wait(240) == 0, (logs / "learner.log").read_text()[-3000:]
    finally:
        for p in procs:
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGTERM)
        for p in procs:
            try:
                p.wait(15)
            except subprocess.TimeoutExpired:
                os.killpg(p.pid, signal.SIGKILL)
                p.wait(5)
    summary = json.loads((out / "summary.json").read_text())
    print(f"cut at {before:,} env steps; finished at {summary['env_steps']:,}")
    assert summary["env_steps"] >= STEPS and summary["updates"] > 0
    steps = [r["env_steps"] for r in rows()]
    assert steps == sorted(steps) and steps[-1] >= STEPS  # one learner, counting on: nothing it took was lost
    log = (logs / "learner.log").read_text()
    assert "restart" not in log.lower(), log[-3000:]
    assert "crashed" not in (logs / "a1.log").read_text(), (logs / "a1.log").read_text()[-3000:]
    lines = [line.split(" ", 1) for line in heard.read_text().splitlines()]
    after = {key for t, key in lines if float(t) > restored + 1.0}
    assert any("a1-host" in key for key in after), sorted(after)  # the cut host's actor delivers again
    assert any("a2-host" in key for key in after), sorted(after)

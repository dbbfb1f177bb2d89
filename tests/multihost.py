"""Hosts in Linux network namespaces, for the multi-host test and the fault benchmark.

A router namespace holds a bridge; each host gets its own namespace and address, joined to the bridge by a veth
link that ``cut`` takes down and up. ``MultiHostJob`` starts a Zenoh router, a listener that records who delivered
metrics when, a learner host and actor hosts, each as ``convoy`` processes inside their namespaces, and stops them
by process group. Needs root and iproute2 (``.ci/run`` installs it).
"""

from __future__ import annotations

import json
import os
import secrets
import shutil
import signal
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SUBNET = "10.77.{}.{}"
LISTEN = """
import sys, time, zenoh
from convoy.protocol import keys
from convoy.protocol.session import ZenohSettings, open_session
session = open_session(ZenohSettings(mode='client', connect=(sys.argv[1],), shared_memory=False))
out = open(sys.argv[2], 'a', buffering=1)
sub = session.declare_subscriber(keys.metrics_all(sys.argv[3]), lambda s: out.write(f'{time.time()} {s.key_expr}\\n'))
while True:
    time.sleep(1)
"""  # records (time, key) of every metrics message of one job: who delivered when


def available() -> bool:
    """Root, iproute2, and the right to make a namespace (a root container without CAP_SYS_ADMIN has not)."""
    if os.geteuid() != 0 or shutil.which("ip") is None:
        return False
    probe = f"cvyprobe{secrets.token_hex(2)}"
    made = subprocess.run(["ip", "netns", "add", probe], capture_output=True).returncode == 0
    if made:
        subprocess.run(["ip", "netns", "delete", probe], capture_output=True)
    return made


def ip(*args: str) -> None:
    subprocess.run(["ip", *args], check=True, capture_output=True, text=True)


class Hosts:
    """Namespaces ``<tag>-r`` (router, bridge) and ``<tag>-<name>`` for each host, addresses 10.77.N.1 / .2 …"""

    def __init__(self, names: list[str]) -> None:
        self.tag = f"cvy{secrets.token_hex(2)}"
        self.net = secrets.randbelow(200) + 20
        self.names = names
        self.ns: dict[str, str] = {}
        self.addr: dict[str, str] = {}
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


class MultiHostJob:
    """A router, a metrics listener, a learner host and one host per actor namespace, for one job."""

    def __init__(self, hosts: Hosts, job_id: str, job_args: list[str], work: Path, actor_hosts: list[str]) -> None:
        self.hosts, self.job_id, self.work = hosts, job_id, work
        self.endpoint = f"tcp/{hosts.router_addr}:7447"
        self.job = ["--job-id", job_id, *job_args]
        self.actor_hosts = actor_hosts
        self.logs, self.out, self.heard_path = work / "logs", work / "run", work / "heard.txt"
        self.procs: list[subprocess.Popen] = []
        self.learner: subprocess.Popen | None = None

    def _start(self, ns: str, name: str, args: list[str]) -> subprocess.Popen:
        fh = open(self.logs / f"{name}.log", "w")  # noqa: SIM115 (closed with the process)
        cmd = ["ip", "netns", "exec", ns, sys.executable, "-m", "convoy.cli", *args]
        p = subprocess.Popen(cmd, stdout=fh, stderr=subprocess.STDOUT, cwd=ROOT, start_new_session=True)
        self.procs.append(p)
        return p

    def start(self) -> MultiHostJob:
        self.logs.mkdir(parents=True, exist_ok=True)
        net = ["--mode", "client", "--connect", self.endpoint, "--no-shm"]
        self._start(self.hosts.router_ns, "router", ["router", "--listen", self.endpoint])
        listener = [*("ip", "netns", "exec", self.hosts.router_ns, sys.executable, "-c", LISTEN), self.endpoint,
                    str(self.heard_path), self.job_id]  # fmt: skip
        self.procs.append(subprocess.Popen(listener, cwd=ROOT, start_new_session=True, stderr=subprocess.DEVNULL))
        self.learner = self._start(self.hosts.ns["learner"], "learner", ["host", "--name", "learner-host", "--roles",
                                   "learner", "--out", str(self.out), *self.job, *net])  # fmt: skip
        for name in self.actor_hosts:
            self._start(self.hosts.ns[name], name, ["host", "--name", f"{name}-host", "--roles", "actor", "--actors",
                                                    "1", *self.job, *net])  # fmt: skip
        return self

    def rows(self) -> list[dict]:
        path = self.out / "metrics.jsonl"
        return [json.loads(line) for line in path.read_text().splitlines()] if path.exists() else []

    def heard(self) -> list[tuple[float, str]]:
        """(time, key) of every metrics message the router's listener received."""
        if not self.heard_path.exists():
            return []
        return [(float(t), key) for t, key in (line.split(" ", 1) for line in self.heard_path.read_text().splitlines())]

    def log(self, name: str) -> str:
        return (self.logs / f"{name}.log").read_text()

    def stop(self) -> None:
        for p in self.procs:
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGTERM)
        for p in self.procs:
            try:
                p.wait(15)
            except subprocess.TimeoutExpired:
                os.killpg(p.pid, signal.SIGKILL)
                p.wait(5)

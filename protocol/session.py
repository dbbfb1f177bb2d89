"""The one place a Zenoh session is configured and opened.

Default (one laptop): **peer** mode on loopback, multicast scouting off, explicit endpoints — the supervisor
listens on ``tcp/127.0.0.1:<port>``, every process it starts listens on its own loopback port and connects to the
supervisor's, and gossip introduces the peers to each other so that transitions go actor → learner directly. No
broker to install.

Many hosts: **client** mode towards one or more routers (``connect``), with a connect timeout so that start order
does not matter (``-1`` waits for ever); TLS and user/password from the same settings (and so from the job file,
the CLI or the environment). A Python session in **router** mode is a router (tests and ``convoy router``).

Pitfalls handled here (``docs/architecture.md``): shared memory can be switched off (containers have a small
``/dev/shm``); the lease is short (2 s) so that a frozen process is noticed; Zenoh objects never cross a process
boundary — children get these settings (plain data) and open their own session.
"""

from __future__ import annotations

import json
import os
import socket
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, SecretStr


class ZenohSettings(BaseModel):
    """How a process joins the Zenoh network; plain data, so it pickles to children and lives in job files."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    mode: Literal["peer", "client", "router"] = Field("peer", description="peer (one machine), client (→ routers).")
    listen: tuple[str, ...] = Field((), description="Endpoints to listen on, e.g. tcp/127.0.0.1:7447.")
    connect: tuple[str, ...] = Field((), description="Endpoints to connect to (the supervisor's, or routers').")
    connect_timeout_ms: int = Field(-1, ge=-1, description="How long to wait for `connect` endpoints; -1 = forever.")
    multicast: bool = Field(False, description="Multicast scouting (off: unreliable in containers and CI).")
    shared_memory: bool = Field(True, description="Zero-copy shared memory between local processes.")
    lease_ms: int = Field(2000, ge=100, description="A frozen peer is declared gone after this long.")
    tls_root_ca: str | None = Field(None, description="PEM of the CA that signed the routers' certificates.")
    tls_cert: str | None = Field(None, description="This process's certificate (mTLS or a TLS listener).")
    tls_key: str | None = Field(None, description="This process's private key.")
    user: str | None = Field(None, description="user for usrpwd authentication.")
    password: SecretStr | None = Field(
        None, description="password for usrpwd authentication (never written to job files or checkpoints)."
    )

    def rooted(self) -> ZenohSettings:
        """Settings for the process that starts others on this machine: in peer mode it must listen (on a free
        loopback port unless ``listen`` says otherwise) so that its children can connect to it."""
        if self.mode == "peer" and not self.listen:
            return self.model_copy(update={"listen": (loopback(free_port()),)})
        return self

    def child(self, listen_port: bool = True) -> ZenohSettings:
        """The settings a spawned process on this machine uses: connect to what this process listens on (peer
        mode) and listen on its own free loopback port, so gossip can connect the children to each other; and to
        what this process connects to (a router), since peers do not forward for each other."""
        if self.mode != "peer" or not self.listen:
            return self
        connect = (*self.listen, *(c for c in self.connect if c not in self.listen))
        return self.model_copy(update={"connect": connect, "listen": ("tcp/127.0.0.1:0",) if listen_port else ()})

    @classmethod
    def from_env(cls, base: ZenohSettings | None = None) -> ZenohSettings:
        """``CONVOY_ZENOH_MODE``, ``…_CONNECT`` / ``…_LISTEN`` (comma-separated), ``…_USER``, ``…_PASSWORD``,
        ``…_SHM`` (0/1) and ``…_TLS_ROOT_CA`` override ``base`` — how compose hands containers their endpoints."""
        values: dict[str, Any] = (base or cls()).model_dump()
        env = os.environ
        if "CONVOY_ZENOH_MODE" in env:
            values["mode"] = env["CONVOY_ZENOH_MODE"]
        for name in ("connect", "listen"):
            raw = env.get(f"CONVOY_ZENOH_{name.upper()}")
            if raw is not None:
                values[name] = tuple(e.strip() for e in raw.split(",") if e.strip())
        for name in ("user", "password", "tls_root_ca", "tls_cert", "tls_key"):
            raw = env.get(f"CONVOY_ZENOH_{name.upper()}")
            if raw:
                values[name] = raw
        if "CONVOY_ZENOH_SHM" in env:
            values["shared_memory"] = env["CONVOY_ZENOH_SHM"] not in ("0", "false", "no")
        return cls(**values)


def zenoh_config(settings: ZenohSettings) -> Any:
    """A ``zenoh.Config`` for ``settings``."""
    import zenoh

    conf = zenoh.Config()

    def put(path: str, value: Any) -> None:
        conf.insert_json5(path, json.dumps(value))

    put("mode", settings.mode)
    put("scouting/multicast/enabled", settings.multicast)
    put("transport/shared_memory/enabled", settings.shared_memory)
    put("transport/link/tx/lease", settings.lease_ms)
    if settings.listen:
        put("listen/endpoints", list(settings.listen))
    elif settings.mode == "peer":
        put("listen/endpoints", ["tcp/127.0.0.1:0"])  # loopback only, never every interface
    if settings.connect:
        put("connect/endpoints", list(settings.connect))
        put("connect/timeout_ms", settings.connect_timeout_ms)
        put("connect/exit_on_failure", False)
    if settings.tls_root_ca:
        put("transport/link/tls/root_ca_certificate", settings.tls_root_ca)
    if settings.tls_cert and settings.tls_key:
        put("transport/link/tls/listen_certificate", settings.tls_cert)
        put("transport/link/tls/listen_private_key", settings.tls_key)
        put("transport/link/tls/connect_certificate", settings.tls_cert)
        put("transport/link/tls/connect_private_key", settings.tls_key)
    if settings.user and settings.password:
        put("transport/auth/usrpwd/user", settings.user)
        put("transport/auth/usrpwd/password", settings.password.get_secret_value())
    return conf


def open_session(settings: ZenohSettings) -> Any:
    """Open a Zenoh session with ``settings``."""
    import zenoh

    return zenoh.open(zenoh_config(settings))


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port free on ``host`` right now (for listeners the caller is about to open)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


def loopback(port: int) -> str:
    return f"tcp/127.0.0.1:{port}"

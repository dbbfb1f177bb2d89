"""The one place a Zenoh session is configured and opened.

Default (one laptop): nothing to install, multicast scouting off, explicit endpoints on loopback. The process that
roots a job (``convoy train``'s runner, a ``convoy host``) opens its session as a Zenoh **router** listening on
``tcp/127.0.0.1:<port>``; every process it starts is a **client** of it and listens on nothing. Every link is then
opened once, by one side, which usrpwd authentication needs: with peers that listen and connect to each other
(gossip), duplicate links fail authentication (eclipse-zenoh/zenoh#2577).

Many hosts: **client** mode towards one or more routers (``connect``), with a connect timeout so that start order
does not matter (``-1`` waits for ever); TLS and user/password from the same settings (and so from the job file,
the CLI or the environment). A Python session in **router** mode is a router (tests and ``convoy router``).

A job's network is closed to processes without its credential: on one machine (no user set) the process that
roots a job writes a fresh user/password to a private usrpwd dictionary (``secured``) and every
process of the job — and the job service's session for it — opens with that user, password and dictionary, so
Zenoh refuses the transport of any peer that cannot present them (it can neither publish nor subscribe).

Pitfalls handled here (``docs/architecture.md``): shared memory can be switched off (containers have a small
``/dev/shm``); the lease is short (2 s) so that a frozen process is noticed; Zenoh objects never cross a process
boundary — children get these settings (plain data) and open their own session.
"""

from __future__ import annotations

import json
import os
import secrets
import socket
import threading
from collections.abc import Callable
from pathlib import Path
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
    credentials_file: str | None = Field(
        None,
        description="usrpwd dictionary (one user:password per line): only peers that authenticate with one of its "
        "entries may connect to this process; None = any peer that reaches the port.",
    )

    def secured(self, directory: str | Path, user: str) -> ZenohSettings:
        """A process that roots its own network (peer mode, connecting to no one) with no credential of the user's:
        a fresh password for ``user`` in a 0600 dictionary under ``directory``, used to authenticate and to admit,
        so only holders of it join this job's network. One that joins another's network keeps the user's
        credentials (``--user``, ``CONVOY_ZENOH_PASSWORD``, TLS), as the other side expects them."""
        if self.mode != "peer" or self.connect or self.user or self.credentials_file:
            return self
        path = Path(directory) / "zenoh-credentials"
        return self.model_copy(
            update={"user": user, "password": write_credentials(path, user), "credentials_file": str(path)}
        )

    def rooted(self) -> ZenohSettings:
        """Settings for the process that starts others on this machine (peer mode): it becomes its children's
        router, on a free loopback port unless ``listen`` says otherwise, still linked to what it connects to.
        Call after ``secured``, which reads the mode the user asked for."""
        if self.mode != "peer":
            return self
        return self.model_copy(update={"mode": "router", "listen": self.listen or (loopback(free_port()),)})

    def child(self) -> ZenohSettings:
        """The settings a spawned process on this machine uses: under a router root, a client of it that listens
        on nothing, so every link of the job is opened once, by one side (what usrpwd needs: zenoh#2577). Other
        modes (clients of routers on many hosts) are passed on as they are."""
        if self.mode != "router" or not self.listen:
            return self
        return self.model_copy(update={"mode": "client", "connect": self.listen, "listen": ()})

    @classmethod
    def from_env(cls, base: ZenohSettings | None = None) -> ZenohSettings:
        """``CONVOY_ZENOH_MODE``, ``…_CONNECT`` / ``…_LISTEN`` (comma-separated), ``…_USER``, ``…_PASSWORD``,
        ``…_CREDENTIALS_FILE``, ``…_SHM`` (0/1) and ``…_TLS_ROOT_CA`` override ``base`` — how compose hands
        containers their endpoints."""
        values: dict[str, Any] = (base or cls()).model_dump()
        env = os.environ
        if "CONVOY_ZENOH_MODE" in env:
            values["mode"] = env["CONVOY_ZENOH_MODE"]
        for name in ("connect", "listen"):
            raw = env.get(f"CONVOY_ZENOH_{name.upper()}")
            if raw is not None:
                values[name] = tuple(e.strip() for e in raw.split(",") if e.strip())
        for name in ("user", "password", "credentials_file", "tls_root_ca", "tls_cert", "tls_key"):
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
    if settings.credentials_file:
        put("transport/auth/usrpwd/dictionary_file", settings.credentials_file)
    return conf


class SessionAbandoned(RuntimeError):
    """``open_session``'s ``give_up`` said to stop waiting for the session (its supervisor is gone)."""


def open_session(settings: ZenohSettings, give_up: Callable[[], bool] | None = None) -> Any:
    """Open a Zenoh session with ``settings``.

    With ``give_up``, the session opens in a helper thread while this one polls ``give_up`` and raises
    ``SessionAbandoned`` once it is true: a worker forked just before its supervisor was killed was seen blocked
    in ``zenoh.open`` for minutes, its connect endpoint gone, where nothing else could tell it to exit.
    """
    import zenoh

    conf = zenoh_config(settings)
    if give_up is None:
        return zenoh.open(conf)
    result: dict[str, Any] = {}

    def opener() -> None:
        try:
            result["session"] = zenoh.open(conf)
        except BaseException as exc:  # raised again in the caller's thread
            result["error"] = exc

    thread = threading.Thread(target=opener, name="zenoh-open", daemon=True)
    thread.start()
    while thread.is_alive():
        thread.join(0.1)
        if thread.is_alive() and give_up():
            raise SessionAbandoned("gave up opening the Zenoh session")
    if "error" in result:
        raise result["error"]
    return result["session"]


def write_credentials(path: str | Path, user: str) -> SecretStr:
    """A fresh random password for ``user``, written as a one-entry usrpwd dictionary readable by its owner only."""
    if not user or ":" in user or "\n" in user:
        raise ValueError(f"usrpwd user must be non-empty without ':' or newlines, got {user!r}")
    password = secrets.token_urlsafe(24)
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as fh:
        fh.write(f"{user}:{password}\n")
    return SecretStr(password)


def read_credentials(path: str | Path) -> tuple[str, SecretStr]:
    """(user, password) of a dictionary written by ``write_credentials``."""
    user, _, password = Path(path).read_text().splitlines()[0].partition(":")
    return user, SecretStr(password)


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port free on ``host`` right now (for listeners the caller is about to open)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


def loopback(port: int) -> str:
    return f"tcp/127.0.0.1:{port}"

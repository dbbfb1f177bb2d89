"""Single-role commands for multi-host use: ``convoy router``, ``convoy learner``, ``convoy actor``, ``convoy host``.

Each builds the job from the same flags/job file as ``convoy train`` and its Zenoh settings from, in rising
precedence: the job file's ``runtime.zenoh``, the environment (``CONVOY_ZENOH_MODE``, ``…_CONNECT``, ``…_LISTEN``,
``…_USER``, ``…_PASSWORD``, ``…_SHM``, ``…_TLS_ROOT_CA`` — what compose sets), and these flags.
"""

from __future__ import annotations

import argparse
from typing import Any

from convoy.cli.train import add_job_arguments, check_job_inputs, job_from_args
from convoy.protocol import keys
from convoy.protocol.session import ZenohSettings
from convoy.validation import ConfigError

ZENOH_HELP = "Zenoh: flags override CONVOY_ZENOH_* environment variables, which override the job file."


def add_zenoh_arguments(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("zenoh", ZENOH_HELP)
    g.add_argument("--mode", choices=["peer", "client", "router"], help="session mode (client: through routers)")
    g.add_argument("--connect", action="append", metavar="ENDPOINT", help="e.g. tcp/10.0.0.5:7447, repeatable")
    g.add_argument("--listen", action="append", metavar="ENDPOINT", help="e.g. tcp/0.0.0.0:7447, repeatable")
    g.add_argument("--no-shm", action="store_true", help="no shared-memory transport (containers)")
    g.add_argument("--user", help="usrpwd user (password: CONVOY_ZENOH_PASSWORD)")
    g.add_argument("--tls-root-ca", metavar="PEM", help="CA certificate of the routers (TLS endpoints)")


def zenoh_from_args(args: argparse.Namespace, base: ZenohSettings | None = None) -> ZenohSettings:
    values: dict[str, Any] = ZenohSettings.from_env(base).model_dump()
    if args.mode:
        values["mode"] = args.mode
    if args.connect:
        values["connect"] = tuple(args.connect)
    if args.listen:
        values["listen"] = tuple(args.listen)
    if args.no_shm:
        values["shared_memory"] = False
    if args.user:
        values["user"] = args.user
    if args.tls_root_ca:
        values["tls_root_ca"] = args.tls_root_ca
    if values["password"] is not None and hasattr(values["password"], "get_secret_value"):
        values["password"] = values["password"].get_secret_value()
    return ZenohSettings(**values)


def _job_id(args: argparse.Namespace) -> str:
    try:
        return keys.check_id(args.job_id, "job id")
    except ValueError as exc:
        raise ConfigError("--job-id", str(exc)) from None


def cmd_router(args: argparse.Namespace) -> int:
    from convoy.services.host import run_router

    settings = zenoh_from_args(args)
    if not settings.listen:
        settings = settings.model_copy(update={"listen": ("tcp/127.0.0.1:7447",)})
    return run_router(settings)


def cmd_learner(args: argparse.Namespace) -> int:
    from convoy.learner.service import run_learner

    job = job_from_args(args)
    check_job_inputs(job)  # before the learner makes --out
    return run_learner(_job_id(args), job, args.out, zenoh_from_args(args, job.runtime.zenoh))


def cmd_actor(args: argparse.Namespace) -> int:
    from convoy.actors.actor import run_actor

    job = job_from_args(args)
    ident = args.ident or f"actor-{args.index}"
    return run_actor(
        _job_id(args), job, args.index, keys.check_id(ident, "--id"), zenoh_from_args(args, job.runtime.zenoh), None
    )


def cmd_host(args: argparse.Namespace) -> int:
    from convoy.services.host import run_host

    job = job_from_args(args)
    roles = tuple(r.strip() for r in args.roles.split(",") if r.strip())
    bad = [r for r in roles if r not in ("actor", "learner")]
    if bad or not roles:
        raise ConfigError("--roles", f"{args.roles!r}: give actor, learner or actor,learner")
    actors = job.runtime.actors if args.actors is None else args.actors
    settings = zenoh_from_args(args, job.runtime.zenoh)
    return run_host(args.name, _job_id(args), job, roles, actors, args.out, settings)


def add_role_parsers(sub: argparse._SubParsersAction) -> None:
    ro = sub.add_parser(
        "router",
        help="run a Zenoh router (multi-host)",
        description="A Zenoh router in a Python process (what the eclipse/zenoh image runs), until Ctrl-C/SIGTERM.",
    )
    add_zenoh_arguments(ro)
    ro.set_defaults(func=cmd_router)

    for name, func, text in (
        ("learner", cmd_learner, "run the learner of a job (multi-host)"),
        ("actor", cmd_actor, "run one actor of a job (multi-host)"),
        ("host", cmd_host, "run and supervise a job's roles on this host (multi-host)"),
    ):
        p = sub.add_parser(name, help=text, description=text[0].upper() + text[1:] + ". " + ZENOH_HELP)
        p.add_argument("--job-id", required=True, help="the job's id, the same on every host")
        add_job_arguments(p)
        add_zenoh_arguments(p)
        if name in ("learner", "host"):
            p.add_argument("--out", default="runs/job", metavar="DIR", help="checkpoints, metrics (learner)")
        if name == "actor":
            p.add_argument("--index", type=int, default=0, help="actor index (seed, ε spread; default 0)")
            p.add_argument("--id", dest="ident", help="actor id in keys (default actor-INDEX)")
        if name == "host":
            p.add_argument("--name", required=True, help="this host's name (key-safe)")
            p.add_argument("--roles", default="actor", help="actor, learner or actor,learner (default actor)")
        p.set_defaults(func=func)

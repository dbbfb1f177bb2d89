"""``convoy serve``: the job service — REST API, dashboard and the jobs it runs — on this machine."""

from __future__ import annotations

import argparse
import os
import secrets
from pathlib import Path

from convoy.cli.args import add_command, add_limit_flags, limits_from_args
from convoy.validation import ConfigError


def api_token(data_dir: Path) -> tuple[str, str]:
    """(token, where it came from): ``CONVOY_API_TOKEN``, else the one saved on first start, else a new one."""
    env = os.environ.get("CONVOY_API_TOKEN", "").strip()
    if env:
        return env, "CONVOY_API_TOKEN"
    path = data_dir / "api_token"
    if path.is_file() and path.read_text().strip():
        return path.read_text().strip(), str(path)
    token = secrets.token_urlsafe(24)
    data_dir.mkdir(parents=True, exist_ok=True)
    path.touch(mode=0o600)
    path.write_text(token + "\n")
    return token, f"new, saved in {path}"


def cmd_serve(args: argparse.Namespace) -> int:
    """Run the job service: REST API, dashboard, and the jobs it starts.

    Serve the REST job API (OpenAPI at /docs) and the dashboard (/) and run the submitted jobs on this machine.
    Jobs, their history and metrics live in DATA/jobs.sqlite; jobs keep running if the service stops and are
    reattached when it starts again. Mutating requests need 'Authorization: Bearer TOKEN': CONVOY_API_TOKEN, or
    a token generated on first start, saved in DATA/api_token and printed.
    """
    import uvicorn

    from convoy.api.app import create_app
    from convoy.protocol.reports import setup_logging
    from convoy.services.jobservice import JobService

    if not 1 <= args.port <= 65535:
        raise ConfigError("--port", f"must be a TCP port 1–65535 (got {args.port})")
    if args.max_processes < 3:
        raise ConfigError("--max-processes", f"a job needs at least 3 processes (got {args.max_processes})")
    data = Path(args.data)
    setup_logging(timestamps=True)  # the service's log: submissions, state changes and process events, timed
    token, origin = api_token(data)
    service = JobService(data, args.max_processes, limits=limits_from_args(args))
    app = create_app(service, token)
    print(f"convoy serve: http://{args.host}:{args.port}/  (API docs /docs, data {data})")
    print(f"API token ({origin}): {token}", flush=True)
    try:
        uvicorn.run(app, host=args.host, port=args.port, log_level=args.log_level)
    finally:
        service.close()
    return 0


def add_serve_parser(sub: argparse._SubParsersAction) -> None:
    p = add_command(sub, "serve", cmd_serve)
    p.add_argument("--host", default="127.0.0.1", help="address to bind (default: %(default)s, this machine only)")
    p.add_argument("--port", type=int, default=8000, help="HTTP port (default: %(default)s)")
    p.add_argument("--data", default="runs/service", help="jobs database and job outputs (default: %(default)s)")
    p.add_argument("--max-processes", type=int, default=8, help="processes of all running jobs (default: %(default)s)")
    p.add_argument("--log-level", default="warning", help="uvicorn log level (default: %(default)s)")
    add_limit_flags(p)

"""The ``convoy`` console script: a command that is slow to show its first output says at once that it started.

Importing the command line (``convoy.cli.main``: numpy, scipy, pydantic, the envs) takes ~0.6 s on an idle machine
and many times that on a loaded one, and ``convoy serve`` then imports torch, FastAPI and the job service, so
``serve`` and ``analyze`` print their first line here, before any of it is imported (this module imports only
``sys``). What they print next (the service's banner, analyze's progress) comes from the commands themselves.
"""

from __future__ import annotations

import sys

# the commands whose first output would otherwise come only after the heavy imports (and, for analyze, a checkpoint)
STARTING = {
    "serve": "convoy serve: starting (loading the job service and the API)…",
    "analyze": "convoy analyze: starting (loading the checkpoint)…",
}


def command_of(argv: list[str]) -> str | None:
    """The subcommand ``argv`` names (its first word that is not a flag), or None."""
    return next((a for a in argv if not a.startswith("-")), None)


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    cmd = command_of(args)
    if cmd in STARTING and not {"-h", "--help"} & set(args):
        print(STARTING[cmd], flush=True)
    from convoy.cli.main import main as run

    return run(argv)


if __name__ == "__main__":
    sys.exit(main())

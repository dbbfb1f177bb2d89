"""``convoy sweep``: submit a grid of jobs to the job service and follow, summarise, stop or resume it.

The commands speak HTTP to ``--url`` (``CONVOY_API_URL``) like ``convoy jobs``: ``submit`` (``POST /sweeps``),
``list``, ``status`` (``GET /sweeps/ID``), ``watch``, ``summary`` (``GET /sweeps/ID/summary``), ``stop``,
``resume`` and ``delete``. Errors are one line ``error: <field>: <problem> — <fix>``, exit code 2.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable
from typing import Any

from rich.console import Console
from rich.progress import BarColumn, Progress, TaskProgressColumn, TextColumn, TimeElapsedColumn
from rich.table import Table
from rich.text import Text

from convoy.cli.jobs import Api, CliError, add_client, fmt, plain, positive, print_json, run_client
from convoy.cli.sweep_file import load_sweep
from convoy.validation import ConfigError

FINAL = ("completed", "stopped", "failed")


def states_text(states: dict[str, int]) -> str:
    """``2 completed, 1 running, 3 queued``."""
    order = ("completed", "running", "starting", "stopping", "queued", "stopped", "failed", "deleted")
    return ", ".join(f"{states[s]} {s}" for s in order if states.get(s))


def cmd_submit(api: Api, args: argparse.Namespace, out: Console) -> int:
    """Submit a sweep file (TOML or JSON).

    Read FILE (a sweep: name, [base], [grid], actors, threshold; see experiments/ for examples), apply --scale,
    check it here and submit it (POST /sweeps). Its jobs queue on the service's process budget, oldest first.
    """
    try:
        body = load_sweep(args.file, args.scale)
    except ConfigError as exc:
        raise CliError(exc.field, str(exc).split(": ", 1)[-1], f"fix {args.file}") from None
    sweep = api.call("POST", "/sweeps", json=body)
    if args.json:
        print_json(out, sweep)
    else:
        groups = len({m["group"] for m in sweep["jobs"]})
        plain(out, f"submitted sweep {sweep['id']}: {len(sweep['jobs'])} jobs in {groups} groups, queued")
        plain(out, f"follow it with: convoy sweep watch {sweep['id']}")
    return 0


def cmd_list(api: Api, args: argparse.Namespace, out: Console) -> int:
    """List the sweeps.

    List the sweeps (GET /sweeps): id, state, progress and the states of their jobs.
    """
    sweeps = api.call("GET", "/sweeps")["sweeps"]
    if args.json:
        print_json(out, sweeps)
        return 0
    if not sweeps:
        plain(out, "no sweeps")
        return 0
    table = Table(title=f"sweeps at {api.url}")
    for col in ("id", "state", "progress", "jobs"):
        table.add_column(col, justify="right" if col == "progress" else "left", no_wrap=col == "id")
    for s in sweeps:
        table.add_row(Text(s["id"]), s["state"], f"{s['fraction']:.0%}", Text(states_text(s["states"])))
    out.print(table)
    return 0


def cmd_status(api: Api, args: argparse.Namespace, out: Console) -> int:
    """Show one sweep and its jobs.

    Show a sweep (GET /sweeps/ID): its state and every job with its grid point, state and progress.
    """
    sweep = api.call("GET", f"/sweeps/{args.id}")
    if args.json:
        print_json(out, sweep)
        return 0
    title = f"sweep {sweep['id']}: {sweep['state']}, {sweep['fraction']:.0%} ({states_text(sweep['states'])})"
    table = Table(title=title)
    for col in ("job", "group", "seed", "state", "env steps"):
        table.add_column(col, justify="right" if col in ("seed", "env steps") else "left", no_wrap=col == "job")
    for m in sweep["jobs"]:
        steps = f"{m['env_steps']:,}/{m['steps']:,}"
        table.add_row(Text(m["id"]), Text(m["group"]), fmt(m["point"].get("seed")), m["state"], steps)
    out.print(table)
    return 0


def cmd_watch(api: Api, args: argparse.Namespace, out: Console) -> int:
    """Follow a sweep until all its jobs end.

    Show a live progress bar of a sweep (all its env steps) with its jobs' states (in a pipe or a file: one line
    per change), polling GET /sweeps/ID, until no job is queued or running. Exit code 0 when all completed or
    stopped, 1 when one failed. Ctrl-C stops watching, not the sweep.
    """
    t0, printed = time.monotonic(), ""
    columns = (TextColumn("[bold]{task.description}"), BarColumn(), TaskProgressColumn(),
               TextColumn("{task.fields[states]}"), TimeElapsedColumn())  # fmt: skip
    with Progress(*columns, console=out, auto_refresh=False, disable=not out.is_terminal) as bar:
        task = bar.add_task(args.id, total=1.0, states="")
        while True:
            sweep = api.call("GET", f"/sweeps/{args.id}")
            text = states_text(sweep["states"])
            if out.is_terminal:
                bar.update(task, completed=sweep["fraction"], states=text)
                bar.refresh()
            else:
                line = f"{sweep['id']} {sweep['state']}: {sweep['fraction']:.0%} of its env steps · {text}"
                if line != printed:
                    plain(out, line)
                    printed = line
            if sweep["state"] in FINAL:
                break
            if args.timeout is not None and time.monotonic() - t0 > args.timeout:
                raise CliError("watch", f"sweep {args.id} is still running after {args.timeout:g} s",
                               "watch it again, or give a larger --timeout")  # fmt: skip
            time.sleep(args.interval)
    line = f"sweep {sweep['id']} {sweep['state']}: {text}, watched {time.monotonic() - t0:.1f} s"
    if sweep["state"] == "failed":
        failed = [m["id"] for m in sweep["jobs"] if m["state"] == "failed"]
        raise CliError("", line, f"see `convoy jobs status {failed[0]}`, then `convoy sweep resume {args.id}`", 1)
    plain(out, line)
    return 0


def mean_text(stats: dict[str, Any]) -> str:
    """``41.2 ± 3.1 (n=5)``, or – without values."""
    if not stats or stats.get("mean") is None:
        return "–"
    return f"{fmt(stats['mean'])} ± {fmt(stats['ci95'])} (n={stats['n']})"


def cmd_summary(api: Api, args: argparse.Namespace, out: Console) -> int:
    """Aggregate a sweep's groups: mean and 95 % CI over seeds.

    Summarise a sweep (GET /sweeps/ID/summary) per group (its grid point but the seed): the final greedy return,
    the last common point of the greedy curve and, with a threshold, how many seeds reached it and after how many
    env steps, each as mean ± 95 % Student-t CI over seeds. --plot writes the curves with their CI bands.
    """
    params = {"threshold": args.threshold} if args.threshold is not None else None
    summary = api.call("GET", f"/sweeps/{args.id}/summary", params=params)
    if args.json:
        print_json(out, summary)
    else:
        table = Table(title=f"sweep {summary['id']} ({summary['state']}): mean ± 95 % CI over seeds")
        columns = ["group", "jobs", "final greedy return", "curve at its last common step"]
        if summary["threshold"] is not None:
            columns.append(f"env steps to {fmt(summary['threshold'])}")
        for col in columns:
            table.add_column(col, justify="left" if col == "group" else "right")
        for g in summary["groups"]:
            curve = g["curve"]
            full = [i for i, n in enumerate(curve["n"]) if n == max(curve["n"], default=0)]
            last = "–"
            if full:
                i = full[-1]
                last = f"{fmt(curve['mean'][i])} ± {fmt(curve['ci95'][i])} at {curve['env_steps'][i]:,}"
            cells = [g["group"], states_text(g["states"]), mean_text(g["final"]), last]
            if "threshold" in g:
                th = g["threshold"]
                cells.append(f"{th['reached']}/{th['of']} reached; {mean_text(th['env_steps'])}")
            table.add_row(*(Text(c) for c in cells))
        out.print(table)
    if args.plot:
        from convoy.analysis.curves import plot_groups

        path = plot_groups(summary["groups"], args.plot, f"sweep {summary['id']}")
        plain(out, f"wrote {path}")
    return 0


def cmd_stop(api: Api, args: argparse.Namespace, out: Console) -> int:
    """Stop every queued or running job of a sweep.

    Stop a sweep (POST /sweeps/ID/stop): queued jobs are cancelled, running ones checkpoint and stop. `convoy
    sweep resume ID` continues them.
    """
    sweep = api.call("POST", f"/sweeps/{args.id}/stop")
    plain(out, f"{sweep['id']}: {states_text(sweep['states'])}")
    return 0


def cmd_resume(api: Api, args: argparse.Namespace, out: Console) -> int:
    """Queue a sweep's stopped and failed jobs again.

    Resume a sweep (POST /sweeps/ID/resume): every stopped or failed job continues from its last checkpoint.
    """
    sweep = api.call("POST", f"/sweeps/{args.id}/resume")
    plain(out, f"{sweep['id']}: {states_text(sweep['states'])}")
    return 0


def cmd_delete(api: Api, args: argparse.Namespace, out: Console) -> int:
    """Delete a sweep with all its jobs.

    Delete a sweep (DELETE /sweeps/ID): every job of it is ended and removed with its history and files.
    """
    api.call("DELETE", f"/sweeps/{args.id}")
    plain(out, f"deleted sweep {args.id} and its jobs")
    return 0


COMMANDS: dict[str, Callable[[Api, argparse.Namespace, Console], int]] = {
    "submit": cmd_submit,
    "list": cmd_list,
    "status": cmd_status,
    "watch": cmd_watch,
    "summary": cmd_summary,
    "stop": cmd_stop,
    "resume": cmd_resume,
    "delete": cmd_delete,
}


def cmd_sweep(args: argparse.Namespace) -> int:
    """Run grids of jobs (algorithms × seeds × settings) on a running `convoy serve`.

    A sweep is a base job and a grid; each combination is one job of the service. Its summary aggregates the
    seeds of each group with 95 % confidence intervals. Reading commands need no token; submit, stop, resume and
    delete send 'Authorization: Bearer TOKEN'.
    """
    return run_client(args, COMMANDS[args.sweep_command])


def add_sweep_parser(sub: argparse._SubParsersAction) -> None:
    """``convoy sweep …``, each subcommand with a complete ``--help``."""
    add_sub = add_client(sub, "sweep", cmd_sweep, COMMANDS, (
        "convoy sweep submit experiments/fig8_speaker_listener.toml --scale quick",
        "convoy sweep watch fig8-1a2b3c",
        "convoy sweep summary fig8-1a2b3c --plot fig8.png",
    ))  # fmt: skip

    def add(name: str, with_id: bool = True) -> argparse.ArgumentParser:
        p = add_sub(name)
        if with_id:
            p.add_argument("id", help="sweep id (see `convoy sweep list`)")
        return p

    p = add("submit", with_id=False)
    p.add_argument("file", help="the sweep file (.toml or .json)")
    p.add_argument("--scale", help="one of the file's [scales.NAME] tables, e.g. quick or paper (default: none)")
    p.add_argument("--json", action="store_true", help="print the new sweep as JSON")
    add("list", with_id=False).add_argument("--json", action="store_true", help="print the sweeps as JSON")
    add("status").add_argument("--json", action="store_true", help="print the sweep as JSON")
    p = add("watch")
    p.add_argument("--interval", type=positive, default=2.0, metavar="S", help="seconds between polls (default: 2)")
    p.add_argument("--timeout", type=positive, metavar="S", help="give up (exit 2) after S seconds (default: never)")
    p = add("summary")
    p.add_argument("--threshold", type=float, help="time to this return (default: the sweep's threshold)")
    p.add_argument("--plot", metavar="PNG", help="write the groups' curves with 95 %% CI bands")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    for name in ("stop", "resume", "delete"):
        add(name)

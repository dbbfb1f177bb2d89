"""``convoy jobs``: the command-line client of the job service (``convoy serve``), one subcommand per action.

``submit``, ``list``, ``status``, ``scale``, ``stop``, ``resume``, ``delete``, ``metrics``, ``logs``, ``evaluate``
and ``watch`` speak HTTP to ``--url`` (``CONVOY_API_URL``, default http://127.0.0.1:8000) with ``--token``
(``CONVOY_API_TOKEN``) as the bearer token of the mutating routes. Every error the API answers is printed as one
line ``error: <field>: <problem> — <fix>`` with exit code 2; a service that does not answer is ``error: cannot
reach <url> (...)``, also exit 2.
``watch`` exits 0 when the job completes or is stopped and 1 when it fails.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import time
from collections.abc import Callable
from typing import Any

import httpx
from rich.console import Console
from rich.progress import BarColumn, Progress, TaskProgressColumn, TextColumn, TimeElapsedColumn
from rich.table import Table
from rich.text import Text

from convoy.api.lifecycle import FINAL_STATES, JobState
from convoy.api.models import MAX_ACTORS, JobSubmit
from convoy.api.remedy import WORDS_HEADER
from convoy.cli.args import add_command, add_model_flags, env_params, given, parse_pairs
from convoy.cli.train import add_job_flags
from convoy.config import MESSAGE_SOURCES

DEFAULT_URL = "http://127.0.0.1:8000"
STATES: tuple[str, ...] = tuple(JobState)  # every state, in lifecycle order, for --state
LOG_COLUMNS = ("env_steps", "episodes", "updates", "return", "loss", "env_steps_per_s", "policy_lag", "actors_alive")
HTTP_TIMEOUT_S = 30.0


class CliError(Exception):
    """An error to print as one line ``error: <field>: <problem> — <fix>`` and exit with ``code``."""

    def __init__(self, field: str, problem: str, fix: str = "", code: int = 2) -> None:
        super().__init__(problem)
        self.field, self.problem, self.fix, self.code = field, problem, fix, code

    def line(self) -> str:
        text = f"{self.field}: {self.problem}" if self.field else self.problem
        return " ".join((f"{text} — {self.fix}" if self.fix else text).split())  # one line, whatever the server said


class Unreachable(CliError):
    """The service did not answer at all."""

    def __init__(self, url: str) -> None:
        super().__init__("", f"cannot reach {url} (is `convoy serve` running?)")


def api_error(resp: httpx.Response) -> CliError:
    """The API's ``{"field", "problem", "fix"}`` body as a CliError (its fix in the command line's words: ``Api`` asks
    for them); anything else still as one line."""
    try:
        body = resp.json()
    except ValueError:
        body = None
    if isinstance(body, dict) and {"field", "problem"} <= body.keys():
        return CliError(str(body["field"]), str(body["problem"]), str(body.get("fix") or ""))
    text = " ".join(resp.text.split())[:200] or resp.reason_phrase
    problem = f"{resp.status_code} {resp.reason_phrase} from {resp.request.url}: {text}"
    return CliError("http", problem, "is --url the address of `convoy serve`? (its API docs are at URL/docs)")


class Api:
    """A thin httpx client of the job API that turns every failure into a ``CliError``."""

    def __init__(self, url: str, token: str | None, timeout: float = HTTP_TIMEOUT_S) -> None:
        self.url = url.rstrip("/")
        headers = {WORDS_HEADER: "cli"}  # the API's fixes as convoy commands (api/remedy.py), not routes
        if token:
            headers["Authorization"] = f"Bearer {token}"
        try:
            self.client = httpx.Client(base_url=self.url, headers=headers, timeout=timeout)
        except (httpx.InvalidURL, ValueError) as exc:
            raise CliError("--url", f"{url!r} is not a URL ({exc})", f"give one like {DEFAULT_URL}") from None

    def __enter__(self) -> Api:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.client.close()

    def call(self, method: str, path: str, **kwargs: Any) -> Any:
        """The decoded JSON answer of one request (None for an empty body)."""
        try:
            resp = self.client.request(method, path, **kwargs)
        except (httpx.ConnectError, httpx.ConnectTimeout):
            raise Unreachable(self.url) from None
        except (httpx.UnsupportedProtocol, httpx.InvalidURL) as exc:
            raise CliError("--url", f"{self.url!r}: {exc}", f"give one like {DEFAULT_URL}") from None
        except httpx.TransportError as exc:
            problem = f"{method} {self.url}{path} failed: {type(exc).__name__} {exc}".strip()
            raise CliError("http", problem, "check that `convoy serve` is healthy (GET /healthz)") from None
        if resp.status_code >= 400:
            raise api_error(resp)
        if not resp.content:
            return None
        try:
            return resp.json()
        except ValueError:
            raise CliError("http", f"{method} {path}: the answer is not JSON", "is --url a convoy service?") from None


# --- formatting --------------------------------------------------------------------------------------------------


def fmt(value: Any, digits: int = 4) -> str:
    """A metric value for a table: ints as they are, floats with ``digits`` significant digits, None as –."""
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "–" if value is None else str(value)
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, int) or (isinstance(value, float) and value.is_integer() and abs(value) < 1e15):
        return str(int(value))
    if isinstance(value, float):
        return f"{value:.0f}" if abs(value) >= 10**digits else f"{value:.{digits}g}"
    return str(value)


def plain(out: Console, text: str) -> None:
    """One line as it is: no markup, highlighting or wrapping (ids, paths and JSON stay intact in pipes)."""
    out.print(text, highlight=False, markup=False, soft_wrap=True)


def print_json(out: Console, data: Any) -> None:
    """Indented JSON, never wrapped or coloured (for scripts and ``jq``)."""
    plain(out, json.dumps(data, indent=2))


def first(*values: Any) -> Any:
    """The first value that is not None (None if all are)."""
    return next((v for v in values if v is not None), None)


def alive_of(job: dict[str, Any]) -> str:
    return f"{job['actors_alive']}/{job['actors']}"


def state_text(job: dict[str, Any]) -> str:
    if job["state"] == "queued" and job.get("queue_position"):
        return f"queued #{job['queue_position']}"
    return str(job["state"])


def summary_line(job: dict[str, Any], elapsed: float | None = None) -> str:
    """One line: the job's state, env steps, return, updates, time watched and error."""
    prog = job["progress"]
    parts = [f"job {job['id']} {job['state']}: {prog['env_steps']:,}/{job['steps']:,} env steps"]
    if prog.get("return") is not None:
        parts.append(f"return {fmt(prog['return'])}")
    if prog.get("updates") is not None:
        parts.append(f"{prog['updates']:,} updates")
    if elapsed is not None:
        parts.append(f"watched {elapsed:.1f} s")
    if job.get("error"):
        parts.append(f"error: {' '.join(str(job['error']).split())}")
    return ", ".join(parts)


# --- commands ----------------------------------------------------------------------------------------------------


def submit_body(args: argparse.Namespace) -> dict[str, Any]:
    """The ``POST /jobs`` body from the flags; flags not given are left to the service's defaults."""
    names = ("algo", "env", "steps", "num_envs", "seed", "actors", "eval_episodes", "eval_messages", "eval_every",
             "log_every", "name")  # fmt: skip
    body: dict[str, Any] = given(args, (*names, "checkpoint_every", "hierarchical"))
    params = env_params(args)
    if params:
        body["env_params"] = params
    hp = parse_pairs(args.hp, "--hp")
    if hp:
        body["algo_params"] = hp
    runtime = parse_pairs(args.runtime, "--runtime")
    if runtime:
        body["runtime"] = runtime
    return body


def cmd_submit(api: Api, args: argparse.Namespace, out: Console) -> int:
    """Submit a training job.

    Submit a job (POST /jobs) and print its id and state. The flags are those of `convoy train`; the ones not
    given take the service's defaults. The job waits in the queue until the service has processes free (actors +
    2).
    """
    job = api.call("POST", "/jobs", json=submit_body(args))
    if args.json:
        print_json(out, job)
    else:
        plain(out, f"submitted {job['id']}: {state_text(job)}")
        plain(out, f"follow it with: convoy jobs watch {job['id']}")
    return 0


def cmd_list(api: Api, args: argparse.Namespace, out: Console) -> int:
    """List the jobs.

    List the jobs (GET /jobs), oldest first: id, algorithm/env, state, progress, actors alive/requested and the
    last training return.
    """
    params = {"state": args.state} if args.state else None
    jobs = api.call("GET", "/jobs", params=params)["jobs"]
    if args.json:
        print_json(out, jobs)
        return 0
    if not jobs:
        out.print(f"no {args.state + ' ' if args.state else ''}jobs", highlight=False)
        return 0
    table = Table(title=f"jobs at {api.url}")
    table.add_column("id", no_wrap=True)
    table.add_column("algo/env")
    table.add_column("state")
    table.add_column("progress", justify="right")
    table.add_column("actors", justify="right", header_style="bold")
    table.add_column("return", justify="right")
    for job in jobs:
        prog = job["progress"]
        cells = (job["id"], f"{job['algo']}/{job['env']}", state_text(job), f"{prog['fraction']:.0%}")
        table.add_row(*(Text(c) for c in (*cells, alive_of(job), fmt(prog.get("return")))))
    out.print(table)
    out.print("actors: alive/requested", highlight=False)
    return 0


def cmd_status(api: Api, args: argparse.Namespace, out: Console) -> int:
    """Show one job.

    Show every field of one job (GET /jobs/ID).
    """
    job = api.call("GET", f"/jobs/{args.id}")
    if args.json:
        print_json(out, job)
        return 0
    prog, cfg = job["progress"], job["config"]
    table = Table(title=f"job {job['id']}", show_header=False)
    table.add_column("field", style="bold")
    table.add_column("value", overflow="fold")
    rows: list[tuple[str, str]] = [
        ("state", state_text(job)),
        ("algo / env", f"{job['algo']} / {job['env']}"),
        ("actors alive/requested", alive_of(job)),
        ("env steps", f"{prog['env_steps']:,} of {job['steps']:,} ({prog['fraction']:.0%})"),
        ("updates", fmt(prog.get("updates"))),
        ("return", fmt(prog.get("return"))),
        ("loss", fmt(prog.get("loss"))),
        ("env steps/s", fmt(prog.get("env_steps_per_s"), 3)),
        ("updates/s", fmt(prog.get("updates_per_s"), 3)),
        ("policy lag", fmt(prog.get("policy_lag"), 3)),
        ("dropped messages", dropped_text(prog.get("dropped") or {})),
        ("env params", json.dumps(cfg.get("env_params", {}))),
        ("algo params", json.dumps(cfg.get("algo_params", {}))),
        ("num envs / seed", f"{cfg.get('num_envs')} / {cfg.get('seed')}"),
        ("last checkpoint", job.get("last_checkpoint") or "–"),
        ("created", time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(job["created_at"]))),
        ("updated", time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(job["updated_at"]))),
    ]
    final = job.get("final")
    if final:
        rows[4:4] = [("final greedy return", final_text(final))]
    if job.get("error"):
        rows.append(("error", job["error"]))
    for name, value in rows:
        table.add_row(name, Text(value))
    out.print(table)
    return 0


def final_text(final: dict[str, Any]) -> str:
    """``39.16 ± 3.96 (best 67.30 at 20,000); random 16.13, constant-8 23.67, scripted 60.08``."""
    text = f"{fmt(final.get('eval_return'))} ± {fmt(final.get('eval_ci95'))}"
    if final.get("best_eval_return") is not None:
        text += f" (best {fmt(final['best_eval_return'])} at {final.get('best_eval_step') or 0:,})"
    refs = ", ".join(f"{name} {fmt(pair[0])}" for name, pair in (final.get("references") or {}).items() if pair)
    return f"{text}; {refs}" if refs else text


def dropped_text(dropped: dict[str, dict[str, int]]) -> str:
    """``learner: action-range 3, non-finite 6; actors: garbage 50`` (roles with nothing dropped left out)."""
    parts = []
    for role, reasons in dropped.items():
        counts = ", ".join(f"{reason} {n:,}" for reason, n in reasons.items() if n)
        if counts:
            parts.append(f"{role}: {counts}")
    return "; ".join(parts) or "none"


def cmd_scale(api: Api, args: argparse.Namespace, out: Console) -> int:
    """Change the actor count of a queued or running job.

    Ask for ACTORS actor processes (PATCH /jobs/ID); a running job scales live. A finished job is scaled by
    `convoy jobs resume ID --actors N` instead.
    """
    job = api.call("PATCH", f"/jobs/{args.id}", json={"actors": args.actors})
    plain(out, f"{job['id']}: {job['actors']} actors requested ({state_text(job)})")
    return 0


def cmd_stop(api: Api, args: argparse.Namespace, out: Console) -> int:
    """Stop a job (it checkpoints first).

    Stop a job (POST /jobs/ID/stop): a queued job is cancelled, a running one checkpoints and stops. `convoy
    jobs resume ID` continues it.
    """
    job = api.call("POST", f"/jobs/{args.id}/stop")
    plain(out, f"{job['id']}: {state_text(job)}")
    return 0


def cmd_resume(api: Api, args: argparse.Namespace, out: Console) -> int:
    """Continue a stopped, failed or completed job.

    Queue a stopped, failed or completed job again (POST /jobs/ID/resume); it continues from its last
    checkpoint, optionally with another actor count or a larger step budget.
    """
    body = {k: v for k, v in (("actors", args.actors), ("steps", args.steps)) if v is not None}
    job = api.call("POST", f"/jobs/{args.id}/resume", json=body)
    text = f"{job['id']}: {state_text(job)}, {job['actors']} actors, {job['steps']:,} env steps in all"
    plain(out, text)
    return 0


def cmd_delete(api: Api, args: argparse.Namespace, out: Console) -> int:
    """Delete a job with its history and files.

    Delete a job (DELETE /jobs/ID): its processes are ended, its history, metrics and output files removed.
    """
    api.call("DELETE", f"/jobs/{args.id}")
    plain(out, f"deleted {args.id} (its processes, history, metrics and files)")
    return 0


def cmd_logs(api: Api, args: argparse.Namespace, out: Console) -> int:
    """Print a job's process logs (crashes, tracebacks).

    Print the last lines of a job's process logs (GET /jobs/ID/logs): its host's log, where starts, respawns,
    crashes and their tracebacks go. A failed job's error names its cause; this shows the whole story.
    """
    for line in api.call("GET", f"/jobs/{args.id}/logs", params={"lines": args.lines})["lines"]:
        plain(out, line)
    return 0


def cmd_metrics(api: Api, args: argparse.Namespace, out: Console) -> int:
    """Print a job's metric rows.

    Print the metric rows of a job (GET /jobs/ID/metrics) as a table, one row per --log-every env steps.
    Columns: env_steps, episodes, updates, return, loss, env_steps_per_s, policy_lag, actors_alive, or those
    named by --names.
    """
    params: dict[str, Any] = {}
    if args.since is not None:
        params["since"] = args.since
    if args.names:
        params["names"] = args.names
    if args.limit is not None:
        params["limit"] = args.limit
    page = api.call("GET", f"/jobs/{args.id}/metrics", params=params)
    rows: list[dict[str, Any]] = page["rows"]
    if args.json:
        for row in rows:
            plain(out, json.dumps(row))
        return 0
    if not rows:
        out.print(f"no metric rows for {args.id}{' after step ' + str(args.since) if args.since is not None else ''}")
        return 0
    seen: dict[str, None] = {}
    for row in rows:
        seen.update(dict.fromkeys(row))
    if args.names:
        wanted = ["env_steps"] + [n.strip() for n in args.names.split(",") if n.strip() and n.strip() != "env_steps"]
        columns = [c for c in wanted if c in seen]
    else:
        columns = [c for c in LOG_COLUMNS if c in seen]
    table = Table(title=f"metrics of {args.id}")
    for col in columns:
        table.add_column(col, justify="right", no_wrap=col == "env_steps")
    for row in rows:
        table.add_row(*(Text(fmt(row.get(col))) for col in columns))
    out.print(table)
    more = "" if args.names else " (--names a,b for other columns, --json for all)"
    out.print(f"{len(rows)} rows; newer ones: convoy jobs metrics {args.id} --since {page['last_step']}{more}")
    return 0


def cmd_watch(api: Api, args: argparse.Namespace, out: Console) -> int:
    """Follow a job live until it finishes.

    Show a live progress bar of a job with its return, env-steps/s, actors alive and policy lag (in a pipe or a
    file: one line whenever they change), polling GET /jobs/ID and its new metric rows, until the job completes,
    stops or fails; then print a one-line summary.
    Exit code 0 when it completed or stopped, 1 when it failed. Ctrl-C stops watching, not the job.
    """
    t0 = time.monotonic()
    job = api.call("GET", f"/jobs/{args.id}")
    start = int(job["progress"]["env_steps"])
    cursor: int | None = start - 1 if start > 0 else None  # the latest row, not a long job's whole history
    last: dict[str, Any] = {}
    columns = (
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        TaskProgressColumn(),
        TextColumn("{task.fields[state]}"),
        TextColumn("return {task.fields[ret]}"),
        TextColumn("{task.fields[speed]} env-steps/s"),
        TextColumn("actors {task.fields[alive]}"),
        TextColumn("lag {task.fields[lag]}"),
        TimeElapsedColumn(),
    )
    live = out.is_terminal  # a bar in a terminal; in a pipe or a file, one plain line per change
    printed = ""
    with Progress(*columns, console=out, auto_refresh=False, disable=not live) as bar:
        task = bar.add_task(job["id"], total=job["steps"], state="", ret="–", speed="–", alive="–", lag="–")
        while True:
            params = {"since": cursor} if cursor is not None else {}
            page = api.call("GET", f"/jobs/{args.id}/metrics", params=params)
            if page["rows"]:
                last = page["rows"][-1]
                cursor = page["last_step"]
            elif cursor is not None and (page["last_step"] or 0) < cursor:
                cursor, last = page["last_step"], {}  # a resume cut the history back to its checkpoint: rewind
            prog = job["progress"]
            done = min(prog["env_steps"], job["steps"])
            fields: dict[str, Any] = {
                "state": state_text(job),
                "ret": fmt(first(last.get("return"), prog.get("return"))),
                "speed": fmt(first(last.get("env_steps_per_s"), prog.get("env_steps_per_s")), 3),
                "alive": alive_of(job),
                "lag": fmt(first(last.get("policy_lag"), prog.get("policy_lag")), 3),
            }
            if live:
                bar.update(task, total=job["steps"], completed=done, **fields)
                bar.refresh()
            else:
                text = (
                    f"{job['id']} {fields['state']}: {done:,}/{job['steps']:,} env steps · return {fields['ret']} · "
                    f"{fields['speed']} env-steps/s · actors {fields['alive']} · lag {fields['lag']}"
                )
                if text != printed:
                    plain(out, text)
                    printed = text
            if job["state"] in FINAL_STATES:
                break
            if args.timeout is not None and time.monotonic() - t0 > args.timeout:
                raise CliError(
                    "watch",
                    f"job {args.id} is still {job['state']} after {args.timeout:g} s",
                    "watch it again, or give a larger --timeout",
                )
            time.sleep(args.interval)
            job = api.call("GET", f"/jobs/{args.id}")
    line = summary_line(job, time.monotonic() - t0)
    if job["state"] == "failed":
        raise CliError("", line, f"see its log, then `convoy jobs resume {args.id}`", code=1)
    plain(out, line)
    return 0


def cmd_evaluate(api: Api, args: argparse.Namespace, out: Console) -> int:
    """Evaluate a job's checkpoint on the service, in the background.

    Start greedy episodes of the job's checkpoint.pt (or best.pt) on the service (POST /jobs/ID/evaluate: its
    own process, the API answers at once), then wait for the result (GET /jobs/ID/evaluations/EID) and print
    it; --no-wait prints the evaluation's id and returns.
    """
    body = {"episodes": args.episodes, "messages": args.messages, "checkpoint": args.checkpoint}
    if args.channel:
        body["channel"] = args.channel
    ev = api.call("POST", f"/jobs/{args.id}/evaluate", json=body)
    plain(out, f"evaluation {ev['id']} of {args.id}: {args.episodes} episodes of {args.checkpoint}, running")
    if args.no_wait:
        return 0
    while ev["state"] == "running":
        time.sleep(1.0)
        ev = api.call("GET", f"/jobs/{args.id}/evaluations/{ev['id']}")
    if ev["state"] == "failed":
        raise CliError("evaluation", f"{ev['id']} failed: {ev['error']}", f"see `convoy jobs logs {args.id}`", 1)
    r = ev["result"]
    plain(out, f"greedy return {fmt(r['mean_return'])} ± {fmt(r['ci95'])} over {r['episodes']} episodes "
               f"(messages {r['messages']}); random policy {fmt(r['random_return'])}")  # fmt: skip
    return 0


COMMANDS: dict[str, Callable[[Api, argparse.Namespace, Console], int]] = {
    "submit": cmd_submit,
    "list": cmd_list,
    "status": cmd_status,
    "scale": cmd_scale,
    "stop": cmd_stop,
    "resume": cmd_resume,
    "delete": cmd_delete,
    "metrics": cmd_metrics,
    "logs": cmd_logs,
    "watch": cmd_watch,
    "evaluate": cmd_evaluate,
}


def cmd_jobs(args: argparse.Namespace) -> int:
    """Submit, watch and control the jobs of a running `convoy serve`.

    Talk to the job service started by `convoy serve` (its REST API, OpenAPI at URL/docs). Reading commands need
    no token; submit, scale, stop, resume, delete and evaluate send 'Authorization: Bearer TOKEN'. API errors are
    printed as 'error: FIELD: PROBLEM — FIX' with exit code 2.
    """
    return run_client(args, COMMANDS[args.jobs_command])


def run_client(args: argparse.Namespace, command: Callable[[Api, argparse.Namespace, Console], int]) -> int:
    """Connect to ``--url`` with ``--token`` and run ``command``; a ``CliError`` is one ``error:`` line."""
    out, err = Console(), Console(stderr=True)
    url = args.url or os.environ.get("CONVOY_API_URL", "").strip() or DEFAULT_URL
    token = args.token if args.token is not None else os.environ.get("CONVOY_API_TOKEN", "").strip() or None
    try:
        with Api(url, token) as api:
            return command(api, args, out)
    except CliError as exc:
        err.print(Text.assemble(("error:", "bold red"), " ", exc.line()), soft_wrap=True)
        return exc.code


# --- parser ------------------------------------------------------------------------------------------------------


def connection_options(p: argparse.ArgumentParser, default: Any) -> None:
    p.add_argument(
        "--url",
        default=default,
        help=f"the service's address (default: $CONVOY_API_URL, else {DEFAULT_URL})",
    )
    p.add_argument(
        "--token",
        default=default,
        help="bearer token of the mutating commands (default: $CONVOY_API_TOKEN; `convoy serve` prints it)",
    )


def positive(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number of seconds, got {text!r}") from None
    if not math.isfinite(value) or value <= 0:
        raise argparse.ArgumentTypeError(f"must be > 0, got {text!r}")
    return value


def add_client(
    sub: argparse._SubParsersAction,
    name: str,
    func: Callable[[argparse.Namespace], int],
    commands: dict[str, Callable[[Api, argparse.Namespace, Console], int]],
    examples: tuple[str, ...],
) -> Callable[[str], argparse.ArgumentParser]:
    """``convoy NAME …``, a client of the service: ``--url``/``--token`` before or after its subcommand, which lands
    in ``args.NAME_command``. Returns the function that adds one subcommand of ``commands``, run through ``func``."""
    top = add_command(
        sub,
        name,
        func,
        epilog="examples:\n" + "\n".join(f"  {line}" for line in examples),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    connection_options(top, None)
    subs = top.add_subparsers(dest=f"{name}_command", required=True, metavar=f"{name.upper()}_COMMAND")
    common = argparse.ArgumentParser(add_help=False)
    connection_options(common, argparse.SUPPRESS)  # also accepted after the subcommand

    def add(command: str) -> argparse.ArgumentParser:
        p = add_command(subs, command, commands[command], parents=[common])
        p.set_defaults(func=func)  # one entry point: connects to the service, then runs commands[command]
        return p

    return add


def add_jobs_parser(sub: argparse._SubParsersAction) -> None:
    """``convoy jobs …``: the subcommands, each with a complete ``--help``."""
    add = add_client(sub, "jobs", cmd_jobs, COMMANDS, (
        "convoy jobs submit --algo ma-mesn --steps 200000 --actors 2 --set n_agents=3 --hp lr=0.001",
        "convoy jobs list --state running",
        "convoy jobs watch ma-mesn-1a2b3c",
        "convoy jobs metrics ma-mesn-1a2b3c --names return,loss --since 10000",
        "convoy jobs scale ma-mesn-1a2b3c 4",
        "convoy jobs resume ma-mesn-1a2b3c --steps 400000",
    ))  # fmt: skip

    p = add("submit")
    add_job_flags(p)
    add_model_flags(p, JobSubmit, ("checkpoint_every",))
    p.add_argument("--name", help="prefix of the job id: letters, digits, _ . - (default: the algorithm)")
    p.add_argument("--json", action="store_true", help="print the new job as JSON")

    p = add("list")
    p.add_argument("--state", help=f"only jobs in this state: {', '.join(STATES)}")
    p.add_argument("--json", action="store_true", help="print the jobs as JSON")

    p = add("status")
    p.add_argument("id", help="job id (see `convoy jobs list`)")
    p.add_argument("--json", action="store_true", help="print the job as JSON")

    p = add("scale")
    p.add_argument("id", help="job id")
    p.add_argument("actors", type=int, help=f"actor processes wanted, 1–{MAX_ACTORS}")

    p = add("stop")
    p.add_argument("id", help="job id")

    p = add("resume")
    p.add_argument("id", help="job id")
    p.add_argument("--actors", type=int, help="actor processes (default: as before)")
    p.add_argument("--steps", type=int, help="new total env-step budget (default: as before)")

    p = add("delete")
    p.add_argument("id", help="job id")

    p = add("metrics")
    p.add_argument("id", help="job id")
    p.add_argument("--since", type=int, metavar="STEP", help="only rows with env_steps > STEP")
    p.add_argument("--names", metavar="A,B", help="only these metrics (comma-separated), e.g. return,loss")
    p.add_argument("--limit", type=int, metavar="N", help="at most N rows")
    p.add_argument("--json", action="store_true", help="one JSON object per row, every metric")

    p = add("logs")
    p.add_argument("id", help="job id")
    p.add_argument(
        "--lines", type=int, default=200, metavar="N", help="how many of the last lines (default: %(default)s)"
    )

    p = add("evaluate")
    p.add_argument("id", help="job id")
    p.add_argument("--episodes", type=int, default=100, metavar="N", help="greedy episodes (default: %(default)s)")
    p.add_argument("--messages", choices=MESSAGE_SOURCES, default="sent", help="what the agents hear (default: sent)")
    p.add_argument("--channel", metavar="SPEC", help="a lossy channel, e.g. drop=0.3,flip=0.01")
    p.add_argument("--checkpoint", default="checkpoint.pt", choices=("checkpoint.pt", "best.pt"),
                   help="the last checkpoint or the best greedy point (default: %(default)s)")  # fmt: skip
    p.add_argument("--no-wait", action="store_true", help="print the evaluation's id and return")

    p = add("watch")
    p.add_argument("id", help="job id")
    p.add_argument(
        "--interval", type=positive, default=1.0, metavar="S", help="seconds between polls (default: %(default)s)"
    )
    p.add_argument(
        "--timeout", type=positive, metavar="S", help="give up (exit 2) after S seconds (default: wait for the end)"
    )

"""The job service's persistence: jobs, their state transitions (``api/lifecycle.py``), their metric history and the
sweeps that group them, in one SQLite file.

Why SQLite, and why this shape
------------------------------
The API must find every job again after a restart, with its full metric history, and it must not need a database
server to do so. One SQLite file next to the runs does that with the standard library only.

* **WAL journal mode.** In write-ahead-log mode readers never block the writer and the writer never blocks readers:
  a ``sqlite3`` shell, a CLI or a second read-only API process can read the file while the learner's metrics stream
  in, and a commit is one append to the log (fast, crash-safe). ``synchronous=NORMAL`` is the usual WAL pairing: a
  power cut may lose the last few commits but never corrupts the file — acceptable for job records and metrics that
  the learner re-emits on resume anyway.
* **One connection, one lock.** The store opens a single connection with ``check_same_thread=False`` and guards it
  with one ``threading.Lock``, so FastAPI's threadpool, the SSE pollers and the background threads that watch jobs
  can all share it. Inside this process the lock serialises every call; each call is a short indexed query, so this
  is cheaper and simpler than a pool of connections. Every write runs in one ``BEGIN IMMEDIATE … COMMIT``
  transaction (the connection is in autocommit mode and the store opens transactions itself), so a reader never
  sees half of a batch of metric rows.
* **Schema version in ``PRAGMA user_version``.** A fresh file gets ``SCHEMA_VERSION``; opening a file written by a
  newer Convoy (a higher ``user_version``) raises ``StoreError`` instead of guessing at columns it does not know.
* **JSON columns.** A job's config, its progress dict and each metric row are stored as JSON text: the learner adds
  metric names freely and the store does not need a migration for each. Metric rows are keyed by ``(job, step)``
  where the step is the row's ``env_steps``; a clustered primary key makes ``step > since`` polls a range scan.

Non-finite floats
-----------------
Losses and returns can be NaN or ±inf. JSON columns are written with Python's ``json`` defaults, which spell them
``NaN``, ``Infinity`` and ``-Infinity``, and read back with ``json.loads``, which turns them into
``float('nan')``/``float('inf')``/``float('-inf')`` again — a faithful round trip that keeps NaN, +inf and -inf
apart (mapping them all to ``null`` would not). These columns are only read through this module; whoever serves them
as strict JSON (the HTTP layer) must map non-finite floats itself. numpy/torch scalars and arrays are converted with
their ``tolist()`` on the way in.

Polling metrics without duplicates or gaps
------------------------------------------
``metrics(job, since=s, limit=n)`` returns rows with ``step > s`` in ascending step order, at most ``n`` of them. A
client that asks again with ``since`` = the last step it got receives exactly the rows after that one: steps are
unique per job, so no row comes twice, and rows are ordered, so none is skipped — provided the learner appends steps
in ascending order (it does: ``env_steps`` only grows) and each batch commits atomically (it does). A resume from a
checkpoint at step ``c`` first calls ``cut_metrics(job, c)`` and the learner then re-emits steps above ``c``; a
client whose cursor is beyond ``c`` should rewind its cursor to ``c`` when it sees the job re-queued (``last_step``
dropping below its cursor tells it so).
"""

from __future__ import annotations

import builtins
import json
import operator
import sqlite3
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from convoy.api.lifecycle import (
    ALLOWED_TRANSITIONS,
    InvalidTransition,
    JobRecord,
    JobState,
    StoreError,
    SweepRecord,
    UnknownJob,
    UnknownSweep,
)

__all__ = ["SCHEMA_VERSION", "JobStore"]

SCHEMA_VERSION = 2
"""Written to ``PRAGMA user_version``; bump it (and add a migration) whenever the tables change."""


_SCHEMA: tuple[str, ...] = (
    """CREATE TABLE IF NOT EXISTS jobs (
        id TEXT PRIMARY KEY,
        state TEXT NOT NULL,
        config TEXT NOT NULL,
        actors INTEGER NOT NULL,
        created_at REAL NOT NULL,
        updated_at REAL NOT NULL,
        out_dir TEXT,
        error TEXT,
        last_checkpoint TEXT,
        progress TEXT NOT NULL DEFAULT '{}'
    )""",
    "CREATE INDEX IF NOT EXISTS jobs_by_state ON jobs (state, created_at, id)",
    "CREATE INDEX IF NOT EXISTS jobs_by_created ON jobs (created_at, id)",
    """CREATE TABLE IF NOT EXISTS transitions (
        seq INTEGER PRIMARY KEY AUTOINCREMENT,
        job_id TEXT NOT NULL,
        at REAL NOT NULL,
        from_state TEXT,
        to_state TEXT NOT NULL,
        reason TEXT NOT NULL DEFAULT ''
    )""",
    "CREATE INDEX IF NOT EXISTS transitions_by_job ON transitions (job_id, seq)",
    """CREATE TABLE IF NOT EXISTS metrics (
        job_id TEXT NOT NULL,
        step INTEGER NOT NULL,
        row TEXT NOT NULL,
        PRIMARY KEY (job_id, step)
    ) WITHOUT ROWID""",
    # version 2: sweeps, each a request and its jobs in grid order ({"id", "point"}); the jobs are ordinary rows
    """CREATE TABLE IF NOT EXISTS sweeps (
        id TEXT PRIMARY KEY,
        created_at REAL NOT NULL,
        spec TEXT NOT NULL,
        jobs TEXT NOT NULL
    )""",
)

_JOB_COLUMNS = "id, state, config, actors, created_at, updated_at, out_dir, error, last_checkpoint, progress"


def _json_default(obj: Any) -> Any:
    """Let numpy/torch scalars and arrays through (via ``tolist()``) without importing either."""
    tolist = getattr(obj, "tolist", None)
    if callable(tolist):
        return tolist()
    raise TypeError(f"{type(obj).__name__} is not JSON-serialisable")


def _dumps(obj: Any, what: str) -> str:
    """JSON text with NaN/±inf spelled ``NaN``/``Infinity`` (see the module docstring), or a ``StoreError``."""
    try:
        return json.dumps(obj, default=_json_default, allow_nan=True)
    except (TypeError, ValueError) as exc:
        raise StoreError(f"{what} cannot be stored as JSON: {exc}") from exc


def _coerce_state(state: JobState | str) -> JobState:
    """A ``JobState`` from a state or its name, or a ``StoreError`` listing the valid names."""
    if isinstance(state, JobState):
        return state
    try:
        return JobState(state)
    except ValueError:
        valid = ", ".join(s.value for s in tuple(JobState))
        raise StoreError(f"unknown job state {state!r}; valid states: {valid}") from None


def _as_int(value: Any, what: str, *, minimum: int | None = None) -> int:
    """An ``int`` (numpy ints welcome, bools and floats refused), checked against ``minimum``."""
    if isinstance(value, bool):
        raise StoreError(f"{what} must be an int, got bool {value!r}")
    try:
        out = operator.index(value)
    except TypeError:
        raise StoreError(f"{what} must be an int, got {type(value).__name__} {value!r}") from None
    if minimum is not None and out < minimum:
        raise StoreError(f"{what} must be ≥ {minimum}, got {out}")
    return out


def _as_dict(value: Any, what: str) -> dict[str, Any]:
    if not isinstance(value, dict):
        raise StoreError(f"{what} must be a dict, got {type(value).__name__}")
    return value


def _as_opt_str(value: Any, what: str) -> str | None:
    if value is None:
        return None
    if isinstance(value, Path):
        return str(value)
    if not isinstance(value, str):
        raise StoreError(f"{what} must be a str or None, got {type(value).__name__}")
    return value


class JobStore:
    """Jobs, transitions, metric history and sweeps in one SQLite file (WAL); every method is thread-safe.

    Use it as a context manager, or call ``close()`` when done. ``":memory:"`` gives a private in-memory store.
    """

    def __init__(self, path: str | Path) -> None:
        self.path = str(path)
        self._lock = threading.Lock()
        if self.path != ":memory:":
            Path(self.path).expanduser().parent.mkdir(parents=True, exist_ok=True)
            self.path = str(Path(self.path).expanduser())
        try:
            conn = sqlite3.connect(self.path, check_same_thread=False, isolation_level=None, timeout=5.0)
        except sqlite3.Error as exc:
            raise StoreError(f"cannot open job store {self.path!r}: {exc}") from exc
        self._conn: sqlite3.Connection | None = conn
        try:
            self.journal_mode = self._init_schema(conn)
        except BaseException:
            conn.close()
            self._conn = None
            raise

    def _init_schema(self, conn: sqlite3.Connection) -> str:
        """Refuse newer files, switch to WAL, create the tables once; returns the journal mode in effect."""
        try:
            version = conn.execute("PRAGMA user_version").fetchone()[0]
            self._check_version(version)
            mode = str(conn.execute("PRAGMA journal_mode=WAL").fetchone()[0]).lower()
            conn.execute("PRAGMA synchronous=NORMAL")
            conn.execute("PRAGMA busy_timeout=5000")
            if version < SCHEMA_VERSION:
                conn.execute("BEGIN IMMEDIATE")
                try:
                    # Another process may have initialised the file meanwhile: read the version again under the lock.
                    version = conn.execute("PRAGMA user_version").fetchone()[0]
                    self._check_version(version)
                    for statement in _SCHEMA:
                        conn.execute(statement)
                    conn.execute(f"PRAGMA user_version = {SCHEMA_VERSION}")
                except BaseException:
                    conn.execute("ROLLBACK")
                    raise
                conn.execute("COMMIT")
        except sqlite3.DatabaseError as exc:
            raise StoreError(f"{self.path!r} is not a usable Convoy job store: {exc}") from exc
        return mode

    def _check_version(self, version: int) -> None:
        if version > SCHEMA_VERSION:
            raise StoreError(
                f"job store {self.path!r} has schema version {version}, but this Convoy understands only up to "
                f"version {SCHEMA_VERSION}: it was written by a newer Convoy. Upgrade Convoy, or point the API at "
                f"another database file."
            )

    # -- lifecycle -------------------------------------------------------------------------------------------------

    def close(self) -> None:
        """Close the connection (checkpointing the WAL into the main file); safe to call twice."""
        with self._lock:
            if self._conn is not None:
                self._conn.close()
                self._conn = None

    def __enter__(self) -> JobStore:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    def _open_conn(self) -> sqlite3.Connection:
        if self._conn is None:
            raise StoreError(f"job store {self.path!r} is closed")
        return self._conn

    @contextmanager
    def _read(self) -> Iterator[sqlite3.Connection]:
        """Hold the lock for a read; no transaction needed, each SELECT sees committed data only."""
        with self._lock:
            yield self._open_conn()

    @contextmanager
    def _write(self) -> Iterator[sqlite3.Connection]:
        """Hold the lock and run the body in one transaction, rolled back on any exception."""
        with self._lock:
            conn = self._open_conn()
            conn.execute("BEGIN IMMEDIATE")
            try:
                yield conn
            except BaseException:
                conn.execute("ROLLBACK")
                raise
            conn.execute("COMMIT")

    # -- jobs ------------------------------------------------------------------------------------------------------

    @staticmethod
    def _record(row: tuple[Any, ...]) -> JobRecord:
        return JobRecord(
            id=row[0],
            state=JobState(row[1]),
            config=json.loads(row[2]),
            actors=int(row[3]),
            created_at=float(row[4]),
            updated_at=float(row[5]),
            out_dir=row[6],
            error=row[7],
            last_checkpoint=row[8],
            progress=json.loads(row[9]),
        )

    def _get(self, conn: sqlite3.Connection, job_id: str) -> JobRecord:
        row = conn.execute(f"SELECT {_JOB_COLUMNS} FROM jobs WHERE id = ?", (job_id,)).fetchone()
        if row is None:
            raise UnknownJob(job_id)
        return self._record(row)

    def _require(self, conn: sqlite3.Connection, job_id: str) -> None:
        if conn.execute("SELECT 1 FROM jobs WHERE id = ?", (job_id,)).fetchone() is None:
            raise UnknownJob(job_id)

    def create(
        self,
        job_id: str,
        config: dict[str, Any],
        actors: int,
        out_dir: str | None = None,
        state: JobState | str = JobState.queued,
    ) -> JobRecord:
        """Add a job (normally queued) and the first entry of its transition history; a taken id is refused."""
        row = self._job_row(job_id, config, actors, out_dir, state)
        with self._write() as conn:
            self._insert_job(conn, row)
            return self._get(conn, job_id)

    @staticmethod
    def _job_row(
        job_id: str,
        config: dict[str, Any],
        actors: int,
        out_dir: str | None,
        state: JobState | str,
        progress: dict[str, Any] | None = None,
    ) -> tuple[Any, ...]:
        if not isinstance(job_id, str) or not job_id:
            raise StoreError(f"job id must be a non-empty str, got {job_id!r}")
        config_json = _dumps(_as_dict(config, "config"), f"config of job {job_id!r}")
        progress_json = _dumps(_as_dict(progress or {}, "progress"), f"progress of job {job_id!r}")
        return (job_id, _coerce_state(state).value, config_json, _as_int(actors, "actors", minimum=0),
                _as_opt_str(out_dir, "out_dir"), progress_json)  # fmt: skip

    @staticmethod
    def _insert_job(conn: sqlite3.Connection, row: tuple[Any, ...]) -> None:
        job_id, state, config_json, actors, out_dir, progress_json = row
        now = time.time()
        if conn.execute("SELECT 1 FROM jobs WHERE id = ?", (job_id,)).fetchone() is not None:
            raise StoreError(f"job {job_id!r} already exists; pick another id or delete it first")
        conn.execute(
            f"INSERT INTO jobs ({_JOB_COLUMNS}) VALUES (?, ?, ?, ?, ?, ?, ?, NULL, NULL, ?)",
            (job_id, state, config_json, actors, now, now, out_dir, progress_json),
        )
        conn.execute(
            "INSERT INTO transitions (job_id, at, from_state, to_state, reason) VALUES (?, ?, NULL, ?, 'created')",
            (job_id, now, state),
        )

    # -- sweeps ----------------------------------------------------------------------------------------------------

    def create_sweep(
        self,
        sweep_id: str,
        spec: dict[str, Any],
        jobs: list[tuple[str, dict[str, Any], int, str, dict[str, Any]]],
        progress: dict[str, dict[str, Any]] | None = None,
        extra: list[tuple[str, dict[str, Any], int, str]] | None = None,
    ) -> SweepRecord:
        """Add a sweep and all its jobs (``(id, config, actors, out_dir, point)``, queued) in one transaction: a
        crash leaves either the whole sweep or nothing. ``progress[id]``: a job's first progress; ``extra``: jobs
        that run for the sweep without being its grid points (``(id, config, actors, out_dir)``: its populations)."""
        progress = progress or {}
        heads = [(job_id, config, actors, out_dir) for job_id, config, actors, out_dir, _ in jobs] + (extra or [])
        rows = [self._job_row(job_id, config, actors, out_dir, JobState.queued, progress.get(job_id))
                for job_id, config, actors, out_dir in heads]  # fmt: skip
        members = _dumps([{"id": j[0], "point": j[4]} for j in jobs], f"jobs of sweep {sweep_id!r}")
        with self._write() as conn:
            if conn.execute("SELECT 1 FROM sweeps WHERE id = ?", (sweep_id,)).fetchone() is not None:
                raise StoreError(f"sweep {sweep_id!r} already exists")
            for row in rows:
                self._insert_job(conn, row)
            conn.execute(
                "INSERT INTO sweeps (id, created_at, spec, jobs) VALUES (?, ?, ?, ?)",
                (sweep_id, time.time(), _dumps(spec, f"spec of sweep {sweep_id!r}"), members),
            )
        return self.sweep(sweep_id)

    def sweep(self, sweep_id: str) -> SweepRecord:
        """The sweep's record; ``UnknownSweep`` if there is none."""
        with self._read() as conn:
            row = conn.execute("SELECT id, created_at, spec, jobs FROM sweeps WHERE id = ?", (sweep_id,)).fetchone()
        if row is None:
            raise UnknownSweep(sweep_id)
        return SweepRecord(row[0], float(row[1]), json.loads(row[2]), json.loads(row[3]))

    def sweeps(self) -> list[SweepRecord]:
        """Every sweep, oldest first."""
        with self._read() as conn:
            rows = conn.execute("SELECT id, created_at, spec, jobs FROM sweeps ORDER BY created_at, id").fetchall()
        return [SweepRecord(r[0], float(r[1]), json.loads(r[2]), json.loads(r[3])) for r in rows]

    def delete_sweep(self, sweep_id: str) -> None:
        """Remove the sweep's record (its jobs are deleted one by one by the service, files and all)."""
        with self._write() as conn:
            if conn.execute("DELETE FROM sweeps WHERE id = ?", (sweep_id,)).rowcount == 0:
                raise UnknownSweep(sweep_id)

    def get(self, job_id: str) -> JobRecord:
        """The job's current record; ``UnknownJob`` if there is none."""
        with self._read() as conn:
            return self._get(conn, job_id)

    def exists(self, job_id: str) -> bool:
        with self._read() as conn:
            return conn.execute("SELECT 1 FROM jobs WHERE id = ?", (job_id,)).fetchone() is not None

    def list(self, state: JobState | str | None = None) -> builtins.list[JobRecord]:
        """All jobs, or those in ``state``, oldest first (ties broken by id so the order is stable)."""
        with self._read() as conn:
            if state is None:
                rows = conn.execute(f"SELECT {_JOB_COLUMNS} FROM jobs ORDER BY created_at, id").fetchall()
            else:
                rows = conn.execute(
                    f"SELECT {_JOB_COLUMNS} FROM jobs WHERE state = ? ORDER BY created_at, id",
                    (_coerce_state(state).value,),
                ).fetchall()
        return [self._record(r) for r in rows]

    def transition(self, job_id: str, to: JobState | str, reason: str = "") -> JobRecord:
        """Move the job to ``to`` if the table allows it, and log the move; failed keeps ``reason`` as the error."""
        to = _coerce_state(to)
        reason = str(reason or "")
        now = time.time()
        with self._write() as conn:
            current = self._get(conn, job_id).state
            if to not in ALLOWED_TRANSITIONS[current]:
                raise InvalidTransition(job_id, current, to)
            if to is JobState.failed:
                conn.execute(
                    "UPDATE jobs SET state = ?, updated_at = ?, error = ? WHERE id = ?",
                    (to.value, now, reason or "failed (no reason given)", job_id),
                )
            elif to is JobState.queued:
                conn.execute(
                    "UPDATE jobs SET state = ?, updated_at = ?, error = NULL WHERE id = ?", (to.value, now, job_id)
                )
            else:
                conn.execute("UPDATE jobs SET state = ?, updated_at = ? WHERE id = ?", (to.value, now, job_id))
            conn.execute(
                "INSERT INTO transitions (job_id, at, from_state, to_state, reason) VALUES (?, ?, ?, ?, ?)",
                (job_id, now, current.value, to.value, reason),
            )
            return self._get(conn, job_id)

    def transitions(self, job_id: str) -> builtins.list[dict[str, Any]]:
        """The job's history, oldest first: ``at``, ``from_state`` (None for creation), ``to_state``, ``reason``."""
        with self._read() as conn:
            self._require(conn, job_id)
            rows = conn.execute(
                "SELECT at, from_state, to_state, reason FROM transitions WHERE job_id = ? ORDER BY seq", (job_id,)
            ).fetchall()
        return [{"at": r[0], "from_state": r[1], "to_state": r[2], "reason": r[3]} for r in rows]

    def update(
        self,
        job_id: str,
        *,
        actors: int | None = None,
        progress: dict[str, Any] | None = None,
        last_checkpoint: str | None = None,
        out_dir: str | None = None,
        error: str | None = None,
        config: dict[str, Any] | None = None,
    ) -> JobRecord:
        """Change only the fields given (``None`` = leave as is); ``progress`` is merged key by key, not replaced.

        The state is not changed here — use ``transition`` so the history stays complete. ``error`` is cleared by a
        transition to queued.
        """
        sets: dict[str, Any] = {}
        if actors is not None:
            sets["actors"] = _as_int(actors, "actors", minimum=0)
        if last_checkpoint is not None:
            sets["last_checkpoint"] = _as_opt_str(last_checkpoint, "last_checkpoint")
        if out_dir is not None:
            sets["out_dir"] = _as_opt_str(out_dir, "out_dir")
        if error is not None:
            sets["error"] = _as_opt_str(error, "error")
        if config is not None:
            sets["config"] = _dumps(_as_dict(config, "config"), f"config of job {job_id!r}")
        if progress is not None:
            _as_dict(progress, "progress")
        with self._write() as conn:
            record = self._get(conn, job_id)
            if progress is not None:
                sets["progress"] = _dumps({**record.progress, **progress}, f"progress of job {job_id!r}")
            if not sets:
                return record
            sets["updated_at"] = time.time()
            assignments = ", ".join(f"{column} = ?" for column in sets)
            conn.execute(f"UPDATE jobs SET {assignments} WHERE id = ?", (*sets.values(), job_id))
            return self._get(conn, job_id)

    def delete(self, job_id: str) -> None:
        """Remove the job with its transitions and metrics, in one transaction."""
        with self._write() as conn:
            self._require(conn, job_id)
            conn.execute("DELETE FROM metrics WHERE job_id = ?", (job_id,))
            conn.execute("DELETE FROM transitions WHERE job_id = ?", (job_id,))
            conn.execute("DELETE FROM jobs WHERE id = ?", (job_id,))

    def queue_position(self, job_id: str) -> int | None:
        """1-based place among queued jobs (by created_at, then id); None if the job is not queued."""
        with self._read() as conn:
            row = conn.execute("SELECT state, created_at FROM jobs WHERE id = ?", (job_id,)).fetchone()
            if row is None:
                raise UnknownJob(job_id)
            if row[0] != JobState.queued.value:
                return None
            ahead = conn.execute(
                "SELECT COUNT(*) FROM jobs WHERE state = ? AND (created_at < ? OR (created_at = ? AND id < ?))",
                (JobState.queued.value, row[1], row[1], job_id),
            ).fetchone()[0]
        return int(ahead) + 1

    def count_by_state(self) -> dict[str, int]:
        """How many jobs are in each state, every state present (zeros too) so Prometheus gauges never vanish."""
        counts = {s.value: 0 for s in tuple(JobState)}
        with self._read() as conn:
            for state, n in conn.execute("SELECT state, COUNT(*) FROM jobs GROUP BY state"):
                counts[state] = int(n)
        return counts

    # -- metrics ---------------------------------------------------------------------------------------------------

    def append_metrics(self, job_id: str, rows: builtins.list[dict[str, Any]]) -> int:
        """Store metric rows keyed by their ``env_steps``; a step already stored is replaced (a resumed learner
        re-emits its steps). All rows are checked before any is written. Returns the number of distinct steps
        written (a step repeated within one batch counts once; the last copy wins)."""
        encoded: dict[int, str] = {}
        for i, row in enumerate(rows):
            if not isinstance(row, dict):
                raise StoreError(f"metric row {i} for job {job_id!r} must be a dict, got {type(row).__name__}")
            if "env_steps" not in row:
                raise StoreError(f"metric row {i} for job {job_id!r} has no 'env_steps' (the step it is keyed by)")
            step = _as_int(row["env_steps"], f"metric row {i} for job {job_id!r}: 'env_steps'")
            encoded[step] = _dumps({**row, "env_steps": step}, f"metric row {i} (step {step}) for job {job_id!r}")
        with self._write() as conn:
            self._require(conn, job_id)
            conn.executemany(
                "INSERT INTO metrics (job_id, step, row) VALUES (?, ?, ?) "
                "ON CONFLICT (job_id, step) DO UPDATE SET row = excluded.row",
                [(job_id, step, text) for step, text in encoded.items()],
            )
        return len(encoded)

    def cut_metrics(self, job_id: str, after_step: int) -> int:
        """Delete rows with step > ``after_step`` (resuming from a checkpoint taken there); returns how many."""
        after_step = _as_int(after_step, "after_step")
        with self._write() as conn:
            self._require(conn, job_id)
            cursor = conn.execute("DELETE FROM metrics WHERE job_id = ? AND step > ?", (job_id, after_step))
            return int(cursor.rowcount)

    def metrics(
        self,
        job_id: str,
        since: int | None = None,
        names: builtins.list[str] | None = None,
        limit: int | None = None,
    ) -> builtins.list[dict[str, Any]]:
        """Rows with step > ``since`` in ascending step order, at most ``limit`` of them.

        With ``names`` each row keeps ``env_steps`` plus those keys (keys a row lacks are simply absent). Polling with
        ``since`` = the last step received gives every row exactly once (see the module docstring).
        """
        clauses: builtins.list[str] = ["job_id = ?"]
        params: builtins.list[Any] = [job_id]
        if since is not None:
            clauses.append("step > ?")
            params.append(_as_int(since, "since"))
        sql = f"SELECT row FROM metrics WHERE {' AND '.join(clauses)} ORDER BY step"
        if limit is not None:
            sql += " LIMIT ?"
            params.append(_as_int(limit, "limit", minimum=0))
        wanted = None if names is None else {str(n) for n in names}
        with self._read() as conn:
            self._require(conn, job_id)
            texts = [r[0] for r in conn.execute(sql, params)]
        out: builtins.list[dict[str, Any]] = []
        for text in texts:
            row = json.loads(text)
            if wanted is not None:
                row = {k: v for k, v in row.items() if k == "env_steps" or k in wanted}
            out.append(row)
        return out

    def last_step(self, job_id: str) -> int | None:
        """The highest stored step, or None when the job has no metrics yet."""
        with self._read() as conn:
            self._require(conn, job_id)
            value = conn.execute("SELECT MAX(step) FROM metrics WHERE job_id = ?", (job_id,)).fetchone()[0]
        return None if value is None else int(value)

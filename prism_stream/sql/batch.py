"""Batch jobs: many samples from one table of jobs, logged in DuckDB.

A jobs table (CSV, Parquet, or a DuckDB query) has one row per job:

- ``output`` (required) and either ``inputs`` (paths or globs, a list or one
  string separated by ``;``) or ``query`` (a DuckDB SELECT, run as the
  ``sql`` command does);
- exactly one of ``ratio``, ``count``, ``k``;
- optionally ``job_id``, ``mode``, ``color_space``, ``quant_bits``,
  ``color_depth``, ``seed``, ``rgb_columns``, ``chunk_size``.

Every job runs in its own worker process (``jobs`` at a time) through
:func:`prism_stream.sample` or :func:`prism_stream.engines.sql.sample_query`, and
its outcome goes into the table ``prism_runs`` of a DuckDB database file:
one row per job, keyed by a fingerprint of its inputs, options and output,
replaced on every attempt. A job whose row says ``done`` and whose output
exists is skipped on the next run unless ``force``. Outputs are written
atomically by the engine; the leftovers of an attempt that was killed
(hidden ``.prism-tmp`` files beside the output whose owner process is gone)
are removed before the job runs again, and the killed attempt's ``running``
row is replaced.
"""

from __future__ import annotations

import ctypes
import hashlib
import json
import multiprocessing as mp
import os
import signal
import tempfile
import time
import warnings
from collections import deque
from dataclasses import dataclass, field
from datetime import datetime, timezone
from multiprocessing.connection import wait

import duckdb

from ..errors import InputNotFound, PrismError, UsageError
from ..formats.guard import first_line
from ..run import remote, signals, staging

OPTION_TYPES = {
    "ratio": float,
    "count": int,
    "k": int,
    "mode": str,
    "color_space": str,
    "quant_bits": int,
    "color_depth": str,
    "seed": int,
    "rgb_columns": str,
    "chunk_size": int,
}
COLUMNS = ("job_id", "inputs", "query", "output", *OPTION_TYPES)

RUNS_TABLE = """
CREATE TABLE IF NOT EXISTS prism_runs (
    job_key VARCHAR PRIMARY KEY,
    job_id VARCHAR,
    inputs VARCHAR[],
    query VARCHAR,
    output VARCHAR,
    points BIGINT,
    bins BIGINT,
    rule VARCHAR,
    k BIGINT,
    target BIGINT,
    kept BIGINT,
    seed UBIGINT,
    options JSON,
    status VARCHAR,
    error VARCHAR,
    started TIMESTAMP,
    ended TIMESTAMP,
    seconds DOUBLE,
    peak_rss_bytes BIGINT
)
"""


@dataclass
class Job:
    """One row of the jobs table, validated."""

    job_id: str
    output: str
    inputs: list = field(default_factory=list)
    query: str | None = None
    options: dict = field(default_factory=dict)

    @property
    def key(self) -> str:
        """Fingerprint of what the job computes: inputs, query, options and output."""
        what = {"inputs": [os.path.abspath(p) for p in self.inputs], "query": self.query,
                "output": os.path.abspath(self.output), "options": dict(sorted(self.options.items()))}
        return hashlib.sha256(json.dumps(what, sort_keys=True).encode()).hexdigest()[:32]


@dataclass
class Outcome:
    """What became of one job in this run."""

    job: Job
    status: str  # done, failed, skipped
    error: str | None = None
    summary: dict | None = None
    seconds: float = 0.0


def read_jobs(jobs: str, label: str | None = None) -> list[Job]:
    """The jobs of a CSV or Parquet file, or of a DuckDB query returning one row per job."""
    label = label or jobs
    lower = jobs.lower()
    is_file = lower.endswith((".csv", ".tsv", ".parquet", ".pq"))
    if is_file and not os.path.isfile(jobs):
        raise InputNotFound("no such jobs file", jobs)
    params = [jobs]  # a file's path is bound as a parameter, never pasted into the SQL
    if lower.endswith((".csv", ".tsv")):
        sql = "SELECT * FROM read_csv(?, header = true, all_varchar = true)"
    elif lower.endswith((".parquet", ".pq")):
        sql = "SELECT * FROM read_parquet(?)"
    else:
        sql, params = jobs, None
        label = "jobs query"
    con = duckdb.connect()
    try:
        cur = con.execute(sql, params)
        names = [d[0].lower() for d in cur.description]
        rows = cur.fetchall()
    except duckdb.Error as exc:
        first = first_line(exc)
        raise UsageError(f"cannot read the jobs: {first}", label) from None
    finally:
        con.close()
    unknown = [n for n in names if n not in COLUMNS]
    if unknown:
        raise UsageError(f"unknown job column(s) {', '.join(unknown)} (known: {', '.join(COLUMNS)})", label)
    if "output" not in names or not ({"inputs", "query"} & set(names)):
        raise UsageError("the jobs need an output column and an inputs or query column", label)
    out = []
    for i, row in enumerate(rows, 1):
        out.append(_job(dict(zip(names, row)), i, label))
    seen: dict = {}
    for j in out:
        real = os.path.realpath(j.output)
        if real in seen:
            raise UsageError(f"jobs {seen[real]} and {j.job_id} both write {j.output}", label)
        seen[real] = j.job_id
    return out


def _blank(v) -> bool:
    return v is None or (isinstance(v, str) and not v.strip())


def _job(row: dict, number: int, label: str) -> Job:
    job_id = str(row.get("job_id")).strip() if not _blank(row.get("job_id")) else str(number)
    where = f"{label}: job {job_id}"
    if _blank(row.get("output")):
        raise UsageError("no output", where)
    inputs = row.get("inputs")
    if isinstance(inputs, str):
        inputs = [p.strip() for p in inputs.split(";") if p.strip()]
    inputs = list(inputs or [])
    query = None if _blank(row.get("query")) else str(row["query"])
    if bool(inputs) == bool(query):
        raise UsageError("give inputs or a query (one of them)", where)
    options = {}
    for name, kind in OPTION_TYPES.items():
        v = row.get(name)
        if _blank(v):
            continue
        try:
            options[name] = _whole(v) if kind is int else kind(v)
        except (TypeError, ValueError, OverflowError):
            what = "a whole number" if kind is int else f"a {kind.__name__}"
            raise UsageError(f"{name} {v!r} is not {what}", where) from None
    seed = options.get("seed")
    if seed is not None and not 0 <= seed < 1 << 64:
        raise UsageError(f"seed {seed} is not in 0..2^64-1", where)
    return Job(job_id, str(row["output"]).strip(), inputs, query, options)


def _whole(v) -> int:
    """A job's integer field: an int, or a number written with a point that is whole (``100.0``, a Parquet
    double); ``100.7`` is refused, as the command line refuses ``--count 100.7``, never cut to 100."""
    from decimal import Decimal, InvalidOperation

    if isinstance(v, bool):
        raise ValueError(v)
    if isinstance(v, int):
        return v
    if isinstance(v, float):
        if not v.is_integer():
            raise ValueError(v)
        return int(v)
    try:  # a string or a DECIMAL column: exactly, never through a float (9007199254740993.0 stays itself)
        d = Decimal(v.strip() if isinstance(v, str) else v)
    except (InvalidOperation, TypeError):
        raise ValueError(v) from None
    if not d.is_finite() or d != d.to_integral_value():
        raise ValueError(v)
    return int(d)


def _die_with_parent(parent: int) -> None:
    """Linux: the worker gets SIGKILL when the batch process dies, so no job outlives a killed batch.

    The batch may die while the worker starts, before the death signal is
    set: the worker then has another parent already, and exits at once.
    """
    try:
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass
    if os.getppid() != parent:
        os._exit(1)


def _work(job: Job, conn, parent: int) -> None:
    """Worker process: run one job and send back ("done", summary) or ("failed", message)."""
    _die_with_parent(parent)
    from ..engines.local import sample
    from ..engines.sql import sample_query
    from ..run.summary import peak_rss_bytes

    opts = dict(job.options)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            if job.query is not None:
                summary = sample_query(job.query, job.output, overwrite=True, **opts)
            else:
                summary = sample(job.inputs, job.output, overwrite=True, **opts)
        result = ("done", summary.as_dict())
    except PrismError as exc:
        result = ("failed", str(exc))
    except Exception as exc:  # noqa: BLE001 - a bug of ours is still one job's failure, not the batch's
        result = ("failed", f"internal error: {type(exc).__name__}: {exc}")
    if result[0] == "failed":
        result = (*result, peak_rss_bytes())
    conn.send(result)
    conn.close()


class RunLog:
    """The ``prism_runs`` table in a DuckDB file, opened for each write so others can read it between jobs."""

    def __init__(self, path: str):
        self.path = path
        folder = os.path.dirname(os.path.abspath(path))
        if not os.path.isdir(folder):
            raise UsageError("the log's folder does not exist", path)
        with self._connect() as con:
            con.execute(RUNS_TABLE)

    def _connect(self):
        try:
            return duckdb.connect(self.path)
        except duckdb.Error as exc:
            first = first_line(exc)
            raise UsageError(f"cannot open the run log: {first}", self.path) from None

    def done(self, keys: list[str]) -> set[str]:
        with self._connect() as con:
            rows = con.execute("SELECT job_key FROM prism_runs WHERE status = 'done'").fetchall()
        return {r[0] for r in rows} & set(keys)

    def record(self, job: Job, status: str, started: datetime, ended: datetime | None = None,
               summary: dict | None = None, error: str | None = None, peak_rss: int | None = None) -> None:
        s = summary or {}
        seconds = (ended - started).total_seconds() if ended else None
        row = [job.key, job.job_id, [os.path.abspath(p) for p in job.inputs], job.query,
               os.path.abspath(job.output), s.get("points"), s.get("bins"), s.get("rule"), s.get("k"),
               s.get("target"), s.get("kept"), s.get("seed", job.options.get("seed", 0)),
               json.dumps(s.get("options") or job.options, sort_keys=True), status, error, started, ended, seconds,
               s.get("peak_rss_bytes", peak_rss)]
        with self._connect() as con:
            con.execute("INSERT OR REPLACE INTO prism_runs VALUES (" + ", ".join("?" * len(row)) + ")", row)


def _utc_now() -> datetime:
    """UTC wall time without a zone (the log's TIMESTAMP columns are UTC)."""
    return datetime.now(timezone.utc).replace(tzinfo=None)


def _clean_leftovers(output: str) -> None:
    """Remove what killed attempts left behind: temporaries of dead processes beside the output and in the
    temporary folder (a live process's, another run writing the same output say, are kept)."""
    staging.sweep(os.path.dirname(os.path.abspath(output)) or ".")
    staging.sweep(tempfile.gettempdir())


def _log_apart(jobs: list, log: str) -> None:
    """The run log is no job's output (a job would replace it, the log's next write fail), nor in a job's output
    folder (directory mode, ``out/*.las``: the job writes files there), nor an input."""
    from ..run.outputs import output_pattern

    real = os.path.realpath(log)
    for j in jobs:
        out = os.path.realpath(j.output)
        try:  # FOLDER/*.EXT writes into FOLDER, as the run reads it (a name with ? or [ is that file)
            folder = os.path.realpath(output_pattern(j.output, None)[0])
        except UsageError:  # an output pattern the job's run refuses, on its own line
            folder = out
        if out == real or real.startswith(folder.rstrip(os.sep) + os.sep):
            raise UsageError(f"the run log would be job {j.job_id}'s output or in its output folder (--log names "
                             "another file)", log)
        if any(os.path.realpath(i) == real for i in j.inputs if not remote.is_remote(i)):
            raise UsageError(f"the run log is job {j.job_id}'s input (--log names another file)", log)


def run_batch(jobs, log: str, *, workers: int = 1, force: bool = False, on_outcome=None) -> list[Outcome]:
    """Run every job not already done, ``workers`` at a time; log each in ``log``; return the outcomes.

    ``jobs`` is a list of :class:`Job` or what :func:`read_jobs` reads.
    ``on_outcome(outcome)`` is called as each job ends (the CLI prints a line).
    """
    if workers < 1:
        raise UsageError(f"--jobs must be at least 1, not {workers}")
    if isinstance(jobs, str):
        if os.path.realpath(jobs) == os.path.realpath(log):
            raise UsageError("the run log cannot be the jobs table (--log names another file)", log)
        jobs = read_jobs(jobs)
    _log_apart(jobs, log)
    runlog = RunLog(log)
    done = set() if force else runlog.done([j.key for j in jobs])
    outcomes: list[Outcome] = []
    pending: deque = deque()
    for j in jobs:
        if j.key in done and os.path.exists(j.output):
            outcomes.append(Outcome(j, "skipped"))
            if on_outcome:
                on_outcome(outcomes[-1])
        else:
            pending.append(j)
    ctx = mp.get_context("spawn")
    running: dict = {}  # parent end of the pipe -> (job, process, started, t0)
    starting: list = []  # every worker started, (job, process)
    try:
        while pending or running:
            while pending and len(running) < workers:
                job = pending.popleft()
                _clean_leftovers(job.output)
                started = _utc_now()
                runlog.record(job, "running", started)
                parent, child = ctx.Pipe(duplex=False)
                proc = ctx.Process(target=_work, args=(job, child, os.getpid()), daemon=True)
                starting.append((job, proc))  # in the cleanup's reach before it exists
                with signals.held():  # a signal in the middle of start() would leave a worker we cannot name
                    proc.start()
                child.close()
                running[parent] = (job, proc, started, time.perf_counter())
            for conn in wait(list(running)):
                job, proc, started, t0 = running.pop(conn)
                try:
                    result = conn.recv()
                except EOFError:
                    result = None
                conn.close()
                proc.join()
                ended = _utc_now()
                if result is None:
                    how = f"signal {-proc.exitcode}" if proc.exitcode and proc.exitcode < 0 else \
                        f"exit code {proc.exitcode}"
                    result = ("failed", f"the worker died ({how}) before finishing", None)
                if result[0] == "done":
                    runlog.record(job, "done", started, ended, summary=result[1])
                    out = Outcome(job, "done", summary=result[1], seconds=time.perf_counter() - t0)
                else:
                    _clean_leftovers(job.output)
                    runlog.record(job, "failed", started, ended, error=result[1], peak_rss=result[2])
                    out = Outcome(job, "failed", error=result[1], seconds=time.perf_counter() - t0)
                outcomes.append(out)
                if on_outcome:
                    on_outcome(out)
    finally:
        for job, proc in starting:
            if proc.pid is not None and proc.exitcode is None:
                proc.kill()
                proc.join()
                _clean_leftovers(job.output)
    return outcomes

"""``prism-stream batch``: run a table of jobs, logged in a DuckDB run log."""

from __future__ import annotations

import json

import click

from . import options as o


@click.command("batch", short_help="Run many samples from a table of jobs; resumable.")
@click.argument("jobs", metavar="JOBS")
@click.option("--jobs", "-j", "workers", type=click.IntRange(1), default=1, show_default=True,
              help="Jobs run at a time (one worker process each).")
@click.option("--log", default="prism_runs.duckdb", show_default=True,
              help="DuckDB file holding the run log table prism_runs.")
@click.option("--force", is_flag=True, help="Run every job, even those the log says are done.")
@click.option("--json", "as_json", is_flag=True, help="Print every job's outcome as JSON on stdout.")
@o.quiet
def batch(jobs, workers, log, force, as_json, quiet):
    """Run many samples from a table of jobs; skip those already done; exit 1 if any failed.

    JOBS is a CSV or Parquet file, or a DuckDB query, with one row per job:
    output, inputs (';'-separated) or query, one of ratio/count/k, and any of
    job_id, mode, color_space, quant_bits, color_depth, seed, rgb_columns,
    chunk_size.

    \b
    Example:
      prism-stream batch jobs.csv --jobs 2 --log runs.duckdb
    """
    def show(out):
        if as_json or (quiet and out.status != "failed"):
            return
        if out.status == "done":
            s = out.summary
            click.echo(f"done     {out.job.job_id}: {s['kept']:,} of {s['points']:,} points -> {out.job.output} "
                       f"({out.seconds:.1f} s)")
        elif out.status == "skipped":
            click.echo(f"skipped  {out.job.job_id}: done in an earlier run ({out.job.output})")
        else:
            click.echo(f"failed   {out.job.job_id}: {out.error}", err=True)

    from prism_stream.sql.batch import run_batch  # here, not at the top: `prism-stream` starts without DuckDB

    # the jobs' path, read by run_batch (which refuses a log that is the jobs table, or a job's output or input)
    outcomes = run_batch(jobs, log, workers=workers, force=force, on_outcome=show)
    counts = {s: sum(x.status == s for x in outcomes) for s in ("done", "skipped", "failed")}
    if as_json:
        click.echo(json.dumps([{"job_id": x.job.job_id, "output": x.job.output, "status": x.status,
                                "error": x.error, "summary": x.summary} for x in outcomes], indent=2))
    elif not quiet:
        click.echo(f"{len(outcomes)} jobs: {counts['done']} done, {counts['skipped']} skipped, "
                   f"{counts['failed']} failed; log: {log} (table prism_runs)")
    if counts["failed"]:
        raise SystemExit(1)

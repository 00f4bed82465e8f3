"""``prism-stream batch``: run a table of jobs, logged in a DuckDB run log."""

from __future__ import annotations

import json

import typer


def batch(
    jobs: str = typer.Argument(..., metavar="JOBS", help="A CSV or Parquet file, or a DuckDB query, with one row "
                               "per job: output, inputs (';'-separated) or query, one of ratio/count/k, and any "
                               "of job_id, mode, color_space, quant_bits, color_depth, seed, rgb_columns, "
                               "chunk_size."),
    workers: int = typer.Option(1, "--jobs", "-j", min=1, help="Jobs run at a time (one worker process each)."),
    log: str = typer.Option("prism_runs.duckdb", "--log", help="DuckDB file holding the run log table prism_runs."),
    force: bool = typer.Option(False, "--force", help="Run every job, even those the log says are done."),
    as_json: bool = typer.Option(False, "--json", help="Print every job's outcome as JSON on stdout."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="Print only failures."),
):
    """Run many samples from a table of jobs; skip those already done; exit 1 if any failed.

    Example: prism-stream batch jobs.csv --jobs 2 --log runs.duckdb
    """
    def show(o):
        if as_json or (quiet and o.status != "failed"):
            return
        if o.status == "done":
            s = o.summary
            typer.echo(f"done     {o.job.job_id}: {s['kept']:,} of {s['points']:,} points -> {o.job.output} "
                       f"({o.seconds:.1f} s)")
        elif o.status == "skipped":
            typer.echo(f"skipped  {o.job.job_id}: done in an earlier run ({o.job.output})")
        else:
            typer.echo(f"failed   {o.job.job_id}: {o.error}", err=True)

    from prism_stream.batch import read_jobs, run_batch  # here, not at the top: `prism-stream` starts without DuckDB

    outcomes = run_batch(read_jobs(jobs), log, workers=workers, force=force, on_outcome=show)
    counts = {s: sum(o.status == s for o in outcomes) for s in ("done", "skipped", "failed")}
    if as_json:
        typer.echo(json.dumps([{"job_id": o.job.job_id, "output": o.job.output, "status": o.status,
                                "error": o.error, "summary": o.summary} for o in outcomes], indent=2))
    elif not quiet:
        typer.echo(f"{len(outcomes)} jobs: {counts['done']} done, {counts['skipped']} skipped, "
                   f"{counts['failed']} failed; log: {log} (table prism_runs)")
    if counts["failed"]:
        raise typer.Exit(1)

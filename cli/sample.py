"""``prism-stream sample`` (the default command): sample inputs into one output."""

from __future__ import annotations

import dataclasses
import os

import click

from . import options as o
from .report import check_summary_file, emit


@click.command("sample", short_help="Downsample clouds by color (the default command).")
@click.argument("paths", nargs=-1, required=True, metavar="INPUT... OUTPUT")
@o.request_options(exclude=("order",), helps={
    "temp_dir": "Folder for the candidate spill or the key cache (default: system temp; with --dask the units' "
                "spills go beside the output)."})
@click.option("--plan", "plan_only", is_flag=True, help="Pass one and the solve only: print N, bins, k*/K, T, the "
              "expected output, how points spread over bins, the spill a run will make and the temporary disk it "
              "needs; write nothing. Give INPUT alone, or the run's INPUT... OUTPUT (the output is checked as "
              "the run checks it, and not written).")
@click.option("--dask", metavar="ADDRESS|local:N", help="Run on a Dask cluster: a scheduler address "
              "(tcp://host:8786) or local:N worker processes. OUTPUT is a Parquet dataset folder, or FOLDER/*.laz "
              "(or *.las, *.copc.laz) for one file a tile.")
@o.report_options
def sample(paths, plan_only, dask, as_json, summary_file, quiet, **options):
    """Downsample colored point clouds by color (PRISM), streaming the input once (or twice).

    INPUT... are files (.las .laz .parquet .ply .pcd .e57 .xyz), globs or
    folders, together one cloud; OUTPUT is .parquet, .las, .laz, .copc.laz
    (COPC: an octree for viewers), .ply or .xyz (text), or a folder (directory
    mode: one output per input; FOLDER/*.laz: the same, each one LAZ).

    Inputs and an OUTPUT file may be URLs in object storage (s3://, gs://,
    az://; https:// inputs): LAS/LAZ and Parquet, globs and folders too.
    Credentials and the endpoint come from the store's own configuration,
    never from options: for S3 AWS_ACCESS_KEY_ID, AWS_SECRET_ACCESS_KEY,
    AWS_PROFILE, ~/.aws, and AWS_ENDPOINT_URL for another endpoint.

    \b
    Examples:
      prism-stream big.laz out.parquet --ratio 0.01
      prism-stream big.laz preview.copc.laz --ratio 0.01
      prism-stream tiles/ out/ --ratio 0.01        (one output per input, one global solve)
      prism-stream 's3://bucket/tiles/*.laz' s3://bucket/out.parquet --ratio 0.01
    """
    planned = None
    if plan_only:  # INPUT alone, or the run's own arguments: the output is checked as the run checks it
        inputs, output = (list(paths), None) if len(paths) == 1 else (list(paths[:-1]), None)
        planned = paths[-1] if len(paths) > 1 else None
    else:
        if len(paths) < 2:
            raise click.UsageError("give at least one input and the output (or --plan)")
        inputs, output = list(paths[:-1]), paths[-1]
    request = o.request_of(options, progress=not quiet and not as_json)
    if plan_only and request.per_file:
        raise click.UsageError("--plan makes one global plan and --per-file solves each file on its own: plan "
                               "each file alone")
    if planned is not None:
        check_planned_output(inputs, planned, request, dask)
        request = dataclasses.replace(request, output_format=None)  # checked with the output; a plan writes none
    if summary_file is not None:
        check_summary_file(summary_file, *_paths(inputs, output, request, dask), request.overwrite)
    engine = o.engine(dask)
    summary = engine(inputs, output, request)
    data = summary.as_dict()
    if plan_only:
        from prism_stream.run.remote import size as file_size

        size = sum(file_size(p) for p in summary.inputs)
        data["expected_output_bytes"] = int(size * summary.kept / summary.points) if summary.points else 0
    if planned is not None:
        data["planned_output"] = planned
    emit(data, as_json=as_json, summary_file=summary_file, quiet=quiet, plan=plan_only, overwrite=request.overwrite)


PLANNED = "with --plan the last of several paths is the run's OUTPUT (plan several inputs alone as a folder or a glob)"


def check_planned_output(inputs, output: str, request, dask) -> None:
    """A plan given the run's OUTPUT refuses what the run would refuse before pass one (from the options and
    the headers); nothing is written. A plan of several inputs and no output gives them as a folder or a glob.
    An existing folder of readable files taken as the output is said, in case it was meant as an input."""
    import warnings

    from prism_stream.errors import PrismError, PrismWarning
    from prism_stream.run.inputs import expand_inputs

    try:
        if dask:
            from prism_stream.engines.dask.driver import check_output

            check_output(expand_inputs(inputs), output, request.overwrite)
        else:
            from prism_stream.engines.local import check_run

            check_run(inputs, output, request)
    except PrismError as exc:
        exc.message = f"{exc.message}; {PLANNED}"
        raise
    if os.path.isdir(output):
        try:
            inside = expand_inputs([output])
        except PrismError:
            inside = []
        if inside:
            warnings.warn(PrismWarning(f"{output}: taken as the run's OUTPUT folder, though it holds {len(inside)} "
                                       f"readable file(s); {PLANNED}"), stacklevel=2)


def _paths(inputs, output, request, dask) -> tuple[list, list]:
    """(input files, outputs) of a run: what its summary file may not replace."""
    from prism_stream.run.inputs import expand_inputs
    from prism_stream.run.outputs import Layout

    if output is None or dask:
        return expand_inputs(inputs), [output]
    layout = Layout.of(inputs, output, request.output_format, overwrite=True)
    outputs = [layout.final_path(i) for i in range(len(layout.files))] if layout.directory else [output]
    return layout.files, [*outputs, output]

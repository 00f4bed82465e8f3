"""``prism-stream sample`` (the default command): sample inputs into one output."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import List, Optional

import typer

import prism_stream

from . import options as o
from .report import print_plan, print_summary


def sample(
    paths: List[str] = typer.Argument(..., metavar="INPUT... OUTPUT",
                                      help="Input files, globs or Parquet folders, then the output "
                                           "(.parquet, .las, .laz). With --plan, inputs only."),
    ratio: Optional[float] = o.Ratio,
    count: Optional[int] = o.Count,
    k: Optional[int] = o.K,
    mode: str = o.Mode,
    color_space: str = o.ColorSpace,
    quant_bits: int = o.QuantBits,
    quant_step: Optional[float] = o.QuantStep,
    color_depth: str = o.ColorDepth,
    seed: int = o.Seed,
    plan: bool = typer.Option(False, "--plan", help="Pass one and the solve only: print N, bins, k*/K, T, the "
                              "expected output and how points spread over bins; write nothing."),
    chunk_size: int = o.ChunkSize,
    threads: Optional[int] = o.Threads,
    rgb_columns: Optional[str] = o.RgbColumns,
    as_json: bool = o.Json,
    summary_file: Optional[Path] = o.SummaryFile,
    overwrite: bool = o.Overwrite,
    quiet: bool = o.Quiet,
    temp_dir: Optional[str] = o.TempDir,
    flag: Optional[str] = typer.Option(None, "--flag", help="Keep every point and add a keep flag instead: a "
                                       "column / extra-bytes dimension of this name, or `withheld` (LAS "
                                       "withheld bit set on dropped points)."),
    output_format: Optional[str] = typer.Option(None, "--format", help="Directory mode: format of each output "
                                                "(parquet, las, laz...); default: each input's own."),
    per_file: bool = typer.Option(False, "--per-file", help="Directory mode: solve each file on its own instead "
                                  "of one global solve across all files."),
    dask: Optional[str] = typer.Option(None, "--dask", metavar="ADDRESS|local:N", help="Run on a Dask cluster: "
                                       "a scheduler address (tcp://host:8786) or local:N worker processes. "
                                       "OUTPUT is a Parquet dataset folder, or FOLDER/*.laz for one file a tile."),
):
    """Downsample a colored point cloud by color (PRISM), streaming it twice.

    Examples: prism-stream big.laz out.parquet --ratio 0.01;
    prism-stream tiles/ out/ --ratio 0.01 (directory mode: one output per input, one global solve).
    """
    if plan:
        inputs, output = paths, None
    else:
        if len(paths) < 2:
            raise typer.BadParameter("give at least one input and the output", param_hint="INPUT... OUTPUT")
        inputs, output = paths[:-1], paths[-1]
    engine = prism_stream.sample
    if dask:
        from prism_stream.dask_engine import on_cluster

        engine = on_cluster(dask)
    summary = engine(
        inputs, output, ratio=ratio, count=count, k=k, mode=mode, color_space=color_space, quant_bits=quant_bits,
        quant_step=quant_step, color_depth=color_depth, seed=seed, chunk_size=chunk_size, threads=threads,
        rgb_columns=o.split_columns(rgb_columns), overwrite=overwrite, progress=not quiet and not as_json,
        temp_dir=temp_dir, flag=flag, output_format=output_format, per_file=per_file,
    )
    data = summary.as_dict()
    if plan:
        size = sum(os.path.getsize(p) for p in summary.inputs)
        data["expected_output_bytes"] = int(size * summary.kept / summary.points) if summary.points else 0
    if summary_file:
        summary_file.write_text(json.dumps(data, indent=2) + "\n")
    if as_json:
        typer.echo(json.dumps(data, indent=2))
    elif not quiet:
        (print_plan if plan else print_summary)(data)

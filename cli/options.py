"""Options shared by the subcommands, declared once."""

from __future__ import annotations

from typing import Optional

import typer

Ratio = typer.Option(None, "--ratio", "-r", help="Target ratio of the input's N points, in (0, 1].",
                     rich_help_panel="Target (give one)")
Count = typer.Option(None, "--count", "-n", help="Target number of points T.", rich_help_panel="Target (give one)")
K = typer.Option(None, "--k", "-k", help="Fixed cap: every bin keeps at most K points.",
                 rich_help_panel="Target (give one)")
Mode = typer.Option("exact", "--mode", help="exact: exactly T points (K or K+1 per bin); "
                    "paper: the paper's single integer k* whose total is closest to T.")
ColorSpace = typer.Option("rgb", "--color-space", help="rgb: the 8-bit channels (the paper); "
                          "chroma: channels normalized by r+g+b (the reference code).")
QuantBits = typer.Option(0, "--quant-bits", min=0, max=7, help="Drop this many low bits of each channel (0..7).")
QuantStep = typer.Option(None, "--quant-step", help="Quantize each channel by a float step q >= 1, "
                         "floor(c / q + 0.5) (the authors' script's -q); instead of --quant-bits.")
ColorDepth = typer.Option("auto", "--color-depth", help="LAS 16-bit color fields: auto (8-bit if every value "
                          "<= 255), 8 or 16 (v >> 8).")
Seed = typer.Option(0, "--seed", min=0, help="Seed of the point priorities (0..2^64-1).")
ChunkSize = typer.Option(1 << 20, "--chunk-size", min=1, help="Points read at a time (does not change the output).")
Threads = typer.Option(None, "--threads", min=1, help="Decoder threads for LAZ and Parquet, and read-ahead "
                       "(default: every core; does not change the output).")
RgbColumns = typer.Option(None, "--rgb-columns", help="Parquet color column names, comma-separated "
                          "(default red,green,blue, any case).")
Json = typer.Option(False, "--json", help="Print the run summary as JSON on stdout.")
SummaryFile = typer.Option(None, "--summary", help="Also write the JSON summary to this file.")
Quiet = typer.Option(False, "--quiet", "-q", help="No progress bars, no summary text (errors still print).")
Overwrite = typer.Option(False, "--overwrite", help="Replace an existing output.")
TempDir = typer.Option(None, "--temp-dir", help="Folder for the key cache (4 bytes a point; default: system temp).")


def split_columns(value: Optional[str]):
    if not value:
        return None
    names = tuple(v.strip() for v in value.split(","))
    if len(names) != 3 or not all(names):
        raise typer.BadParameter("give three names: red,green,blue", param_hint="--rgb-columns")
    return names

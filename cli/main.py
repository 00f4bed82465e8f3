"""Entry point: subcommands, the default command, and one-line errors."""

from __future__ import annotations

import os
import sys
import warnings

import typer
from typer.core import TyperGroup

import prism_stream
from prism_stream.errors import PrismError

from .batch import batch
from .evaluate import evaluate
from .sample import sample
from .sql import sql

SUBCOMMANDS = ("sample", "sql", "batch", "eval")


class DefaultToSample(TyperGroup):
    """`prism-stream IN OUT ...` means `prism-stream sample IN OUT ...`."""

    def parse_args(self, ctx, args):
        if args and args[0] not in self.commands and args[0] not in ("--help", "-h", "--version"):
            args = ["sample", *args]
        return super().parse_args(ctx, args)


app = typer.Typer(cls=DefaultToSample, add_completion=False, no_args_is_help=True,
                  pretty_exceptions_enable=False, rich_markup_mode=None,
                  help="PRISM color-stratified point cloud sampling, streamed. "
                       "`prism-stream IN... OUT --ratio R` runs the `sample` command.")


def _version(value: bool):
    if value:
        typer.echo(f"prism-stream {prism_stream.__version__}")
        raise typer.Exit()


@app.callback()
def main(version: bool = typer.Option(False, "--version", callback=_version, is_eager=True,
                                      help="Print the version and exit.")):
    """PRISM color-stratified point cloud sampling, streamed."""


app.command("sample")(sample)
app.command("sql")(sql)
app.command("batch")(batch)
app.command("eval")(evaluate)


def _one_line_warning(message, category, filename, lineno, file=None, line=None):
    sys.stderr.write(f"prism-stream: warning: {message}\n")


def run(argv=None) -> int:
    """Console-script entry: never a traceback for expected failures."""
    warnings.showwarning = _one_line_warning
    try:
        # standalone mode: Typer prints usage errors itself (exit 2)
        app(args=argv, prog_name="prism-stream")
    except PrismError as exc:
        sys.stderr.write(f"prism-stream: error: {exc}\n")
        sys.exit(exc.exit_code)
    except KeyboardInterrupt:
        sys.stderr.write("prism-stream: error: interrupted; no output was written\n")
        sys.exit(130)
    except Exception as exc:  # noqa: BLE001 - a bug of ours: one line, and the traceback on request
        if os.environ.get("PRISM_STREAM_DEBUG"):
            raise
        sys.stderr.write(f"prism-stream: internal error: {type(exc).__name__}: {exc} "
                         "(set PRISM_STREAM_DEBUG=1 for the traceback, and please report it)\n")
        sys.exit(70)
    return 0


if __name__ == "__main__":
    run()

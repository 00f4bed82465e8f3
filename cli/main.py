"""Entry point: subcommands, the default command, and one-line errors."""

from __future__ import annotations

import os
import sys
import warnings

import click

import prism_stream
from prism_stream.errors import PrismError

from .batch import batch
from .evaluate import evaluate
from .sample import sample
from .sql import sql


class DefaultToSample(click.Group):
    """`prism-stream IN OUT ...` means `prism-stream sample IN OUT ...`."""

    def parse_args(self, ctx, args):
        if args and args[0] not in self.commands and args[0] not in ("--help", "-h", "--version"):
            args = ["sample", *args]
        return super().parse_args(ctx, args)


@click.group(cls=DefaultToSample, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(prism_stream.__version__, "--version", prog_name="prism-stream",
                      message="%(prog)s %(version)s")
def app():
    """PRISM color-stratified point cloud sampling, streamed.

    `prism-stream IN... OUT --ratio R` runs the `sample` command.
    """


app.add_command(sample)
app.add_command(sql)
app.add_command(batch)
app.add_command(evaluate)


def _one_line_warning(message, category, filename, lineno, file=None, line=None):
    sys.stderr.write(f"prism-stream: warning: {message}\n")


def _fail(message: str, code: int):
    sys.stderr.write(f"prism-stream: error: {message}\n")
    sys.exit(code)


def run(argv=None) -> None:
    """Console-script entry: one line on stderr for every failure, never a traceback for an expected one.

    Always ends in SystemExit, with the exit code of the README's table.
    """
    warnings.showwarning = _one_line_warning
    try:
        app.main(args=argv, prog_name="prism-stream", standalone_mode=False)
    except click.exceptions.Exit as exc:
        sys.exit(exc.exit_code)
    except click.UsageError as exc:  # a bad option value, a missing argument: one line, exit 2
        hint = f" (see prism-stream {exc.ctx.info_name} --help)" if exc.ctx is not None else ""
        _fail(exc.format_message().replace("\n", " ") + hint, 2)
    except click.ClickException as exc:
        _fail(exc.format_message().replace("\n", " "), exc.exit_code)
    except PrismError as exc:
        _fail(str(exc), exc.exit_code)
    except (KeyboardInterrupt, click.exceptions.Abort):
        _fail("interrupted; no output was written", 130)
    except Exception as exc:  # noqa: BLE001 - a bug of ours: one line, and the traceback on request
        if os.environ.get("PRISM_STREAM_DEBUG"):
            raise
        _fail(f"internal error: {type(exc).__name__}: {exc} (set PRISM_STREAM_DEBUG=1 for the traceback, "
              "and please report it)", 70)
    sys.exit(0)


if __name__ == "__main__":
    run()

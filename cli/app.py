"""The command group: subcommands, and the default command (`prism-stream IN OUT` runs `sample`)."""

from __future__ import annotations

import click

import prism_stream

from .batch import batch
from .evaluate import evaluate
from .rank import rank
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
app.add_command(rank)

"""The command group: subcommands, and the default command (`prism-stream IN OUT` runs `sample`)."""

from __future__ import annotations

import click

import prism_stream

from .batch import batch
from .check import check
from .evaluate import evaluate
from .info import info
from .rank import rank
from .sample import sample
from .sql import sql


class DefaultToSample(click.Group):
    """`prism-stream IN OUT ...` means `prism-stream sample IN OUT ...`.

    With no arguments the help is printed (on stderr, exit 2, as click does for a group); a first word that
    is not a command, not a file and close to a command's name is refused as the typo it likely is.
    """

    def parse_args(self, ctx, args):
        if not args and not ctx.resilient_parsing:  # (shell completion parses resiliently: no help there)
            click.echo(ctx.get_help(), err=True)
            ctx.exit(2)
        first = args[0] if args else ""
        if args and first not in self.commands and first not in ("--help", "-h", "--version"):
            near = None if ctx.resilient_parsing else _near_command(first, self.commands)
            if near:
                raise click.UsageError(f"no command {first!r}; did you mean {near!r}? (an input file of that "
                                       f"name: give it as ./{first})", ctx)
            args = ["sample", *args]
        return super().parse_args(ctx, args)


def _near_command(word: str, commands) -> str | None:
    """The command ``word`` is a likely typo of: a bare word (no extension, folder or glob), no file of that
    name, within a letter or two of a command's name."""
    import difflib
    import os
    import re

    if not re.fullmatch(r"[A-Za-z][A-Za-z-]*", word) or os.path.exists(word):
        return None
    found = difflib.get_close_matches(word.lower(), list(commands), n=1, cutoff=0.6)
    return found[0] if found else None


@click.group(cls=DefaultToSample, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(prism_stream.__version__, "--version", prog_name="prism-stream",
                      message="%(prog)s %(version)s")
def app():
    """PRISM color-stratified point cloud sampling, streamed.

    `prism-stream IN... OUT --ratio R` runs the `sample` command.
    """


@click.command("help", short_help="Print the help of prism-stream or of one command.")
@click.argument("command", required=False)
@click.pass_context
def help_command(ctx, command):
    """Print the help of prism-stream, or of COMMAND (`prism-stream help sample`)."""
    group = ctx.parent.command
    if command is None:
        click.echo(ctx.parent.get_help())
        return
    found = group.get_command(ctx, command)
    if found is None:
        near = _near_command(command, group.commands)
        hint = f"; did you mean {near!r}?" if near else f" (commands: {', '.join(sorted(group.commands))})"
        raise click.UsageError(f"no command {command!r}{hint}", ctx)
    with click.Context(found, info_name=command, parent=ctx.parent) as sub:
        click.echo(found.get_help(sub))


app.add_command(sample)
app.add_command(sql)
app.add_command(batch)
app.add_command(evaluate)
app.add_command(rank)
app.add_command(info)
app.add_command(check)
app.add_command(help_command)

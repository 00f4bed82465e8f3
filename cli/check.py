"""``prism-stream check``: what in a LAS/LAZ/COPC, PLY, Parquet or XYZ file a reader would refuse or misread."""

from __future__ import annotations

import json

import click


@click.command("check", short_help="Validate files: what a reader would refuse, misread or complain about.")
@click.argument("inputs", nargs=-1, required=True, metavar="FILE...")
@click.option("--strict", is_flag=True, help="Warnings count as errors: exit 1 when any file has one.")
@click.option("--json", "as_json", is_flag=True,
              help="Print a JSON list instead, one object per file: path, format, errors, warnings.")
def check(inputs, strict, as_json):
    """Check FILE... (LAS, LAZ, COPC, PLY, Parquet, XYZ; globs and folders too), whatever wrote them, and print one
    line per problem on stdout, `PATH: error: cause` or `PATH: warning: cause`, nothing for a clean file.
    Points are read in chunks: memory stays bounded whatever the size.

    \b
    LAS/LAZ/COPC: extra-bytes descriptors (a min/max flagged valid must hold the
      data, min <= max, integers within +-2^53; every extra byte named by the
      first LASF_Spec/4 record, no second one); the WKT bit for point formats
      6-10; WKT records pyproj parses, and in a COPC written as EVLRs; point
      count, bounds and points by return against the points; a scale of 0 or
      a scale or offset that is not a finite number; prism-stream
      provenance with another generating software (warning); COPC: the info
      VLR first at byte 375, the hierarchy's counts summing to the header's.
    PLY: trailing whitespace in the header (warning); a comment line over
      1,023 bytes (warning: Open3D's reader aborts); binary element counts
      against the bytes that follow (list elements walked); ASCII: one data
      line a record.
    Parquet: every page decoded; with a GeoParquet `geo` key: JSON, primary column, WKB encoding,
      PROJJSON CRS, a bbox holding the data, WKB points equal to x/y/z.
    XYZ: one width and numbers on every line (else exit 6, as a corrupt
      file); the `//` header line's names against the columns; colors past
      255 (warning); the provenance line as JSON (warning).

    \b
    Exit codes: 0 no errors (warnings allowed, unless --strict); 1 a file has
    an error (or, with --strict, a warning). A file that cannot be read at all
    is one line on stderr and the code of the README's table (3 missing or
    unreadable, 4 not a format check reads, 6 corrupt or truncated; with
    several, the last one's); the other files are checked all the same.

    \b
    Examples:
      prism-stream check out.copc.laz
      prism-stream check 'tiles/*.laz' --strict --json
    """
    from prism_stream.errors import PrismError
    from prism_stream.formats.validate import validate
    from prism_stream.run.inputs import expand_inputs

    reports, failures = [], []
    for item in inputs:
        try:
            files = expand_inputs([item])
        except PrismError as exc:
            failures.append(exc)
            continue
        for path in files:
            try:
                reports.append(validate(path))
            except PrismError as exc:
                failures.append(exc)
    if as_json:
        click.echo(json.dumps([r.as_dict() for r in reports], indent=2))
    else:
        for r in reports:
            for line in r.lines():
                click.echo(line)
    for exc in failures[:-1]:  # the last one is main's one line, with its exit code
        click.echo(f"prism-stream: error: {exc}", err=True)
    if failures:
        raise failures[-1]
    if any(r.errors or (strict and r.warnings) for r in reports):
        raise click.exceptions.Exit(1)

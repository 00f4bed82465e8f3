"""The prism-stream command line: a thin Typer layer over :mod:`prism_stream`."""

"""PRISM for SQL users: DuckDB functions and table macros (:mod:`.functions`), batch jobs (:mod:`.batch`).

``from prism_stream.sql import register`` adds the functions to a connection.
"""


def register(con):
    """Add the PRISM functions and table macros to a DuckDB connection (returned for chaining)."""
    from .functions import register as _register

    return _register(con)

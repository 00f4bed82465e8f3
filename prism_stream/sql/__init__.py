"""PRISM for SQL users: DuckDB functions and table macros (:mod:`.functions`), batch jobs (:mod:`.batch`).

``from prism_stream.sql import register`` adds the functions to a connection.

No value of ours is ever pasted into SQL text: file paths and settings are
bound as parameters or passed as DuckDB ``config``; the one thing that must
be written into a statement, a column name, goes through
:func:`..formats.query.identifier`.
"""

from ..formats.query import identifier  # noqa: F401 - prism_stream.sql.identifier


def register(con):
    """Add the PRISM functions and table macros to a DuckDB connection (returned for chaining)."""
    from .functions import register as _register

    return _register(con)

"""Which columns an output writes: the one schema of several inputs (``--columns``) and ``--keep``/``--drop``.

Every writer asks this module, so a selection is refused, or applied, the same way in every format.
"""

from __future__ import annotations

import os

import pyarrow as pa

from ..errors import UnsupportedFormat, UsageError
from .conversion import color_fields

# the columns a point's coordinates may come from when there are no x, y, z columns (evaluate.cloud reads them)
LIST_NAMES = ("xyz", "position", "positions", "coordinates", "coords", "point", "points")
WKB_NAMES = ("wkb", "geometry", "geom")
# said where a list named like coordinates does not hold them: how to have another column read instead
LISTS_FIRST = "a list of numbers named like coordinates is read for them before WKB points: rename it if it holds " \
    "something else"


def by_lower(names) -> dict:
    """Each name by its lower case, as columns are matched ignoring case; of names that differ only by case,
    the one written in lower case (x beside X), else the first."""
    out = {}
    for n in names:
        key = n.lower()
        if key not in out or n == key:
            out[key] = n
    return out


def numbers(kind) -> bool:
    """Whether a column type holds numbers (integers, floats, decimals; not booleans or text)."""
    return pa.types.is_integer(kind) or pa.types.is_floating(kind) or pa.types.is_decimal(kind)


def wkb_typed(kind) -> bool:
    """Whether a column type can hold WKB (binary or large binary)."""
    return pa.types.is_binary(kind) or pa.types.is_large_binary(kind)


def named(schema: pa.Schema, want: str) -> list[str]:
    """The columns of ``schema`` named ``want`` ignoring case: the one written in lower case first (x beside
    X), then the others in order."""
    return sorted((n for n in schema.names if n.lower() == want), key=lambda n: n != want)


def numeric_axes(schema: pa.Schema, leave=()) -> list:
    """For x, y and z, the column a run reads it from (numeric; of names that differ only by case the
    lower-case one unless it holds no numbers), or None; ``leave``: names not to take."""
    return [next((n for n in named(schema, a) if n not in leave and numbers(schema.field(n).type)), None)
            for a in "xyz"]


def kept_coordinates(schema: pa.Schema) -> list[str]:
    """The columns of ``schema`` its points' coordinates are read from, decided by the schema alone (so the
    same for every chunk, row and engine): numeric x, y, z (any case; of names that differ only by case, the
    lower-case one unless it holds no numbers); else the first list of numbers named like coordinates
    (LIST_NAMES order; a fixed-size list of three, or a list of any length, as DuckDB writes its FLOAT[3]
    arrays, whose rows must then hold three numbers each: refused where they do not); else WKB points: the
    binary column GeoParquet metadata names primary, else the first binary column named like them. A list of
    text, or a fixed-size list of another length, is not one. Every reader of coordinates (--space, --denoise,
    eval, the writers of x, y, z) takes these, so they are the columns --keep keeps, --drop refuses and a
    Parquet input decodes."""
    axes = numeric_axes(schema)
    if None not in axes:
        return axes
    for want in LIST_NAMES:
        for n in named(schema, want):
            kind = schema.field(n).type
            if not numbers(getattr(kind, "value_type", None) or pa.null()):
                continue
            if (pa.types.is_fixed_size_list(kind) and kind.list_size == 3) or pa.types.is_list(kind) \
                    or pa.types.is_large_list(kind):
                return [n]
    from .geo import file_geo

    primary = (file_geo(schema.metadata) or {}).get("primary_column")  # GeoParquet's, by any name, first
    binary = ([primary] if primary in schema.names else []) + [n for w in WKB_NAMES for n in named(schema, w)]
    return [n for n in binary if wkb_typed(schema.field(n).type)][:1]


def not_coordinates(schema: pa.Schema) -> str | None:
    """Why a schema with none of :func:`kept_coordinates` has none: a column named like coordinates that does
    not hold numbers ("column 'x' holds string, not numbers"), or None."""
    for want in ("x", "y", "z", *LIST_NAMES):
        for n in named(schema, want):
            kind = schema.field(n).type
            values = getattr(kind, "value_type", None) if want not in "xyz" else kind
            if values is not None and not numbers(values):
                return f"column {n!r} holds {kind}, not numbers"
    return None


def schema_difference(first: pa.Schema, other: pa.Schema, limit: int = 8) -> str:
    """What ``other``'s columns lack, add or type differently against ``first``'s, in one line."""
    a = {f.name: f.type for f in first}
    b = {f.name: f.type for f in other}

    def listed(names):
        names = list(names)
        more = f" and {len(names) - limit} more" if len(names) > limit else ""
        return ", ".join(names[:limit]) + more

    parts = []
    missing = [n for n in a if n not in b]
    extra = [n for n in b if n not in a]
    typed = [f"{n} ({b[n]}, not {a[n]})" for n in a if n in b and a[n] != b[n]]
    if missing:
        parts.append(f"missing {listed(missing)}")
    if extra:
        parts.append(f"extra {listed(extra)}")
    if typed:
        parts.append(f"other type {listed(typed)}")
    if not parts:
        parts.append("the same columns in another order")
    return "; ".join(parts)


COLUMN_RULES = ("same", "union", "intersection")


APART = "an output folder: one output per input"  # how a local run writes inputs apart, as a refusal says it


def common_schema(sources, columns: str = "same", apart: str = APART) -> tuple[pa.Schema, list[str]]:
    """The one schema of a Parquet output of ``sources``, and what it changed (one line each).

    ``same``: every input has the first's columns and types, or a one-line
    error names the difference. ``union``: every column of any input (a file
    without it gives nulls); ``intersection``: the columns every input has.
    Either way a column whose type differs between inputs takes the type that
    holds them all (float -> double, int32 -> int64...), or the run stops.
    ``apart``: how the engine writes inputs apart, which a refusal suggests.
    """
    schemas = [s.arrow_schema() for s in sources]
    first = schemas[0] if schemas else pa.schema([])
    if columns not in COLUMN_RULES:
        raise UsageError(f"--columns must be one of {', '.join(COLUMN_RULES)}, not {columns!r}")
    differing = [(s, sc) for s, sc in zip(sources[1:], schemas[1:])
                 if not sc.remove_metadata().equals(first.remove_metadata())]
    if not differing:
        return first, []
    if columns == "same":
        s, sc = differing[0]
        raise UsageError(f"its columns differ from {os.path.basename(sources[0].path)}'s "
                         f"({schema_difference(first, sc)}); one Parquet output needs one schema (--columns union "
                         f"or intersection writes them together; or write {apart})", s.path)
    _refuse_points_apart(sources, schemas, columns, apart)
    names = list(dict.fromkeys(n for sc in schemas for n in sc.names))
    everywhere = [n for n in names if all(n in sc.names for sc in schemas)]
    chosen = names if columns == "union" else everywhere
    notes = []
    fields = []
    for name in chosen:
        types = [sc.field(name).type for sc in schemas if name in sc.names]
        try:
            unified = pa.unify_schemas([pa.schema([pa.field(name, t)]) for t in types],
                                       promote_options="permissive").field(name).type
        except (pa.ArrowInvalid, pa.ArrowTypeError, pa.ArrowNotImplementedError):
            raise UsageError(f"--columns {columns}: column {name!r} has types "
                             f"{', '.join(sorted({str(t) for t in types}))} in different inputs, which no one type "
                             "holds", sources[0].path) from None
        if len({str(t) for t in types}) > 1:
            notes.append(f"column {name!r} has types {', '.join(sorted({str(t) for t in types}))} in the inputs: "
                         f"written as {unified}")
        missing = [os.path.basename(s.path) for s, sc in zip(sources, schemas) if name not in sc.names]
        if missing:
            shown = ", ".join(missing[:4]) + (f" and {len(missing) - 4} more" if len(missing) > 4 else "")
            notes.append(f"column {name!r} is missing from {shown}: null for their points (--columns union)")
        fields.append(pa.field(name, unified, nullable=bool(missing) or any(
            sc.field(name).nullable for sc in schemas if name in sc.names)))
    dropped = [n for n in names if n not in chosen]
    if dropped:
        notes.append(f"column(s) {', '.join(dropped)} left out: not in every input (--columns intersection)")
    return pa.schema(fields, metadata=first.metadata), notes


def conform(batch: pa.RecordBatch, schema: pa.Schema) -> pa.RecordBatch:
    """A batch of one input in the output's common schema: its columns by name, cast; a missing one null."""
    if batch.schema.remove_metadata().equals(schema.remove_metadata()):
        return batch
    names = batch.schema.names
    arrays = [batch.column(names.index(f.name)).cast(f.type) if f.name in names else pa.nulls(batch.num_rows, f.type)
              for f in schema]
    return pa.RecordBatch.from_arrays(arrays, schema=schema)


def column_notes(sources, columns: str, schema: pa.Schema) -> list[str]:
    """What --columns changed of the inputs (:func:`common_schema`'s notes), of the columns ``schema`` (the
    output's, after --keep/--drop) holds."""
    if columns == "same" or not sources:
        return []
    common, texts = common_schema(sources, columns)
    gone = [n for n in common.names if n not in schema.names]
    return [t for t in texts if not any(t.startswith(f"column {n!r} ") for n in gone)]


def one_layout(sources, needs: str) -> pa.Schema:
    """The first input's schema, every other input's being the same, or a one-line refusal naming the one
    that differs and what the output ``needs`` ("one PLY output needs one vertex layout")."""
    first = sources[0] if sources else None
    schema = first.arrow_schema() if first is not None else pa.schema([])
    for s in sources[1:]:
        if not s.arrow_schema().remove_metadata().equals(schema.remove_metadata()):
            raise UnsupportedFormat(f"its attributes differ from {first.path}'s; {needs}", s.path)
    return schema


def _refuse_points_apart(sources, schemas: list, columns: str, apart: str) -> None:
    """--columns union or intersection of inputs that hold their coordinates or colors in different columns
    (x, y, z beside a ``position`` list; Red, Green, Blue beside red, green, blue): refused, as one output would
    leave some points without them (a union's nulls, an intersection's missing columns)."""
    for what, held in (("colors", lambda s, sc: [c for c in color_fields(s) if c in sc.names]),
                       ("coordinates", lambda s, sc: kept_coordinates(sc))):
        forms = [(s, tuple(held(s, sc)), sc) for s, sc in zip(sources, schemas)]
        forms = [f for f in forms if f[1]]  # an input with none (colors only) has none to lose
        for s, form, sc in forms[1:]:
            first = os.path.basename(forms[0][0].path)
            if form != forms[0][1]:
                raise UsageError(f"--columns {columns}: its {what} are in {', '.join(form)}, and "
                                 f"{first}'s in {', '.join(forms[0][1])}: one output "
                                 f"would leave some points without them (convert the inputs to one form, or write "
                                 f"{apart})", s.path)
            ours, theirs = sc.field(form[0]).type, forms[0][2].field(form[0]).type
            if what == "colors" and len(form) == 1 and ours != theirs:  # a packed word kept whole
                raise UsageError(f"--columns {columns}: its packed color word {form[0]!r} is {ours}, and "
                                 f"{first}'s is {theirs}: one column of a wider type would not hold either's "
                                 f"bits (convert the inputs to one type, or write {apart})", s.path)


def select_columns(schema: pa.Schema, sources, selection: tuple | None, path: str) -> pa.Schema:
    """``schema`` with the columns --keep/--drop leave out removed; a name the inputs lack, or a coordinate
    or color column, is refused (the output must stay a colored point cloud that samples again)."""
    if selection is None:
        return schema
    selection = _colors_as_unpacked(selection, sources, [schema], path)
    how, names = selection
    lower = by_lower(schema.names)
    _refuse_unknown(selection, [schema], path, sources)
    chosen = {n if n in schema.names else lower[n.lower()] for n in names}
    needed = set()
    for s in sources[:1]:
        needed |= {c for c in color_fields(s) if c in schema.names}
        # numeric x, y, z as the readers take them (x and y alone too: PLY writes them); a text x is a column
        needed |= {n for n in numeric_axes(schema) if n is not None}
        needed |= set(getattr(s, "geometry_columns", lambda: set())()) & set(schema.names)
    for s in sources:  # each input's own coordinates (as its schema names them: a list, WKB points, X, Y, Z)
        needed |= set(kept_coordinates(s.arrow_schema())) & set(schema.names)
    if how == "drop":
        refused = sorted(chosen & needed)
        if refused:
            raise UsageError(f"--drop {refused[0]!r}: the output keeps its coordinates and colors (its readers, "
                             "and a sample of it, need them)", path)
        kept = [f for f in schema if f.name not in chosen]
    else:  # and the alpha of a packed rgba word, unpacked beside its colors (not refused to --drop)
        needed |= {a for s in sources for a in getattr(s, "word_alpha", ()) if a in schema.names}
        kept = [f for f in schema if f.name in chosen or f.name in needed]
    return pa.schema(kept, metadata=schema.metadata)


def decoded_columns(sources, selection: tuple | None) -> list:
    """Of each source, the columns a run with --keep/--drop ``selection`` needs decoded (None: every one): those
    any output of the run keeps (:func:`select_columns` of each input's :func:`own_selection`, which keeps its
    coordinates: :func:`kept_coordinates`; a column one input's output keeps is decoded from every input that
    has it, as one output may hold them all), a packed rgba word's alpha and every column any input declares a
    geometry (a writer takes the first input's for all). Its colors are the source's own to add."""
    if selection is None:
        return [None] * len(sources)
    schemas = [s.arrow_schema() for s in sources]
    kept = set().union(*(getattr(s, "geometry_columns", set)() for s in sources))
    kept |= {a for s in sources for a in getattr(s, "word_alpha", ())}
    for s, schema in zip(sources, schemas):
        kept |= set(select_columns(schema, [s], own_selection(selection, s), s.path).names)
    return [[n for n in schema.names if n in kept] for schema in schemas]


def read_only_kept(sources, selection: tuple | None) -> None:
    """--keep/--drop: a source that can decode some of its columns alone (Parquet) decodes only those the run
    needs (:func:`decoded_columns`); called after the refusals, before the first point is read."""
    for s, names in zip(sources, decoded_columns(sources, selection)):
        if names is not None and hasattr(s, "read_only"):
            s.read_only(names)


def _has(schema: pa.Schema, name: str) -> bool:
    """Whether ``schema`` has the column ``name`` (as --keep/--drop match: exactly, else ignoring case)."""
    return name in schema.names or name.lower() in {n.lower() for n in schema.names}


def _colors_as_unpacked(selection: tuple, sources, schemas: list, path: str) -> tuple:
    """--keep/--drop naming a packed color word (PCL's rgb/rgba, written as red, green, blue): kept whatever
    --keep says (the name is dropped from it), refused to --drop as the colors are."""
    words = {w.lower() for s in sources for w in (getattr(s, "packed", None), getattr(s, "color_field", None))
             if w and len(color_fields(s)) == 3 and w not in color_fields(s)}
    named = [n for n in selection[1] if n.lower() in words and not any(_has(sc, n) for sc in schemas)]
    if not named:
        return selection
    if selection[0] == "drop":
        raise UsageError(f"--drop {named[0]!r}: the packed color word is written as red, green, blue, which the "
                         "output keeps (its readers, and a sample of it, need them)", path)
    rest = tuple(n for n in selection[1] if n not in named)
    return "keep", rest


def _refuse_unknown(selection: tuple, schemas: list, path: str, sources=()) -> None:
    """Refuse a --keep/--drop name that none of ``schemas`` has (a typo), listing the first one's columns; one
    that an input has but the output's columns lack (--columns intersection, a LAS output of the first input's
    layout) says so."""
    for name in selection[1]:
        if not any(_has(schema, name) for schema in schemas):
            if any(_has(s.arrow_schema(), name) for s in sources):
                raise UsageError(f"--{selection[0]} {name!r}: only some inputs have it, and this output's columns "
                                 "leave it out (in Parquet output --columns union keeps every input's; an output "
                                 "folder gives each input its own)", path)
            listed = ", ".join(schemas[0].names[:16]) + ("..." if len(schemas[0].names) > 16 else "")
            raise UsageError(f"--{selection[0]} {name!r}: the inputs have no such column (columns: {listed})", path)
        for schema in schemas:  # matched ignoring case, it must name one column
            alike = [n for n in schema.names if n.lower() == name.lower()]
            if name not in schema.names and len(alike) > 1:
                raise UsageError(f"--{selection[0]} {name!r} could be any of the columns {', '.join(alike)}: give "
                                 "the one meant as it is written", path)


def check_selection_apart(selection: tuple | None, sources) -> None:
    """--keep/--drop for inputs written apart (an output folder, Dask's tiles): a name that no input has is
    refused (a typo); one that only some have applies to those (:func:`own_selection`)."""
    if selection is not None and sources:
        schemas = [s.arrow_schema() for s in sources]
        _refuse_unknown(_colors_as_unpacked(selection, sources, schemas, sources[0].path), schemas, sources[0].path)


def own_selection(selection: tuple | None, source) -> tuple | None:
    """--keep/--drop as it applies to one input written apart: the names it has (a --keep of none of its
    columns keeps its coordinates and colors; a --drop of none drops nothing)."""
    if selection is None:
        return None
    schema = source.arrow_schema()
    selection = _colors_as_unpacked(selection, [source], [schema], source.path)
    names = tuple(n for n in selection[1] if _has(schema, n))
    if selection[0] == "drop" and not names:
        return None
    return selection[0], names

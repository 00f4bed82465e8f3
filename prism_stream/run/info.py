"""What a cloud is, from its headers (``prism-stream info``); with a target, what a run would keep.

Per file: the format and its version, the point count, the bounds (LAS
headers; Parquet column statistics), the CRS, the columns and their types,
the color columns and the color depth their types allow, and the provenance
of a file prism-stream wrote. Nothing is decoded unless a target is given:
then pass one runs over the colors (as ``--plan``) and adds each file's
color depth, the distinct bins, K and T.
"""

from __future__ import annotations


import pyarrow as pa

from ..errors import PrismError
from ..formats import extension, open_source
from ..formats.columns import kept_coordinates
from ..formats.conversion import color_fields
from ..formats.geo import source_crs
from . import remote
from .inputs import expand_inputs


def depth_of_types(types: list) -> str:
    """The color depth a file's color column types allow, before its values are seen."""
    odd = [t for t in types if not (pa.types.is_floating(t) or pa.types.is_integer(t))]
    if odd:
        return f"none: {odd[0]} is not a number (a run refuses these colors)"
    if any(pa.types.is_floating(t) for t in types) and not all(pa.types.is_floating(t) for t in types):
        return "none: floats and integers mixed (a run refuses these colors)"
    if all(pa.types.is_floating(t) for t in types):
        return "float (0..1 read as floor(255 c))"
    if all(pa.types.is_integer(t) and t.bit_width <= 8 for t in types):
        return "8"
    return "8 or 16 (16-bit fields: decided by the values, --color-depth auto)"


def bounds(source) -> dict | None:
    """{"min": [x, y, z], "max": [...]} from the header alone (LAS), or Parquet's column statistics."""
    header = getattr(source, "header", None)
    if hasattr(header, "mins") and hasattr(header, "maxs"):
        return {"min": [float(v) for v in header.mins], "max": [float(v) for v in header.maxs]}
    file = getattr(source, "file", None)
    if file is not None and hasattr(file, "metadata"):
        meta = file.metadata
        held = kept_coordinates(file.schema_arrow)  # the x, y, z a run reads (numeric; x beside X: x)
        if len(held) != 3 or meta.num_row_groups == 0:
            return None
        paths = [meta.row_group(0).column(j).path_in_schema for j in range(meta.num_columns)]
        lo, hi = [], []
        for n in held:
            index = paths.index(n)  # a top-level column's leaf is its own name (a struct before it has more)
            stats = [meta.row_group(g).column(index).statistics for g in range(meta.num_row_groups)]
            if not stats or any(s is None or not s.has_min_max for s in stats):
                return None
            lo.append(float(min(s.min for s in stats)))
            hi.append(float(max(s.max for s in stats)))
        return {"min": lo, "max": hi}
    return None


def provenance(path: str, fmt: str) -> dict | None:
    """The provenance prism-stream wrote into the file, if it did."""
    try:
        if fmt in (".las", ".laz", ".copc.laz"):
            from ..formats.las import read_provenance
        elif fmt in (".parquet", ".pq"):
            from ..formats.parquet import read_provenance
        elif fmt == ".ply":
            from ..formats.ply import read_provenance
        elif fmt == ".xyz":
            from ..formats.xyzout import read_provenance
        else:
            return None
        return read_provenance(path)
    except Exception:  # noqa: BLE001 - a provenance that does not parse is reported as none
        return None


def file_info(path: str, ordinal: int = 0, **open_options) -> dict:
    """One file's facts, from its headers."""
    with open_source(path, ordinal, **open_options) as source:
        schema = source.arrow_schema()
        colors = [n for n in color_fields(source) if n in schema.names]
        crs = source_crs(source)
        fmt = extension(path)
        info = {
            "path": remote.absolute(path),
            "bytes": remote.size(path),
            "points": source.count,
            **source.describe(),
            "bounds": bounds(source),
            "crs": None if crs is None else {"name": crs.name, "epsg": crs.to_epsg()},
            "color_columns": {n: str(schema.field(n).type) for n in colors},
            "color_depth_by_type": depth_of_types([schema.field(n).type for n in colors]) if colors else None,
            "columns": {f.name: str(f.type) for f in schema},
            "prism_stream": provenance(path, fmt),
        }
    return info


def info(inputs, request=None, open_options: dict | None = None) -> dict:
    """Every input file's facts, the total, and (``request`` with a target) the plan of a run."""
    files = expand_inputs(inputs)
    if open_options is None:
        open_options = request.open_options() if request is not None else {}
    described, failed = [], []
    for i, f in enumerate(files):
        try:
            described.append(file_info(f, i, **open_options))
        except PrismError as exc:
            if request is not None or len(files) == 1:
                raise  # a plan needs every file; one file's error is the command's
            failed.append(exc)  # the headers of the others are described all the same (as `check` goes on)
    out = {"files": described}
    if failed:
        out["errors"] = failed
    counts = [f["points"] for f in out["files"]]
    out["points"] = sum(counts) if all(c is not None for c in counts) else None
    out["bytes"] = sum(f["bytes"] or 0 for f in out["files"])
    if request is not None:
        from ..engines.local import sample

        summary = sample(files, None, request)
        plan = summary.as_dict()
        out["plan"] = {k: plan[k] for k in ("points", "bins", "target", "kept", "k", "rule", "extra", "options")
                       if k in plan}
        depth = {s["path"]: s.get("color_depth") for s in plan.get("sources", [])}
        for f, name in zip(out["files"], files):
            f["color_depth"] = depth.get(remote.absolute(name), depth.get(name))
    return out


def size_text(n: int | None) -> str:
    if n is None:
        return "?"
    for unit, step in (("GiB", 2**30), ("MiB", 2**20), ("KiB", 2**10)):
        if n >= step:
            return f"{n / step:.1f} {unit}"
    return f"{n} B"


def text(data: dict) -> str:
    """The facts as lines a person reads."""
    lines = []
    for f in data["files"]:
        lines.append(f"{f['path']}")
        kind = f["format"] + (f" {f['version']}, point format {f['point_format']}" if "point_format" in f else "")
        lines.append(f"  format      {kind}, {size_text(f['bytes'])}")
        lines.append(f"  points      {f['points']:,}" if f["points"] is not None else "  points      unknown")
        if f["bounds"]:
            lo, hi = f["bounds"]["min"], f["bounds"]["max"]
            lines.append("  bounds      " + ", ".join(f"{a} {lo[i]:.10g}..{hi[i]:.10g}" for i, a in enumerate("xyz")))
        crs = f["crs"]
        lines.append(f"  crs         {crs['name']}" + (f" (EPSG:{crs['epsg']})" if crs["epsg"] else "") if crs
                     else "  crs         none")
        colors = ", ".join(f"{n} ({t})" for n, t in f["color_columns"].items()) or "none found"
        lines.append(f"  colors      {colors}")
        if f.get("color_depth"):
            lines.append(f"  color depth {f['color_depth']} (decided from the values)")
        elif f["color_depth_by_type"]:
            lines.append(f"  color depth {f['color_depth_by_type']}")
        others = [n for n in f["columns"] if n not in f["color_columns"] and n.lower() not in ("x", "y", "z")]
        shown = ", ".join(others[:20]) + (f" and {len(others) - 20} more" if len(others) > 20 else "")
        lines.append(f"  columns     {len(f['columns'])}: x, y, z, the colors" + (f", {shown}" if shown else ""))
        if f["prism_stream"]:
            p = f["prism_stream"]
            what = p.get("software", "prism-stream")
            lines.append(f"  written by  {what}: {p.get('kept', '?'):,} of {p.get('points', '?'):,} points"
                         if isinstance(p.get("kept"), int) and isinstance(p.get("points"), int)
                         else f"  written by  {what}")
    total = data["points"]
    lines.append(f"{len(data['files'])} file(s), {total:,} points, {size_text(data['bytes'])}" if total is not None
                 else f"{len(data['files'])} file(s)")
    if "plan" in data:
        p = data["plan"]
        k = f", K = {p['k']}" if p.get("k") is not None else ""
        target = f"T = {p['target']:,}" if p.get("target") is not None else "no target (a fixed --k)"
        lines.append(f"plan        {p['bins']:,} distinct bins; {target}{k}; a run keeps {p['kept']:,}")
    return "\n".join(lines)

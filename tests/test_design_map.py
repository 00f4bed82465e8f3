"""docs/DESIGN.md opens with a map of a run (step, module, function): every function it names exists in the
module it names, so the map a newcomer reads first cannot drift from the code."""

from __future__ import annotations

import importlib
import re
from pathlib import Path

DESIGN = Path(__file__).resolve().parent.parent / "docs" / "DESIGN.md"


def _rows():
    text = DESIGN.read_text()
    start = text.index("| step | module | function |")
    for line in text[start:].splitlines()[2:]:
        if not line.startswith("|"):
            break
        cells = [c.strip() for c in line.strip("|").split("|")]
        yield cells[0], re.findall(r"`([^`]+)`", cells[1]), re.findall(r"`([^`]+)`", cells[2])


def _resolve(module: str, name: str):
    """``name`` (``f``, ``Class.method``, or ``package.f`` from prism_stream) in ``module`` (``engines/reads.py``)."""
    candidates = [module[:-3].replace("/", "."), *name.split(".")[:1]]
    for base in candidates:
        try:
            obj = importlib.import_module(f"prism_stream.{base}")
        except ModuleNotFoundError:
            continue
        parts = name.split(".")[1:] if base == name.split(".")[0] else name.split(".")
        try:
            for part in parts:
                obj = getattr(obj, part)
            return obj
        except AttributeError:
            continue
    return None


def test_every_function_the_map_names_is_where_it_says():
    rows = list(_rows())
    assert len(rows) >= 10, "the map's table was not found"
    missing = []
    for step, modules, names in rows:
        assert modules, f"row {step!r} names no module"
        for name in names:
            for part in (p.strip() for p in name.split("->")):
                if not any(_resolve(m, part) is not None for m in modules):
                    missing.append(f"{step}: {part} (in {', '.join(modules)})")
    assert not missing, "DESIGN.md's map names what the code lacks: " + "; ".join(missing)

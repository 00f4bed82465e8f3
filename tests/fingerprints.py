"""Fingerprints of what a run writes and reports, kept in tests/data/fingerprints.json, so a restructuring of
the engines (one pipeline instead of four copies) is held to the bytes the code before it wrote.

A case copies its inputs under a folder whose absolute path has a fixed length (the provenance names the
inputs by absolute path, and a path's length moves every offset after it), then hashes every output file
with that folder's path masked by a marker of the same length, and a LAS header's creation date zeroed (a new
header gets the day of the run: the records made one day failed the next). The summary is kept as JSON with what varies
from run to run (timings, peak memory, free disk) reduced to its keys.

``PRISM_STREAM_RECORD_FINGERPRINTS=1 pytest tests/test_pipeline_fingerprints.py ...`` records them (the
code that recorded them is named in the file); otherwise a case compares against the record.
"""

from __future__ import annotations

import base64
import hashlib
import json
import os
import re
import shutil
from pathlib import Path

RECORD = Path(__file__).resolve().parent / "data" / "fingerprints.json"
BASE_LENGTH = 160  # every case's inputs and outputs under a folder of this absolute path length
VARYING = {"seconds", "peak_rss_bytes", "free_bytes", "folder", "workers"}


def base_folder(tmp_path: Path) -> Path:
    """A folder under ``tmp_path`` whose absolute path is BASE_LENGTH characters long."""
    pad = BASE_LENGTH - len(str(tmp_path)) - 1
    assert pad > 0, f"tmp_path too long for the fingerprints: {tmp_path}"
    base = tmp_path / ("f" * pad)
    base.mkdir()
    return base


def copy_inputs(base: Path, *paths) -> list[str]:
    out = []
    for p in paths:
        shutil.copyfile(p, base / Path(p).name)
        out.append(str(base / Path(p).name))
    return out


def _masked(data: bytes, base: Path) -> bytes:
    """``data`` with ``base``'s path masked, also inside base64 (a Parquet footer's ARROW:schema holds the
    schema's metadata, the provenance with it, in base64: masked and encoded again, it keeps its length; a
    PLY header cuts it into comment lines, joined before it is masked)."""
    path = str(base).encode()
    mask = b"#" * len(path)
    if data[:4] == b"LASF":  # a LAS header's creation day and year (bytes 90-93): the day of the run, where the
        data = data[:90] + b"\0" * 4 + data[94:]  # output's header is new (a PCD input's, a ranked tile's)
    data = data.replace(b"\ncomment prism-stream+ ", b"")  # a PLY provenance's continuation lines, joined

    def inner(m):
        try:
            raw = base64.b64decode(m.group(0), validate=True)
        except ValueError:
            return m.group(0)
        return base64.b64encode(raw.replace(path, mask)) if path in raw else m.group(0)

    return re.sub(rb"[A-Za-z0-9+/]{64,}={0,2}", inner, data.replace(path, mask))


def _files(path: Path) -> list[Path]:
    if path.is_dir():
        return sorted(p for p in path.rglob("*") if p.is_file())
    return [path] if path.exists() else []


def _keys_only(value):
    if isinstance(value, dict):
        return {k: _keys_only(v) for k, v in sorted(value.items())}
    return None


def _summary(summary: dict, base: Path, varying: set) -> dict:
    def walk(value):
        if isinstance(value, dict):
            return {k: (_keys_only(v) if k in varying else walk(v)) for k, v in sorted(value.items())}
        if isinstance(value, list):
            return [walk(v) for v in value]
        if isinstance(value, str):
            return value.replace(str(base), "<BASE>")
        return value

    return walk({k: v for k, v in summary.items() if k != "version"})


def fingerprint(base: Path, outputs, summary, varying=()) -> dict:
    """The case's record: each output file's size and masked hash (by its path under ``base``), and the summary
    with the fields in VARYING and ``varying`` reduced to their keys."""
    files = {}
    for out in outputs:
        for f in _files(Path(out)):
            data = _masked(f.read_bytes(), base)
            files[str(f.relative_to(base))] = [len(data), hashlib.sha256(data).hexdigest()]
    d = summary.as_dict() if hasattr(summary, "as_dict") else summary
    return {"files": files, "summary": json.loads(json.dumps(_summary(d, base, VARYING | set(varying)), default=str))}


def check(case: str, record: dict) -> None:
    """Compare ``record`` with the recorded one (or record it, under PRISM_STREAM_RECORD_FINGERPRINTS)."""
    if os.environ.get("PRISM_STREAM_RECORD_FINGERPRINTS"):
        kept = json.loads(RECORD.read_text()) if RECORD.exists() else {}
        kept[case] = record
        RECORD.write_text(json.dumps(dict(sorted(kept.items())), indent=1, sort_keys=True) + "\n")
        return
    kept = json.loads(RECORD.read_text())
    assert case in kept, f"no fingerprint recorded for {case}"
    want = kept[case]
    assert record["files"] == want["files"], f"{case}: the outputs differ from the recorded bytes"
    assert record["summary"] == want["summary"], f"{case}: the summary differs from the recorded one"

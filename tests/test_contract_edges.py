"""The output contract's edges, for every input -> output pair of the local engine (issue 13).

Inputs: LAS, LAZ, Parquet, PLY, PCD, XYZ, E57. Outputs: Parquet, LAS, LAZ,
PLY. For each pair, on a small cloud built here:

- the points kept are the oracle's (tests/oracle.py, which knows nothing of
  prism_stream), in input order (x is the record's own number);
- the provenance is in the output's own metadata (Parquet key
  ``prism_stream``, LAS VLR ``prism-stream``/1, a PLY ``comment
  prism-stream``), once, and says the right N, kept count, seed and depth;
- every input attribute is in the output with its type and values, or the
  sink named it in a notice (a PrismWarning, the same line as
  ``sink.notes``);
- colors are stored by the rule that binned them.

Then the color-depth boundaries: files whose largest channel value is
exactly 255 (8-bit), 256 and 65535 (16-bit), in every input format that can
hold 16-bit color (LAS, LAZ, Parquet, PLY, XYZ; PCD packs 8-bit channels and
E57 maps colors through its declared limits, tested in test_formats_e57).
"""

from __future__ import annotations

import json
import warnings

import laspy
import numpy as np
import plyfile
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

import prism_stream
from prism_stream import PrismWarning
from prism_stream.formats.ply import provenance_text

import oracle
from conftest import write_las, write_parquet

N = 400
SEED = 11
RATIO = 0.2
INPUTS = ["las", "laz", "parquet", "ply", "pcd", "xyz", "e57"]
OUTPUTS = ["parquet", "las", "laz", "ply"]


def palette_colors(n=N, seed=3, top=255):
    """(n, 3) integer colors from a 60-color palette; channel maximum exactly ``top``."""
    rng = np.random.default_rng(seed)
    pal = rng.integers(0, top + 1, size=(60, 3))
    pal[0, 0] = top
    pick = pal[rng.integers(0, 60, n)]
    pick[0] = pal[0]
    return pick.astype(np.int64)


def ident(n=N):
    return np.arange(n, dtype=np.uint32) * 7 + 3


def typed(n=N) -> dict:
    """Attributes of the number types the inputs can hold beside ident: each must keep its type, or be named."""
    i = np.arange(n)
    return {"tiny": (i % 250 - 125).astype(np.int8), "level": (i * 3 - 600).astype(np.int16),
            "dist": i * 0.125 - 7.0, "big": i.astype(np.int64) * 10_000_000_019}


# -- inputs: each returns (path, {attribute: values as stored}, (r, g, b) as stored) --------------------

def make_las(tmp_path, rgb, ext="las"):
    # write_las adds its header offsets (1000, 2000, 10): x is the record number
    xyz = np.stack([np.arange(N, dtype=np.float64) - 1000.0, np.zeros(N), np.zeros(N)], axis=1)
    path = write_las(tmp_path / f"in.{ext}", rgb, point_format=3, extra={"ident": ident(), **typed()}, xyz=xyz)
    las = laspy.read(str(path))
    attrs = {n: np.asarray(las[n]) for n in las.point_format.dimension_names
             if n not in ("X", "Y", "Z", "red", "green", "blue")}
    return path, attrs, (rgb[:, 0], rgb[:, 1], rgb[:, 2])


def make_parquet(tmp_path, rgb, ctype=np.uint8):
    attrs = {"ident": ident(), "quality": np.linspace(0, 1, N, dtype=np.float32), **typed(),
             "wide": np.arange(N, dtype=np.uint64) << 40, "count16": np.arange(N, dtype=np.uint16),
             "flagged": np.arange(N) % 3 == 0}
    cols = {"x": np.arange(N, dtype=np.float64), "y": np.zeros(N), "z": np.ones(N),
            "red": rgb[:, 0].astype(ctype), "green": rgb[:, 1].astype(ctype), "blue": rgb[:, 2].astype(ctype),
            **attrs}
    return write_parquet(tmp_path / "in.parquet", cols), attrs, tuple(cols[c] for c in ("red", "green", "blue"))


def make_ply(tmp_path, rgb, ctype="u1"):
    v = np.zeros(N, dtype=[("x", "f4"), ("y", "f4"), ("z", "f4"), ("red", ctype), ("green", ctype),
                           ("blue", ctype), ("ident", "u4"), ("quality", "f4"), ("tiny", "i1"), ("level", "i2"),
                           ("dist", "f8"), ("count16", "u2")])
    v["x"] = np.arange(N)
    for j, c in enumerate(("red", "green", "blue")):
        v[c] = rgb[:, j]
    v["ident"] = ident()
    v["quality"] = np.linspace(0, 1, N)
    more = typed()
    v["tiny"], v["level"], v["dist"], v["count16"] = more["tiny"], more["level"], more["dist"], np.arange(N)
    path = tmp_path / "in.ply"
    plyfile.PlyData([plyfile.PlyElement.describe(v, "vertex")]).write(str(path))
    return path, {n: v[n] for n in ("ident", "quality", "tiny", "level", "dist", "count16")}, \
        tuple(v[c] for c in ("red", "green", "blue"))


def make_pcd(tmp_path, rgb):
    rec = np.zeros(N, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("rgb", "<u4"), ("ident", "<u4")])
    rec["x"] = np.arange(N)
    c = rgb.astype(np.uint32)
    rec["rgb"] = (c[:, 0] << 16) | (c[:, 1] << 8) | c[:, 2]
    rec["ident"] = ident()
    head = (f"VERSION 0.7\nFIELDS x y z rgb ident\nSIZE 4 4 4 4 4\nTYPE F F F U U\nCOUNT 1 1 1 1 1\nWIDTH {N}\n"
            f"HEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {N}\nDATA binary\n")
    path = tmp_path / "in.pcd"
    path.write_bytes(head.encode() + rec.tobytes())
    return path, {"ident": rec["ident"]}, (rgb[:, 0], rgb[:, 1], rgb[:, 2])


def make_xyz(tmp_path, rgb):
    path = tmp_path / "in.xyz"
    ids = ident()
    path.write_text("".join(f"{i} 0 1 {r} {g} {b} {k}\n" for i, ((r, g, b), k) in enumerate(zip(rgb, ids))))
    return path, {"field_7": ids.astype(np.float64)}, (rgb[:, 0], rgb[:, 1], rgb[:, 2])


def make_e57(tmp_path, rgb):
    pye57 = pytest.importorskip("pye57")
    data = {"cartesianX": np.arange(N, dtype=np.float64), "cartesianY": np.zeros(N), "cartesianZ": np.ones(N),
            "intensity": np.linspace(0, 1, N).astype(np.float32),
            "colorRed": rgb[:, 0].astype(np.uint8), "colorGreen": rgb[:, 1].astype(np.uint8),
            "colorBlue": rgb[:, 2].astype(np.uint8)}
    path = tmp_path / "in.e57"
    e57 = pye57.E57(str(path), mode="w")
    e57.write_scan_raw(data)
    e57.close()
    return path, {"intensity": data["intensity"]}, tuple(data[c] for c in ("colorRed", "colorGreen", "colorBlue"))


MAKERS = {"las": make_las, "laz": lambda t, rgb: make_las(t, rgb, "laz"), "parquet": make_parquet,
          "ply": make_ply, "pcd": make_pcd, "xyz": make_xyz, "e57": make_e57}


# -- outputs, read without prism_stream ----------------------------------------------------------------

def read_output(path):
    """({attribute: values}, provenance dicts found, comments) of an output, read by the format's own library."""
    s = str(path)
    if s.endswith(".parquet"):
        t = pq.read_table(s)
        meta = t.schema.metadata or {}
        prov = [json.loads(meta[b"prism_stream"])] if b"prism_stream" in meta else []
        return {n: t.column(n).to_numpy(zero_copy_only=False) for n in t.column_names}, prov
    if s.endswith((".las", ".laz")):
        las = laspy.read(s)
        prov = [json.loads(bytes(v.record_data)) for v in las.header.vlrs
                if v.user_id == "prism-stream" and v.record_id == 1]
        cols = {n: np.asarray(las[n]) for n in las.point_format.dimension_names if n not in ("X", "Y", "Z")}
        cols.update(x=np.asarray(las.x), y=np.asarray(las.y), z=np.asarray(las.z))
        return cols, prov
    ply = plyfile.PlyData.read(s)
    text = provenance_text(ply.comments)  # one comment line, or more for a long provenance
    prov = [] if text is None else [json.loads(text)]
    v = ply["vertex"].data
    return {n: np.asarray(v[n]) for n in v.dtype.names}, prov


def run(src, out, **opts):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        summary = prism_stream.sample(str(src), str(out), ratio=RATIO, seed=SEED, **opts)
    stray = [f"{w.category.__name__}: {w.message}" for w in caught if not issubclass(w.category, PrismWarning)]
    assert not stray, stray  # no numpy (or other) warning leaks
    return summary, [str(w.message) for w in caught if issubclass(w.category, PrismWarning)]


def named(notes, name):
    return [n for n in notes if f"'{name}'" in n]


@pytest.mark.parametrize("out_ext", OUTPUTS)
@pytest.mark.parametrize("in_ext", INPUTS)
def test_every_pair_keeps_the_oracles_points_attributes_and_provenance(tmp_path, in_ext, out_ext):
    rgb = palette_colors()
    src, attrs, stored = MAKERS[in_ext](tmp_path, rgb)
    out = tmp_path / f"out.{out_ext}"
    summary, notes = run(src, out)
    want = oracle.sample([stored], ratio=RATIO, seed=SEED)
    rows = want.kept[0]
    got, provs = read_output(out)

    # the oracle's points, in input order: x is each record's number
    assert summary.kept == len(rows) == len(got["x"])
    assert np.allclose(got["x"], rows, rtol=0, atol=1e-6), "points differ from the oracle's, or out of order"

    # provenance: once, in the output's own metadata, with the run's numbers
    assert len(provs) == 1, f"{len(provs)} provenance records in {out.name}"
    p = provs[0]
    assert (p["points"], p["kept"], p["seed"]) == (N, len(rows), SEED)
    assert p["options"]["ratio"] == RATIO
    assert [s["color_depth"] for s in p["sources"]] == want.depths

    # every input attribute: kept with its type and values, or named in a notice (and, if written in another
    # type, still the same numbers)
    for name, values in attrs.items():
        if name in got and not named(notes, name):
            assert got[name].dtype == values.dtype, (name, got[name].dtype, values.dtype)
            assert np.array_equal(got[name], values[rows]), name
        elif name in got or f"{name}_float" in got:
            # a float in LAS's integer dimension of its name is kept beside it, under the name the notice gives
            moved = f"{name}_float" if f"'{name}_float'" in " ".join(named(notes, name)) else name
            assert np.array_equal(got[moved].astype(np.float64), values[rows].astype(np.float64)), \
                f"attribute {name!r}, named in a notice, has other values in the {out_ext} output: {notes}"
        else:
            assert named(notes, name), f"attribute {name!r} of the {in_ext} input is missing from the " \
                                       f"{out_ext} output and no notice names it: {notes}"

    # colors, by the rule that binned them
    (r8, g8, b8), decision = oracle.to_8bit(stored)
    if out_ext == "ply":
        for c, v in zip(("red", "green", "blue"), (r8, g8, b8)):
            assert got[c].dtype == np.uint8 and np.array_equal(got[c], np.asarray(v)[rows]), c
    elif out_ext in ("las", "laz"):
        for c, raw, v in zip(("red", "green", "blue"), stored, (r8, g8, b8)):
            expect = np.asarray(raw)[rows] if in_ext in ("las", "laz") or decision == "16" \
                else np.asarray(v)[rows] * 256
            assert np.array_equal(got[c], expect), c


def test_notices_are_one_line_each_and_name_the_output(tmp_path):
    src, _, _ = make_parquet(tmp_path, palette_colors())
    table = pq.read_table(src).append_column("label", pa.array([str(i) for i in range(N)]))
    pq.write_table(table, src)
    out = tmp_path / "out.ply"
    _, notes = run(src, out)
    assert notes and all("\n" not in n and n.startswith(f"{out}: ") for n in notes)
    assert len(named(notes, "label")) == 1


# -- color depth at its boundaries ------------------------------------------------------------------------

DEPTH_INPUTS = {
    "las": lambda t, rgb: make_las(t, rgb),
    "laz": lambda t, rgb: make_las(t, rgb, "laz"),
    "parquet": lambda t, rgb: make_parquet(t, rgb, np.uint16),
    "ply": lambda t, rgb: make_ply(t, rgb, "u2"),
    "xyz": make_xyz,
}


@pytest.mark.parametrize("top, decision", [(255, "8"), (256, "16"), (65535, "16")])
@pytest.mark.parametrize("in_ext", sorted(DEPTH_INPUTS))
def test_color_depth_boundary(tmp_path, in_ext, top, decision):
    rgb = palette_colors(top=top, seed=top)
    assert rgb.max() == top
    src, _, stored = DEPTH_INPUTS[in_ext](tmp_path, rgb)
    want = oracle.sample([stored], ratio=RATIO, seed=SEED)
    assert want.depths == [decision]  # the oracle's own rule, SPEC 1
    (r8, g8, b8), _ = oracle.to_8bit(stored)
    keys = oracle.bin_keys(r8, g8, b8)
    for out_ext in ("parquet", "ply"):
        out = tmp_path / f"out.{out_ext}"
        summary, _ = run(src, out, overwrite=True)
        got, provs = read_output(out)
        rows = want.kept[0]
        assert [s["color_depth"] for s in provs[0]["sources"]] == [decision]
        assert summary.bins == len(np.unique(keys)) and summary.kept == len(rows)
        assert np.allclose(got["x"], rows, rtol=0, atol=1e-6), (in_ext, top, out_ext)
        if out_ext == "ply":  # the 8-bit channels written are the oracle's, so their keys are too
            out_keys = oracle.bin_keys(got["red"], got["green"], got["blue"])
            assert np.array_equal(out_keys, keys[rows])

"""SPEC 1: color depth is decided per file (all values <= 255 means 8-bit), recorded, and overridable.

The expected decisions come from the data README's description of each
file ("8-bit values stored as-is", "shifted left by 8", "scaled by 257",
"mixed", "full-range"), not from running the engine.
"""

from __future__ import annotations

import laspy
import numpy as np
import pyarrow.parquet as pq
import pytest

import oracle
from conftest import edge_file, random_colors, real_file, write_las, write_parquet
from prism_stream import PrismWarning, sample
from prism_stream.errors import CorruptInput, UsageError

# file, folder, decision, distinct RGB triples per the data README (None: >> 8 merges some triples)
README_DEPTHS = [
    ("pdal__autzen_trim.las", "real", "8", 19_492),  # 8-bit values as-is
    ("pdal__warsaw_small.las", "real", "16", 2_442),  # v * 256
    ("potree__lion_takanawa.copc.laz", "real", "16", 105_110),  # v * 256
    ("laspy__fullwave.laz", "real", "16", 612),  # v * 257
    ("loadersgl__points-1.4.las", "edge", "16", 3),  # v * 257, up to 65535
    ("pdal__las_with_several_extra_byte_bloc.laz", "real", "16", None),  # v * 256 but 24 points hold raw 255
    ("loadersgl__pdrf5-1.3.las", "edge", "16", None),  # synthetic full-range 16-bit
    ("loadersgl__pdrf8-1.4.laz", "edge", "16", None),
    ("loadersgl__pdrf10-1.4.las", "edge", "16", None),
    ("lazperf__point-color.las", "edge", "8", 1_050),  # Autzen subset, 8-bit as-is
]


def _file(name, folder):
    return real_file(name) if folder == "real" else edge_file(name)


@pytest.mark.parametrize("name,folder,decision,distinct", README_DEPTHS, ids=[c[0] for c in README_DEPTHS])
def test_auto_depth_decision_is_recorded(name, folder, decision, distinct):
    path = _file(name, folder)
    s = sample(str(path), None, ratio=0.5)
    assert s.sources[0]["color_depth"] == decision
    assert s.plan["sources"][0]["color_depth"] == decision
    # the bins are those of the oracle's 8-bit colors under that decision
    r, g, b = oracle.read_las_colors(path)
    (r8, g8, b8), want = oracle.to_8bit((r, g, b))
    assert want == decision
    assert s.bins == len(np.unique(oracle.bin_keys(r8, g8, b8)))
    if distinct is not None:
        # >> 8 inverts x256 and x257 exactly, so the 8-bit triples stay distinct
        assert s.bins == distinct


def test_mixed_file_is_16_bit_and_its_raw_255_points_fall_in_bin_zero(tmp_path):
    """A "low bytes are all zero" test would call this file 8-bit; "max <= 255" does not."""
    path = real_file("pdal__las_with_several_extra_byte_bloc.laz")
    r, g, b = oracle.read_las_colors(path)
    raw = (r == 255) & (g == 255) & (b == 255)
    assert raw.sum() == 24  # the README's 24 odd points
    keys = oracle.bin_keys(r >> 8, g >> 8, b >> 8)
    assert np.all(keys[raw] == 0)
    s = sample(str(path), None, k=1)
    assert s.sources[0]["color_depth"] == "16"
    assert s.bins == len(np.unique(keys))


def test_forced_8_on_a_16_bit_file_is_a_usage_error(tmp_path):
    path = real_file("pdal__warsaw_small.las")
    with pytest.raises(UsageError):
        sample(str(path), str(tmp_path / "out.parquet"), ratio=0.1, color_depth="8")
    assert not (tmp_path / "out.parquet").exists()


def test_forced_8_fails_even_when_the_first_chunks_fit(tmp_path):
    colors = np.concatenate([random_colors(300, seed=1), random_colors(300, seed=2, depth=16)])
    path = write_las(tmp_path / "late.las", colors)
    with pytest.raises(UsageError):
        sample(str(path), str(tmp_path / "out.parquet"), ratio=0.1, color_depth="8", chunk_size=100)
    assert not (tmp_path / "out.parquet").exists()


def test_forced_16_on_an_8_bit_file(tmp_path):
    """autzen holds values <= 236: read as 16-bit every point is (0, 0, 0), one bin."""
    path = real_file("pdal__autzen_trim.las")
    out = tmp_path / "out.parquet"
    with pytest.warns(PrismWarning, match="one bin"):
        s = sample(str(path), str(out), ratio=0.01, color_depth="16", seed=2)
    assert s.sources[0]["color_depth"] == "16"
    assert s.bins == 1 and s.kept == 1_100
    want = oracle.sample([oracle.read_las_colors(path)], ratio=0.01, color_depth="16", seed=2)
    las = laspy.read(str(path))
    got = pq.read_table(out, columns=["gps_time"]).column(0).to_numpy()
    np.testing.assert_array_equal(got, las.gps_time[want.kept[0]])


def test_forced_8_on_an_8_bit_file_equals_auto(tmp_path):
    path = str(real_file("pdal__autzen_trim.las"))
    a = sample(path, str(tmp_path / "a.parquet"), ratio=0.02, color_depth="8")
    b = sample(path, str(tmp_path / "b.parquet"), ratio=0.02)
    assert a.sources[0]["color_depth"] == b.sources[0]["color_depth"] == "8"
    assert pq.read_table(tmp_path / "a.parquet").equals(pq.read_table(tmp_path / "b.parquet"))


def test_depth_is_decided_per_file_not_per_cloud(tmp_path):
    eight = write_las(tmp_path / "a.las", random_colors(500, seed=1), seed=1)
    sixteen = write_las(tmp_path / "b.las", random_colors(500, seed=2, depth=16), seed=2)
    s = sample([str(eight), str(sixteen)], None, ratio=0.1)
    assert [x["color_depth"] for x in s.sources] == ["8", "16"]


# -- the late switch: a file read as 8-bit until a value above 255 shows up ------------------


def _late_switch_colors(n_low: int, n_high: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    low = random_colors(n_low, seed=seed, palette=60)  # all <= 255
    high = random_colors(n_high, seed=seed + 1, palette=60, depth=16)
    colors = np.concatenate([low, high])
    # make sure the first value above 255 really comes late
    assert colors[:n_low].max() <= 255 and colors[n_low:].max() > 255
    return colors[np.r_[np.arange(n_low), n_low + rng.permutation(n_high)]]


def _check_against_oracle(inputs_arg, sources_rgb, out, **opts):
    o = {k: v for k, v in opts.items() if k not in ("chunk_size", "quant_bits")}
    o["bits"] = opts.get("quant_bits", 0)
    want = oracle.sample(sources_rgb, **o)
    s = sample(inputs_arg, str(out), overwrite=True, **opts)
    assert [x["color_depth"] for x in s.sources] == want.depths
    assert (s.bins, s.kept, s.k) == (want.bins, want.kept_total, want.k)
    t = pq.read_table(out, columns=["intensity", "red", "green", "blue"])
    got_rgb = np.stack([t.column(c).to_numpy() for c in ("red", "green", "blue")], axis=1)
    want_rgb = np.concatenate([np.stack(src, axis=1)[idx] for src, idx in zip(sources_rgb, want.kept)])
    want_idx = np.concatenate([idx for idx in want.kept])
    np.testing.assert_array_equal(t.column("intensity").to_numpy(), want_idx % 65536)
    np.testing.assert_array_equal(got_rgb, want_rgb)
    return s, want


@pytest.mark.parametrize("chunk_size", [1, 7, 250, 999, 1000, 1001, 1 << 20])
@pytest.mark.parametrize("opts", [
    dict(ratio=0.1, mode="exact", seed=3),
    dict(ratio=0.05, mode="paper", color_space="chroma", seed=4),
    dict(k=2, color_space="rgb", quant_bits=3, seed=5),
], ids=["exact", "paper-chroma", "k-bits3"])
def test_late_switch_to_16_bit_equals_oracle(chunk_size, opts, tmp_path):
    colors = _late_switch_colors(1000, 1500, seed=chunk_size % 97)
    path = write_las(tmp_path / "late.las", colors)
    s, want = _check_against_oracle(str(path), [(colors[:, 0], colors[:, 1], colors[:, 2])],
                                    tmp_path / "out.parquet", chunk_size=chunk_size, **opts)
    assert s.sources[0]["color_depth"] == "16"
    # the first 1000 points (all <= 255) are in the bin of (0, 0, 0) now
    assert want.counts[want.keys == 0].sum() >= 1000


@pytest.mark.parametrize("chunk_size", [64, 1 << 20])
def test_late_switch_in_a_later_source(chunk_size, tmp_path):
    """The points moved to key 0 are the switching file's, not the files before it."""
    first = random_colors(700, seed=1, palette=80)  # 8-bit, stays 8-bit
    late = _late_switch_colors(500, 600, seed=9)
    last = random_colors(300, seed=2, palette=80)
    paths = [write_las(tmp_path / f"{i}.laz", c, seed=i) for i, c in enumerate((first, late, last))]
    rgb = [(c[:, 0], c[:, 1], c[:, 2]) for c in (first, late, last)]
    s, _ = _check_against_oracle([str(p) for p in paths], rgb, tmp_path / "out.parquet",
                                 ratio=0.2, seed=7, chunk_size=chunk_size)
    assert [x["color_depth"] for x in s.sources] == ["8", "16", "8"]


def test_late_switch_in_parquet_row_groups(tmp_path):
    colors = _late_switch_colors(800, 800, seed=4).astype(np.uint16)
    path = write_parquet(tmp_path / "late.parquet", {
        "intensity": np.arange(len(colors), dtype=np.uint16),
        "red": colors[:, 0], "green": colors[:, 1], "blue": colors[:, 2]}, row_group_size=300)
    for chunk in (100, 1 << 20):
        _check_against_oracle(str(path), [(colors[:, 0], colors[:, 1], colors[:, 2])],
                              tmp_path / f"out{chunk}.parquet", ratio=0.1, seed=1, chunk_size=chunk)


# -- Parquet colors: uint8 as they are, floats floor(255 c), bad floats refused -------------------


def _parquet_cloud(tmp_path, name, r, g, b):
    n = len(r)
    return write_parquet(tmp_path / name, {"intensity": np.arange(n, dtype=np.uint16), "red": r, "green": g,
                                           "blue": b})


def test_uint8_parquet_colors(tmp_path):
    c = random_colors(3000, seed=5, palette=150).astype(np.uint8)
    path = _parquet_cloud(tmp_path, "u8.parquet", c[:, 0], c[:, 1], c[:, 2])
    s, _ = _check_against_oracle(str(path), [(c[:, 0], c[:, 1], c[:, 2])], tmp_path / "out.parquet",
                                 ratio=0.05, seed=2, color_space="chroma")
    assert s.sources[0]["color_depth"] == "8"


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_float_parquet_colors_floor_255c(dtype, tmp_path):
    rng = np.random.default_rng(3)
    palette = rng.random((100, 3)).astype(dtype)
    # values at and next to the bin edges: 0, 1, k/255 and just under
    edges = np.array([0.0, 1.0, 1 / 255, 2 / 255, np.nextafter(dtype(1.0), dtype(0.0)), 0.5], dtype=dtype)
    palette[: len(edges)] = edges[:, None]
    c = palette[rng.integers(0, 100, size=4000)]
    path = _parquet_cloud(tmp_path, "f.parquet", c[:, 0], c[:, 1], c[:, 2])
    s, want = _check_against_oracle(str(path), [(c[:, 0], c[:, 1], c[:, 2])], tmp_path / "out.parquet",
                                    ratio=0.1, seed=8)
    assert s.sources[0]["color_depth"] == "float"
    # floor(255 c) independently of the oracle's code path: the bins are the distinct floor triples
    q = np.floor(255.0 * c.astype(np.float64)).astype(np.int64)
    assert s.bins == len(np.unique(q, axis=0))
    assert q.max() == 255 and q.min() == 0


@pytest.mark.parametrize("bad", [1.0000001, -0.001, 255.0, float("nan"), float("inf")])
def test_float_colors_outside_unit_interval_are_corrupt_input(bad, tmp_path):
    c = np.full((50, 3), 0.5)
    c[37, 1] = bad
    path = _parquet_cloud(tmp_path, "bad.parquet", c[:, 0], c[:, 1], c[:, 2])
    out = tmp_path / "out.parquet"
    with pytest.raises(CorruptInput) as err:
        sample(str(path), str(out), ratio=0.5, chunk_size=16)
    assert "bad.parquet" in str(err.value)
    assert not out.exists()
    with pytest.raises(oracle.OracleInputError):
        oracle.to_8bit((c[:, 0], c[:, 1], c[:, 2]))


def test_uint16_parquet_colors_follow_the_las_rule(tmp_path):
    c = random_colors(2000, seed=6, depth=16).astype(np.uint16)
    path = _parquet_cloud(tmp_path, "u16.parquet", c[:, 0], c[:, 1], c[:, 2])
    s, _ = _check_against_oracle(str(path), [(c[:, 0], c[:, 1], c[:, 2])], tmp_path / "out.parquet",
                                 ratio=0.05, seed=2)
    assert s.sources[0]["color_depth"] == "16"
    assert s.bins == len(np.unique(c >> 8, axis=0))


def test_float_ply_colors_floor_255c(tmp_path):
    """PLY float color properties follow the same rule as Parquet float columns."""
    from plyfile import PlyData, PlyElement

    rng = np.random.default_rng(0)
    palette = rng.random((50, 3)).astype(np.float32)
    palette[:3] = [[1.0, 0.0, 1 / 255], [0.5, 0.5, 0.5], [2 / 255, 1.0, 0.0]]
    c = palette[rng.integers(0, 50, size=2000)]
    v = np.zeros(len(c), dtype=[("x", "f4"), ("y", "f4"), ("z", "f4"), ("intensity", "u2"),
                                ("red", "f4"), ("green", "f4"), ("blue", "f4")])
    v["x"] = rng.random(len(c))
    v["intensity"] = np.arange(len(c))
    v["red"], v["green"], v["blue"] = c.T
    path = tmp_path / "float.ply"
    PlyData([PlyElement.describe(v, "vertex")], text=False).write(str(path))
    s, _ = _check_against_oracle(str(path), [tuple(c.T)], tmp_path / "out.parquet", ratio=0.1, seed=3)
    assert s.sources[0]["color_depth"] == "float"
    assert s.bins == len(np.unique(np.floor(255.0 * c.astype(np.float64)), axis=0))


@pytest.mark.parametrize("top, refused", [(65535, False), (65536, True)])
def test_colors_beyond_16_bits_are_corrupt_input(tmp_path, top, refused):
    """SPEC 1 knows 8- and 16-bit values: 65535 is the largest a color may hold, in any integer type."""
    c = random_colors(500, seed=8, depth=16).astype(np.uint32)
    c[7, 1] = top
    path = _parquet_cloud(tmp_path, "u32.parquet", c[:, 0], c[:, 1], c[:, 2])
    out = tmp_path / "out.parquet"
    if refused:
        with pytest.raises(CorruptInput, match="color value 65536 does not fit in 16 bits"):
            sample(str(path), str(out), ratio=0.1)
        assert not out.exists()
    else:
        s, _ = _check_against_oracle(str(path), [(c[:, 0], c[:, 1], c[:, 2])], out, ratio=0.1, seed=1)
        assert s.sources[0]["color_depth"] == "16"


def test_8bit_channel_types_decide_the_depth_at_once():
    """uint8 channels can hold no value above 255: the file is 8-bit from its first chunk (so the one-read
    path keeps no heap for a 16-bit outcome); a wider type in a later chunk is refused, not misread."""
    from prism_stream.core.bins import ColorDepth

    narrow = ColorDepth("auto", "cloud.ply")
    narrow.prepare(*(np.array([1, 200], np.uint8),) * 3)
    assert not narrow.undecided and narrow.decision == "8"
    wide = ColorDepth("auto", "cloud.las")
    wide.prepare(*(np.array([1, 200], np.uint16),) * 3)
    assert wide.undecided and wide.decision == "8"
    with pytest.raises(CorruptInput, match="cloud.ply: color channels change type between chunks"):
        narrow.prepare(*(np.array([1, 300], np.uint16),) * 3)

"""A small input held in memory gives the streaming path's bytes, with numpy alone.

A run of at most ``PRISM_STREAM_MEMORY_POINTS`` points (default 1,048,576)
is read once and held in memory; the keys, the solve and each bin's q_b
smallest priorities (one sort) come from numpy, so the numba loops never
load. The rest of the suite runs with the variable at 0 (tests/conftest.py)
and so tests the streaming path; here it is removed, and every output is
compared byte for byte with the candidate spill's and the two-read path's.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pyarrow as pa
import pytest

import oracle
from conftest import REAL, covering, prism_stream_command, random_colors, write_las, write_parquet
from prism_stream import sample
from prism_stream.errors import UsageError
from prism_stream.engines import local

AUTZEN = REAL / "pdal__autzen_trim.las"
RUNS = [dict(ratio=0.01), dict(ratio=0.05, seed=3), dict(ratio=0.5, seed=11), dict(ratio=0.01, mode="paper", seed=5),
        dict(k=1), dict(k=3, seed=9), dict(ratio=0.02, quant_bits=2, seed=1), dict(quant_step=3.5, ratio=0.03),
        dict(count=123, color_space="chroma", seed=2**64 - 1)]


@pytest.fixture
def memory(monkeypatch):
    """The default: inputs of up to 1,048,576 points in memory."""
    monkeypatch.delenv("PRISM_STREAM_MEMORY_POINTS", raising=False)


def _three(monkeypatch, inputs, tmp_path, name, **kw):
    """(summary, bytes) of the same run in memory, with the candidate spill, and reading twice."""
    out = []
    for how, reads in (("memory", "auto"), ("spill", "auto"), ("two", "two")):
        if how == "memory":
            monkeypatch.delenv("PRISM_STREAM_MEMORY_POINTS", raising=False)
        else:
            monkeypatch.setenv("PRISM_STREAM_MEMORY_POINTS", "0")
        o = tmp_path / f"{how}-{name}"
        s = sample(inputs, str(o), reads=reads, overwrite=True, **kw)
        out.append((s, o.read_bytes() if o.is_file() else None))
    (m, mb), (sp, sb), (t, tb) = out
    assert "held in memory" in m.plan["why"] and "spill_points" not in m.plan
    assert "held in memory" not in sp.plan["why"] and t.plan["reads"] == 2
    return out


@pytest.mark.parametrize("name", sorted(p.name for p in REAL.iterdir()))
def test_same_bytes_as_streaming_on_every_real_cloud(name, real_cloud, tmp_path, monkeypatch):
    cloud = real_cloud(name)
    for i, kw in enumerate(covering(RUNS, name, [p.name for p in REAL.iterdir()])):
        (m, mb), (sp, sb), (_, tb) = _three(monkeypatch, str(cloud), tmp_path, f"{i}.parquet", chunk_size=40_000,
                                            **kw)
        assert mb == sb == tb, (name, kw)
        assert "spill_points" in sp.plan


@pytest.mark.parametrize("ext,order", [(".parquet", "input"), (".laz", "rank"), (".ply", "input")])
def test_ranks_in_memory_are_the_streaming_ranks(tmp_path, monkeypatch, ext, order):
    """`rank` took the streaming path on every input (3.6-3.9 s and 370 MiB on the bundled cloud against
    sample's 1.6-2.3 s): ranks of a held sample are two numpy sorts, the same bytes (issue 28, item 6)."""
    inputs = [str(AUTZEN), str(REAL / "pdal__warsaw_small.las")] if ext != ".ply" else [
        str(REAL / "odm__option-0000.ply")]
    for i, kw in enumerate([dict(ratio=0.05, seed=3), dict(ratio=1.0), dict(count=777, seed=2**64 - 1)]):
        (m, mb), (sp, sb), (t, tb) = _three(monkeypatch, inputs, tmp_path, f"r{i}{ext}", rank="prism_rank",
                                            order=order, **kw)
        assert mb == sb == tb, kw
        assert m.plan["rank"]["method"] == "numpy" and m.plan["rank"]["points"] == m.kept


def test_las_output_flag_mode_and_several_files(tmp_path, monkeypatch):
    a = write_las(tmp_path / "a.las", random_colors(3_000, seed=1))
    late = random_colors(4_000, seed=2)
    late[3_500] = [4000, 10, 10]  # a 16-bit value late in b: its first 3,500 points move to key 0
    b = write_las(tmp_path / "b.las", late)
    c = write_parquet(tmp_path / "c.parquet", {"red": np.linspace(0, 1, 500), "green": np.full(500, 0.25),
                                                "blue": np.linspace(1, 0, 500)})  # float colors
    for i, kw in enumerate([dict(ratio=0.05), dict(k=2, seed=4)]):
        outs = _three(monkeypatch, [str(a), str(b)], tmp_path, f"{i}.laz", chunk_size=700, **kw)
        assert outs[0][1] == outs[1][1] == outs[2][1], kw
        assert outs[0][0].sources[1]["color_depth"] == "16"
    flagged = _three(monkeypatch, [str(a), str(b), str(c)], tmp_path, "flag.parquet", ratio=0.1, flag="keep",
                     columns="union")
    assert flagged[0][1] == flagged[1][1] == flagged[2][1]
    assert flagged[0][0].plan["reads"] == 1  # a flag run reads twice only when it streams


def test_directory_mode_per_file_and_shared_and_a_plan(tmp_path, monkeypatch, memory):
    (tmp_path / "in").mkdir()
    for name, seed in (("one.las", 1), ("two.las", 2)):
        write_las(tmp_path / "in" / name, random_colors(2_000, seed=seed))
    s = sample(str(tmp_path / "in"), str(tmp_path / "out") + "/", ratio=0.1, per_file=True)
    monkeypatch.setenv("PRISM_STREAM_MEMORY_POINTS", "0")
    t = sample(str(tmp_path / "in"), str(tmp_path / "out2") + "/", ratio=0.1, per_file=True)
    for name in ("one.las", "two.las"):
        assert (tmp_path / "out" / name).read_bytes() == (tmp_path / "out2" / name).read_bytes()
    assert s.kept == t.kept
    # directory mode with one solve over both files: in memory (the default) and streaming, same bytes
    monkeypatch.delenv("PRISM_STREAM_MEMORY_POINTS")
    u = sample(str(tmp_path / "in"), str(tmp_path / "out3") + "/", ratio=0.1)
    monkeypatch.setenv("PRISM_STREAM_MEMORY_POINTS", "0")
    v = sample(str(tmp_path / "in"), str(tmp_path / "out4") + "/", ratio=0.1)
    assert "held in memory" in u.plan["why"] and "spill_points" in v.plan
    for name in ("one.las", "two.las"):
        assert (tmp_path / "out3" / name).read_bytes() == (tmp_path / "out4" / name).read_bytes()
    monkeypatch.delenv("PRISM_STREAM_MEMORY_POINTS")
    plan = sample(str(AUTZEN), None, ratio=0.01)
    assert plan.kept == 1_100 and "held in memory" in plan.plan["why"]


def test_the_oracle_on_random_clouds(tmp_path, memory):
    rng = np.random.default_rng(5)
    for trial in range(12):
        n = int(rng.integers(1, 5_000))
        rgb = random_colors(n, seed=trial, palette=int(rng.integers(1, 300)), depth=16 if trial % 3 == 0 else 8)
        path = write_parquet(tmp_path / f"c{trial}.parquet",
                             pa.table({c: rgb[:, i].astype(np.uint16) for i, c in enumerate("rgb")}
                                      | {"i": np.arange(n)}))
        kw = [dict(ratio=float(rng.uniform(0.001, 1))), dict(k=int(rng.integers(1, 5))),
              dict(ratio=float(rng.uniform(0.01, 0.5)), mode="paper")][trial % 3]
        seed = int(rng.integers(0, 2**63))
        out = tmp_path / f"o{trial}.parquet"
        s = sample(str(path), str(out), seed=seed, rgb_columns=("r", "g", "b"), **kw)
        assert "held in memory" in s.plan["why"]
        want = oracle.sample([tuple(rgb[:, i] for i in range(3))], seed=seed, **kw)
        assert np.array_equal(np.sort(pa.parquet.read_table(out)["i"].to_numpy()), np.sort(want.kept[0]))


def test_no_numba_loop_loads_and_the_summary_says_so(tmp_path):
    env = {k: v for k, v in os.environ.items() if k != "PRISM_STREAM_MEMORY_POINTS"}
    code = ("import sys, json, prism_stream; s = prism_stream.sample(sys.argv[1], sys.argv[2], ratio=0.01); "
            "print(json.dumps({'numba': 'numba' in sys.modules, 'plan': s.plan}))")
    done = subprocess.run([sys.executable, "-c", code, str(AUTZEN), str(tmp_path / "o.parquet")], env=env,
                          capture_output=True, text=True, check=True)
    got = json.loads(done.stdout.strip().splitlines()[-1])
    assert got["numba"] is False and got["plan"]["reads"] == 1
    text = subprocess.run([*prism_stream_command(), str(AUTZEN), str(tmp_path / "o2.parquet"), "--ratio", "0.01"],
                          env=env, capture_output=True, text=True, check=True).stdout
    assert "reads       1 (a small input (at most 1,048,576 points) is held in memory)" in text


def test_the_limit_and_its_variable(tmp_path, monkeypatch):
    monkeypatch.setenv("PRISM_STREAM_MEMORY_POINTS", "109999")  # one point short of Autzen: it streams
    s = sample(str(AUTZEN), str(tmp_path / "a.parquet"), ratio=0.01)
    assert "spill_points" in s.plan
    monkeypatch.setenv("PRISM_STREAM_MEMORY_POINTS", "110000")
    s = sample(str(AUTZEN), str(tmp_path / "b.parquet"), ratio=0.01)
    assert "held in memory" in s.plan["why"]
    for reads in ("two",):  # an explicit --reads always streams
        s = sample(str(AUTZEN), str(tmp_path / f"{reads}.parquet"), ratio=0.01, reads=reads)
        assert s.plan["reads"] == 2
    monkeypatch.setenv("PRISM_STREAM_MEMORY_POINTS", "many")
    with pytest.raises(UsageError, match="PRISM_STREAM_MEMORY_POINTS must be a number of points, not 'many'"):
        sample(str(AUTZEN), str(tmp_path / "c.parquet"), ratio=0.01)
    assert not (tmp_path / "c.parquet").exists() and local.MEMORY_POINTS == 1 << 20

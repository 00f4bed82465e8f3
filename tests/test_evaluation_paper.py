"""`eval` in the paper's terms: its entropy definitions, its ablation protocol, its baselines' own sizes,
the authors' outlier removal. Oracles here import nothing from the code they check but the file readers."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from fractions import Fraction

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from conftest import REAL, real_file, write_parquet
from oracle import open3d_sor_reference
from prism_stream.evaluate import Cloud, chamfer_distance, hausdorff_distance, nss_sample, sample_distances
from prism_stream.evaluate.baselines import voxel_centroid_sample
from prism_stream.evaluate.denoise import Denoise, sor_keep
from prism_stream.evaluate.entropy import Strata, regroup
from prism_stream.evaluate.run import evaluate
from prism_stream.errors import UsageError
from prism_stream.core.histogram import Histogram


def brute_entropy(labels) -> float:
    _, c = np.unique(np.asarray(labels), return_counts=True, axis=0)
    p = c / c.sum()
    return float(-(p * np.log2(p)).sum())


def colors(n=3000, seed=0):
    rng = np.random.default_rng(seed)
    base = rng.integers(0, 256, size=(40, 3))
    return np.clip(base[rng.integers(0, 40, n)] + rng.integers(-6, 7, size=(n, 3)), 0, 255)


def hist_of(rgb):
    keys = (rgb[:, 0].astype(np.uint32) << 16) | (rgb[:, 1].astype(np.uint32) << 8) | rgb[:, 2].astype(np.uint32)
    return Histogram.from_keys(keys)


def oracle_label(rgb, scheme, space="rgb", bits=0, step=None):
    """Each point's bin, written from the definitions in docs/EVALUATION.md, one point at a time."""
    out = []
    for r, g, b in rgb.tolist():
        if scheme == "rgb8":
            out.append((r, g, b))
        elif scheme == "rgb-grid":
            out.append((r // 32, g // 32, b // 32))
        elif scheme == "hue-sat":
            hi, lo = max(r, g, b), min(r, g, b)
            span = Fraction(hi - lo)
            if span == 0:
                h = Fraction(0)
            elif hi == r:
                h = ((g - b) / span) % 6
            elif hi == g:
                h = (b - r) / span + 2
            else:
                h = (r - g) / span + 4
            s = Fraction(hi - lo, hi) if hi else Fraction(0)
            out.append((min(math.floor(h * 6), 35), min(math.floor(s * 10), 9)))
        else:
            c = (r, g, b)
            if space == "chroma":
                s = r + g + b
                c = (0, 0, 0) if s == 0 else tuple((255 * v) / s for v in c)
                if step is None:
                    c = tuple(math.floor(v + 0.5) for v in c)
            if step is not None:
                c = tuple(math.floor(v / step + 0.5) for v in c)
            out.append(tuple(int(v) >> bits for v in c))
    return out


@pytest.mark.parametrize("scheme, space, bits, step", [
    ("rgb8", "rgb", 0, None), ("rgb-grid", "rgb", 0, None), ("hue-sat", "rgb", 0, None),
    ("sampler", "rgb", 2, None), ("sampler", "chroma", 1, None), ("sampler", "rgb", 0, 4.0),
    ("sampler", "chroma", 0, 2.0), ("sampler", "chroma", 0, 1.0), ("sampler", "rgb", 0, 2.5),
])
def test_each_entropy_scheme_bins_as_documented(scheme, space, bits, step):
    rgb = np.vstack([colors(), [[0, 0, 0], [255, 255, 255], [1, 0, 0], [128, 128, 127], [7, 7, 7]]])
    got = regroup(hist_of(rgb), scheme, Strata(space, bits, step))
    labels = oracle_label(rgb, scheme, space, bits, step)
    _, want = np.unique(np.array(labels), axis=0, return_counts=True)
    assert sorted(got.tolist()) == sorted(want.tolist())


def test_step_one_is_the_unquantized_sampler_bins():
    rgb = colors(5000, seed=3)
    for space in ("rgb", "chroma"):
        a = regroup(hist_of(rgb), "sampler", Strata(space, 0, 1.0))
        b = regroup(hist_of(rgb), "sampler", Strata(space, 0, None))
        assert sorted(a.tolist()) == sorted(b.tolist())


@pytest.mark.parametrize("bad", ["nope", "rgb8,magic", ""])
def test_entropy_bins_reject_unknown_names(bad):
    with pytest.raises(UsageError, match="--entropy-bins takes"):
        evaluate([str(real_file("pdal__warsaw_small.las"))], methods=("random",), entropy_bins=bad, metrics=False)


def test_all_schemes_side_by_side_and_prism_k1_is_uniform_on_its_own_bins():
    src = str(real_file("pdal__warsaw_small.las"))
    res = evaluate([src], methods=("prism", "random"), k=1, entropy_bins="all", metrics=False)
    prism, rand = res.rows
    assert prism.method == "PRISM (k=1)" and rand.count == prism.count  # equal-T after a fixed k
    assert set(prism.entropy) == {"rgb8", "sampler", "rgb-grid", "hue-sat"}
    e = prism.entropy["sampler"]
    assert e["output"] == pytest.approx(math.log2(e["bins_input"]))  # one point per bin
    assert prism.entropy_gain == prism.entropy["rgb8"]["gain"]  # first scheme is the headline
    with Cloud(src) as cloud:
        assert e["input"] == pytest.approx(brute_entropy(_all_rgb(cloud)))  # rgb, 8-bit: the sampler's default


def _all_rgb(cloud):
    h = cloud.histogram()
    rgb = np.column_stack([(h.keys >> s) & 255 for s in (16, 8, 0)])
    return [tuple(c) for c in rgb.repeat(h.counts, axis=0).tolist()]


def test_paper_ablation_fixes_k_and_measures_every_row():
    src = str(real_file("pdal__warsaw_small.las"))
    res = evaluate([src], methods=("prism",), ablation=True, ablation_protocol="paper", ablation_k=10,
                   entropy_bins=("sampler", "rgb8"))
    rows = res.ablation
    assert len(rows) in (6, 12)  # bits; and steps when the sampler has them
    for r in rows:
        assert r.params.get("k") == 10 and r.target_ratio is None
        assert r.chamfer is not None and r.hausdorff is not None and r.seconds > 0
        assert r.entropy_gain == r.entropy["sampler"]["gain"]
    by = {(r.params["color_space"], r.params["quant_bits"], r.params["quant_step"]): r for r in rows}
    # more quantization, fewer strata, fewer points kept at a fixed k
    for space in ("rgb", "chroma"):
        counts = [by[space, b, None].count for b in (1, 2, 4)]
        assert counts[0] >= counts[1] >= counts[2]


def test_ratio_ablation_is_still_there():
    src = str(real_file("pdal__warsaw_small.las"))
    res = evaluate([src], ratios=(0.1,), methods=("prism",), ablation=True, ablation_protocol="ratio",
                   metrics=False)
    assert len(res.ablation) == 8 and all(r.count == 300 for r in res.ablation)


# ---------------------------------------------------------------- baselines at their own sizes

def grid_cloud(tmp_path, n=4000, seed=1):
    rng = np.random.default_rng(seed)
    xyz = rng.uniform(0, 10, size=(n, 3))
    rgb = colors(n, seed).astype(np.uint8)
    path = write_parquet(tmp_path / "c.parquet", {"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2], "red": rgb[:, 0],
                                                  "green": rgb[:, 1], "blue": rgb[:, 2]}, row_group_size=700)
    return path, xyz, rgb


def test_centroid_voxel_grid_is_the_mean_point_and_mean_color_per_voxel(tmp_path):
    path, xyz, rgb = grid_cloud(tmp_path)
    size = 1.7
    out = tmp_path / "v.parquet"
    got = voxel_centroid_sample(str(path), str(out), voxel_size=size, chunk_size=500)
    cells = {}
    lo = xyz.min(axis=0)
    for p, c in zip(xyz, rgb):
        cells.setdefault(tuple(np.floor((p - lo) / size).astype(int)), []).append((p, c))
    want = sorted((tuple(np.round(np.mean([p for p, _ in v], axis=0), 9)),
                   tuple(int(math.floor(x + 0.5)) for x in np.mean([c for _, c in v], axis=0))) for v in cells.values())
    have = sorted((tuple(np.round(p, 9)), tuple(int(x) for x in c)) for p, c in zip(got.xyz, got.rgb))
    assert have == want
    t = pq.read_table(out)
    assert t.num_rows == len(cells) and t.column_names == ["x", "y", "z", "red", "green", "blue"]


def test_distances_to_new_points_are_measured_both_ways(tmp_path):
    path, xyz, _ = grid_cloud(tmp_path, n=1500)
    got = voxel_centroid_sample(str(path), voxel_size=2.5)
    with Cloud(str(path), chunk_size=400) as cloud:
        d = sample_distances(cloud, got.xyz, subset=False)
    assert d.chamfer == pytest.approx(chamfer_distance(xyz, got.xyz))
    assert d.hausdorff == pytest.approx(hausdorff_distance(xyz, got.xyz))


def test_nss_at_its_own_size_caps_every_normal_bin(tmp_path):
    path, xyz, _ = grid_cloud(tmp_path, n=3000)
    out = tmp_path / "n.parquet"
    res = nss_sample(str(path), str(out), per_bin=7, seed=0)
    bins = res.params["occupied_normal_bins"]
    assert res.params["per_bin"] == 7 and res.kept <= 7 * bins and res.kept == pq.read_metadata(out).num_rows
    with pytest.raises(UsageError):
        nss_sample(str(path), str(tmp_path / "m.parquet"), per_bin=7, ratio=0.1)


def test_paper_baselines_need_their_sizes():
    src = str(real_file("pdal__warsaw_small.las"))
    with pytest.raises(UsageError, match="--voxel-size"):
        evaluate([src], methods=("voxel",), baselines="paper")
    with pytest.raises(UsageError, match="--nss-per-bin"):
        evaluate([src], methods=("nss",), baselines="paper")
    res = evaluate([src], ratios=(0.1,), methods=("voxel", "nss"), baselines="paper", voxel_size=20.0,
                   nss_per_bin=10)
    assert [r.method for r in res.rows] == ["Voxel grid (paper size)", "NSS (paper size)"]
    assert all(r.chamfer > 0 for r in res.rows)


# ---------------------------------------------------------------- outlier removal

def test_the_sor_reference_finds_neighbours_as_brute_force_does():
    """The KD-tree in the reference is checked once against all pairwise distances (3,000 points)."""
    with Cloud(str(real_file("pdal__warsaw_small.las"))) as cloud:
        xyz = np.concatenate([c.xyz for c in cloud.chunks()])
    want = open3d_sor_reference(xyz, 100, 2.0, brute=True)
    assert 0 < (~want).sum() < len(xyz) // 2
    assert np.array_equal(open3d_sor_reference(xyz, 100, 2.0), want)


@pytest.mark.parametrize("name", ["pdal__warsaw_small.las", "laspy__fullwave.laz", "odm__option-0000.ply",
                                  "pdal__autzen_trim.las"])
def test_sor_removes_the_points_open3d_removes(name):
    """Against the reference above; bench/sor_check.py holds both to Open3D itself where it loads."""
    with Cloud(str(real_file(name))) as cloud:
        xyz = np.concatenate([c.xyz for c in cloud.chunks()])
    want = open3d_sor_reference(xyz, 100, 2.0)
    assert (~want).sum() > 0 and np.array_equal(sor_keep(xyz, 100, 2.0), want)


@settings(max_examples=300, deadline=None)
@given(n=st.integers(2, 40), k=st.integers(1, 50), std_ratio=st.floats(0.05, 3.0), seed=st.integers(0, 2**32 - 1))
def test_sor_matches_the_reference_on_small_clouds(n, k, std_ratio, seed):
    """Few points on a coarse integer grid: duplicates (d_i = 0), ties, k above N, and cuts where N - 1
    against N or <= against < decide. Only a point within rounding of the cut may differ (the two sum
    in different orders)."""
    xyz = np.random.default_rng(seed).integers(0, 5, size=(n, 3)).astype(np.float64)
    want, d, cut = open3d_sor_reference(xyz, k, std_ratio, brute=True, with_distances=True)
    differ = sor_keep(xyz, k, std_ratio) != want
    assert not differ[np.abs(d - cut) > 1e-9 * max(cut, 1.0)].any()


def test_sor_rule_on_a_tiny_cloud_by_hand():
    xyz = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0], [50, 50, 50], [0, 0, 0.0]])
    d = []
    for p in xyz:
        dist = np.sort(np.linalg.norm(xyz - p, axis=1))[:3]
        d.append(dist.mean())
    d = np.array(d)
    mu = d[d > 0].sum() / len(d)
    sigma = math.sqrt(((d[d > 0] - mu) ** 2).sum() / (len(d) - 1))
    assert np.array_equal(sor_keep(xyz, 3, 1.0), (d > 0) & (d < mu + sigma))
    assert not sor_keep(xyz, 3, 1.0)[4]
    # every d_i equal: sigma is 0 and each d_i equals the cut, which keeps a point only when strictly below it
    assert not sor_keep(np.array([[0.0, 0, 0], [1, 0, 0]]), 2, 2.0).any()


@pytest.mark.parametrize("text", ["sor", "sor:10", "sor:0,2", "sor:10,-1", "knn:10,2"])
def test_bad_denoise_is_a_usage_error(text):
    with pytest.raises(UsageError, match="--denoise"):
        Denoise.parse(text)


def test_denoise_is_a_prestep_every_method_sees(tmp_path):
    src = str(real_file("pdal__warsaw_small.las"))
    res = evaluate([src], ratios=(0.1,), methods=("prism", "random"), denoise="sor:100,2.0", metrics=False)
    info = res.inputs["pdal__warsaw_small.las"]
    assert info["denoise"]["removed"] == 162 and info["points"] == 3000 - 162
    assert all(r.points == 2838 and r.count == 284 for r in res.rows)


def test_eval_cli_new_options_fail_in_one_line(tmp_path):
    src = str(real_file("pdal__warsaw_small.las"))
    for args, message in [(["--denoise", "sor:x"], "--denoise takes"), (["--entropy-bins", "hsv"], "--entropy-bins"),
                          (["--baselines", "paper", "--methods", "voxel"], "--voxel-size"),
                          (["--preset", "nobody"], "--preset takes")]:
        done = subprocess.run([sys.executable, "-m", "prism_stream_cli.main", "eval", src, "--quiet", *args],
                              capture_output=True, text=True, cwd=tmp_path, timeout=120)
        assert done.returncode == 2, (args, done.stderr)
        assert message in done.stderr and len(done.stderr.strip().splitlines()) == 1


def test_json_carries_every_entropy_scheme(tmp_path):
    src = str(real_file("pdal__warsaw_small.las"))
    out = tmp_path / "t.json"
    done = subprocess.run([sys.executable, "-m", "prism_stream_cli.main", "eval", src, "--ratio", "0.1",
                           "--methods", "prism,random", "--entropy-bins", "all", "--no-distances", "--quiet",
                           "--out", str(out)], capture_output=True, text=True, timeout=200)
    assert done.returncode == 0, done.stderr
    d = json.loads(out.read_text())
    assert d["settings"]["entropy_bins"] == ["rgb8", "sampler", "rgb-grid", "hue-sat"]
    for r in d["table"]:
        assert set(r["entropy"]) == set(d["settings"]["entropy_bins"])


def test_preset_authors_on_a_ply_with_diffuse_colors():
    """SOR(100, 2.0) first, then PRISM chroma step 1 at k = 1; the baselines at PRISM's count."""
    src = str(real_file("odm__option-0000.ply"))
    res = evaluate([src], methods=("prism", "random"), preset="authors", entropy_bins="sampler", metrics=False)
    prism, rand = res.rows
    assert res.inputs["odm__option-0000.ply"]["denoise"]["removed"] == 510  # as Open3D removes (measured)
    assert prism.method == "PRISM chroma q1 (k=1)" and prism.count == rand.count
    e = prism.entropy["sampler"]
    assert e["output"] == pytest.approx(math.log2(e["bins_input"])) and e["gain"] > rand.entropy["sampler"]["gain"]


@pytest.mark.parametrize("name", sorted(p.name for p in REAL.iterdir()))
def test_streamed_sor_removes_the_in_memory_points(name, real_cloud, tmp_path):
    """Tiles of 20,000 points (many tiles, borders, points redone against every tile): the same mask, bit for bit.

    A cloud of more than 120,000 points is decimated regularly to about that many (its extent and shape kept;
    its size is not what the tiling is checked on): bench/sor_check.py runs the whole clouds."""
    from prism_stream.evaluate.denoise import sor_keep_streamed

    path = real_cloud(name)
    with Cloud(str(path)) as cloud:
        if cloud.points > 120_000:
            xyz = np.concatenate([c.xyz for c in cloud.chunks()])[::-(-cloud.points // 120_000)]
            path = write_parquet(tmp_path / "decimated.parquet", {
                "x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2], "red": np.zeros(len(xyz), np.uint8),
                "green": np.zeros(len(xyz), np.uint8), "blue": np.zeros(len(xyz), np.uint8)})
    work = tmp_path / "work"
    work.mkdir()
    with Cloud(str(path)) as cloud:
        xyz = np.concatenate([c.xyz for c in cloud.chunks()])
        keep, info = sor_keep_streamed(cloud, str(work), 100, 2.0, tile_points=20_000)
        want = sor_keep(xyz, 100, 2.0)
        assert np.array_equal(np.asarray(keep), want)
    assert info["tiles"] == 1 or len(xyz) > 20_000
    assert info["removed"] == int((~want).sum()) > 0
    assert sorted(os.listdir(work)) == ["sor-keep.u1"]  # the tile files and distances are gone


def test_streamed_sor_redoes_far_outliers_exactly(tmp_path):
    """A few points far from every tile's overlap: their neighbours lie in other tiles, found by the redo."""
    from prism_stream.evaluate.denoise import sor_keep_streamed

    rng = np.random.default_rng(3)
    xyz = np.concatenate([rng.uniform(0, 100, (6000, 3)), [[300, 300, 0], [-200, 50, 9], [50, -250, 4]]])
    xyz[:, 2] *= 0.01
    src = tmp_path / "c.parquet"
    n = len(xyz)
    pq.write_table(pa.table({"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2], "red": np.zeros(n, np.uint8),
                             "green": np.zeros(n, np.uint8), "blue": np.zeros(n, np.uint8)}), src)
    work = tmp_path / "w"
    work.mkdir()
    with Cloud(str(src)) as cloud:
        keep, info = sor_keep_streamed(cloud, str(work), 10, 1.0, tile_points=500)
    assert info["redone_points"] >= 3
    assert np.array_equal(np.asarray(keep), sor_keep(xyz, 10, 1.0))
    assert not np.asarray(keep)[-3:].any()


def test_denoise_with_more_neighbours_than_points_is_a_usage_error_and_large_k_stays_bounded(tmp_path, monkeypatch):
    """K above the cloud's points is refused in one line (it asked for 53.7 GiB at once); a K the cloud holds is
    queried a few points at a time, within QUERY_BYTES, and gives the in-memory mask."""
    from prism_stream.evaluate import denoise
    from prism_stream.evaluate.denoise import sor_keep_streamed

    src = str(real_file("pdal__warsaw_small.las"))  # 3,000 points
    with pytest.raises(UsageError, match="more than the cloud's 3,000 points") as caught:
        evaluate([src], ratios=(0.1,), methods=("random",), denoise="sor:3001,2.0", metrics=False)
    assert "\n" not in str(caught.value) and str(caught.value).startswith(src)
    asked = []

    class Counted(denoise.cKDTree):
        def query(self, x, k=1, **kw):
            asked.append(len(np.atleast_2d(x)) * k * 16)
            return super().query(x, k=k, **kw)

    monkeypatch.setattr(denoise, "cKDTree", Counted)
    monkeypatch.setattr(denoise, "QUERY_BYTES", 1 << 20)
    work = tmp_path / "w"
    work.mkdir()
    with Cloud(src) as cloud:
        xyz = np.concatenate([c.xyz for c in cloud.chunks()])
        keep, _ = sor_keep_streamed(cloud, str(work), 1000, 2.0, tile_points=2_500)
    assert asked and max(asked) <= 4 << 20  # within the budget (the redo takes a quarter of it a row)
    monkeypatch.undo()
    assert np.array_equal(np.asarray(keep), sor_keep(xyz, 1000, 2.0))

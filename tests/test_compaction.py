"""The spill compacted during pass one (issue 26): what it drops is never selected, and the output is the oracle's.

A point is a candidate if it may be selected at its arrival; as the counts grow the bound falls, and
``Spill.compact`` drops the spilled points that no longer can be (``CandidateFilter.standing_rules``,
``cutoffs.standing_cuts``). Here: runs compacted after every chunk against the independent oracle
(``tests/oracle.py``), the filter driven by hand with bins that get no heap slot, and the rules broken
on purpose (a quota one too small, a second-rule threshold too small) caught.
"""

from __future__ import annotations

import numpy as np
import pyarrow.parquet as pq
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import oracle
from prism_stream import sample
from prism_stream.core import candidates as cand_mod
from prism_stream.core.kernels import loop_channels
from prism_stream.core.bins import BinSpec
from prism_stream.core.quotas import Options
from prism_stream.engines import reads
from prism_stream.run.spill import Spill
from test_oracle import random_run


@settings(max_examples=10, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.data())
def test_runs_compacted_at_every_chunk_match_the_oracle(tmp_path_factory, monkeypatch, data):
    """Several LAS files (8- and 16-bit, so some files stay undecided and wait for their end), every option."""
    monkeypatch.setattr(Spill, "_due", lambda self, more: True)  # a compaction at every chunk
    _, want, summary, out = random_run(tmp_path_factory, data)
    if summary.plan["reads"] == 1 and "spill_points" in summary.plan:
        assert summary.plan["spill_points"] <= summary.plan["spill_points_peak"] <= summary.plan["spill_points_written"]
    t = pq.read_table(out, columns=["intensity"])
    np.testing.assert_array_equal(t.column("intensity").to_numpy(), np.concatenate(want.kept) % 65536)


def _stream(n, bins, order, seed):
    """(r, g, b) uint8 of n points over ``bins`` random colors, in random order or each color at once."""
    rng = np.random.default_rng(seed)
    palette = rng.choice(1 << 24, size=bins, replace=False).astype(np.uint32)
    idx = np.sort(rng.integers(0, bins, n)) if order == "sorted" else rng.integers(0, bins, n)
    c = palette[idx]
    return (c >> 16).astype(np.uint8), ((c >> 8) & 255).astype(np.uint8), (c & 255).astype(np.uint8)


def _drive(tmp_path, rgb, options, chunk, pool_budget, every=True):
    """Feed the filter by hand, a Spill of the index alone compacted after every chunk (``every``): the ids
    left in the spill, and the spill."""
    r, g, b = rgb
    f = cand_mod.CandidateFilter(options.spec, options, len(r), pool_budget=pool_budget)
    spill = Spill(str(tmp_path), records=False)

    class Source:
        ordinal = 0

        @staticmethod
        def spill_state(chunk, at):
            return None

    spill.begin_source(Source)
    if every:
        spill._due = lambda more: True  # a compaction at every chunk, with the chunk's own candidates
    f.begin_source()
    for a in range(0, len(r), chunk):
        z = min(len(r), a + chunk)
        keys, cand = f.chunk(*loop_channels(r[a:z], g[a:z], b[a:z]), 0, a, False)
        spill.add(None, keys, cand, a, f)
    ids = np.concatenate([i for _, i in spill.index()] or [np.zeros(0, np.uint64)])
    spill.filter = f
    return ids, spill


BITS = 2  # quantization bits of these streams: a table of 2^18 keys, which every compaction reads


def _oracle_ids(rgb, **opts):
    want = oracle.sample([rgb], bits=BITS, **opts)
    return want.kept[0].astype(np.uint64)


CASES = [dict(n=60_000, bins=5_000, order="random", opts=dict(ratio=0.01)),  # K = 0: the second rule
         dict(n=60_000, bins=5_000, order="sorted", opts=dict(ratio=0.05, seed=3)),
         dict(n=60_000, bins=300, order="sorted", opts=dict(ratio=0.05, seed=5)),
         dict(n=60_000, bins=2_000, order="sorted", opts=dict(ratio=0.2, mode="paper", seed=7)),
         dict(n=60_000, bins=400, order="sorted", opts=dict(k=7, seed=9)),
         dict(n=60_000, bins=20, order="random", opts=dict(ratio=0.5, seed=11))]


@pytest.mark.parametrize("case", CASES, ids=lambda c: f"{c['bins']}-{c['order']}-{c['opts']}")
@pytest.mark.parametrize("pool", [1 << 20, 1 << 12], ids=["slots", "few-slots"])
def test_the_compacted_spill_holds_the_sample(case, pool, tmp_path):
    """With a pool of 4 KiB (24 heap slots of 16 words) most bins have none (every point of them a candidate): the compaction
    still bounds them, and after every chunk's compaction the spill holds the oracle's whole sample."""
    rgb = _stream(case["n"], case["bins"], case["order"], seed=case["bins"])
    opts = case["opts"]
    want = _oracle_ids(rgb, **opts)
    ids, spill = _drive(tmp_path, rgb, Options(quant_bits=BITS, **opts), 2_000, pool)
    assert np.isin(want, ids).all()
    assert spill.compactions >= 1
    (tmp_path / "never").mkdir()
    _, loose = _drive(tmp_path / "never", rgb, Options(quant_bits=BITS, **opts), 2_000, pool, every=False)
    assert spill.size <= loose.size and spill.admitted <= loose.admitted  # the floors it leaves admit fewer
    assert spill.peak <= loose.peak
    if (case["order"] == "sorted" or pool < 1 << 20) and case["opts"].get("ratio", 0) < 0.5:
        assert spill.size < loose.size / 2, (spill.size, loose.size)


@pytest.mark.parametrize("opts", [dict(ratio=0.01), dict(ratio=0.05, mode="paper", seed=2)])
def test_heaps_narrowed_for_bins_left_without_one_keep_the_sample(opts, tmp_path, monkeypatch):
    """Every slot taken (a 16 KiB pool, 5,000 bins), then K_t falls: the heaps narrow below WIDTH and the
    bins left out take a heap at their next point. No compaction here, so the spill is the filter's own
    candidates: it must hold the oracle's sample, and admit fewer points than with no narrowing."""
    rgb = _stream(60_000, 5_000, "random", seed=8)
    want = _oracle_ids(rgb, **opts)
    options = Options(quant_bits=BITS, **opts)
    seen = []
    real = cand_mod.CandidateFilter._readmit
    monkeypatch.setattr(cand_mod.CandidateFilter, "_readmit", lambda self, **kw: (seen.append(self.width),
                                                                                 real(self, **kw)))
    ids, narrowed = _drive(tmp_path, rgb, options, 2_000, 1 << 14, every=False)
    assert np.isin(want, ids).all()
    assert seen and min(seen) < cand_mod.WIDTH, seen  # the case does narrow and readmit
    monkeypatch.setattr(cand_mod, "MIN_WIDTH", cand_mod.WIDTH)
    (tmp_path / "wide").mkdir()
    ids, wide = _drive(tmp_path / "wide", rgb, options, 2_000, 1 << 14, every=False)
    assert np.isin(want, ids).all()
    assert narrowed.admitted < wide.admitted, (narrowed.admitted, wide.admitted)
    # and the readmitted bins kept their counts: the histogram is the one the heaps never touch
    assert np.array_equal(narrowed.filter.counts(), wide.filter.counts())


@pytest.mark.parametrize("opts", [dict(ratio=0.047, seed=3), dict(k=7, seed=9), dict(ratio=0.2, mode="paper")])
def test_a_standing_quota_one_too_small_is_caught(opts, tmp_path, monkeypatch):
    """cap_t = K_t + 1 (or k): with one less, a compaction drops a point the sample selects (at ratio 0.047,
    E = 120 bins keep K + 1)."""
    rgb = _stream(60_000, 300, "sorted", seed=1)
    want = _oracle_ids(rgb, **opts)
    monkeypatch.setattr(cand_mod, "SLACK", 0)  # the filter too: its own cap one too small
    ids, _ = _drive(tmp_path, rgb, Options(quant_bits=BITS, **opts), 2_000, 1 << 20)
    assert not np.isin(want, ids).all(), "a quota one too small went unnoticed"


def test_a_second_rule_threshold_too_small_is_caught(tmp_path, monkeypatch):
    """theta must be the E_t-th smallest bin priority of the bins past K_t: the (E_t / 2)-th loses points."""
    rgb = _stream(60_000, 5_000, "random", seed=2)
    want = _oracle_ids(rgb, ratio=0.01)
    ids, _ = _drive(tmp_path, rgb, Options(ratio=0.01, quant_bits=BITS), 2_000, 1 << 12)
    assert np.isin(want, ids).all()
    real = cand_mod.CandidateFilter._standing_theta
    monkeypatch.setattr(cand_mod.CandidateFilter, "_standing_theta",
                        lambda self, kt, e, block: real(self, kt, max(1, e // 2), block))
    (tmp_path / "half").mkdir()
    ids, _ = _drive(tmp_path / "half", rgb, Options(ratio=0.01, quant_bits=BITS), 2_000, 1 << 12)
    assert not np.isin(want, ids).all(), "a threshold too small went unnoticed"


def test_standing_theta_is_the_e_th_smallest_bin_priority(tmp_path):
    """The radix select against a sort of every bin priority past K_t, in blocks smaller than the table."""
    rgb = _stream(30_000, 3_000, "random", seed=4)
    f = cand_mod.CandidateFilter(BinSpec("rgb", 0), Options(ratio=0.01), 30_000)
    f.begin_source()
    f.chunk(*loop_channels(*rgb), 0, 0, False)
    counts = f.dense & cand_mod.kernels.COUNT_MASK
    for kt in (0, 5, 9):
        keys = np.flatnonzero(counts > kt).astype(np.uint64)
        bp = np.sort(cand_mod.kernels.priorities_of(keys, f.bin_mix))
        for e in (1, 7, len(bp) // 2, len(bp) - 1):
            assert f._standing_theta(kt, e, block=1 << 13) == int(bp[e - 1])
        assert f._standing_theta(kt, len(bp), block=1 << 13) is None


def test_the_plan_predicts_a_compacted_run(tmp_path, monkeypatch):
    """--plan runs the same filter and the same compactions over the colors: the run's spill, exactly."""
    from conftest import real_file

    monkeypatch.setattr(reads, "compact_mark", lambda bound: 2_000)
    src = str(real_file("pdal__autzen_trim.las"))
    for chunk in (7_000, 50_000):
        plan = sample(src, None, ratio=0.01, chunk_size=chunk, color_depth="8").plan["temp"]
        run = sample(src, str(tmp_path / f"{chunk}.parquet"), ratio=0.01, chunk_size=chunk, color_depth="8").plan
        assert run["spill_compactions"] > 1
        assert plan["spill_points_run"] == run["spill_points"]
        assert plan["spill_points_written_run"] == run["spill_points_written"]
        assert plan["spill_compactions_run"] == run["spill_compactions"]


def _compacting_run(src, tmp_path, monkeypatch):
    """``src`` sampled at 1% in chunks of 7,000 points, its spill compacted from 2,000 candidates on: (summary,
    output, temporary folder)."""
    monkeypatch.setattr(reads, "compact_mark", lambda bound: 2_000)
    tmp = tmp_path / "tmp"
    tmp.mkdir()
    out = tmp_path / "out.parquet"
    return sample(src, str(out), ratio=0.01, chunk_size=7_000, color_depth="8", temp_dir=str(tmp)), out, tmp


def test_a_full_disk_during_a_compaction_reads_twice_and_leaves_nothing(tmp_path, monkeypatch):
    """The survivors are written in place; a write that fails part way (a copy-on-write file system can refuse
    an overwrite) leaves the spill unusable, and the run starts over reading twice, as on a full disk while
    spilling, with nothing left in the temporary folder."""
    import errno

    from conftest import real_file
    from prism_stream.run import staging

    src = str(real_file("pdal__autzen_trim.las"))
    ref = tmp_path / "ref.parquet"
    sample(src, str(ref), ratio=0.01, reads="two", color_depth="8")
    real = staging.ArrayFile.write_at
    calls = []

    def write_at(self, offset, values):
        calls.append(offset)
        if len(calls) == 3:
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(self, offset, values)

    monkeypatch.setattr(staging.ArrayFile, "write_at", write_at)
    s, out, tmp = _compacting_run(src, tmp_path, monkeypatch)
    assert len(calls) >= 3
    assert s.plan["reads"] == 2 and "temporary space" in s.plan["why"], s.plan
    assert pq.read_table(out).equals(pq.read_table(ref))
    assert list(tmp.iterdir()) == []


@pytest.mark.parametrize("where", ["spill.frames", "spill.keys"])
@pytest.mark.parametrize("then", ["full", "room"])
def test_a_write_cut_short_in_a_compaction_is_finished_or_out_of_room(tmp_path, monkeypatch, where, then):
    """``os.pwrite`` writes part of its data when the disk fills part way (the next call fails with ENOSPC):
    the in-place writes write the rest, and a disk that is then full is out of room (two reads, nothing left),
    not an error of its own; one with room left finishes the compaction and the run reads once."""
    import errno
    import os

    from conftest import real_file
    from prism_stream.run import staging

    src = str(real_file("pdal__autzen_trim.las"))
    ref = tmp_path / "ref.parquet"
    sample(src, str(ref), ratio=0.01, reads="two", color_depth="8")
    real = os.pwrite
    calls = []

    def pwrite(fd, data, offset):
        if os.path.basename(os.readlink(f"/proc/self/fd/{fd}")) == where:
            calls.append(offset)
            if len(calls) == 3 and len(data) > 1:  # the disk fills part way through this write
                return real(fd, data[: len(data) // 2], offset)
            if len(calls) == 4 and then == "full":
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return real(fd, data, offset)

    monkeypatch.setattr(staging.os, "pwrite", pwrite)
    s, out, tmp = _compacting_run(src, tmp_path, monkeypatch)
    assert len(calls) >= 4
    if then == "full":
        assert s.plan["reads"] == 2 and "temporary space" in s.plan["why"], s.plan
    else:
        assert s.plan["reads"] == 1 and s.plan["spill_compactions"] >= 1, s.plan
    assert pq.read_table(out).equals(pq.read_table(ref))
    assert list(tmp.iterdir()) == []


def _folder_bytes(folder) -> int:
    return sum(p.stat().st_size for p in folder.rglob("*") if p.is_file())


@pytest.mark.parametrize("name", ["pdal__autzen_trim.las", "pdal__1.2-with-color.parquet"])
def test_a_compaction_never_takes_more_disk_than_the_spill_holds(name, tmp_path, monkeypatch):
    """Compacted at every chunk, the temporary folder never grows during a compaction (its size is sampled after
    every write the spill makes): the survivors go where the candidates were, not into a copy beside them."""
    from conftest import EDGE, real_file
    from prism_stream.run import staging

    src = str(real_file(name)) if name.endswith(".las") else str(EDGE / name)
    ref = tmp_path / "ref.parquet"
    sample(src, str(ref), ratio=0.05, reads="two", color_depth="8")
    tmp = tmp_path / "tmp"
    tmp.mkdir()
    seen = {"in": False, "peak": 0, "over": []}
    real_mark, real_rewrite = staging.mark, Spill._rewrite

    def mark(path, fd):
        real_mark(path, fd)
        if seen["in"]:
            now = _folder_bytes(tmp)
            if now > seen["start"]:
                seen["over"].append((path, now, seen["start"]))

    def rewrite(self, keep):
        seen["in"], seen["start"] = True, _folder_bytes(tmp)
        try:
            return real_rewrite(self, keep)
        finally:
            seen["in"] = False
            seen["peak"] += 1

    monkeypatch.setattr(staging, "mark", mark)
    monkeypatch.setattr(Spill, "_rewrite", rewrite)
    monkeypatch.setattr(Spill, "_due", lambda self, more: True)
    out = tmp_path / "out.parquet"
    s = sample(src, str(out), ratio=0.05, chunk_size=5_000, color_depth="8", temp_dir=str(tmp))
    assert s.plan["reads"] == 1 and s.plan["spill_compactions"] >= 2 and seen["peak"] >= 2, s.plan
    assert not seen["over"], seen["over"][:3]
    assert pq.read_table(out).equals(pq.read_table(ref))


def test_frames_that_pickle_larger_wait_until_the_reads_pass_them(tmp_path):
    """A frame whose survivors pickle to more bytes than it had (no format does; a state made to) waits in
    memory until the reads have passed the room it needs: the index and every frame still agree, and the spill
    still holds the oracle's sample."""
    rgb = _stream(20_000, 500, "sorted", seed=2)
    options = Options(quant_bits=BITS, ratio=0.05, seed=1)
    r, g, b = rgb
    f = cand_mod.CandidateFilter(options.spec, options, len(r), pool_budget=1 << 12)
    spill = Spill(str(tmp_path))
    grown = []

    class Source:
        ordinal = 0

        @staticmethod
        def spill_state(chunk, at):  # the ids, and a pad that grows each time a compaction writes the frame again
            pad = b"p" * (1_000 * len(grown))
            grown.append(1)
            return chunk[at], pad

        @staticmethod
        def restore(state):
            return state[0]

    spill.begin_source(Source)
    spill._due = lambda more: True
    f.begin_source()
    for a in range(0, len(r), 1_000):
        z = min(len(r), a + 1_000)
        keys, cand = f.chunk(*loop_channels(r[a:z], g[a:z], b[a:z]), 0, a, False)
        spill.add(np.arange(a, z, dtype=np.uint64), keys, cand, a, f)
    assert spill.compactions >= 5
    ids = np.concatenate([i for _, i in spill.index()])
    frames = list(spill._frames(0))
    assert sum(len(i) for _, i, _ in frames) == len(ids) == spill.size
    for _, i, state in frames:
        np.testing.assert_array_equal(state[0], i)
    assert np.isin(_oracle_ids(rgb, ratio=0.05, seed=1), ids).all()
    spill.close()


@settings(max_examples=200, deadline=None)
@given(st.lists(st.integers(1, 50), max_size=60), st.integers(1, 120), st.integers(1, 70), st.integers(0, 3))
def test_quota_groups_are_the_cutoff_scans_groups(caps, words, block, per_slot):
    from prism_stream.core.cutoffs import quota_groups, slot_groups

    caps = np.array(caps, dtype=np.int32)
    assert quota_groups(caps, words, block, per_slot) == slot_groups(caps, words, per_slot)


def test_a_floor_one_level_too_deep_is_caught(tmp_path, monkeypatch):
    """After a compaction each bin's floor rules out the points to come above its standing cut's level:
    one level deeper (a factor sqrt(2) lower) and points the sample selects are never spilled."""
    rgb = _stream(60_000, 300, "random", seed=6)
    opts = dict(ratio=0.05, seed=2)
    want = _oracle_ids(rgb, **opts)
    ids, spill = _drive(tmp_path, rgb, Options(quant_bits=BITS, **opts), 2_000, 1 << 20)
    assert np.isin(want, ids).all() and spill.compactions > 5
    real = cand_mod.CandidateFilter.tighten

    def deeper(self, rules, cut):
        real(self, rules, cut)
        some = (self.floor > 0) & (self.floor < cand_mod.LEVELS - 1)
        self.floor[some] += 1

    monkeypatch.setattr(cand_mod.CandidateFilter, "tighten", deeper)
    (tmp_path / "deep").mkdir()
    ids, _ = _drive(tmp_path / "deep", rgb, Options(quant_bits=BITS, **opts), 2_000, 1 << 20)
    assert not np.isin(want, ids).all(), "a floor one level too deep went unnoticed"


@settings(max_examples=80, deadline=None)
@given(seed=st.integers(0, 2**32), slots=st.integers(1, 12), words=st.integers(4, 64), points=st.integers(0, 3_000),
       passes=st.integers(0, 3), radix_min=st.integers(0, 100), mapped=st.booleans())
def test_a_quota_past_the_words_gets_the_top_of_its_bucket(seed, slots, words, points, passes, radix_min, mapped):
    """standing_cuts with quotas past ``words``, or (when the heaps would take more than ``EXACT_PASSES`` passes)
    past ``RADIX_MIN_CAP``: such a slot's cut is the top of the 2^-16-wide priority range holding its q-th
    smallest (an upper bound, same top 16 bits: SlotBuckets, or SlotRadix's two passes), every other slot's is
    its q-th smallest, a slot with fewer than q points keeps all. Before, a quota past ``words`` kept every point
    (a cloud of few large bins was never compacted), and many large quotas took a pass over the spill for each
    group of them."""
    from prism_stream.core import cutoffs

    old = cutoffs.EXACT_PASSES, cutoffs.RADIX_MIN_CAP, cutoffs.SlotRadix.MAP_SLOTS
    cutoffs.EXACT_PASSES, cutoffs.RADIX_MIN_CAP = passes, radix_min
    cutoffs.SlotRadix.MAP_SLOTS = old[2] if mapped else 0  # a map from slot to place, or a binary search
    try:
        _check_standing_cuts(seed, slots, words, points, passes, radix_min)
    finally:
        cutoffs.EXACT_PASSES, cutoffs.RADIX_MIN_CAP, cutoffs.SlotRadix.MAP_SLOTS = old


def test_wide_quotas_are_counted_only_where_it_saves_passes():
    """counted_slots: nothing while the heaps take at most EXACT_PASSES passes; the quotas over RADIX_MIN_CAP
    when counting them (two passes for words / 64 slots) leaves fewer passes in all; nothing when a few wide
    quotas among many narrow ones would only add the two (the review's case)."""
    from prism_stream.core import cutoffs

    words = 1 << 12  # 64 slots a pair of counting passes
    few = np.full(4, 1_000, np.int64)  # 4,012 words: one group
    assert len(cutoffs.counted_slots(few, words)[0]) == 0
    many = np.full(40, 1_000, np.int64)  # 10 groups of heaps, or 2 counting passes
    wide, held, groups = cutoffs.counted_slots(many, words)
    np.testing.assert_array_equal(wide, np.arange(40))
    assert not held.any() and (many == 1_000).all()  # the heaps hold none of them; the quotas themselves stay
    narrow = np.concatenate([np.full(3_000, 10, np.int64), [1_000]])  # 10 groups either way, +2 counting
    assert len(cutoffs.quota_groups(narrow, words, per_slot=cutoffs.FINDER_SLOT_WORDS + 1)) > cutoffs.EXACT_PASSES
    wide, held, groups = cutoffs.counted_slots(narrow, words)
    assert len(wide) == 0 and held is narrow


@pytest.mark.parametrize("pass_", [1, 2])
def test_a_count_that_would_pass_32_bits_keeps_the_slot_whole(pass_):
    """SlotRadix counts in 4 bytes: a bucket of one slot that would pass 2^32 - 1 (past 10^12 of its points in the
    index) flags the slot, which then keeps every point (the largest cut), in either pass; the other slots' cuts
    are those of a run without it."""
    from prism_stream.core import cutoffs
    from prism_stream.core.candidates import Standing

    rule = np.zeros(8, np.int32)
    rule[[2, 5]] = [1, 2]
    rules = Standing(rule, np.array([10, 10], np.int32), np.uint64(7))
    keys = np.tile(np.array([2, 5], np.uint32), 100)
    ids = np.arange(200, dtype=np.uint64)

    def cuts(swell):
        radix = cutoffs.SlotRadix(rules, np.array([0, 1]))
        fed = []

        def feed(f):
            fed.append(1)
            if swell and len(fed) == pass_:
                f.counts[:1 << cutoffs.SlotRadix.BITS] = np.uint32(0xFFFFFFFF)  # slot 0's counts, full
            f.add_ids(keys, ids)

        return radix.upper_cuts(rules.caps, feed)

    plain, swollen = cuts(False), cuts(True)
    assert plain[0] < np.iinfo(np.uint64).max and swollen[0] == np.iinfo(np.uint64).max
    assert swollen[1] == plain[1]


def test_a_second_counting_pass_that_sees_fewer_points_is_caught():
    """SlotRadix's second pass must see the points of the first (the spill's index, read twice): fewer would
    put the cut below the q-th smallest, so it stops instead, as radix_cut does."""
    from prism_stream.core import cutoffs
    from prism_stream.core.candidates import Standing

    rule = np.zeros(8, np.int32)
    rule[3] = 1
    rules = Standing(rule, np.array([10], np.int32), np.uint64(7))
    keys, ids = np.full(50, 3, np.uint32), np.arange(50, dtype=np.uint64)
    fed = []

    def feed(f):
        fed.append(1)
        f.add_ids(keys[:50 if len(fed) == 1 else 5], ids[:50 if len(fed) == 1 else 5])

    with pytest.raises(AssertionError, match="fewer points"):
        cutoffs.SlotRadix(rules, np.array([0])).upper_cuts(rules.caps, feed)


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**32), slots=st.integers(1, 60), points=st.integers(0, 20_000), mapped=st.booleans())
def test_slot_radix_bounds_many_slots_at_once(seed, slots, points, mapped):
    """SlotRadix over many slots in one pair of passes (any subset of the capped slots, by a map from slot to
    place or a binary search): each slot's cut is an upper bound of its q-th smallest priority with the same top
    16 bits, the largest priority when it has fewer than q points, and the slots outside the subset count
    nothing."""
    from prism_stream.core import cutoffs
    from prism_stream.core.candidates import Standing
    from prism_stream.core.kernels import priorities_of_np

    rng = np.random.default_rng(seed)
    space = 256
    rule = np.zeros(space, np.int32)
    capped = np.sort(rng.choice(space, slots, replace=False))
    rule[capped] = np.arange(1, slots + 1, dtype=np.int32)
    rule[rng.choice(np.setdiff1d(np.arange(space), capped), 3, replace=False)] = -1
    caps = rng.integers(1, 3 * max(1, points // max(1, slots * 4)) + 2, slots).astype(np.int32)
    rules = Standing(rule, caps, np.uint64(rng.integers(0, 2**63)))
    keys = np.concatenate([capped, rng.integers(0, space, points)])[:points].astype(np.uint32)
    ids = rng.permutation(10 * points + 1)[:points].astype(np.uint64)
    chosen = np.flatnonzero(rng.random(slots) < 0.7)
    if not len(chosen):
        chosen = np.array([slots - 1])
    old = cutoffs.SlotRadix.MAP_SLOTS
    cutoffs.SlotRadix.MAP_SLOTS = old if mapped else 0
    try:
        radix = cutoffs.SlotRadix(rules, chosen)
        assert (len(radix.where[1]) > 0) == mapped  # a map from slot to place, or a binary search
        cut = radix.upper_cuts(caps[chosen], lambda f: [f.add_ids(keys[a:a + 999], ids[a:a + 999])
                                                      for a in range(0, points, 999)])
    finally:
        cutoffs.SlotRadix.MAP_SLOTS = old
    prios = priorities_of_np(ids, rules.seed_mix)
    for r, s in enumerate(chosen):
        mine = np.sort(prios[keys == capped[s]])
        q = int(caps[s])
        if len(mine) < q:
            assert cut[r] == np.iinfo(np.uint64).max, (r, s)
            continue
        assert mine[q - 1] <= cut[r] and mine[q - 1] >> np.uint64(48) == cut[r] >> np.uint64(48), (r, s)
        assert (int(cut[r]) + 1) % (1 << 48) == 0 or cut[r] == np.iinfo(np.uint64).max


def _check_standing_cuts(seed, slots, words, points, passes, radix_min):
    from prism_stream.core import cutoffs
    from prism_stream.core.candidates import Standing
    from prism_stream.core.kernels import priorities_of_np

    rng = np.random.default_rng(seed)
    space = 64
    rule = np.zeros(space, np.int32)
    capped = np.sort(rng.choice(space, slots, replace=False))
    rule[capped] = np.arange(1, slots + 1, dtype=np.int32)
    rule[rng.choice(np.setdiff1d(np.arange(space), capped), 3, replace=False)] = -1  # kept whole: no slot
    caps = rng.integers(1, 3 * words, slots).astype(np.int32)
    rules = Standing(rule, caps, np.uint64(rng.integers(0, 2**63)))
    keys = rng.integers(0, space, points).astype(np.uint32)
    ids = rng.permutation(10 * points + 1)[:points].astype(np.uint64)

    def feed(finder):
        for a in range(0, points, 257):
            finder.add_ids(keys[a:a + 257], ids[a:a + 257])

    passes_seen, chosen = [], []

    def counted(finder):
        passes_seen.append(type(finder).__name__)
        feed(finder)

    real = cutoffs.counted_slots
    cutoffs.counted_slots = lambda c, w: chosen.append(real(c, w)) or chosen[-1]  # (slots, held, groups)
    try:
        cut = cutoffs.standing_cuts(rules, counted, words=words)
    finally:
        cutoffs.counted_slots = real
    wide = np.zeros(slots, bool)
    wide[chosen[0][0]] = True
    if wide.any():  # only past the passes allowed, only quotas over the threshold
        assert len(cutoffs.quota_groups(caps, words, per_slot=cutoffs.FINDER_SLOT_WORDS + 1)) > passes
        assert (caps[wide] > radix_min).all()
    assert passes_seen.count("SlotRadix") == 2 * -(-int(wide.sum()) // max(1, words >> 8))
    prios = priorities_of_np(ids, rules.seed_mix)
    top = np.iinfo(np.uint64).max
    for s in range(slots):
        mine = np.sort(prios[keys == capped[s]])
        q = int(caps[s])
        if len(mine) < q:
            assert cut[s] == top
            continue
        exact = mine[q - 1]
        if q <= words and not wide[s]:  # a heap holds it (a group of its own if need be): exact
            assert cut[s] == exact, s
        else:
            assert exact <= cut[s] and exact >> np.uint64(48) == cut[s] >> np.uint64(48), s
            assert (int(cut[s]) + 1) % (1 << 48) == 0 or cut[s] == top


@pytest.mark.parametrize("counted", [False, True], ids=["buckets", "radix"])
def test_runs_compacted_with_quotas_past_the_words_match_the_oracle(tmp_path_factory, monkeypatch, counted):
    """Every compaction's quotas past the cutoff words (4 words): the bucket bounds, at every chunk, and the
    output is still the oracle's; ``radix``: every capped slot counted in SlotRadix's two passes instead."""
    from prism_stream.core import cutoffs

    monkeypatch.setattr(Spill, "_due", lambda self, more: True)
    monkeypatch.setattr(cutoffs, "STANDING_WORDS", 4)
    radix = []
    if counted:  # every capped slot counted, whatever it saves
        def every(caps, words):
            wide = np.flatnonzero(caps > 0)
            held = caps.copy()
            held[wide] = 0
            return wide, held, cutoffs.quota_groups(held, words, per_slot=cutoffs.FINDER_SLOT_WORDS + 1)

        monkeypatch.setattr(cutoffs, "counted_slots", every)
        real_cuts = cutoffs.SlotRadix.upper_cuts
        monkeypatch.setattr(cutoffs.SlotRadix, "upper_cuts",
                            lambda self, caps, feed: radix.append(len(caps)) or real_cuts(self, caps, feed))
    real = cutoffs.standing_cuts
    seen = []
    monkeypatch.setattr(cutoffs, "standing_cuts",
                        lambda rules, feed, words=4: seen.append(len(rules.caps)) or real(rules, feed, words))

    @settings(max_examples=6, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
    @given(st.data())
    def run(data):
        _, want, summary, out = random_run(tmp_path_factory, data)
        t = pq.read_table(out, columns=["intensity"])
        np.testing.assert_array_equal(t.column("intensity").to_numpy(), np.concatenate(want.kept) % 65536)

    run()
    assert seen  # the compactions ran with these words
    assert bool(radix) == counted


def test_the_heaps_are_set_aside_during_a_compaction_or_kept_when_the_disk_refuses(tmp_path, monkeypatch):
    """A compaction writes the filter's heaps and level counts to the spill's folder and lets them go while it
    runs (they are not read there), then reads them back: the run is the oracle's either way, and a disk that
    refuses the file leaves them in memory."""
    import builtins
    import errno
    import os

    from prism_stream.run import spill as spill_mod

    rgb = _stream(60_000, 700, "random", 3)
    options = Options(ratio=0.05, seed=4)
    want = None
    real_rules = cand_mod.CandidateFilter.standing_rules
    for refuse in (False, True):
        held = []

        def rules(self, *a, **kw):
            held.append(self.pool is not None)
            return real_rules(self, *a, **kw)

        monkeypatch.setattr(cand_mod.CandidateFilter, "standing_rules", rules)
        if refuse:
            def full(path, mode="r", *a, **kw):
                if str(path).endswith("heaps.aside") and "w" in mode:
                    raise OSError(errno.ENOSPC, "No space left on device")
                return builtins.open(path, mode, *a, **kw)

            monkeypatch.setattr(spill_mod, "open", full, raising=False)
        folder = tmp_path / str(refuse)
        folder.mkdir()
        ids, _ = _drive(folder, rgb, options, 5_000, pool_budget=1 << 16)
        assert held and all(h == refuse for h in held), held
        if want is None:
            want = ids
        else:
            assert np.array_equal(ids, want)
        assert not any(n.endswith("heaps.aside") for _, _, files in os.walk(tmp_path) for n in files)

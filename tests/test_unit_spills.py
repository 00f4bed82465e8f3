"""A cluster unit's spill holds every point of the unit the run can select (issue 14).

On the Dask engine's one-read path each work unit runs the candidate filter
on its own (``engines.dask.tasks.scan_unit_spill``), with the run's target and
the counts it has seen: its own, plus a prior (counts of other units, with
their final bin keys). The promise, for any split of a file into units, any
prior drawn from the other units, every rule, and a file that may prove
16-bit late: the union of the units' spills, and of the units the engine
reads again (``UnitSpill.needs_reread``: they spill nothing for the 16-bit
outcome), contains every point the oracle (tests/oracle.py) selects; only a
file that proves 16-bit late has units read again; and each unit reports its
own counts, not its prior's.
"""

from __future__ import annotations

import os
import tempfile
import shutil

import laspy
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from prism_stream.core.histogram import Histogram
from prism_stream.core.kernels import loop_channels
from prism_stream.engines.dask.tasks import Prior, UnitRef, merge_prior, scan_unit_spill
from prism_stream.run.request import Request
from prism_stream.run.spill import Spill

import oracle

SETTINGS = settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
OPEN = (("rgb_columns", None), ("threads", 1))


def write_las(path, rgb) -> None:
    header = laspy.LasHeader(point_format=3, version="1.2")
    pts = laspy.ScaleAwarePointRecord.zeros(len(rgb), header=header)
    pts.red, pts.green, pts.blue = rgb.T
    with laspy.open(path, mode="w", header=header) as w:
        w.write_points(pts)


def histogram_of(keys) -> Histogram:
    return Histogram.from_keys(np.asarray(keys, dtype=np.uint32))


@SETTINGS
@given(n=st.integers(1, 3_000), palette=st.integers(1, 60), units=st.integers(1, 6), seed=st.integers(0, 2**64 - 1),
       rule=st.sampled_from(["ratio", "paper", "count", "k"]), ratio=st.floats(0.001, 1.0), k=st.integers(1, 6),
       bits=st.integers(0, 4), depth=st.sampled_from(["8", "late16", "16"]), data=st.data())
def test_the_units_spills_hold_the_sample(n, palette, units, seed, rule, ratio, k, bits, depth, data):
    rng = np.random.default_rng(data.draw(st.integers(0, 2**32 - 1)))
    colors = rng.integers(0, 256, (palette, 3))
    rgb = colors[np.minimum(rng.geometric(0.15, n) - 1, palette - 1)].astype(np.uint16)
    if depth == "16":
        rgb = rgb * 257
    elif depth == "late16":
        rgb[rng.integers(0, n), rng.integers(0, 3)] = 4000  # some units see it, the others look 8-bit
    target = {"ratio": dict(ratio=ratio), "paper": dict(ratio=ratio, mode="paper"),
              "count": dict(count=max(1, int(ratio * n))), "k": dict(k=k)}[rule]
    result = oracle.sample([tuple(rgb.T)], seed=seed, bits=bits, **target)
    selected = set(oracle.point_ids(0, n)[result.kept[0]].tolist())
    (r, g, b), _ = oracle.to_8bit(tuple(rgb.T))
    final_keys = oracle.bin_keys(r, g, b, bits=bits)  # with the file's decision
    file_decision = "16" if rgb.max(initial=0) > 255 else "8"

    options = Request.of(None, seed=seed, quant_bits=bits, **target).options
    cuts = sorted(set(rng.integers(0, n + 1, units - 1).tolist()) | {0, n})
    ranges = list(zip(cuts[:-1], cuts[1:]))
    found = set()
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "cloud.las")
        write_las(path, rgb)
        # each unit alone first: the bounds it proves (CandidateFilter.limits), usable by the others where
        # its keys are final (its own depth decision is the file's)
        alone = [scan_unit_spill(UnitRef(path, 0, a, z, OPEN), options, n, 500, tmp)
                 for a, z in ranges]
        for u, (a, z) in enumerate(ranges):
            others = [j for j in range(len(ranges)) if j != u and data.draw(st.booleans())]
            prior = None
            if others:
                counts = histogram_of(np.concatenate([final_keys[slice(*ranges[j])] for j in others]))
                bounded = [alone[j] for j in others if alone[j][1].decision == file_decision and alone[j][2] is not None]
                merged = merge_prior(None, *[(s_, f_, lim) for s_, f_, lim in bounded])
                prior = Prior(counts, merged.limit_keys, merged.limits, merged.evidence)
            ref = UnitRef(path, 0, a, z, OPEN)
            scan, facts, _ = scan_unit_spill(ref, options, n, int(data.draw(st.integers(1, 700))), tmp,
                                             prior)
            (r8, g8, b8), _ = oracle.to_8bit(tuple(rgb[a:z].T))  # the unit's own decision
            own_hist = histogram_of(oracle.bin_keys(r8, g8, b8, bits=bits))
            assert np.array_equal(scan.histogram.keys, own_hist.keys)
            assert np.array_equal(scan.histogram.counts, own_hist.counts)
            assert facts.decision == scan.decision == ("16" if rgb[a:z].max(initial=0) > 255 else "8")
            assert facts.final == (facts.decision == "16")  # 16-bit fields that look 8-bit may still move
            spill = Spill.reopen(facts.folder)
            try:
                assert facts.points == spill.size
                if facts.needs_reread(file_decision):  # the engine reads the unit again: all its points
                    assert depth == "late16"
                    found.update(oracle.point_ids(0, n)[a:z].tolist())
                    continue
                for _, ids in spill.index():
                    found.update(ids.tolist())
            finally:
                spill.close()
    assert selected <= found


def test_a_unit_that_proves_16_bit_after_its_first_chunk_is_read_again(tmp_path):
    """Its first points moved to key 0 with nothing spilled for that outcome: the spill alone misses points
    of bin 0 the oracle selects, so the unit must be read again (``refiled`` > 0)."""
    rng = np.random.default_rng(3)
    n = 3_000
    rgb = rng.integers(0, 256, (50, 3))[rng.integers(0, 50, n)].astype(np.uint16)
    rgb[2_500, 0] = 4_000  # in the unit's third chunk of 1,000
    path = str(tmp_path / "cloud.las")
    write_las(path, rgb)
    options = Request.of(None, seed=1, ratio=0.01).options
    scan, facts, _ = scan_unit_spill(UnitRef(path, 0, 0, n, OPEN), options, n, 1_000, str(tmp_path))
    assert facts.decision == "16" and facts.refiled == 2_000 and facts.needs_reread("16")
    result = oracle.sample([tuple(rgb.T)], seed=1, ratio=0.01)
    selected = set(oracle.point_ids(0, n)[result.kept[0]].tolist())
    spill = Spill.reopen(facts.folder)
    try:
        spilled = {i for _, ids in spill.index() for i in ids.tolist()}
    finally:
        spill.close()
    assert not selected <= spilled  # what the re-read is for


@settings(max_examples=60, deadline=None)
@given(n=st.integers(1, 20_000), palette=st.integers(1, 300), ratio=st.sampled_from([0.001, 0.01, 0.1, 0.5]),
       seed=st.integers(0, 2**32), chunk=st.integers(50, 5_000), mode=st.sampled_from(["exact", "paper", "k"]))
def test_every_limit_has_at_least_the_cap_of_its_bins_points_below_it(n, palette, ratio, seed, chunk, mode):
    """The bound another unit may rule with (CandidateFilter.limits): at least cap_t = K_t + 1 >= K + 1 of
    the bin's points seen here lie at or below it, counted by brute force over the stream's priorities."""
    from prism_stream.core import kernels
    from prism_stream.core.candidates import CandidateFilter

    rng = np.random.default_rng(seed)
    colors = rng.integers(0, 256, (palette, 3)).astype(np.uint8)
    rgb = colors[np.minimum(rng.geometric(min(1.0, 2.0 / palette), n) - 1, palette - 1)]
    opts = dict(k=max(1, int(ratio * 100))) if mode == "k" else dict(ratio=ratio, mode=mode)
    options = Request.of(None, seed=seed, **opts).options
    f = CandidateFilter(options.spec, options, n)
    keys = []
    for a in range(0, n, chunk):
        k, _ = f.chunk(*loop_channels(*rgb[a:a + chunk].T), 0, a, False)
        keys.append(k)
    keys = np.concatenate(keys)
    prios = kernels.priorities_of_np(np.arange(n, dtype=np.uint64), kernels.seed_mix(seed))
    cap = f.cap() if mode != "k" else options.k  # q_b <= cap: K_t + 1, or k
    lk, lim = f.limits()
    for key, bound in zip(lk.tolist(), lim.tolist()):
        assert np.count_nonzero(prios[keys == key] <= np.uint64(bound)) >= cap, (key, bound, cap)


def _stream_filter(n, palette, ratio, seed, chunk, mode, first_id=0):
    """A CandidateFilter fed a random stream; its keys and the stream's priorities (for brute force)."""
    from prism_stream.core import kernels
    from prism_stream.core.candidates import CandidateFilter

    rng = np.random.default_rng(seed)
    colors = rng.integers(0, 256, (palette, 3)).astype(np.uint8)
    rgb = colors[np.minimum(rng.geometric(min(1.0, 2.0 / palette), n) - 1, palette - 1)]
    opts = dict(k=max(1, int(ratio * 100))) if mode == "k" else dict(ratio=ratio, mode=mode)
    options = Request.of(None, seed=0, **opts).options
    f = CandidateFilter(options.spec, options, n)
    keys = []
    for a in range(0, n, chunk):
        k, _ = f.chunk(*loop_channels(*rgb[a:a + chunk].T), 0, first_id + a, False)
        keys.append(k)
    prios = kernels.priorities_of_np(first_id + np.arange(n, dtype=np.uint64), kernels.seed_mix(0))
    return f, np.concatenate(keys), prios


@settings(max_examples=20, deadline=None)
@given(n=st.integers(1, 20_000), palette=st.integers(1, 300), ratio=st.sampled_from([0.001, 0.01, 0.1, 0.5]),
       seed=st.integers(0, 2**32), chunk=st.integers(50, 5_000), mode=st.sampled_from(["exact", "paper", "k"]),
       units=st.integers(1, 4))
def test_summed_evidence_never_counts_more_points_than_lie_below_its_level(n, palette, ratio, seed, chunk, mode,
                                                                          units):
    """CandidateFilter.evidence of several units over distinct points, summed by merge_evidence: every
    (bin, level, count) has at least that many of the units' points of the bin below tau[level]."""
    from prism_stream.core.candidates import TAU
    from prism_stream.engines.dask.tasks import merge_evidence

    parts, all_keys, all_prios = [], [], []
    for u in range(units):
        f, keys, prios = _stream_filter(n, palette, ratio, seed + u, chunk, mode, first_id=u << 40)
        parts.append(f.evidence())
        for piece, whole in zip(f.evidence(block=1 + u), parts[-1]):  # made a few slots at a time: the same rows
            assert piece.dtype == whole.dtype and np.array_equal(piece, whole)
        all_keys.append(keys)
        all_prios.append(prios)
    for ev in parts[:1] + [merge_evidence(*parts)]:
        keys, prios = (all_keys[0], all_prios[0]) if ev is parts[0] else (np.concatenate(all_keys),
                                                                          np.concatenate(all_prios))
        for key, level, count in zip(*[e.tolist() for e in ev]):
            assert np.count_nonzero(prios[keys == key] < TAU[level]) >= count, (key, level, count)
    merged = merge_evidence(*parts)
    assert len(merged[0]) == 0 or np.isin(merged[0], np.concatenate([p[0] for p in parts])).all()


def _unit_result(rng, bins: int):
    """A made-up scan_unit_spill result: (scan, spill facts, (limit keys, limits, evidence)), the shapes the
    real ones have (sorted distinct keys; evidence one entry per bin and level, the deepest level first)."""
    from types import SimpleNamespace

    keys = np.unique(rng.integers(0, bins, rng.integers(0, 12))).astype(np.uint32)
    histogram = Histogram(keys, rng.integers(1, 50, len(keys)).astype(np.int64))
    lim_keys = np.unique(rng.choice(keys, rng.integers(0, len(keys) + 1), replace=False)).astype(np.uint32) \
        if len(keys) else np.zeros(0, np.uint32)
    limits = rng.integers(0, 2**64 - 1, len(lim_keys), dtype=np.uint64)
    pairs = sorted({(int(k), int(lv)) for k in lim_keys for lv in rng.integers(0, 128, rng.integers(0, 4))},
                   key=lambda kl: (kl[0], -kl[1]))
    evidence = (np.array([k for k, _ in pairs], np.uint32), np.array([lv for _, lv in pairs], np.uint8),
                rng.integers(1, 30, len(pairs)).astype(np.int64))
    return SimpleNamespace(histogram=histogram), None, (lim_keys, limits, evidence)


@settings(max_examples=150, deadline=None)
@given(seed=st.integers(0, 2**32), units=st.integers(1, 14), bins=st.integers(1, 9), first=st.booleans())
def test_a_prior_made_of_folds_is_the_prior_made_of_the_units(seed, units, bins, first):
    """The driver folds the units' results FAN_IN at a time while they wait for a prior
    (merge_prior(..., fold=True)): the prior made of the folds, in any grouping, is the one made of the units
    themselves, to the bit (counts, bounds and evidence). A fold made with merge_evidence instead (each fold
    a prior) would raise levels and drop a bin's shallow ones before the sum: a weaker prior."""
    rng = np.random.default_rng(seed)
    results = [_unit_result(rng, bins) for _ in range(units)]
    earlier = merge_prior(*[_unit_result(rng, bins) for _ in range(3)]) if first else None
    want = merge_prior(earlier, *results)
    # a random tree of folds over the results, in a random order
    handles = [results[i] for i in rng.permutation(units)]
    while len(handles) > 1 and rng.random() < 0.8:
        a = int(rng.integers(0, len(handles)))
        b = int(rng.integers(a + 1, len(handles) + 1))
        handles[a:b] = [merge_prior(*handles[a:b], fold=True)]
    got = merge_prior(earlier, *handles)
    pairs = [(got.histogram.keys, want.histogram.keys), (got.histogram.counts, want.histogram.counts),
             (got.limit_keys, want.limit_keys), (got.limits, want.limits), *zip(got.evidence, want.evidence)]
    for mine, theirs in pairs:
        assert mine.dtype == theirs.dtype and np.array_equal(mine, theirs)
    folded = merge_prior(*results, fold=True)  # a fold holds one entry per bin and level seen, no more
    seen = {(int(k), int(lv)) for _, _, lim in results for k, lv in zip(lim[2][0], lim[2][1])}
    assert len(folded.evidence[0]) == len(seen)


@pytest.mark.parametrize("damage", ["truncate", "extend", "remove", "meta"])
def test_a_units_spill_changed_before_it_is_read_back_is_one_line(tmp_path, damage):
    """A unit's spill is read back by other tasks, in other processes: the sizes its task left are in
    spill.meta, and a spill truncated, extended, removed or whose meta is garbage is TempDataChanged (exit 11,
    naming the staging folder), not an UnpicklingError or a failed assertion on the driver (issue 32)."""
    from prism_stream.errors import TempDataChanged

    rng = np.random.default_rng(4)
    n = 3_000
    path = str(tmp_path / "cloud.las")
    write_las(path, rng.integers(0, 256, (n, 3)).astype(np.uint16))
    options = Request.of(None, seed=1, ratio=0.05).options
    _, facts, _ = scan_unit_spill(UnitRef(path, 0, 0, n, OPEN), options, n, 1_000, str(tmp_path))
    Spill.reopen(facts.folder).close()  # as written: it opens
    target = os.path.join(facts.folder, "spill.frames" if damage != "meta" else "spill.meta")
    if damage == "truncate":
        os.truncate(target, os.path.getsize(target) // 2)
    elif damage == "extend":
        with open(target, "ab") as f:
            f.write(b"\0" * 100)
    elif damage == "remove":
        shutil.rmtree(facts.folder)
    else:
        with open(target, "wb") as f:
            f.write(rng.bytes(64))
    with pytest.raises(TempDataChanged) as caught:
        Spill.reopen(facts.folder).close()
    assert caught.value.exit_code == 11 and str(caught.value).startswith(facts.folder), caught.value
    import pickle

    assert str(pickle.loads(pickle.dumps(caught.value))) == str(caught.value)  # as it reaches the driver


@settings(max_examples=150, deadline=None)
@given(seed=st.integers(0, 2**32), units=st.integers(1, 9), bins=st.integers(1, 60), block=st.integers(1, 5),
       fold=st.booleans(), shuffled=st.booleans())
def test_priors_merged_a_range_of_keys_at_a_time_are_the_priors_merged_whole(seed, units, bins, block, fold,
                                                                           shuffled):
    """merge_prior cuts its parts into ranges of keys (keyblocks.merged) so that its temporaries are a
    range's, not all the parts' (3.3 GiB above four 8.6M-bin parts, merged whole): the counts, bounds and
    evidence it makes range by range are the ones made whole, to the bit, whatever the range size, and with
    a unit's bounds and evidence in the order its filter's slots hold them (arrival, not key order)."""
    from prism_stream.core import keyblocks

    rng = np.random.default_rng(seed)
    results = [_unit_result(rng, bins) for _ in range(units)]
    if shuffled:
        for _, _, lim in results:
            order, ev_order = rng.permutation(len(lim[0])), rng.permutation(len(lim[2][0]))
            lim[0][:], lim[1][:] = lim[0][order], lim[1][order]
            for column in lim[2]:
                column[:] = column[ev_order]
    earlier = merge_prior(*[_unit_result(rng, bins) for _ in range(2)], fold=fold)
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(keyblocks, "BLOCK", 1 << 40)
        want = merge_prior(earlier, *results, fold=fold)
        mp.setattr(keyblocks, "BLOCK", block)
        got = merge_prior(earlier, *results, fold=fold)
    pairs = [(got.histogram.keys, want.histogram.keys), (got.histogram.counts, want.histogram.counts),
             (got.limit_keys, want.limit_keys), (got.limits, want.limits), *zip(got.evidence, want.evidence)]
    for mine, theirs in pairs:
        assert mine.dtype == theirs.dtype and np.array_equal(mine, theirs)
    assert np.all(np.diff(got.limit_keys.astype(np.int64)) > 0)


@settings(max_examples=200, deadline=None)
@given(lists=st.lists(st.lists(st.integers(0, 50), max_size=40), max_size=6), block=st.integers(1, 6))
def test_key_ranges_hold_every_key_once_and_at_most_a_block_of_each_part(lists, block):
    from prism_stream.core import keyblocks

    parts = [np.sort(np.array(k, np.uint32)) for k in lists]
    seen = [[] for _ in parts]
    last = -1
    for span in keyblocks.spans(parts, block):
        keys_here = set()
        for i, (lo, hi) in enumerate(span):
            seen[i].extend(range(lo, hi))
            here = parts[i][lo:hi]
            keys_here |= set(here.tolist())
            # at most a block of entries, besides the copies of one key
            assert hi - lo <= block + max([int(np.sum(here == v)) for v in set(here.tolist())] or [0])
        if keys_here:
            assert min(keys_here) > last  # the ranges in key order, a key in one range only
            last = max(keys_here)
    for i, p in enumerate(parts):
        assert seen[i] == list(range(len(p)))


def test_a_units_spill_is_compacted_as_its_prior_and_its_own_counts_tighten_the_bound(tmp_path):
    """A unit compacts its spill once it passes its share of the run's bound (tasks.unit_compact_mark), as
    the local engine compacts the whole input's: the spill keeps every point the sample takes from the
    unit, and fewer than without it. Without the compaction, units over many small bins spilled most of
    their points (85% over 2^24 bins, twice the bound): a point let through while the prior knew few bins
    stayed in the spill."""
    from prism_stream.engines.dask import tasks

    rng = np.random.default_rng(11)
    n, a, z = 200_000, 10_000, 40_000  # a unit of [a, z), its prior made of [0, a): a few of the bins known
    rgb = (rng.integers(0, 256, (60_000, 3))[rng.integers(0, 60_000, n)] * 257).astype(np.uint16)  # decided 16-bit
    path = str(tmp_path / "cloud.las")
    write_las(path, rgb)
    options = Request.of(None, seed=5, ratio=0.05).options
    result = oracle.sample([tuple(rgb.T)], seed=5, ratio=0.05)
    ids = oracle.point_ids(0, n)
    ours = set(ids[result.kept[0]].tolist()) & set(ids[a:z].tolist())  # what the sample takes of the unit
    first = scan_unit_spill(UnitRef(path, 0, 0, a, OPEN), options, n, 1_000, str(tmp_path))
    prior = merge_prior(None, first)
    spills = {}
    for compacting in (True, False):
        with pytest.MonkeyPatch.context() as mp:
            if not compacting:
                mp.setattr(tasks, "unit_compact_mark", lambda *a: None)
            _, facts, _ = scan_unit_spill(UnitRef(path, 0, a, z, OPEN), options, n, 1_000, str(tmp_path), prior)
        spill = Spill.reopen(facts.folder)
        try:
            spills[compacting] = (facts, {i for _, ids in spill.index() for i in ids.tolist()})
        finally:
            spill.close()
    (compacted, kept), (plain, everything) = spills[True], spills[False]
    assert compacted.compactions >= 1 and plain.compactions == 0
    assert ours and ours <= kept <= everything and len(kept) < 0.7 * len(everything)
    assert compacted.points == len(kept)

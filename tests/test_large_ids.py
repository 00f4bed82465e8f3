"""Ids past 2^32 (issue 26): a unit with more than 2^32 points cannot be made on this disk, so a source
reports its records at an offset past 2^33 (and an ordinal past 1); the one-read filter, the spill, the
cutoffs and the keep masks must give the points an in-memory oracle selects from the same ids."""

from __future__ import annotations

import numpy as np
import pyarrow as pa
import pytest

from conftest import write_parquet, random_colors
from prism_stream import Options, solve
from prism_stream.core import kernels
from prism_stream.core.candidates import CandidateFilter
from prism_stream.core.cutoffs import Rules, cutoffs_by_groups
from prism_stream.core.histogram import Histogram
from prism_stream.core.passes import scan_candidates
from prism_stream.core.selection import Selector
from prism_stream.formats.base import Unit
from prism_stream.formats.parquet import ParquetSource
from prism_stream.run.spill import Spill

OFFSET = (1 << 33) + 12_345  # records before these are not there: the file's row i is record OFFSET + i
ORDINAL = 3


class OffsetSource(ParquetSource):
    """A Parquet file whose rows are records [OFFSET, OFFSET + rows) of a source of OFFSET + rows records."""

    def __init__(self, path):
        super().__init__(path, ORDINAL)
        self.rows = self.count
        self.count = OFFSET + self.rows

    def _batches(self, chunk_size, start, stop, columns):
        stop = self.count if stop is None else stop
        for pos, batch in super()._batches(chunk_size, start - OFFSET, stop - OFFSET, columns):
            yield pos + OFFSET, batch

    def unit(self) -> Unit:
        return Unit(self, OFFSET, self.count)


@pytest.mark.parametrize("opts", [dict(ratio=0.05), dict(k=3, seed=9), dict(count=700, mode="paper")])
def test_ids_past_2_32_through_spill_cutoffs_and_masks(tmp_path, opts):
    n = 20_000
    rgb = random_colors(n, seed=4, palette=300).astype(np.uint8)
    path = write_parquet(tmp_path / "p.parquet", pa.table({"x": np.arange(n, dtype=np.float64), "red": rgb[:, 0],
                                                           "green": rgb[:, 1], "blue": rgb[:, 2]}))
    src = OffsetSource(str(path))
    options = Options(**opts)
    spec = options.spec
    try:
        candidates = CandidateFilter(spec, options, n)
        with Spill(str(tmp_path)) as spill:
            scan_candidates(src.unit(), candidates, options.color_depth, 3_000, spill)
            spill.flush()
            plan = solve(Histogram.from_dense(candidates.counts()), options)
            ids_spilled = np.concatenate([i for _, i in spill.index()])
            assert ids_spilled.min() >= (ORDINAL << kernels.ID_SHIFT) + OFFSET > 2**41
            rules = Rules(plan)

            def feed(finder):
                for keys, ids in spill.index():
                    finder.add_ids(keys, ids)

            cutoffs = cutoffs_by_groups(rules, feed, words=50)  # groups, and a radix select for a bin past 50
            selector = Selector(plan, cutoffs, rules)
            got = np.sort(np.concatenate([ids[selector.mask_ids(keys, ids)] for keys, ids in spill.index()]))
            # consecutive ids (the two-read path's key cache) past 2^32 give the same cutoffs
            all_keys = spec.keys(rgb[:, 0], rgb[:, 1], rgb[:, 2], 0, compiled=False).astype(np.uint32)
            first = (ORDINAL << kernels.ID_SHIFT) | OFFSET

            def feed_runs(finder):
                for a in range(0, n, 3_000):
                    finder.add(all_keys[a:a + 3_000], first + a)

            assert np.array_equal(cutoffs_by_groups(rules, feed_runs, words=50).cut, cutoffs.cut)
    finally:
        src.close()
    # the oracle: every point's id and priority, each bin's q_b smallest by a sort
    ids = np.uint64((ORDINAL << kernels.ID_SHIFT) | OFFSET) + np.arange(n, dtype=np.uint64)
    prios = kernels.priorities_of_np(ids, kernels.seed_mix(options.seed))
    want = []
    for key, q in zip(plan.keys, plan.quotas):
        members = np.flatnonzero(all_keys == key)
        want.append(ids[members[np.argsort(prios[members])[:q]]])
    want = np.sort(np.concatenate(want))
    assert len(got) == plan.kept and np.array_equal(got, want)
    assert got.max() > 2**32 and (got & np.uint64((1 << kernels.ID_SHIFT) - 1)).min() >= OFFSET

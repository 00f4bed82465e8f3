"""The per-unit building blocks (scan, solve, cutoffs, select), driven by hand
over small work units, give exactly the local engine's output (SPEC 5: the
output does not depend on partitioning or engine)."""

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

import prism_stream
from prism_stream import Options, merge_units, scan, select, solve
from prism_stream.core.bins import decided_keys
from prism_stream.core.cutoffs import CutoffFinder, Rules, merge_bottoms
from prism_stream.formats import open_source

from conftest import REAL

CASES = [
    ("pdal__autzen_trim.las", dict(ratio=0.01)),
    ("pdal__warsaw_small.las", dict(ratio=0.2, mode="paper")),
    ("laspy__fullwave.laz", dict(count=500, color_space="chroma", quant_bits=1)),
    ("pdal__las_with_several_extra_byte_bloc.laz", dict(k=3, seed=7)),
]


def unit_plan(path, options, unit_size):
    """(plan, units, depths): pass one over units and the solve, by hand."""
    sources = [open_source(path, 0)]
    units = [u for s in sources for u in s.units(unit_size)]
    histogram, depths = merge_units([scan(u, options.spec, options.color_depth) for u in units],
                                    options.color_depth)
    meta = tuple({"ordinal": s.ordinal, "path": s.path, "points": s.count, "color_depth": depths[s.ordinal]}
                 for s in sources)
    return solve(histogram, options, meta), units, depths


def unit_pipeline(path, options, unit_size):
    plan, units, depths = unit_plan(path, options, unit_size)
    rules = Rules(plan)
    bottoms = []
    for u in units:
        finder = CutoffFinder(rules)
        for chunk in u.color_chunks(10_000):
            keys = decided_keys(plan.spec, chunk.rgb, depths[u.source.ordinal], u.source.path)
            finder.add(keys, (u.source.ordinal << 40) | chunk.start)
        bottoms.append(finder.bottoms())
    cutoffs = merge_bottoms(rules, bottoms)
    batches = [chunk.to_arrow(mask) for u in units for chunk, mask in select(u, plan, cutoffs, 10_000)]
    return plan, pa.Table.from_batches(batches)


@pytest.mark.parametrize("name,opts", CASES)
@pytest.mark.parametrize("unit_size", [7_777, 100_000])
def test_units_match_local_engine(tmp_path, name, opts, unit_size):
    path = REAL / name
    assert path.is_file(), f"test data file not found: {path} (see tests/data/README.md)"
    options = Options(**opts)
    plan, table = unit_pipeline(str(path), options, unit_size)
    out = tmp_path / "out.parquet"
    summary = prism_stream.sample(str(path), str(out), **opts)
    assert plan.kept == summary.kept == table.num_rows
    assert plan.bins == summary.bins and plan.k == summary.k
    local = pq.read_table(out)
    assert local.schema.names == table.schema.names
    for name_ in local.schema.names:
        assert np.array_equal(local[name_].to_numpy(), table[name_].to_numpy()), name_


@pytest.mark.parametrize("name,opts", CASES)
def test_a_rule_table_is_zero_where_the_plan_has_no_bin(name, opts):
    """"Drop" is 0 (np.zeros: the OS maps a page of the 64 MiB table only where a bin is, bench/PROFILE.md);
    the plan's bins are each marked: keep all, or their capped slot + 1, in key order."""
    from prism_stream.core import kernels

    plan, _, _ = unit_plan(str(REAL / name), Options(**opts), 100_000)
    rule = Rules(plan).rule
    assert kernels.RULE_DROP == 0 and len(rule) == plan.spec.key_space
    marked = np.flatnonzero(rule)
    whole = plan.keys[(plan.quotas == plan.counts) & (plan.counts > 0)]
    capped = plan.keys[plan.capped]
    assert np.array_equal(marked, np.sort(np.concatenate([whole, capped])))
    assert (rule[whole] == kernels.RULE_KEEP).all()
    assert np.array_equal(rule[capped], np.arange(1, len(capped) + 1))

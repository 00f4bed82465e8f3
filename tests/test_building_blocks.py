"""The per-unit building blocks (scan, solve, cutoffs, select), driven by hand
over small work units, give exactly the local engine's output (SPEC 5: the
output does not depend on partitioning or engine)."""

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

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


@settings(max_examples=40, deadline=None)
@given(groups=st.lists(st.integers(1, 40), min_size=1, max_size=12), unit_size=st.integers(1, 120))
def test_parquet_units_are_whole_row_groups_up_to_the_unit_size(tmp_path_factory, groups, unit_size):
    """A Parquet file's units are consecutive whole row groups, as many as fit ``unit_size`` (a larger group
    alone), covering every row once in order; reading the units gives the file's rows (one unit per group
    made thousands of units of a file written in 100,000-row groups)."""
    path = tmp_path_factory.mktemp("pq") / "g.parquet"
    n = sum(groups)
    table = pa.table({"x": np.arange(n, dtype=np.float64), "red": np.arange(n, dtype=np.uint16) % 256,
                      "green": np.zeros(n, np.uint16), "blue": np.zeros(n, np.uint16)})
    with pq.ParquetWriter(str(path), table.schema) as w:
        pos = 0
        for g in groups:
            w.write_table(table.slice(pos, g))
            pos += g
    src = open_source(str(path), 0)
    assert list(src.row_groups) == groups
    units = src.units(unit_size)
    bounds = np.cumsum([0] + groups).tolist()
    assert units[0].start == 0 and units[-1].stop == n
    assert all(a.stop == b.start for a, b in zip(units, units[1:]))
    for i, u in enumerate(units):
        assert u.start in bounds and u.stop in bounds
        size = u.stop - u.start
        assert size <= unit_size or bounds.index(u.stop) - bounds.index(u.start) == 1  # a larger group alone
        if i + 1 < len(units):  # greedy: the next group would not have fit
            nxt = bounds[bounds.index(u.stop) + 1]
            assert nxt - u.start > unit_size
    chunks = [c for u in units for c in u.point_chunks(7)]
    assert [c.start for c in chunks] == np.cumsum([0] + [len(c) for c in chunks])[:-1].tolist()
    xs = np.concatenate([c.to_arrow().column("x").to_numpy() for c in chunks])
    assert np.array_equal(xs, np.arange(n, dtype=np.float64))
    src.close()

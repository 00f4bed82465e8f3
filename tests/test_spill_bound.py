"""Issue 26's bound on a small grid of synthetic streams: the spill of one read stays within 2 T (1 + ln(N / T)).

``bench/spill_sim.py`` feeds the candidate filter itself (the numba kernel of pass one) with bin keys and ids,
no file; bench/RESULTS_SCALE.md has its whole grid. Here: a few seconds of it, in random order, with the heaps
free to widen and with no heap ever widening (the priority levels alone past 16 words), and with ``--k``.
"""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

_path = Path(__file__).resolve().parents[1] / "bench" / "spill_sim.py"
_spec = importlib.util.spec_from_file_location("spill_sim", _path)
sim = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(sim)

GRID = [(10**5, 1, 0.001), (10**5, 100, 0.01), (10**5, 3_000, 0.05), (3 * 10**5, 10_000, 0.001),
        (3 * 10**5, 600, 0.2), (3 * 10**5, 50, 0.5), (10**6, 200_000, 0.01), (10**6, 2_000, 0.01),
        (10**6, 150, 0.05)]


@pytest.mark.parametrize("widen", [True, False], ids=["heaps-widen", "levels-only"])
@pytest.mark.parametrize("n,bins,ratio", GRID)
def test_random_order_spills_within_the_bound(n, bins, ratio, widen, monkeypatch):
    if not widen:
        monkeypatch.setattr(sim.cand_mod, "WIDEN_BYTES", 0)
    row = sim.simulate(n, bins, ratio=ratio, seed=bins, compact=False)  # the filter's own candidates
    assert 0 < row["spill"] <= row["bound"], row
    assert row["filter_mib"] < 512, row


@pytest.mark.parametrize("k", [3, 40, 300, 2_000])
def test_a_fixed_k_spills_within_the_bound(k):
    row = sim.simulate(10**6, 300, k=k, seed=k, compact=False)
    assert 0 < row["spill"] <= row["bound"], row


@pytest.mark.parametrize("n,bins,ratio", [(10**6, 100, 0.001), (10**6, 3_000, 0.01), (2 * 10**6, 10_000, 0.05),
                                          (10**6, 200_000, 0.0001)])
def test_sorted_order_is_held_within_the_bound_by_compaction(n, bins, ratio, monkeypatch):
    """Each color at once: the filter admits more than the bound (no bound from the counts so far can do
    better), and the spill, compacted at its mark, never holds more than the bound (64K-point chunks)."""
    monkeypatch.setattr(sim, "CHUNK", 1 << 16)
    loose = sim.simulate(n, bins, ratio=ratio, order="sorted", seed=bins, compact=False)
    assert loose["spill"] > loose["bound"], loose
    row = sim.simulate(n, bins, ratio=ratio, order="sorted", seed=bins)
    assert row["written"] == loose["spill"] and row["compactions"] >= 1
    assert row["spill"] <= row["peak"] <= row["bound"], row


def test_the_bound_is_not_met_without_the_levels(monkeypatch):
    """So the grid above measures the levels: with heaps that cannot widen and no levels, K = 166 spills all."""
    monkeypatch.setattr(sim.cand_mod, "WIDEN_BYTES", 0)
    monkeypatch.setattr(sim.cand_mod, "TAU", sim.np.zeros(sim.cand_mod.LEVELS, dtype=sim.np.uint64))
    row = sim.simulate(10**6, 150, ratio=0.05, seed=150, compact=False)
    assert row["spill"] == row["n"] > row["bound"]

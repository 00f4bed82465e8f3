"""The engine-independent core: pure steps, arrays and work units in, arrays out, no I/O policy.

The data flow, one module a step::

    bins       a point's stratum: color depth, color space, quantization -> bin key
    histogram  pass one's counts: per unit (a Tally), per source, global (Histogram)
    quotas     the solve: histogram + Options -> Plan (frozen, JSON)
    cutoffs    each capped bin's priority cutoff: per-unit bottoms, their bounded merge
    selection  the keep decision: plan + cutoffs -> mask of a chunk
    passes     the two loops over a work unit, written once: scan (pass one), select (pass two)
    kernels    the hash and the loops under all of them (numba, in jit.py, loaded on first use; numpy twins)
"""

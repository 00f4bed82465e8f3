"""Human-readable summaries on stdout."""

from __future__ import annotations

import typer


def _lines(d: dict) -> list[str]:
    p = d["plan"]
    kname = "k*" if d["rule"] == "paper" else "K"
    if d["rule"] == "k":
        rule = f"fixed k = {d['k']}"
    elif d["rule"] == "paper":
        rule = f"paper (integer k* closest to T): k* = {d['k']}"
    else:
        rule = f"exact: K = {d['k']}, {d['extra']} bins keep K+1"
    depth = ", ".join(sorted({s["color_depth"] for s in d["sources"]})) or "-"
    out = [
        f"inputs      {len(d['inputs'])} file(s), color depth {depth}",
        f"points N    {d['points']:,}",
        f"bins B      {d['bins']:,} ({d['options']['color_space']}, {d['options']['bits']} quant bits)",
        f"target T    {d['target']:,}" if d["target"] is not None else f"target T    - ({kname} fixed)",
        f"rule        {rule}",
        f"kept        {d['kept']:,} ({100 * d['ratio_achieved']:.3f}% of N)",
        f"bins        {p['bins_capped']:,} capped, {p['bins_kept_whole']:,} kept whole, "
        f"{p['bins_dropped']:,} dropped",
    ]
    if "bin_size" in p:
        b = p["bin_size"]
        out.append(f"bin sizes   min {b['min']:,}, median {b['median']:,.0f}, p90 {b['p90']:,.0f}, "
                   f"p99 {b['p99']:,.0f}, max {b['max']:,}")
    return out


def print_summary(d: dict) -> None:
    lines = _lines(d)
    secs = d["seconds"]
    lines.append(f"time        {secs.get('total', 0):.2f} s (histogram {secs.get('scan', 0):.2f}, "
                 f"cutoffs {secs.get('cutoffs', 0):.2f}, select {secs.get('select', 0):.2f}); "
                 f"peak RSS {d['peak_rss_bytes'] / 2**20:.0f} MiB")
    lines.append(f"output      {d['output']}")
    typer.echo("\n".join(lines))


def print_plan(d: dict) -> None:
    lines = _lines(d)
    lines.append(f"expected    {d['kept']:,} points, about {d['expected_output_bytes'] / 2**20:.1f} MiB "
                 "(at the input's bytes per point)")
    lines.append("plan only: nothing was written")
    typer.echo("\n".join(lines))

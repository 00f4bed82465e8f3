"""What the commands print: the summary as text or JSON, and the summary file."""

from __future__ import annotations

import json
import os
import stat

import click

from prism_stream.errors import OutputError, OutputExists, UsageError


def _n(v) -> str:
    return "-" if v is None else f"{v:,}"


def _lines(d: dict, kept: str = "kept        ") -> list[str]:
    """The summary's lines; ``kept`` labels the kept count (a plan's: what a run would keep)."""
    p = d["plan"]
    if "per_file" in p:
        runs = p["per_file"]
        return [f"inputs      {len(d['inputs'])} file(s), solved one by one (--per-file)",
                f"points N    {_n(d['points'])}",
                f"target T    {_n(d['target'])}",
                f"{kept}{_n(d['kept'])} ({100 * d['ratio_achieved']:.3f}% of N)",
                *[f"  {os.path.basename(r['inputs'][0])}: {_n(r['kept'])} of {_n(r['points'])} points, "
                  f"{_n(r['bins'])} bins, {'k*' if r['rule'] == 'paper' else 'K'} = {_n(r['k'])}"
                  + (f" ({r['plan']['denoise']['removed']:,} outliers removed first)" if "denoise" in r["plan"] else "")
                  for r in runs]]
    kname = "k*" if d["rule"] == "paper" else "K"
    if d["rule"] == "k":
        rule = f"fixed k = {d['k']}"
    elif d["rule"] == "paper":
        rule = f"paper (integer k* closest to T): k* = {d['k']}"
    else:
        rule = f"exact: K = {d['k']}, {d['extra']} bins keep K+1"
    depth = ", ".join(sorted({s["color_depth"] for s in d["sources"]})) or "-"
    query = any(s.get("format") == "sql" for s in d["sources"])
    out = [f"inputs      {'a query' if query else str(len(d['inputs'])) + ' file(s)'}, color depth {depth}"]
    if "denoise" in p:
        out.append(_denoised(p["denoise"]))
    out += [
        f"points N    {_n(d['points'])}{' (after the removal)' if 'denoise' in p else ''}",
        f"bins B      {_n(d['bins'])} ({d['options']['color_space']}, {_quantized(d['options'])})",
        f"target T    {_n(d['target'])}" if d["target"] is not None else f"target T    - ({kname} fixed)",
        f"rule        {rule}",
        f"{kept}{_n(d['kept'])} ({100 * d['ratio_achieved']:.3f}% of N)",
        *([f"space       --space {p['space']['share']}: {_n(p['space']['spatial_points'])} points placed "
           f"spatially, {_n(p['space']['prism_points'])} by PRISM (whose T the rule and bins are)"]
          if "space" in p else []),
        f"bins        {p['bins_capped']:,} capped, {p['bins_kept_whole']:,} kept whole, "
        f"{p['bins_dropped']:,} dropped",
    ]
    if "rank" in p:
        r = p["rank"]
        out.append(f"ranks       {r['column']} of {_n(d['kept'])} points ({r['order']} order): rank < T is the "
                   f"sample for T")
    if "bin_size" in p:
        b = p["bin_size"]
        out.append(f"bin sizes   min {b['min']:,}, median {b['median']:,.0f}, p90 {b['p90']:,.0f}, "
                   f"p99 {b['p99']:,.0f}, max {b['max']:,}")
    return out


def _denoised(c: dict) -> str:
    """The outlier removal's line (``--denoise``)."""
    if not c["points_before"]:
        return f"denoise     {c['method']}: no points to remove"
    temp = ""
    if "temp_bytes_forecast" in c:
        temp = (f"; about {c['temp_bytes_forecast'] / 2**20:,.1f} MiB of temporary disk, "
                f"{c['free_bytes'] / 2**30:,.1f} GiB free")
    return (f"denoise     {c['method']}: removed {c['removed']:,} of {c['points_before']:,} points "
            f"({c['seconds']:.2f} s, two reads of the input; {c['tiles']} tile{'s' if c['tiles'] != 1 else ''}, "
            f"{c['redone_points']:,} points redone against every tile{temp})")


def _quantized(options: dict) -> str:
    step = options.get("quant_step")
    return f"quant step {step:g}" if step is not None else f"{options['quant_bits']} quant bits"


def _reads(p: dict) -> str | None:
    """How the input was read: once with the candidate spill (its size), or twice (and why)."""
    if "reads" not in p:
        return None
    if p["reads"] == 1 and "spill_points" not in p:
        return f"reads       1 ({p.get('why', 'one read')}{'; the spatial share too' if 'space' in p else ''})"
    if p["reads"] == 1:
        size = p.get("spill_bytes", 0)
        shown = f"{size / 2**20:.1f} MiB" if size >= 2**20 else f"{size / 2**10:.1f} KiB"
        more = ""
        if p.get("spill_compactions"):
            held = f", {_n(p['spill_points_peak'])} held at most" if "spill_points_peak" in p else ""
            more = (f"; {_n(p['spill_points_written'])} written{held}, "
                    f"{p['spill_compactions']} compaction{'s' if p['spill_compactions'] > 1 else ''}")
        return (f"reads       1 (candidate spill: {_n(p.get('spill_points', 0))} points, "
                f"{100 * p.get('spill_points', 0) / max(1, p.get('points', 1)):.1f}% of N, {shown}{more})")
    space = " and the spatial share's" if "space" in p and not p.get("why", "").startswith("--space") else ""
    return f"reads       {p['reads']} ({p.get('why', 'two reads')}{space})"


def summary_text(d: dict) -> str:
    lines = _lines(d)
    reads = _reads(d.get("plan", {}))
    if reads:
        lines.append(reads)
    secs = d["seconds"]
    rank = f", ranks {secs['rank']:.2f}" if "rank" in secs else ""
    rank += f", spatial share {secs['space']:.2f}" if "space" in secs else ""
    lines.append(f"time        {secs.get('total', 0):.2f} s (histogram {secs.get('scan', 0):.2f}, "
                 f"cutoffs {secs.get('cutoffs', 0):.2f}{rank}, select {secs.get('select', 0):.2f}); "
                 f"peak RSS {d['peak_rss_bytes'] / 2**20:.0f} MiB")
    temp = d.get("plan", {}).get("temp")
    if temp:
        from prism_stream.run.tempspace import gib  # numpy: not for --help

        lines.append(f"temp        {gib(temp['free_bytes'])} free in {temp['folder']} at the start; spill "
                     f"forecast at most {gib(temp['spill_bytes_bound'])}")
    lines.append(f"output      {d['output']}")
    return "\n".join(lines)


def plan_text(d: dict) -> str:
    lines = _lines(d, kept="would keep  ")  # nothing is kept: the plan says what a run would keep
    if "expected_output_bytes" in d:
        size = d["expected_output_bytes"]
        shown = f"{size / 2**20:.1f} MiB" if size >= 2**20 else f"{size / 2**10:.1f} KiB"
        lines.append(f"expected    {d['kept']:,} points, about {shown} (at the input's bytes per point)")
    space = d.get("options", {}).get("space")
    if space is not None and d.get("target"):
        from prism_stream.core.space import state_bytes  # numpy: not for --help

        lines.append(f"space       --space {space}: a run reads the input once more for the spatial order (held "
                     f"in memory: no read); its scan holds at most {state_bytes(d['target']) / 2**20:,.0f} MiB")
    temp = d.get("plan", {}).get("temp")
    if temp:
        lines += _temp_forecast(temp, d.get("expected_output_bytes", 0), d["plan"], space is not None)
    elif d.get("plan", {}).get("why"):  # no temporary disk to forecast: say why (a small input held in memory)
        lines.append(f"temp        none: {d['plan']['why']} (no spill, no key cache)")
    if d.get("planned_output"):
        lines.append(f"output      {d['planned_output']} (checked as the run checks it)")
    lines.append("plan only: nothing was written")
    return "\n".join(lines)


def _temp_forecast(t: dict, output_bytes: int, reads: dict, space: bool = False) -> list[str]:
    """The plan's forecast of the temporary disk a run takes (:mod:`prism_stream.run.tempspace`): the spill
    the run's filter makes of this input in its order, what random order would give, and what a run does
    with the free space it finds (it decides on the headers' bound, before pass one)."""
    from prism_stream.run.tempspace import gib  # numpy: not for --help

    start = t.get("start", t)
    room = start["free_bytes"] - start["reserve_bytes"] - start.get("rank_bytes", 0) - output_bytes
    if space:  # never the one-read path: pass one, the spatial order and pass two each read the input
        if start["key_cache_bytes"] <= room:
            how = f"a run reads the input three times (--space); the key cache takes {gib(start['key_cache_bytes'])}"
        else:
            how = "a run would be refused: the key cache does not fit (give --temp-dir on a larger disk)"
        return [f"temp        {gib(start['free_bytes'])} free in {start['folder']}: {how}"]
    if reads.get("reads") == 2 and start["key_cache_bytes"] <= room:
        how = f"a run reads the input twice ({reads.get('why')}); the key cache takes {gib(start['key_cache_bytes'])}"
    elif reads.get("reads") != 2 and start["spill_bytes_bound"] <= room:
        how = "a run reads the input once"
        if t.get("spill_bytes_run", 0) > room:
            how += f", and reads it twice when its spill passes {gib(room)}"
    elif start["key_cache_bytes"] <= room:
        how = (f"a run reads the input twice: the spill may take up to {gib(start['spill_bytes_bound'])} "
               f"(the key cache takes {gib(start['key_cache_bytes'])})")
    else:
        how = "a run would be refused: neither the spill nor the key cache fits (give --temp-dir on a larger disk)"
    out = []
    if "spill_points_run" in t:
        out.append(f"spill       {t['spill_points_run']:,} points ({gib(t['spill_bytes_run'])}) when run, the "
                   "run's filter over this input in its order")
        if t.get("spill_compactions_run"):
            out.append(f"{' ' * 12}{t['spill_points_written_run']:,} written, {t['spill_points_peak_run']:,} held at "
                       f"most, {t['spill_compactions_run']} compaction{'s' if t['spill_compactions_run'] > 1 else ''}")
    out.append(f"{'' if out else 'spill       '}{' ' * 12 if out else ''}random order: about "
               f"{t['spill_points_expected']:,} ({gib(t['spill_bytes_expected'])}), at most "
               f"{t['spill_points_bound']:,} ({gib(t['spill_bytes_bound'])})")
    out.append(f"temp        {gib(start['free_bytes'])} free in {start['folder']}: {how}")
    return out


def check_summary_file(path: str | None, inputs, outputs, overwrite: bool) -> None:
    """Before any work: the summary file may be neither an input nor an output, and is new unless --overwrite.

    ``inputs`` are the run's input files (globs and folders expanded),
    ``outputs`` every file or folder the run will write. Paths are compared
    after resolving symbolic links, and existing files by identity (a hard
    link to an input is that input).
    """
    if path is None:
        return
    real = os.path.realpath(path)
    for kind, taken in (("an input", inputs), ("the output", outputs)):
        for t in taken:
            if not t:
                continue
            rt = os.path.realpath(t)
            if rt == real or _same_file(t, path):
                raise UsageError(f"--summary would overwrite {kind} ({t})", path)
    if os.path.isdir(path):
        raise UsageError("--summary is a directory; give a file name", path)
    if _stream(path):
        return  # a device or a pipe (/dev/stderr, a FIFO): written into, replacing nothing
    if os.path.lexists(path) and not overwrite:
        raise OutputExists("already exists (use --overwrite to replace it)", path)
    folder = os.path.dirname(os.path.abspath(path))  # a link to a file is replaced, never its target
    if not os.path.isdir(folder):
        raise OutputError("the summary file's folder does not exist", path)
    try:  # a file made and removed: access() says yes to root where no file can be made (/proc)
        import tempfile

        with tempfile.NamedTemporaryFile(dir=folder, prefix=".prism-summary-probe-"):
            pass
    except OSError as exc:
        raise OutputError(f"the summary file's folder is not writable ({exc.strerror or exc})", path) from None


def _stream(path: str) -> bool:
    """Whether ``path`` is (or links to) something other than a regular file or folder (a device, a FIFO), or
    links through a process's open file (``/dev/stdout`` -> ``/proc/self/fd/1``, whatever it was opened on): a
    stream to write into, never a file to replace."""
    seen = 0
    link = path
    while os.path.islink(link) and seen < 40:  # a link to a descriptor names the descriptor, not a place
        target = os.readlink(link)
        if target.startswith("/proc/") and "/fd/" in target or target.startswith("/dev/fd/"):
            return True
        link = os.path.join(os.path.dirname(link), target)
        seen += 1
    try:
        mode = os.stat(path).st_mode
    except OSError:
        return False
    return not (stat.S_ISREG(mode) or stat.S_ISDIR(mode))


def _same_file(a: str, b: str) -> bool:
    try:
        return os.path.samefile(a, b)
    except OSError:
        return False


def emit(data: dict, *, as_json: bool, summary_file: str | None, quiet: bool, plan: bool = False,
         overwrite: bool = False) -> None:
    """Write the summary file (atomically; a new file unless ``overwrite``), then print the summary."""
    text = json.dumps(data, indent=2)
    if summary_file and _stream(summary_file):
        try:
            with open(summary_file, "a") as f:  # a device, a pipe, a descriptor: written into (after what it holds)
                f.write(text + "\n")
        except OSError as exc:
            raise OutputError(f"cannot write the summary: {exc.strerror or exc}", summary_file) from None
    elif summary_file:
        from prism_stream.run.staging import AtomicFile

        try:
            out = AtomicFile(summary_file)
            try:
                with open(out.tmp, "w") as f:
                    f.write(text + "\n")
                out.commit(replace=overwrite)
            except BaseException:
                out.discard()
                raise
        except FileExistsError:
            raise OutputExists("was created by another process meanwhile (use --overwrite to replace it)",
                               summary_file) from None
        except OSError as exc:
            raise OutputError(f"cannot write the summary: {exc.strerror or exc}", summary_file) from None
    if as_json:
        click.echo(text)
    elif not quiet:
        click.echo(plan_text(data) if plan else summary_text(data))

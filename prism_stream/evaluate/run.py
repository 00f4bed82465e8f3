"""The paper's comparison, run: every method on every dataset, measured alike.

For each dataset (one INPUT argument: a file, glob or Parquet folder) and
each target ratio, every method writes its sample to a temporary Parquet
file through the same sinks as the sampler; the sample is read back and
measured against the streamed input (:mod:`.metrics`). Time and peak RSS
cover the method's own run (reading, sampling, writing), not the metrics.
"""

from __future__ import annotations

import dataclasses
import os
import resource
import shutil
import sys
import tempfile
import time
import warnings
from dataclasses import asdict, dataclass, field


import numpy as np
import pyarrow.compute as pc
import pyarrow.parquet as pq

from .. import __version__
from ..engines.local import sample as prism_sample
from ..errors import PrismWarning, UsageError
from ..run.request import Request
from ..core.histogram import Histogram
from ..core.quotas import Options, solve
from ..formats.parquet import packed_color_column
from .baselines import (nss_sample, random_sample, refuse_nss_k, voxel_centroid_sample, voxel_sample,
                        write_selection)
from .cloud import Cloud, check_coordinates
from .denoise import Denoise, sor_keep_streamed
from .entropy import Strata, entropies, parse_schemes
from .options import PRESETS, EvalOptions
from .metrics import Sample, _color_names, entropy_bits, input_preview, preview, read_sample, sample_distances
from .plots import chroma_histogram

LABELS = {"random": "Random", "voxel": "Voxel grid", "nss": "NSS"}
# the fixed-ratio ablation: chromaticity (rgb vs chroma) x quantization bits, exact mode
ABLATION = tuple((space, bits) for space in ("rgb", "chroma") for bits in (0, 1, 2, 4))
# the paper's Table 3: k fixed, quantization 1/2/4 read both ways (bits dropped, float step), chroma then rgb
PAPER_ABLATION = tuple((kind, q, space) for kind in ("step", "bits") for q in (1, 2, 4)
                       for space in ("chroma", "rgb"))


@dataclass
class Row:
    """One method on one dataset at one target ratio: a line of the paper's Table 1."""

    table: str  # "main" or "ablation"
    method: str
    dataset: str
    target_ratio: float | None  # None: a fixed-k row and the baselines sized after it
    points: int
    target: int
    count: int
    ratio: float
    chamfer: float | None
    hausdorff: float | None
    entropy_input: float
    entropy_output: float
    entropy_gain: float
    seconds: float
    peak_rss_mib: float
    start_rss_mib: float
    added_rss_mib: float  # peak minus what the process held when the method started
    params: dict = field(default_factory=dict)
    strata: str = "rgb 0b"  # the PRISM strata the "sampler" entropy bins follow
    entropy: dict = field(default_factory=dict)  # scheme -> {input, output, gain, bins_input, bins_output}
    chroma: list | None = field(default=None, repr=False)  # hue x saturation counts, for plots
    preview: object = field(default=None, repr=False)  # (m, 3) xyz of up to PREVIEW points, for renders
    preview_rgb: object = field(default=None, repr=False)  # (m, 3) uint8

    def as_dict(self) -> dict:
        d = asdict(self)
        d.pop("preview")
        d.pop("preview_rgb")
        return d


@dataclass
class KRow:
    """One point of the k-sensitivity series: a fixed bin capacity k and what it keeps."""

    dataset: str
    k: int
    points: int
    bins: int
    count: int
    ratio: float
    entropy_output: float
    entropy_gain: float

    def as_dict(self) -> dict:
        return asdict(self)


@dataclass
class Evaluation:
    """Everything one ``prism-stream eval`` run measured."""

    settings: dict
    rows: list = field(default_factory=list)
    ablation: list = field(default_factory=list)
    k_sweep: list = field(default_factory=list)
    inputs: dict = field(default_factory=dict)  # dataset -> {"points", "bins", "entropy", "chroma"}
    version: str = __version__

    def as_dict(self, chroma: bool = False) -> dict:
        def rows(rs):
            out = []
            for r in rs:
                d = r.as_dict()
                if not chroma:
                    d.pop("chroma", None)
                out.append(d)
            return out

        inputs = {k: {kk: vv for kk, vv in v.items() if (chroma or kk != "chroma") and kk != "preview"}
                  for k, v in self.inputs.items()}
        return {"version": self.version, "settings": self.settings, "table": rows(self.rows),
                "ablation": rows(self.ablation), "k_sweep": [r.as_dict() for r in self.k_sweep], "inputs": inputs}


class PeakMemory:
    """Peak resident memory of this process over a block, in MiB.

    On Linux the kernel's high-water mark is reset on entry (``clear_refs``),
    so the peak is the block's own; it includes what the process already held
    (``start``). Elsewhere it falls back to the process's lifetime peak.
    """

    def __enter__(self):
        self.exact = _reset_peak()
        self.start = _status_kib("VmRSS") / 1024 if self.exact else 0.0
        return self

    def __exit__(self, *exc):
        if self.exact:
            self.peak = _status_kib("VmHWM") / 1024
        else:
            kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
            self.peak = (kb / 1024 / 1024) if sys.platform == "darwin" else kb / 1024


def _reset_peak() -> bool:
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        return True
    except OSError:
        return False


def _status_kib(field_name: str) -> float:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(field_name + ":"):
                return float(line.split()[1])
    return 0.0


@dataclass(frozen=True)
class PrismRun:
    """One PRISM configuration of a table row: quota rule, strata."""

    strata: Strata
    mode: str | None = "exact"  # None with a fixed k
    k: int | None = None
    ablation: bool = False  # ablation rows always name their strata
    space: str | None = None  # a spatial share (sample --space)

    @property
    def label(self) -> str:
        quota = f"k={self.k}" if self.k is not None else self.mode
        if self.space is not None:
            quota += f", space={self.space}"
        if self.strata == Strata() and not self.ablation:
            return f"PRISM ({quota})"
        return f"PRISM {self.strata.label} ({quota})"


def evaluate(datasets, request: Request | None = None, options: EvalOptions | None = None, *, log=None,
             **given) -> Evaluation:
    """Run the paper's comparison on each dataset (each a file, glob or Parquet folder).

    Parameters
    ----------
    datasets : list
        One entry per dataset; an entry may itself be a list of files (one cloud).
    request : Request, optional
        PRISM's strata (``color_space``, ``quant_bits``, ``quant_step``), a fixed
        ``k`` for the main table, the ``seed`` and how inputs are read
        (``chunk_size``, ``threads``, ``rgb_columns``, ``color_depth``, ``temp_dir``);
        its ratio or count is not used (each row has its own target).
    options : EvalOptions, optional
        What is compared (:class:`.options.EvalOptions`): ``ratios`` (every method
        aims at T = floor(r N + 0.5) points), ``methods``, ``modes``, the ablation
        (``paper``: Table 3, k fixed at ``ablation_k``; ``ratio``: each ratio,
        exact mode, rgb/chroma x bits 0/1/2/4), ``k_sweep``, ``entropy_bins``
        (the first is the headline), ``baselines`` (``equal-t``: every baseline
        aims at PRISM's T; ``paper``: a centroid grid at ``voxel_size`` and NSS
        at ``nss_per_bin`` points a normal bin), ``denoise`` (``sor:K,STD``),
        ``preset`` (``authors``: the authors' script's pipeline, SOR(100, 2.0),
        chroma, step 1, k = 1, for whatever of those is not given), ``metrics``
        (False skips Chamfer and Hausdorff) and ``sweep`` (``ranks``: rank the
        cloud once up to the largest ratio and take each exact-mode sample as
        its points of rank < T; ``runs``: one run per ratio).
    **given
        Fields of either, overriding them (``ratios=(0.01, 0.1)``, ``k=1``...).
    """
    request_names = {f.name for f in dataclasses.fields(Request)}
    eval_names = {f.name for f in dataclasses.fields(EvalOptions)}
    unknown = sorted(set(given) - request_names - eval_names)
    if unknown:
        raise TypeError(f"unknown option(s) {', '.join(unknown)} for evaluate")
    preset = given.get("preset", options.preset if options is not None else None)
    if preset is not None and preset in PRESETS:  # what is not given takes the preset's value
        given = {**given, **{n: v for n, v in PRESETS[preset].items() if given.get(n) is None}}
    options = EvalOptions.of(options, **{n: v for n, v in given.items() if n in eval_names})
    sampling = {n: v for n, v in given.items() if n in request_names and v is not None}
    if request is None and not {"ratio", "count", "k"} & set(sampling):
        sampling["ratio"] = options.ratios[0]  # a Request has a target: the first run's (each row sets its own)
    request = Request.of(request, **sampling)
    if isinstance(datasets, (str, os.PathLike)):
        datasets = [datasets]
    if not datasets:
        raise UsageError("give at least one input to evaluate")
    ratios, methods, modes, k_sweep = options.ratios, options.methods, options.modes, options.k_sweep
    ablation, ablation_protocol, ablation_k = options.ablation, options.ablation_protocol, options.ablation_k
    baselines, voxel_size, nss_per_bin = options.baselines, options.voxel_size, options.nss_per_bin
    denoise, nss_k, tile_points, metrics = options.denoise, options.nss_k, options.tile_points, options.metrics
    previews, sweep = options.previews, options.sweep
    schemes = parse_schemes(options.entropy_bins)
    color_space, quant_bits, quant_step, k = request.color_space, request.quant_bits, request.quant_step, request.k
    seed, chunk_size, threads = request.seed, request.chunk_size, request.threads
    rgb_columns, color_depth, temp_dir = request.rgb_columns, request.color_depth, request.temp_dir
    strata = Strata(color_space or "rgb", int(quant_bits or 0), None if quant_step is None else float(quant_step))
    cleaner = Denoise.parse(denoise) if denoise else None
    ratios = tuple(float(r) for r in ratios)
    for r in ratios:
        Options(ratio=r)  # validates
    ks = tuple(int(v) for v in k_sweep)
    for v in ks + ((int(k),) if k is not None else ()) + ((int(ablation_k),) if ablation else ()):
        Options(k=v)
    if any(a != "0" for a in options.spaces):
        if k is not None:
            raise UsageError("--space rows are exact-mode samples at each --ratio; not with --k (a fixed cap has no "
                             "target to share)")
        if "exact" not in modes or "prism" not in methods:
            raise UsageError("--space rows are PRISM's exact mode with a spatial share: give --mode exact (or "
                             "exact,paper) and prism among --methods")
    say = log or (lambda msg: None)
    open_kw = dict(chunk_size=chunk_size, threads=threads, rgb_columns=rgb_columns, color_depth=color_depth)
    result = Evaluation(settings=dict(ratios=list(ratios), methods=list(methods), modes=list(modes), seed=int(seed),
                                      ablation=bool(ablation), ablation_protocol=ablation_protocol,
                                      ablation_k=int(ablation_k), k_sweep=list(ks), spaces=list(options.spaces),
                                      entropy_bins=list(schemes),
                                      strata=asdict(strata), k=k, baselines=baselines, voxel_size=voxel_size,
                                      nss_per_bin=nss_per_bin, denoise=cleaner.label if cleaner else None,
                                      preset=preset, nss_k=nss_k, tile_points=tile_points, metrics=bool(metrics),
                                      chunk_size=chunk_size, color_depth=color_depth, sweep=sweep))
    ctx = dict(seed=seed, voxel_size=voxel_size, nss_k=nss_k, nss_per_bin=nss_per_bin, tile_points=tile_points,
               metrics=metrics, open_kw=open_kw, temp_dir=temp_dir, schemes=schemes, baselines=baselines,
               previews=previews)
    with tempfile.TemporaryDirectory(prefix="prism-stream-eval-", dir=temp_dir) as tmp:
        for entry in datasets:
            info: dict = {}
            if cleaner is not None:
                entry, info, kw = _denoised(entry, cleaner, tmp, open_kw, say, tile_points)
            else:
                kw = open_kw
            with Cloud(entry, **{**kw, "label": info.pop("label", None)}) as cloud:
                if metrics or any(a != "0" for a in options.spaces):  # distances and --space rows: an input
                    check_coordinates(cloud.sources)  # without coordinates refused here, not after the methods
                if "nss" in methods:  # from the cloud's header, before its rows
                    refuse_nss_k(nss_k, cloud.points, cloud.files[0])
                hist = cloud.histogram()
                h_in = entropy_bits(hist.counts)
                result.inputs[cloud.name] = {"files": [os.path.abspath(f) for f in cloud.files],
                                             "points": cloud.points, "bins": hist.bins, "entropy": h_in,
                                             "chroma": chroma_histogram(hist).tolist(), **info}
                if previews:
                    result.inputs[cloud.name]["preview"] = input_preview(cloud)
                say(f"{cloud.name}: {cloud.points:,} points, {hist.bins:,} colors, H = {h_in:.3f} bits")
                c = dict(ctx, cloud=cloud, tmp=tmp, open_kw=kw)
                if sweep == "ranks" and k is None and "prism" in methods and "exact" in modes and len(ratios) > 1:
                    c["ranked"] = _rank_once(c, strata, max(ratios), len(ratios))
                    say(f"  PRISM exact at {len(ratios)} ratios: one rank run up to {max(ratios):g} "
                        f"({c['ranked']['seconds']:.2f} s), each sample its points of rank < T")
                if k is not None:
                    groups = [None]
                else:
                    groups = list(ratios)
                for r in groups:
                    before = len(result.rows)
                    if k is not None:
                        first = _run_one(c, "main", None, "prism", PrismRun(strata, None, int(k)), strata)
                        result.rows.append(first)
                        _say(say, first)
                        count = first.count
                    else:
                        count = None
                    for m in methods:
                        if m == "prism":
                            if k is None:
                                for mode in modes:
                                    row = _run_one(c, "main", r, m, PrismRun(strata, mode), strata)
                                    result.rows.append(row)
                                    _say(say, row)
                                for a in options.spaces if "exact" in modes else ():
                                    if a == "0":
                                        continue
                                    row = _run_one(c, "main", r, m, PrismRun(strata, "exact", space=a), strata)
                                    result.rows.append(row)
                                    _say(say, row)
                            continue
                        row = _run_one(c, "main", r, m, None, strata, count=count)
                        result.rows.append(row)
                        _say(say, row)
                    same = indistinct_gains(result.rows[before:])
                    if same:
                        warnings.warn(PrismWarning(f"{cloud.name}: {same}"), stacklevel=2)
                if ablation:
                    for run, r in _ablation_runs(ablation_protocol, ablation_k, ratios):
                        row = _run_one(c, "ablation", r, "prism", run, run.strata)
                        result.ablation.append(row)
                        _say(say, row)
                for kk in ks:
                    plan = solve(hist, Options(k=kk))
                    h_out = entropy_bits(plan.quotas)
                    result.k_sweep.append(KRow(cloud.name, kk, plan.points, plan.bins, plan.kept,
                                               plan.kept / plan.points if plan.points else 0.0, h_out, h_out - h_in))
    return result


def _prism_options(c: dict, strata: Strata) -> dict:
    open_kw = c["open_kw"]
    step = {"quant_step": strata.step} if strata.step is not None else {}
    return dict(**step, color_space=strata.color_space, quant_bits=strata.bits, seed=c["seed"],
                chunk_size=open_kw["chunk_size"], threads=open_kw["threads"], rgb_columns=open_kw["rgb_columns"],
                color_depth=open_kw["color_depth"], overwrite=True, temp_dir=c["temp_dir"])


def _rank_once(c: dict, strata: Strata, ratio: float, rows: int) -> dict:
    """Rank the cloud up to ``ratio`` (exact mode): every smaller ratio's sample is a prefix of these ranks."""
    out = os.path.join(c["tmp"], "ranked.parquet")
    t0 = time.perf_counter()
    s = prism_sample(c["cloud"].files, out, ratio=ratio, rank="prism_rank", **_prism_options(c, strata))
    seconds = time.perf_counter() - t0
    table = pq.read_table(out)  # read once: every ratio's sample is a filter of it
    os.unlink(out)
    return {"table": table, "seconds": seconds, "rows": rows, "bins": s.bins}


def _from_ranks(ranked: dict, ratio: float, points: int, out: str) -> int:
    """The exact sample at ``ratio`` as the rows of rank < T of the ranked table, written to ``out``; T."""
    t = Options(ratio=ratio).target(points)
    table = ranked["table"]
    pq.write_table(table.filter(pc.less(table.column("prism_rank"), t)).drop_columns(["prism_rank"]), out)
    return t


def _ablation_runs(protocol: str, k: int, ratios):
    if protocol == "paper":
        for kind, q, space in PAPER_ABLATION:
            strata = Strata(space, q, None) if kind == "bits" else Strata(space, 0, float(q))
            yield PrismRun(strata, None, int(k), ablation=True), None
    else:
        for r in ratios:
            for space, bits in ABLATION:
                yield PrismRun(Strata(space, bits), "exact", ablation=True), r


def _say(say, row) -> None:
    say(f"  {row.method:<28} {row.count:>9,} pts ({row.ratio:.3%})  CD {_fmt(row.chamfer)}  "
        f"HD {_fmt(row.hausdorff)}  dH {row.entropy_gain:+.3f}  {row.seconds:.2f} s")


def _denoised(entry, cleaner: Denoise, tmp: str, open_kw: dict, say, tile_points: int = 2_000_000):
    """The dataset with statistical outliers removed (streamed, :func:`.denoise.sor_keep_streamed`), as a
    Parquet file in ``tmp``; and what it cost."""
    t0 = time.perf_counter()
    with Cloud(entry, **open_kw) as cloud:
        work = tempfile.mkdtemp(prefix="sor-", dir=tmp)
        keep, facts = sor_keep_streamed(cloud, work, cleaner.neighbours, cleaner.std_ratio, tile_points)
        out = os.path.join(tmp, f"denoised-{len(os.listdir(tmp))}.parquet")
        cloud.histogram()
        depth = {cloud.decisions.get(s.ordinal, "8") for s in cloud.sources}
        write_selection(cloud, out, lambda c: keep[c.offset:c.offset + len(c)],
                        {"software": f"prism-stream {__version__}", "denoise": cleaner.label}, overwrite=True)
        name = cloud.name
        # the Parquet copy keeps the source's color column names (PLY diffuse_red...): read those back
        schema = pq.read_schema(out)
        columns = open_kw["rgb_columns"] or _color_names(schema, cloud, out)
        if len(columns) == 1 and packed_color_column(schema) == columns[0]:
            columns = None  # a packed word kept whole (beside an alpha column): the copy's reader finds it
        elif len(columns) != 3:
            raise UsageError("--denoise cannot re-read a packed color word from its cleaned Parquet copy beside "
                             "columns named red, green or blue (a PCD whose own fields have those names keeps its "
                             "rgb word packed); convert the file to three color channels first", cloud.files[0])
    seconds = time.perf_counter() - t0
    removed = facts["removed"]
    points = len(keep)
    del keep
    shutil.rmtree(work, ignore_errors=True)
    say(f"{name}: {cleaner.label} removed {removed:,} of {points:,} points in {seconds:.2f} s "
        f"(streamed: {facts['tiles']} tiles, {facts['redone_points']:,} points redone against every tile)")
    decided = depth.pop() if len(depth) == 1 else "auto"
    kw = dict(open_kw, color_depth=decided if decided in ("8", "16") else open_kw["color_depth"],
              rgb_columns=list(columns) if columns else None)
    info = {"label": name, "denoise": {"method": cleaner.label, "points_before": int(points),
                                       "removed": removed, "seconds": round(seconds, 4), "in_memory": False,
                                       "tiles": facts["tiles"], "redone_points": facts["redone_points"]}}
    return out, info, kw


def indistinct_gains(rows) -> str | None:
    """Why the methods' entropy gains at one target are equal, when they are: every sample's points fell in as
    many distinct bins as it has points (T below the input's distinct colors), so each output's entropy is
    log2 T and the gain cannot tell the methods apart. None otherwise."""
    schemes = [(r, e) for r in rows for e in r.entropy.values()]
    counts = {r.count for r in rows}
    if len(rows) < 2 or len(counts) != 1 or not schemes or any(e.get("bins_output") != r.count for r, e in schemes):
        return None
    return (f"every method's sample of {counts.pop():,} points holds as many distinct colors "
            "as points, so each output's entropy is log2 of its count and the entropy gains are the same: at this "
            "target the gain cannot tell the methods apart (a larger ratio, or coarser entropy bins, can)")


def _fmt(v) -> str:
    return "-" if v is None else f"{v:.4g}"


def _run_one(c: dict, table: str, ratio, method: str, run: PrismRun | None, strata: Strata,
             count: int | None = None) -> Row:
    cloud, tmp, open_kw, seed = c["cloud"], c["tmp"], c["open_kw"], c["seed"]
    tag = f"{table}-{method}-{run.label if run else ''}-{ratio}-{count}"
    out = os.path.join(tmp, "".join(ch if ch.isalnum() else "_" for ch in tag) + ".parquet")
    params: dict = {}
    files = cloud.files
    centroids = None
    target_kw = {"count": count} if count is not None else {"ratio": ratio}
    with PeakMemory() as mem:
        t0 = time.perf_counter()
        ranked = c.get("ranked") if method == "prism" and table == "main" and run.mode == "exact" \
            and run.k is None and run.strata == strata and run.space is None else None
        if ranked is not None:
            target = _from_ranks(ranked, ratio, cloud.points, out)
            params = {"mode": run.mode, "color_space": run.strata.color_space, "quant_bits": run.strata.bits,
                      "quant_step": run.strata.step, "bins": ranked["bins"], "from_ranks": True,
                      "rank_run_seconds": round(ranked["seconds"], 4)}
        elif method == "prism":
            quota = {"k": run.k} if run.k is not None else {"ratio": ratio, "mode": run.mode}
            if run.space is not None:
                quota["space"] = run.space
            s = prism_sample(files, out, **quota, **_prism_options(c, run.strata))
            target = s.target
            params = {"mode": run.mode, "color_space": run.strata.color_space, "quant_bits": run.strata.bits,
                      "quant_step": run.strata.step, "bins": s.bins,
                      ("k" if run.k is not None else "k_star" if run.mode == "paper" else "K"): s.k}
            if run.space is not None:
                params["space"] = run.space
        elif method == "random":
            res = random_sample(files, out, **target_kw, seed=seed, overwrite=True, **open_kw)
        elif method == "voxel":
            if c["baselines"] == "paper":
                centroids = voxel_centroid_sample(files, voxel_size=c["voxel_size"], **open_kw)
                res = centroids.result
            else:
                kw = {"voxel_size": c["voxel_size"]} if c["voxel_size"] else target_kw
                res = voxel_sample(files, out, overwrite=True, **kw, **open_kw)
        else:
            size = {"per_bin": c["nss_per_bin"]} if c["baselines"] == "paper" else target_kw
            res = nss_sample(files, out, **size, seed=seed, k=c["nss_k"], tile_points=c["tile_points"],
                             overwrite=True, temp_dir=c["temp_dir"], **open_kw)
        seconds = time.perf_counter() - t0
    if ranked is not None:  # the row's share of the one rank run, plus its own prefix read
        seconds += ranked["seconds"] / ranked["rows"]
    if method != "prism":
        target, params = res.target, dict(res.params)
    if target is None:
        target = Options(ratio=ratio).target(cloud.points) if ratio is not None else 0
    hist = cloud.histogram()
    if centroids is not None:
        keys = (centroids.rgb[:, 0].astype(np.uint32) << 16) | (centroids.rgb[:, 1].astype(np.uint32) << 8) \
            | centroids.rgb[:, 2].astype(np.uint32)
        sample = Sample("", centroids.xyz, Histogram.from_keys(keys), keys)
    else:
        sample = read_sample(out, cloud)
    chamfer = hausdorff = None
    if c["metrics"] and sample.points:
        d = sample_distances(cloud, sample.xyz, subset=centroids is None)
        chamfer, hausdorff = d.chamfer, d.hausdorff
    ent = entropies(hist, sample.histogram, c["schemes"], strata)
    head = ent[c["schemes"][0]]
    label = run.label if run else LABELS[method] + (" (paper size)" if c["baselines"] == "paper" and
                                                     method in ("voxel", "nss") else "")
    if os.path.exists(out):
        os.unlink(out)
    xy, rgb = preview(sample.xyz, sample.keys) if c["previews"] else (None, None)
    return Row(table=table, method=label, dataset=cloud.name, target_ratio=ratio, points=cloud.points,
               target=int(target), count=sample.points, ratio=sample.points / cloud.points if cloud.points else 0.0,
               chamfer=chamfer, hausdorff=hausdorff, entropy_input=head["input"], entropy_output=head["output"],
               entropy_gain=head["gain"], seconds=round(seconds, 4), peak_rss_mib=round(mem.peak, 1),
               start_rss_mib=round(mem.start, 1), added_rss_mib=round(mem.peak - mem.start, 1), params=params,
               strata=strata.label, entropy=ent, chroma=chroma_histogram(sample.histogram).tolist(),
               preview=xy, preview_rgb=rgb)

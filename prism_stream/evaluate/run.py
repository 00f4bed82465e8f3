"""The paper's comparison, run: every method on every dataset, measured alike.

For each dataset (one INPUT argument: a file, glob or Parquet folder) and
each target ratio, every method writes its sample to a temporary Parquet
file through the same sinks as the sampler; the sample is read back and
measured against the streamed input (:mod:`.metrics`). Time and peak RSS
cover the method's own run (reading, sampling, writing), not the metrics.
"""

from __future__ import annotations

import os
import resource
import sys
import tempfile
import time
from dataclasses import asdict, dataclass, field


from .. import __version__
from ..engines.local import sample as prism_sample
from ..errors import UsageError
from ..core.quotas import Options, solve
from .baselines import nss_sample, random_sample, voxel_sample
from .cloud import DEFAULT_CHUNK, Cloud
from .metrics import color_entropy_gain, entropy_bits, read_sample, sample_distances
from .plots import chroma_histogram

METHODS = ("prism", "random", "voxel", "nss")
MODES = ("exact", "paper")
LABELS = {"random": "Random", "voxel": "Voxel grid", "nss": "NSS"}
# the paper's ablation: chromaticity (rgb vs chroma) and quantization bits
ABLATION = tuple((space, bits) for space in ("rgb", "chroma") for bits in (0, 1, 2, 4))


@dataclass
class Row:
    """One method on one dataset at one target ratio: a line of the paper's Table 1."""

    table: str  # "main" or "ablation"
    method: str
    dataset: str
    target_ratio: float
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
    chroma: list | None = field(default=None, repr=False)  # hue x saturation counts, for plots

    def as_dict(self) -> dict:
        return asdict(self)


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

        inputs = {k: {kk: vv for kk, vv in v.items() if chroma or kk != "chroma"} for k, v in self.inputs.items()}
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


def _label(method: str, mode: str | None = None, space: str = "rgb", bits: int = 0, ablation: bool = False) -> str:
    if method != "prism":
        return LABELS[method]
    if ablation:
        return f"PRISM {space} {bits}b ({mode})"
    return f"PRISM ({mode})"


def _parse(values, allowed, what) -> tuple:
    items = tuple(v.strip().lower() for v in values if v.strip())
    bad = [v for v in items if v not in allowed]
    if bad or not items:
        raise UsageError(f"--{what} takes a comma-separated list of {', '.join(allowed)}, not {','.join(values)!r}")
    return tuple(dict.fromkeys(items))


def evaluate(datasets, *, ratios=(0.01,), methods=METHODS, modes=("exact",), seed: int = 0,
             ablation: bool = False, k_sweep=(), voxel_size: float | None = None, nss_k: int = 10,
             tile_points: int = 2_000_000, metrics: bool = True, chunk_size: int = DEFAULT_CHUNK,
             threads: int = 1, rgb_columns=None, color_depth: str = "auto", temp_dir: str | None = None,
             log=None) -> Evaluation:
    """Run the paper's comparison on each dataset (each a file, glob or Parquet folder).

    Parameters
    ----------
    datasets : list
        One entry per dataset; an entry may itself be a list of files (one cloud).
    ratios : sequence of float
        Target ratios; every method aims at T = floor(r N + 0.5) points.
    methods : subset of ``("prism", "random", "voxel", "nss")``
    modes : subset of ``("exact", "paper")``
        The quota rules PRISM runs under (one row each).
    ablation : bool
        Also run PRISM over color space (rgb, chroma) x quantization bits (0, 1, 2, 4).
    k_sweep : sequence of int
        Fixed bin capacities k for the k-sensitivity series (from the plan alone).
    voxel_size : float or None
        A fixed voxel size instead of searching one per target.
    metrics : bool
        False skips Chamfer and Hausdorff (one input pass per row); entropy stays.
    """
    if isinstance(datasets, (str, os.PathLike)):
        datasets = [datasets]
    if not datasets:
        raise UsageError("give at least one input to evaluate")
    methods = _parse(methods, METHODS, "methods")
    modes = _parse(modes, MODES, "mode")
    ratios = tuple(float(r) for r in ratios)
    for r in ratios:
        Options(ratio=r)  # validates
    ks = tuple(int(k) for k in k_sweep)
    for k in ks:
        Options(k=k)
    say = log or (lambda msg: None)
    open_kw = dict(chunk_size=chunk_size, threads=threads, rgb_columns=rgb_columns, color_depth=color_depth)
    result = Evaluation(settings=dict(ratios=list(ratios), methods=list(methods), modes=list(modes), seed=int(seed),
                                      ablation=bool(ablation), k_sweep=list(ks), voxel_size=voxel_size, nss_k=nss_k,
                                      tile_points=tile_points, metrics=bool(metrics), chunk_size=chunk_size,
                                      color_depth=color_depth))
    with tempfile.TemporaryDirectory(prefix="prism-stream-eval-", dir=temp_dir) as tmp:
        for entry in datasets:
            with Cloud(entry, **open_kw) as cloud:
                hist = cloud.histogram()
                h_in = entropy_bits(hist.counts)
                result.inputs[cloud.name] = {"files": [os.path.abspath(f) for f in cloud.files],
                                             "points": cloud.points, "bins": hist.bins, "entropy": h_in,
                                             "chroma": chroma_histogram(hist).tolist()}
                say(f"{cloud.name}: {cloud.points:,} points, {hist.bins:,} colors, H = {h_in:.3f} bits")
                runs = []
                for r in ratios:
                    for m in methods:
                        if m == "prism":
                            runs += [("main", r, m, mode, "rgb", 0) for mode in modes]
                        else:
                            runs.append(("main", r, m, None, "rgb", 0))
                    if ablation:
                        runs += [("ablation", r, "prism", "exact", s, b) for s, b in ABLATION]
                for table, r, m, mode, space, bits in runs:
                    row = _run_one(cloud, tmp, table, r, m, mode, space, bits, seed, voxel_size, nss_k,
                                   tile_points, metrics, open_kw, temp_dir)
                    (result.rows if table == "main" else result.ablation).append(row)
                    say(f"  {row.method:<24} r={r:<6g} {row.count:>9,} pts  CD {_fmt(row.chamfer)}  "
                        f"HD {_fmt(row.hausdorff)}  dH {row.entropy_gain:+.3f}  {row.seconds:.2f} s")
                for k in ks:
                    plan = solve(hist, Options(k=k))
                    h_out = entropy_bits(plan.quotas)
                    result.k_sweep.append(KRow(cloud.name, k, plan.points, plan.bins, plan.kept,
                                               plan.kept / plan.points if plan.points else 0.0, h_out, h_out - h_in))
    return result


def _fmt(v) -> str:
    return "-" if v is None else f"{v:.4g}"


def _run_one(cloud: Cloud, tmp: str, table, ratio, method, mode, space, bits, seed, voxel_size, nss_k, tile_points,
             metrics, open_kw, temp_dir) -> Row:
    out = os.path.join(tmp, f"{method}-{mode or ''}-{space}-{bits}-{ratio:g}.parquet")
    params: dict = {}
    files = cloud.files
    with PeakMemory() as mem:
        t0 = time.perf_counter()
        if method == "prism":
            s = prism_sample(files, out, ratio=ratio, mode=mode, color_space=space, quant_bits=bits, seed=seed,
                             chunk_size=open_kw["chunk_size"], threads=open_kw["threads"],
                             rgb_columns=open_kw["rgb_columns"], color_depth=open_kw["color_depth"],
                             overwrite=True, temp_dir=temp_dir)
            target = s.target
            params = {"mode": mode, "color_space": space, "quant_bits": bits, "bins": s.bins,
                      ("k_star" if mode == "paper" else "K"): s.k}
        elif method == "random":
            res = random_sample(files, out, ratio=ratio, seed=seed, overwrite=True, **open_kw)
        elif method == "voxel":
            kw = {"voxel_size": voxel_size} if voxel_size else {"ratio": ratio}
            res = voxel_sample(files, out, overwrite=True, **kw, **open_kw)
        else:
            res = nss_sample(files, out, ratio=ratio, seed=seed, k=nss_k, tile_points=tile_points, overwrite=True,
                             temp_dir=temp_dir, **open_kw)
        seconds = time.perf_counter() - t0
    if method != "prism":
        target, params = res.target, dict(res.params)
    target = Options(ratio=ratio).target(cloud.points) if target is None else target
    sample = read_sample(out, cloud)
    hist = cloud.histogram()
    chamfer = hausdorff = None
    if metrics and sample.points:
        d = sample_distances(cloud, sample.xyz)
        chamfer, hausdorff = d.chamfer, d.hausdorff
    h_in = entropy_bits(hist.counts)
    h_out = entropy_bits(sample.histogram.counts)
    os.unlink(out)
    return Row(table=table, method=_label(method, mode, space, bits, table == "ablation"), dataset=cloud.name,
               target_ratio=ratio, points=cloud.points, target=int(target), count=sample.points,
               ratio=sample.points / cloud.points if cloud.points else 0.0, chamfer=chamfer, hausdorff=hausdorff,
               entropy_input=h_in, entropy_output=h_out, entropy_gain=color_entropy_gain(hist, sample.histogram),
               seconds=round(seconds, 4), peak_rss_mib=round(mem.peak, 1), start_rss_mib=round(mem.start, 1),
               added_rss_mib=round(mem.peak - mem.start, 1),
               params=params, chroma=chroma_histogram(sample.histogram).tolist())

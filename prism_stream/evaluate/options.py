"""What ``prism-stream eval`` compares, declared once: :class:`EvalOptions`, beside the sampling options of
its :class:`~prism_stream.run.request.Request` (strata, k, seed, reading). The command line makes its
options from these fields (``cli/options.py``), as it does from the Request's."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from ..errors import UsageError
from ..run.request import PRESETS, option  # noqa: F401 - evaluate.options.PRESETS: sample's presets

METHODS = ("prism", "random", "voxel", "nss")
MODES = ("exact", "paper")
BASELINES = ("equal-t", "paper")
SWEEPS = ("ranks", "runs")
PROTOCOLS = ("paper", "ratio")
EVAL = "Evaluation"


def _listed(value, kind, name: str) -> tuple:
    """A comma-separated text (the command line's) or a sequence, as a tuple of ``kind``."""
    items = [v for v in value.split(",") if v.strip()] if isinstance(value, str) else list(value)
    try:
        return tuple(kind(v) for v in items)
    except (TypeError, ValueError):
        raise UsageError(f"{name}: give comma-separated {kind.__name__}s, not {value!r}") from None


def _shares(value) -> tuple:
    """``--space A,...`` as their normalized texts (each checked as ``sample --space`` checks it)."""
    from ..core.space import parse_share, share_text

    out = []
    for v in _listed(value, str, "--space"):
        try:
            a = parse_share(v.strip())
        except ValueError as exc:
            raise UsageError(str(exc)) from None
        text = share_text(a)
        if text not in out:
            out.append(text)
    return tuple(out)


def _chosen(value, known: tuple, what: str) -> tuple:
    """A comma-separated text or a sequence of names from ``known``, each once, in order."""
    values = value.split(",") if isinstance(value, str) else list(value)
    items = tuple(v.strip().lower() for v in values if v.strip())
    bad = [v for v in items if v not in known]
    if bad or not items:
        raise UsageError(f"--{what} takes a comma-separated list of {', '.join(known)}, not {','.join(values)!r}")
    return tuple(dict.fromkeys(items))


@dataclass(frozen=True)
class EvalOptions:
    """The evaluation's own settings; each field's help is the command line's."""

    ratios: tuple = option((0.01,), "--ratio", "-r", panel=EVAL,
                           help="Target ratio(s), comma-separated, e.g. 0.01,0.05,0.1.")
    methods: tuple = option(METHODS, "--methods", panel=EVAL, help="Methods, comma-separated.")
    modes: tuple = option(("exact",), "--mode", panel=EVAL,
                          help="PRISM quota rule(s): exact, paper, or exact,paper.")
    ablation: bool = option(False, "--ablation", panel=EVAL,
                            help="Also run the paper's ablation (Table 3): chroma and rgb x quantization 1, 2, 4 (as "
                                 "steps and as bits), k fixed.")
    ablation_protocol: str = option("paper", "--ablation-protocol", panel=EVAL,
                                    help="paper: k fixed (--ablation-k); ratio: each --ratio in exact mode, "
                                         "rgb/chroma x bits 0/1/2/4.")
    ablation_k: int = option(10, "--ablation-k", panel=EVAL, help="The fixed k of the paper-protocol ablation.")
    entropy_bins: tuple = option(("rgb8",), "--entropy-bins", panel=EVAL,
                                 help="Entropy histogram(s): rgb8, sampler, rgb-grid, hue-sat, comma-separated, or all "
                                      "(first = headline).")
    baselines: str = option("equal-t", "--baselines", panel=EVAL,
                            help="equal-t: baselines aim at PRISM's T; paper: centroid voxel grid at --voxel-size, "
                                 "NSS at --nss-per-bin.")
    nss_per_bin: int | None = option(None, "--nss-per-bin", panel=EVAL,
                                     help="NSS at its own size: points kept per normal bin (--baselines paper).")
    denoise: str | None = option(None, "--denoise", panel=EVAL, metavar="sor:K,STD",
                                 help="Remove statistical outliers first (Open3D's rule, streamed in XY tiles of "
                                      "--tile-points).")
    preset: str | None = option(None, "--preset", panel=EVAL,
                                help="authors: the authors' script (sor:100,2.0, chroma, step 1, k = 1) for whatever "
                                     "is not given.")
    spaces: tuple = option((), "--space", panel=EVAL, metavar="A,...",
                           help="PRISM with a spatial share (sample --space): one exact-mode row per share A at each "
                                "ratio, e.g. 0.25,0.5,0.75,0.9 (0 is PRISM's own row); --plots draws the trade-off "
                                "curve.")
    k_sweep: tuple = option((), "--k-sweep", panel=EVAL, metavar="K,...",
                            help="Fixed bin capacities, e.g. 1,2,5,10,20: the k-sensitivity series (ratio against k).")
    voxel_size: float | None = option(None, "--voxel-size", panel=EVAL,
                                      help="Fixed voxel size for the voxel grid (default: searched to land near each "
                                           "target).")
    nss_k: int = option(10, "--nss-k", panel=EVAL, help="Neighbours per normal estimate (NSS).")
    tile_points: int = option(2_000_000, "--tile-points", panel=EVAL, help="Points per NSS normal tile.")
    sweep: str = option("ranks", "--sweep", panel=EVAL, choices=SWEEPS,
                        help="PRISM exact rows at several ratios: ranks: rank once up to the largest ratio and take "
                             "each sample as the points of rank < T (same rows, one run); runs: one run per ratio.")
    metrics: bool = option(True, "--distances/--no-distances", panel=EVAL,
                           help="Chamfer and Hausdorff distances (one input pass per row); --no-distances skips "
                                "them.")
    previews: bool = option(False, panel=EVAL, help="Keep small previews of each cloud and sample (for figures).")

    def __post_init__(self):
        if self.preset is not None and self.preset not in PRESETS:
            raise UsageError(f"--preset takes {', '.join(PRESETS)}, not {self.preset!r}")
        object.__setattr__(self, "ratios", _listed(self.ratios, float, "--ratio"))
        object.__setattr__(self, "k_sweep", _listed(self.k_sweep, int, "--k-sweep"))
        object.__setattr__(self, "spaces", _shares(self.spaces))
        object.__setattr__(self, "methods", _chosen(self.methods, METHODS, "methods"))
        object.__setattr__(self, "modes", _chosen(self.modes, MODES, "mode"))
        for name, value, known in (("--baselines", self.baselines, BASELINES), ("--sweep", self.sweep, SWEEPS),
                                   ("--ablation-protocol", self.ablation_protocol, PROTOCOLS)):
            if value not in known:
                raise UsageError(f"{name} takes {' or '.join(known)}, not {value!r}")
        if self.baselines == "paper":
            if "voxel" in self.methods and self.voxel_size is None:
                raise UsageError("--baselines paper runs the voxel grid at a fixed size: give --voxel-size")
            if "nss" in self.methods and self.nss_per_bin is None:
                raise UsageError("--baselines paper runs NSS at its own size: give --nss-per-bin")

    @staticmethod
    def of(options: "EvalOptions | None" = None, **changes) -> "EvalOptions":
        return EvalOptions(**changes) if options is None else dataclasses.replace(options, **changes)

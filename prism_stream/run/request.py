"""The request: every option of a run, declared once and validated once.

The command line, the Python API (``prism_stream.sample(..., **options)``),
the ``sql`` command and the Dask driver all build one :class:`Request` and
pass it whole. Each field carries its own help text and, where it has one,
its command-line flag; ``cli/options.py`` turns these into the options of
every command, so an option is written in one place only.

The sampling options (what decides the output) are :attr:`Request.options`,
the :class:`~prism_stream.core.quotas.Options` the plan records; the others
say how to run and what to write, and never change which points are kept.
"""

from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass, field

from ..core.names import COLOR_DEPTHS, COLOR_SPACES, DEFAULT_CHUNK, MODES
from ..errors import UsageError

TARGET = "Target (give one)"
BINNING = "Binning"
RUNNING = "Running (never changes the output)"
CLEANING = "Cleaning"
# the authors' released script (PRISM.py): Open3D SOR(100, 2.0), chromaticity, step 1.0, k = 1 (eval --preset too)
PRESETS = {"authors": dict(denoise="sor:100,2.0", color_space="chroma", quant_step=1.0, k=1)}
WRITING = "Output"
ORDERS = ("input", "rank")


def option(default, *flags: str, help: str, panel: str, choices=None, metavar: str | None = None, cli: bool = True):
    """A Request field with what the command line needs to offer it."""
    return field(default=default, metadata={"flags": flags, "help": help, "panel": panel, "choices": choices,
                                            "metavar": metavar, "cli": cli and bool(flags)})


def cores() -> int:
    """The cores this process may run on (``taskset``, a container's CPU set), not every core of the machine."""
    try:
        return len(os.sched_getaffinity(0)) or 1
    except (AttributeError, OSError):  # no affinity on this platform
        return os.cpu_count() or 1


@dataclass(frozen=True)
class Request:
    """What to sample and how; see each field's help (``prism-stream sample --help`` prints the same text)."""

    ratio: float | None = option(None, "--ratio", "-r", panel=TARGET,
                                 help="Target ratio of the input's N points, in (0, 1].")
    count: int | None = option(None, "--count", "-n", panel=TARGET, help="Target number of points T.")
    k: int | None = option(None, "--k", "-k", panel=TARGET, help="Fixed cap: every bin keeps at most K points.")
    mode: str = option("exact", "--mode", panel=TARGET, choices=MODES,
                       help="exact: exactly T points (K or K+1 per bin); paper: the paper's single integer k* "
                            "whose total is closest to T.")
    space: str | None = option(None, "--space", panel=TARGET, metavar="A",
                               help="Spend this share of the target (0..1) on a spatially even sample: one point "
                                    "a cell of a grid halved level by level, the rarest coarse color in each, "
                                    "interleaved with PRISM so that every prefix is a sample (docs/SPEC.md section "
                                    "9). 0: PRISM alone (the default); 1: the spatial sample alone. Needs a target "
                                    "in exact mode (a target past 574,969 points sends every point to the "
                                    "temporary folder, about 105 bytes a point; with --dask, the output's "
                                    "staging folder); "
                                    "reads the input (or runs the query) once more.")
    color_space: str = option("rgb", "--color-space", panel=BINNING, choices=COLOR_SPACES,
                              help="rgb: the 8-bit channels (the paper); chroma: channels normalized by r+g+b "
                                   "(the reference code).")
    quant_bits: int = option(0, "--quant-bits", panel=BINNING, help="Drop this many low bits of each channel (0..7).")
    quant_step: float | None = option(None, "--quant-step", panel=BINNING, metavar="Q",
                                      help="Quantize each channel with a float step instead, as the authors' script "
                                           "does: floor(c / Q + 0.5), Q >= 1 (not with --quant-bits).")
    color_depth: str = option("auto", "--color-depth", panel=BINNING, choices=COLOR_DEPTHS,
                              help="16-bit color fields (LAS, PLY ushort, Parquet integers): auto (8-bit if every "
                                   "value <= 255), 8, or 16 (v >> 8).")
    seed: int = option(0, "--seed", panel=BINNING, help="Seed of the point priorities (0..2^64-1).")
    denoise: str | None = option(None, "--denoise", panel=CLEANING, metavar="sor:K,STD",
                                 help="Remove statistical outliers first, by Open3D's rule (K neighbours, a STD-sigma "
                                      "cut; the authors' script: sor:100,2.0), then sample the cleaned cloud. Exact "
                                      "and streamed: two more reads of the input and about 50 bytes a point of "
                                      "temporary disk. Local engine only.")
    preset: str | None = option(None, "--preset", panel=CLEANING, choices=tuple(PRESETS),
                                help="authors: the authors' script's pipeline (--denoise sor:100,2.0 --color-space "
                                     "chroma --quant-step 1 --k 1) for whatever of those is not given (--k only "
                                     "when no target is).")
    preset_filled: tuple | None = option(None, panel=CLEANING, cli=False,
                                         help="The fields the preset filled (None: not applied yet; Request.of "
                                              "applies it knowing what was given, a Request made directly takes "
                                              "it for every field at its default).")
    chunk_size: int = option(DEFAULT_CHUNK, "--chunk-size", panel=RUNNING, help="Points read at a time.")
    threads: int | None = option(None, "--threads", panel=RUNNING,
                                 help="Decoder threads (LAZ, Parquet) and read-ahead (default: every core it may "
                                      "use); a large local LAZ file decodes in that many worker processes.")
    rgb_columns: tuple | None = option(None, "--rgb-columns", panel=RUNNING, metavar="R,G,B",
                                       help="Color column names of Parquet inputs and queries, comma-separated "
                                            "(default red,green,blue, any case).")
    temp_dir: str | None = option(None, "--temp-dir", panel=RUNNING, metavar="DIR",
                                  help="Folder for the candidate spill or the key cache (default: system temp).")
    reads: str = option("auto", "--reads", panel=RUNNING, choices=("auto", "one", "two"),
                        help="auto: read the input once where its size is known up front: held in memory "
                             "up to PRISM_STREAM_MEMORY_POINTS points (default 1048576), else keeping the "
                             "points that may be selected in a temporary spill (on Dask, local Parquet inputs "
                             "are read twice: faster there); one: once wherever it can; two: read it twice "
                             "(pass two decodes it again; 4 bytes a point of temporary space).")
    progress: bool = option(False, panel=RUNNING, help="Progress bars on stderr.", cli=False)
    overwrite: bool = option(False, "--overwrite", panel=WRITING, help="Replace an existing output.")
    flag: str | None = option(None, "--flag", panel=WRITING, metavar="NAME",
                              help="Keep every point and add a keep flag instead: a column / vertex property / "
                                   "extra-bytes dimension of this name, or `withheld` (LAS withheld bit set on "
                                   "dropped points).")
    geometry: bool = option(False, "--geometry", panel=WRITING,
                            help="Parquet output: add a WKB point column `geometry`, which makes the output "
                                 "GeoParquet 1.1 (`geo` metadata with the input's CRS as PROJJSON).")
    output_format: str | None = option(None, "--format", panel=WRITING, metavar="FORMAT",
                                       help="Directory mode: format of each output (parquet, las, laz, copc.laz, ply, xyz); "
                                            "default: each input's own where it is one of these, else Parquet.")
    per_file: bool = option(False, "--per-file", panel=WRITING,
                            help="Directory mode: solve each file on its own instead of one global solve.")
    columns: str = option("same", "--columns", panel=WRITING, choices=("same", "union", "intersection"),
                          help="Inputs whose columns differ, into one Parquet output: same (refuse, naming the "
                               "columns), union (every column; null where a file lacks it) or intersection (the "
                               "columns every file has). Types that differ are widened (float -> double).")
    keep: tuple | None = option(None, "--keep", panel=WRITING, metavar="COL,...",
                                help="Write only these columns (properties, dimensions), and the coordinates and "
                                     "colors (which every output keeps). LAS/LAZ/COPC from LAS: extra-bytes "
                                     "dimensions not kept are left out; the point format's own are in every "
                                     "record, written as 0 (not the return numbers). An output folder: each "
                                     "input's own names.")
    drop: tuple | None = option(None, "--drop", panel=WRITING, metavar="COL,...",
                                help="Leave these columns out (not the coordinates or colors); in LAS/LAZ/COPC "
                                     "output a dropped dimension of the point format itself is written as 0 "
                                     "(e.g. --drop gps_time,user_data).")
    scale: tuple | None = option(None, "--scale", panel=WRITING, metavar="S|SX,SY,SZ",
                                 help="LAS/LAZ/COPC output converted from another format: the coordinate scale "
                                      "(one value for x, y and z, or three; e.g. 0.001). Default: a power of ten "
                                      "as fine as the input's precision (a millionth of the extent; float32: no "
                                      "coarser than its spacing), reaching far past the extent.")
    offset: tuple | None = option(None, "--offset", panel=WRITING, metavar="X,Y,Z",
                                  help="With --scale: the coordinate offset (default: the middle of the extent, "
                                       "on the scale's grid).")
    rank: str | None = option(None, panel=WRITING, cli=False,
                              help="Add each kept point's PRISM rank in a column of this name (the `rank` command "
                                   "names it prism_rank): the points of rank < T are the exact sample for T.")
    order: str = option("input", "--order", panel=WRITING, choices=ORDERS,
                        help="rank: write the points in rank order, a progressive file whose first T rows are "
                             "the exact sample for T; input: keep input order.")

    command: tuple | None = option(None, help="The command line that asked for this run (the outputs' provenance "
                                   "records it).", panel=RUNNING, cli=False)

    def __post_init__(self):
        if isinstance(self.rgb_columns, str):
            object.__setattr__(self, "rgb_columns", split_columns(self.rgb_columns))
        elif self.rgb_columns is not None:
            names = tuple(self.rgb_columns)
            if len(names) != 3 or not all(isinstance(n, str) and n for n in names):
                raise UsageError(f"--rgb-columns needs three names (red,green,blue), not {self.rgb_columns!r}")
            object.__setattr__(self, "rgb_columns", names)
        for name in ("chunk_size", "threads"):
            value = getattr(self, name)
            if value is not None and (isinstance(value, bool) or not isinstance(value, int) or value < 1):
                raise UsageError(f"--{name.replace('_', '-')} must be a positive integer, not {value!r}")
        for name in ("keep", "drop"):
            value = getattr(self, name)
            if value is not None:
                names = tuple(v.strip() for v in value.split(",")) if isinstance(value, str) else tuple(value)
                if not names or not all(isinstance(n, str) and n for n in names):
                    raise UsageError(f"--{name} needs column names, comma-separated, not {value!r}")
                object.__setattr__(self, name, names)
        if self.keep is not None and self.drop is not None:
            raise UsageError("give --keep or --drop, not both")
        for name, count in (("scale", (1, 3)), ("offset", (3,))):
            value = getattr(self, name)
            if value is not None:
                object.__setattr__(self, name, _numbers(value, f"--{name}", count, positive=name == "scale"))
        if self.offset is not None and self.scale is None:
            raise UsageError("--offset needs --scale (the offset is a point of the scale's grid)")
        if self.flag is not None and not str(self.flag).strip():
            raise UsageError("--flag needs a name")
        if self.preset is not None and self.preset_filled is None:  # made directly: defaults take its values
            defaults = {f.name: f.default for f in dataclasses.fields(Request)}
            filled = []
            for name, value in with_preset(self.preset, {}, self).items():
                if getattr(self, name) == defaults[name]:
                    object.__setattr__(self, name, value)
                    filled.append(name)
            object.__setattr__(self, "preset_filled", tuple(filled))
        if self.rank is not None and self.ratio is None and self.count is None and self.k is None:
            object.__setattr__(self, "ratio", 1.0)  # ranks of every point
        object.__setattr__(self, "_options", self._sampling_options())  # validated once, here
        if self.rank is not None:
            if self.k is not None or self.mode != "exact":
                raise UsageError("ranks exist in exact mode only: with --mode paper or --k the sample for T + 1 "
                                 "need not contain the sample for T, so no order makes every prefix a sample")
            if self.flag is not None:
                raise UsageError("--flag writes every point; a ranked output holds the points of rank < T")
        if self.order not in ORDERS:
            raise UsageError(f"--order must be one of {', '.join(ORDERS)}, not {self.order!r}")
        if self.order == "rank" and self.rank is None:
            raise UsageError("--order rank needs ranks (the `rank` command)")

    @property
    def las_grid(self) -> tuple | None:
        """(scales, offsets or None) of LAS output converted from other formats, from --scale/--offset."""
        if self.scale is None:
            return None
        scales = self.scale * 3 if len(self.scale) == 1 else self.scale
        return tuple(scales), self.offset

    @property
    def selection(self) -> tuple | None:
        """("keep" or "drop", names) of --keep/--drop, or None."""
        if self.keep is not None:
            return "keep", self.keep
        if self.drop is not None:
            return "drop", self.drop
        return None

    @property
    def options(self):
        """The sampling options (:class:`~prism_stream.core.quotas.Options`): what the plan records."""
        return self._options

    def _sampling_options(self):
        from ..core.quotas import Options

        return Options(ratio=self.ratio, count=self.count, k=self.k, mode=self.mode, color_space=self.color_space,
                       quant_bits=_int(self.quant_bits, "--quant-bits"), quant_step=self.quant_step,
                       color_depth=self.color_depth,
                       seed=_int(self.seed, "--seed"), denoise=self.denoise, space=self.space)

    @property
    def workers(self) -> int:
        """Threads to use: the option, or every core this process may run on."""
        return self.threads if self.threads is not None else cores()

    def open_options(self) -> dict:
        """What a format's reader takes from the request."""
        return {"threads": self.workers, "rgb_columns": self.rgb_columns}

    @staticmethod
    def of(request: "Request | None" = None, **options) -> "Request":
        """``request`` with ``options`` changed, or a new request from ``options`` alone."""
        names = {f.name for f in dataclasses.fields(Request)}
        if "format" in options:  # the command line's --format (`format` is a Python builtin, hence the field's name)
            if "output_format" in options:
                raise TypeError("give format or output_format, not both (the same option, --format)")
            options["output_format"] = options.pop("format")
        unknown = sorted(set(options) - names)
        if unknown:
            raise TypeError(f"unknown option(s) {', '.join(unknown)}; a Request has {', '.join(sorted(names))}")
        if options.get("preset") is not None:  # applied where it is given, once (not to a request it made)
            given = with_preset(options["preset"], options, request)
            options = {**given, "preset_filled": tuple(n for n in PRESETS[options["preset"]]
                                                       if n in given and options.get(n) is None)}
        elif request is not None and request.preset_filled and "k" in request.preset_filled and \
                any(options.get(n) is not None for n in ("ratio", "count", "rank")):
            # a target given later replaces the k the preset filled (rank: ranks take none)
            options = {**options, "k": options.get("k"), "preset_filled": tuple(
                n for n in request.preset_filled if n != "k")}
        return Request(**options) if request is None else dataclasses.replace(request, **options)


def with_preset(preset: str, given: dict, request: "Request | None" = None) -> dict:
    """``given`` (options by name; None: not given) with the preset's value for each of its options not given
    here nor set in ``request``; its ``k`` only when no target (ratio, count, k) is."""
    if preset not in PRESETS:
        raise UsageError(f"--preset takes {', '.join(PRESETS)}, not {preset!r}")
    defaults = {f.name: f.default for f in dataclasses.fields(Request)}

    def chosen(name):
        if given.get(name) is not None:
            return True
        return request is not None and getattr(request, name) != defaults[name]

    out = {n: v for n, v in given.items() if v is not None or n not in PRESETS[preset]}
    skip = {"k"} if any(chosen(n) for n in ("ratio", "count", "k", "rank")) else set()  # ranks take no --k
    if chosen("quant_bits"):
        skip.add("quant_step")  # bits given: no step beside them
    for name, value in PRESETS[preset].items():
        if not chosen(name) and name not in skip:
            out[name] = value
    return out


def _int(value, flag: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        try:
            if float(value) != int(value):
                raise ValueError
            value = int(value)
        except (TypeError, ValueError, OverflowError):
            raise UsageError(f"{flag} must be an integer, not {value!r}") from None
    return value


def split_columns(value: str) -> tuple:
    names = tuple(v.strip() for v in value.split(","))
    if len(names) != 3 or not all(names):
        raise UsageError(f"--rgb-columns needs three names (red,green,blue), not {value!r}")
    return names


def _numbers(value, option: str, counts: tuple, positive: bool = False) -> tuple:
    """A comma-separated string (or a sequence) of finite numbers, as many as one of ``counts``."""
    import math

    import numpy as np

    one = not isinstance(value, (str, bool)) and np.ndim(value) == 0  # scale=0.001 (or a numpy number) from
    try:  # Python: one number, as --scale 0.001 is
        parts = [value] if one else [p.strip() for p in value.split(",")] if isinstance(value, str) else list(value)
        numbers = tuple(float(p) for p in parts)
    except (TypeError, ValueError):
        raise UsageError(f"{option} takes numbers separated by commas, not {value!r}") from None
    if len(numbers) not in counts:
        raise UsageError(f"{option} takes {' or '.join(map(str, counts))} value(s), not {len(numbers)}: {value!r}")
    if not all(math.isfinite(v) for v in numbers) or (positive and not all(v > 0 for v in numbers)):
        raise UsageError(f"{option} takes {'positive ' if positive else ''}finite numbers, not {value!r}")
    return numbers

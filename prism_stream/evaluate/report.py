"""An evaluation as tables: text laid out like the paper's Table 1, CSV and JSON files."""

from __future__ import annotations

import csv
import io
import json
import os

from ..errors import OutputError, UsageError
from ..formats import AtomicFile

# (header, row field, format) of the text table, in the paper's Table 1 order
COLUMNS = (
    ("Method", "method", "{}"),
    ("Dataset", "dataset", "{}"),
    ("Ratio", "ratio", "{:.3%}"),
    ("CD", "chamfer", "{:.4g}"),
    ("HD", "hausdorff", "{:.4g}"),
    ("Entropy gain", "entropy_gain", "{:+.3f}"),
    ("Time (s)", "seconds", "{:.2f}"),
    ("Points", "count", "{:,}"),
    ("Peak RSS (MiB)", "peak_rss_mib", "{:.0f}"),
    ("Added RSS (MiB)", "added_rss_mib", "{:.0f}"),
)
K_COLUMNS = (
    ("Dataset", "dataset", "{}"),
    ("k", "k", "{}"),
    ("Bins", "bins", "{:,}"),
    ("Points", "count", "{:,}"),
    ("Ratio", "ratio", "{:.3%}"),
    ("Entropy gain", "entropy_gain", "{:+.3f}"),
)
CSV_FIELDS = ("table", "method", "dataset", "target_ratio", "points", "target", "count", "ratio", "chamfer",
              "hausdorff", "entropy_input", "entropy_output", "entropy_gain", "seconds", "peak_rss_mib",
              "start_rss_mib", "added_rss_mib", "strata", "params", "entropy")


def _cell(fmt: str, value) -> str:
    return "-" if value is None else fmt.format(value)


def _get(r, f):
    """A row's field; ``entropy.SCHEME`` reads the gain under that entropy scheme."""
    if f.startswith("entropy."):
        e = r["entropy"] if isinstance(r, dict) else r.entropy
        return e.get(f.split(".", 1)[1], {}).get("gain")
    return r[f] if isinstance(r, dict) else getattr(r, f)


def columns_for(schemes) -> tuple:
    """Table 1's columns, with one entropy-gain column per scheme when there are several."""
    schemes = list(schemes or ["rgb8"])
    if len(schemes) == 1:
        return tuple((f"Entropy gain ({schemes[0]})" if f == "entropy_gain" else h, f, fmt) for h, f, fmt in COLUMNS)
    out = []
    for h, f, fmt in COLUMNS:
        if f == "entropy_gain":
            out += [(f"dH {s}", f"entropy.{s}", "{:+.3f}") for s in schemes]
        else:
            out.append((h, f, fmt))
    return tuple(out)


def text_table(rows, columns=COLUMNS) -> str:
    """A fixed-width table of row objects (or dicts); datasets are separated by a blank line."""
    get = _get
    cells = [[_cell(fmt, get(r, f)) for _, f, fmt in columns] for r in rows]
    widths = [max([len(h)] + [len(c[i]) for c in cells]) for i, (h, _, _) in enumerate(columns)]
    lines = ["  ".join(h.ljust(w) for (h, _, _), w in zip(columns, widths)).rstrip(),
             "  ".join("-" * w for w in widths)]
    previous = None
    for r, c in zip(rows, cells):
        key = (get(r, "dataset"), get(r, "target_ratio") if "target_ratio" in _fields(r) else None)
        if previous is not None and key != previous:
            lines.append("")
        previous = key
        lines.append("  ".join(v.ljust(w) if i < 2 else v.rjust(w) for i, (v, w) in enumerate(zip(c, widths)))
                     .rstrip())
    return "\n".join(lines)


def _fields(r) -> set:
    return set(r) if isinstance(r, dict) else set(vars(r))


def _ablation_title(settings: dict) -> str:
    if settings.get("ablation_protocol", "ratio") == "paper":
        return (f"Ablation (the paper's Table 3): k = {settings.get('ablation_k', 10)}, chroma and rgb, "
                "quantization 1/2/4 as steps (q) and as bits (b)")
    return "Ablation: PRISM color space x quantization bits at each target ratio (exact mode)"


def render(evaluation) -> str:
    """The whole evaluation as text: Table 1, then the ablation and the k sweep if run."""
    cols = columns_for(evaluation.settings.get("entropy_bins"))
    parts = ["Table 1: methods compared (CD, HD in the input's units; entropy gain in bits, "
             "definitions in docs/EVALUATION.md)", text_table(evaluation.rows, cols)]
    if evaluation.ablation:
        parts += ["", _ablation_title(evaluation.settings), text_table(evaluation.ablation, cols)]
    if evaluation.k_sweep:
        parts += ["", "k sensitivity: fixed bin capacity k (from the plan; rgb 8-bit bins)",
                  text_table(evaluation.k_sweep, K_COLUMNS)]
    return "\n".join(parts)


def markdown_table(rows, columns=COLUMNS) -> str:
    """A Markdown table of row objects or dicts."""
    get = _get
    out = ["| " + " | ".join(h for h, _, _ in columns) + " |",
           "|" + "|".join("---" if i < 2 else "---:" for i in range(len(columns))) + "|"]
    for r in rows:
        out.append("| " + " | ".join(_cell(fmt, get(r, f)) for _, f, fmt in columns) + " |")
    return "\n".join(out)


def to_markdown(evaluation) -> str:
    """Table 1, the ablation and the k sweep as Markdown (what docs/EVALUATION.md shows)."""
    d = evaluation if isinstance(evaluation, dict) else evaluation.as_dict()
    cols = columns_for(d["settings"].get("entropy_bins"))
    parts = ["### Table 1", "", markdown_table(d["table"], cols)]
    if d["ablation"]:
        parts += ["", "### Ablation", "", _ablation_title(d["settings"]) + ".", "", markdown_table(d["ablation"], cols)]
    if d["k_sweep"]:
        parts += ["", "### k sensitivity", "", markdown_table(d["k_sweep"], K_COLUMNS)]
    return "\n".join(parts) + "\n"


def to_csv(evaluation) -> str:
    """Table 1 and ablation rows, one line each (``table`` says which); k-sweep rows after them."""
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=CSV_FIELDS + ("k", "bins"), extrasaction="ignore", lineterminator="\n")
    w.writeheader()
    for r in list(evaluation.rows) + list(evaluation.ablation):
        d = r.as_dict()
        d["params"] = json.dumps(d["params"], sort_keys=True)
        d["entropy"] = json.dumps({s: round(e["gain"], 6) for s, e in d["entropy"].items()}, sort_keys=True)
        w.writerow(d)
    for r in evaluation.k_sweep:
        d = r.as_dict()
        w.writerow({"table": "k_sweep", "method": "PRISM (k)", **d})
    return buf.getvalue()


def to_json(evaluation) -> str:
    return json.dumps(evaluation.as_dict(), indent=2) + "\n"


def check_out(path: str) -> str:
    """The table format of ``path`` (``.csv``, ``.json`` or ``.md``), or a usage error."""
    ext = os.path.splitext(str(path))[1].lower()
    if ext not in (".csv", ".json", ".md"):
        raise UsageError("--out must end in .csv, .json or .md", str(path))
    folder = os.path.dirname(os.path.abspath(str(path)))
    if not os.path.isdir(folder):
        raise OutputError("output folder does not exist", str(path))
    return ext


def check_folder(folder: str) -> None:
    """``--plots FOLDER``: a folder, or a name free for one (made with its parents)."""
    if os.path.exists(folder) and not os.path.isdir(folder):
        raise OutputError("--plots names a file, not a folder for the figures", str(folder))


def write(evaluation, path: str, overwrite: bool = True) -> str:
    """Write the tables to ``path`` (``.csv``, ``.json`` or ``.md``), atomically."""
    ext = check_out(path)
    if os.path.exists(path) and not overwrite:
        raise UsageError("already exists", path)
    text = {".csv": to_csv, ".json": to_json, ".md": to_markdown}[ext](evaluation)
    f = AtomicFile(path)
    try:
        with open(f.tmp, "w", newline="") as fh:
            fh.write(text)
        f.commit()
    except OSError as exc:
        f.discard()
        raise OutputError(f"cannot write the table: {exc.strerror or exc}", path) from None
    return path

"""`make mutate`: mutation testing with cosmic-ray, bounded, reported to docs/MUTATION.md.

Run by hand before a release, not in CI (it takes tens of minutes):

    make mutate                       # every target in tests/mutation/targets.toml
    make mutate TARGETS="bins kernels"  # some of them

The checkout is copied to a scratch folder first and mutated there, so the
working tree is never touched (cosmic-ray edits files in place) and a run
can be interrupted safely. Each target's mutants run only that target's
tests. Survivors are explained in tests/mutation/survivors.toml (matched by
module, operator and the mutated line's text): either equivalent (``why``)
or killed since by tests written from the run's findings (``killed_by``).
``--verify`` checks each such claim: it applies the survivor's diff to a
scratch copy and runs the ``killed_by`` tests, which must fail. The report
gives the raw score, the score with verified kills, and marks any survivor
without an explanation, which is the work a release leaves to do.
"""

from __future__ import annotations

import argparse
import ast
import datetime
import hashlib
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
HERE = Path(__file__).resolve().parent


def definition_spans(path: Path, names: list[str]) -> list[tuple[int, int]]:
    """Line spans of the top-level functions/classes (or ``Class.method``) named in ``names``."""
    tree = ast.parse(path.read_text())
    spans = []
    for node in tree.body:
        if not isinstance(node, (ast.FunctionDef, ast.ClassDef, ast.AsyncFunctionDef)):
            continue
        if node.name in names:
            spans.append((node.lineno, node.end_lineno))
        if isinstance(node, ast.ClassDef):
            for sub in node.body:
                if isinstance(sub, (ast.FunctionDef, ast.AsyncFunctionDef)) and f"{node.name}.{sub.name}" in names:
                    spans.append((sub.lineno, sub.end_lineno))
    return spans


def copy_checkout(dest: Path) -> None:
    """The tracked and new (not ignored) files of the working tree, as they are now."""
    files = subprocess.run(["git", "ls-files", "-co", "--exclude-standard", "-z"], cwd=ROOT, check=True,
                           capture_output=True).stdout.decode().split("\0")
    for f in filter(None, files):
        src = ROOT / f
        if src.is_file():
            (dest / f).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src, dest / f)


def cosmic_config(target: dict, settings: dict, python: str) -> str:
    tests = " ".join(target["tests"])
    modules = ", ".join(f'"{m}"' for m in target["modules"])
    select = f" -k '{target['select']}'" if target.get("select") else ""
    command = f"{python} -m pytest -x -q -p no:xdist -p no:cacheprovider {tests}{select}"
    return (f'[cosmic-ray]\nmodule-path = [{modules}]\ntimeout = {float(settings.get("timeout", 120))}\n'
            f'excluded-modules = []\ntest-command = "{command}"\n\n'
            '[cosmic-ray.distributor]\nname = "local"\n')


def skip_outside(session: Path, work: Path, target: dict, settings: dict) -> None:
    """Mark as skipped the mutants outside ``only`` and those of excluded operators."""
    from cosmic_ray.work_db import WorkDB, use_db
    from cosmic_ray.work_item import WorkerOutcome, WorkResult

    only = target.get("only")
    spans = {m: definition_spans(work / m, only) if only else None for m in target["modules"]}
    if only:
        found = {n for m in target["modules"] for n in only if definition_spans(work / m, [n])}
        missing = sorted(set(only) - found)
        if missing:
            sys.exit(f"tests/mutation/targets.toml: target {target['name']!r} names {missing}, found in none of "
                     f"{target['modules']} (moved? update the paths)")
    included = [re.compile(p) for p in settings.get("include-operators", [".*"])]
    fraction = float(target.get("sample", settings.get("sample", 1.0)))
    skip = []
    with use_db(str(session), WorkDB.Mode.open) as db:
        for item in db.work_items:
            for m in item.mutations:
                path = Path(m.module_path).as_posix()
                rel = os.path.relpath(path, work) if os.path.isabs(path) else path
                line = m.start_pos[0]
                inside = spans.get(rel) is None or any(a <= line <= b for a, b in spans[rel])
                realistic = any(p.fullmatch(m.operator_name) for p in included)
                # a deterministic sample (same mutants every run of the same code), to bound the time
                key = f"{rel}:{m.start_pos}:{m.operator_name}:{m.occurrence}".encode()
                sampled = int.from_bytes(hashlib.sha256(key).digest()[:8], "big") < fraction * 2 ** 64
                if not (inside and realistic and sampled):
                    skip.append(item.job_id)
        db.set_multiple_results(skip, WorkResult(worker_outcome=WorkerOutcome.SKIPPED))


def results(session: Path, work: Path) -> list[dict]:
    from cosmic_ray.work_db import WorkDB, use_db
    from cosmic_ray.work_item import TestOutcome, WorkerOutcome

    out = []
    with use_db(str(session), WorkDB.Mode.open) as db:
        items = {i.job_id: i for i in db.work_items}
        for job_id, r in db.results:
            if r.worker_outcome == WorkerOutcome.SKIPPED:
                continue
            m = items[job_id].mutations[0]
            path = Path(m.module_path).as_posix()
            rel = os.path.relpath(path, work) if os.path.isabs(path) else path
            text = (work / rel).read_text().splitlines()[m.start_pos[0] - 1].strip()
            out.append({"module": rel, "line": m.start_pos[0], "operator": m.operator_name,
                        "occurrence": m.occurrence, "text": text,
                        "killed": r.test_outcome != TestOutcome.SURVIVED,
                        "outcome": str(r.test_outcome or r.worker_outcome), "diff": r.diff or ""})
    return out


def explanation(survivor: dict, explanations: list[dict]) -> dict | None:
    """The survivors.toml entry that matches a survivor (module, operator regex, a piece of the line), if any."""
    for e in explanations:
        if e["module"] == survivor["module"] and re.search(e.get("operator", ".*"), survivor["operator"]) \
                and e["line_contains"] in survivor["text"]:
            return e
    return None


def explain(survivor: dict, explanations: list[dict]) -> str | None:
    e = explanation(survivor, explanations)
    if e is None:
        return None
    if e.get("killed_by"):
        tests = ", ".join(e["killed_by"])
        verified = survivor.get("verified")
        state = {True: "verified: the mutant applied, they fail", False: "**NOT VERIFIED: they pass with the "
                 "mutant applied**", None: "not verified yet (run.py --verify)"}[verified]
        return f"Killed since by {tests} ({state}).{' ' + e['why'] if e.get('why') else ''}"
    return e["why"]


def mutated_line(diff: str) -> str:
    plus = [ln[1:].strip() for ln in diff.splitlines() if ln.startswith("+") and not ln.startswith("+++")]
    return plus[0] if plus else ""


def report(rows: dict, seconds: dict, explanations: list[dict], path: Path, settings_used: dict,
           targets_used: list, runs: list) -> int:
    total = sum(len(r) for r in rows.values())
    killed = sum(x["killed"] for r in rows.values() for x in r)
    survivors = [x for r in rows.values() for x in r if not x["killed"]]
    entries = [explanation(x, explanations) or {} for x in survivors]
    since = sum(1 for x, e in zip(survivors, entries) if e.get("killed_by") and x.get("verified") is True)
    equivalent = sum(1 for e in entries if e.get("why") and not e.get("killed_by"))
    final = killed + since
    lines = ["# Mutation testing", "",
             "Written by `make mutate` (tests/mutation/run.py, cosmic-ray); run by hand before a release.",
             "Targets, paths and the tests that judge them: tests/mutation/targets.toml; survivors' explanations:",
             "tests/mutation/survivors.toml.", ""]
    for r in runs:
        lines.append(f"Run {r['date']} ({r['cores']} cores): `{r['command']}` (targets: {', '.join(r['targets'])}).")
    lines += ["",
              f"**Raw score: {killed} of {total} mutants killed ({100 * killed / max(1, total):.1f}%)** by the tests "
              "as they were when the run started.", "",
              f"**With the tests written from this run's survivors: {final} of {total} ({100 * final / max(1, total):.1f}%)"
              f"**; each of those {since} kills verified by applying the mutant's diff to a scratch copy and running "
              "the tests named (`run.py --verify`).", "",
              f"**Leaving out the {equivalent} equivalent survivors (explained below): {final} of {total - equivalent} "
              f"({100 * final / max(1, total - equivalent):.1f}%).**", "",
              f"Operators: {', '.join(settings_used.get('include-operators', ['all']))}. `sample` is the "
              "share of the mutants in scope that were run (a deterministic choice).", "",
             "| target | sample | mutants | killed | survived | raw score | killed since | equivalent | final score "
             "| minutes |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    samples = {t["name"]: t.get("sample", settings_used.get("sample", 1.0)) for t in targets_used}
    for name, r in rows.items():
        k = sum(x["killed"] for x in r)
        gone = [explanation(x, explanations) or {} for x in r if not x["killed"]]
        since_t = sum(1 for x in r if not x["killed"] and x.get("verified") is True
                      and (explanation(x, explanations) or {}).get("killed_by"))
        equiv_t = sum(1 for e in gone if e.get("why") and not e.get("killed_by"))
        lines.append(f"| {name} | {samples.get(name, '?')} | {len(r)} | {k} | {len(r) - k} | "
                     f"{100 * k / max(1, len(r)):.1f}% | {since_t} | {equiv_t} | "
                     f"{100 * (k + since_t) / max(1, len(r) - equiv_t):.1f}% | "
                     f"{f'{seconds[name] / 60:.1f}' if seconds.get(name) is not None else 'n/a'} |")
    findings = HERE / "findings.md"  # what the run's survivors showed, beyond missing tests (kept by hand)
    if findings.exists():
        lines += ["", "## Findings", "", findings.read_text().strip()]
    unexplained = 0
    lines += ["", "## Survivors", ""]
    for name, r in rows.items():
        for s in (x for x in r if not x["killed"]):
            why = explain(s, explanations)
            unexplained += why is None
            lines += [f"- `{s['module']}:{s['line']}` {s['operator']}: `{s['text']}` -> `{mutated_line(s['diff'])}`",
                      f"  - {why or '**UNEXPLAINED**: a test is missing, or add the reason to survivors.toml'}"]
    if not any(not x["killed"] for r in rows.values() for x in r):
        lines.append("None.")
    lines += ["", f"Unexplained survivors: {unexplained}.", ""]
    path.write_text("\n".join(lines))
    return unexplained


def verify(saved: dict, explanations: list[dict], python: str, again: bool = False) -> None:
    """Apply each survivor claimed killed (``killed_by``) to a scratch copy and run its tests; record the outcome.

    Claims verified before are skipped unless ``again``."""
    scratch = Path(tempfile.mkdtemp(prefix="prism-verify-"))
    work = scratch / ROOT.name
    try:
        copy_checkout(work)
        subprocess.run(["git", "init", "-q"], cwd=work, check=True)
        env = dict(os.environ, PYTHONPATH=str(work), NUMBA_CACHE_DIR=str(work / ".numba-cache"),
                   PYTHONDONTWRITEBYTECODE="1")
        env.pop("CI", None)
        for name, rows in saved["rows"].items():
            for x in rows:
                e = explanation(x, explanations) if not x["killed"] else None
                if not e or not e.get("killed_by") or (x.get("verified") is True and not again):
                    continue
                diff = x["diff"].split("\n", 1)[1] if x["diff"].startswith("--- mutation diff ---") else x["diff"]
                patch = work / ".mutant.diff"
                patch.write_text(diff if diff.endswith("\n") else diff + "\n")
                # the code may have moved since the run (fixes, new lines): the mutated line is found by its
                # text, the context lines around it may differ
                applied = subprocess.run(["git", "apply", "-C0", str(patch)], cwd=work, capture_output=True,
                                         text=True)
                if applied.returncode != 0:
                    x["verified"] = False
                    print(f"verify: {x['module']}:{x['line']}: the diff no longer applies ({applied.stderr.strip()})")
                    continue
                try:
                    run = subprocess.run([python, "-m", "pytest", "-x", "-q", "-p", "no:xdist", "-p", "no:cacheprovider",
                                          *e["killed_by"]], cwd=work, env=env, capture_output=True, text=True,
                                         timeout=600)
                    x["verified"] = run.returncode == 1  # tests failed; not 4/5 (bad node id, nothing collected)
                finally:
                    subprocess.run(["git", "apply", "-R", "-C0", str(patch)], cwd=work, check=True)
                print(f"verify: {name}: {x['module']}:{x['line']} {x['operator']}: "
                      f"{'killed' if x['verified'] else 'NOT KILLED'} by {', '.join(e['killed_by'])}", flush=True)
    finally:
        shutil.rmtree(scratch, ignore_errors=True)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("targets", nargs="*", help="target names (default: all)")
    parser.add_argument("--report", default=str(ROOT / "docs" / "MUTATION.md"))
    parser.add_argument("--keep", action="store_true", help="keep the scratch copy (path printed)")
    parser.add_argument("--merge", action="store_true",
                        help="keep the saved results of the targets not run this time (docs/MUTATION.json)")
    parser.add_argument("--report-only", action="store_true",
                        help="rewrite the report from the saved results (after editing survivors.toml)")
    parser.add_argument("--verify", action="store_true",
                        help="apply each survivor claimed killed (survivors.toml killed_by) and run those tests; "
                             "save the outcomes and rewrite the report")
    args = parser.parse_args(argv)
    config = tomllib.loads((HERE / "targets.toml").read_text())
    settings = config.get("settings", {})
    if args.report_only or args.verify:
        saved_path = Path(args.report).with_suffix(".json")
        saved = json.loads(saved_path.read_text())
        explanations = tomllib.loads((HERE / "survivors.toml").read_text()).get("survivor", [])
        if args.verify:
            verify(saved, explanations, sys.executable)
            saved_path.write_text(json.dumps(saved, indent=1, sort_keys=True) + "\n")
        unexplained = report(saved["rows"], saved["seconds"], explanations, Path(args.report), settings,
                             config["target"], saved.get("runs", []))
        print(f"mutate: report rewritten ({unexplained} unexplained survivors)")
        return 0
    targets = [t for t in config["target"] if not args.targets or t["name"] in args.targets]
    unknown = set(args.targets) - {t["name"] for t in config["target"]}
    if unknown:
        sys.exit(f"unknown targets {sorted(unknown)}")
    survivors_file = HERE / "survivors.toml"
    explanations = tomllib.loads(survivors_file.read_text()).get("survivor", []) if survivors_file.exists() else []
    python = sys.executable
    cosmic = str(Path(python).with_name("cosmic-ray"))
    scratch = Path(tempfile.mkdtemp(prefix="prism-mutate-"))
    work = scratch / ROOT.name
    rows, seconds = {}, {}
    try:
        copy_checkout(work)  # tests/data is tracked, so the copy carries the test clouds
        env = dict(os.environ, PYTHONPATH=str(work), NUMBA_CACHE_DIR=str(work / ".numba-cache"),
                   PYTHONDONTWRITEBYTECODE="1")
        env.pop("CI", None)
        check = subprocess.run([python, "-c", "import prism_stream; print(prism_stream.__file__)"], cwd=work,
                               env=env, capture_output=True, text=True, check=True).stdout.strip()
        if not check.startswith(str(work)):
            sys.exit(f"the scratch copy is not what the tests import ({check}); refusing to mutate")
        for t in targets:
            t0 = time.perf_counter()
            cfg, session = work / f"{t['name']}.toml", work / f"{t['name']}.sqlite"
            cfg.write_text(cosmic_config(t, settings, python))
            subprocess.run([cosmic, "init", str(cfg), str(session)], cwd=work, env=env, check=True)
            skip_outside(session, work, t, settings)
            base = subprocess.run([cosmic, "baseline", str(cfg)], cwd=work, env=env, capture_output=True, text=True)
            if base.returncode != 0:  # said, and the other targets still run: an hour's results are not thrown away
                print(f"mutate: target {t['name']}: the tests fail without any mutation, target left out:\n"
                      f"{base.stdout[-2000:]}{base.stderr[-2000:]}", flush=True)
                continue
            print(f"mutate: {t['name']}: running mutants", flush=True)
            subprocess.run([cosmic, "exec", str(cfg), str(session)], cwd=work, env=env, check=True)
            rows[t["name"]] = results(session, work)
            seconds[t["name"]] = time.perf_counter() - t0
            partial = Path(args.report).with_suffix(".partial.json")  # an interrupted run keeps its finished targets
            partial.write_text(json.dumps({"rows": rows, "seconds": seconds}, indent=1, sort_keys=True) + "\n")
            k = sum(x["killed"] for x in rows[t["name"]])
            print(f"mutate: {t['name']}: {k} of {len(rows[t['name']])} killed in {seconds[t['name']]:.0f} s",
                  flush=True)
    finally:
        if args.keep:
            print(f"scratch copy kept: {work}")
        else:
            shutil.rmtree(scratch, ignore_errors=True)
    saved = Path(args.report).with_suffix(".json")
    runs = [{"date": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
             "cores": os.cpu_count(), "command": " ".join(["python", "tests/mutation/run.py", *(argv or sys.argv[1:])]),
             "targets": [t["name"] for t in targets]}]
    if args.merge and saved.exists():
        old = json.loads(saved.read_text())
        for name in (t["name"] for t in config["target"]):
            if name not in rows and name in old["rows"]:
                rows[name], seconds[name] = old["rows"][name], old["seconds"][name]
        runs = [r for r in old.get("runs", []) if set(r["targets"]) & set(rows) - set(runs[0]["targets"])] + runs
    rows = {t["name"]: rows[t["name"]] for t in config["target"] if t["name"] in rows}
    saved.write_text(json.dumps({"rows": rows, "seconds": seconds, "runs": runs}, indent=1, sort_keys=True) + "\n")
    unexplained = report(rows, seconds, explanations, Path(args.report), settings, config["target"], runs)
    print(f"mutate: report written to {args.report} ({unexplained} unexplained survivors)")
    return 0


if __name__ == "__main__":
    sys.exit(main())

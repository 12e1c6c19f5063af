"""Does every committed table still follow from its archive? Each table that is an aggregation of committed records is
rebuilt by its bench's table-only path into a temporary results root and compared with the committed one.

    python -m bench.reproduce                      # every rebuildable table; exit status 1 when one differs
    python -m bench.reproduce --only counts claims # some of them (a table's name or its rebuild's name)
    python -m bench.reproduce --skip-slow          # leave out the rebuilds marked slow (minutes each)
    python -m bench.reproduce --list               # the tables, their commands, and why the others are not rebuilt

The ``.md`` is compared as text and the ``.json`` as parsed data, bit for bit, except the keys of :data:`TOLERATED`
(each with its reason) and the checkout's own folder in absolute paths (:data:`CHECKOUT_MARK`). Nothing is written
into bench/results: the benches write under a temporary root (``--results-root``), and an archive a bench would write
back into is copied there first. ``--results DIR`` compares against (and reads the archives of) another copy of
bench/results; ``--out DIR`` keeps the rebuilt tables and writes ``reproduce.md`` there. The tables that are
measurements (timings, GPU profiles) or whose records were never archived are listed in :data:`NOT_REBUILDABLE` with
the reason.
"""
from __future__ import annotations

import argparse
import json
import math
import shutil
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

from bench.common import RESULTS, ROOT, bench_child


@dataclass(frozen=True)
class Rebuild:
    """One bench command that rebuilds ``tables`` (names relative to the results root, no suffix). In ``command``,
    ``{res}`` is the committed results root, ``{out}`` the temporary one the tables go to, ``{tmp}`` a scratch folder;
    ``copy`` lists paths of ``{res}`` copied first: a folder to ``{tmp}`` (an archive the bench writes back into), a
    file to ``{out}`` (a table's own .json that its table is made from); ``slow``: half a minute or more on two
    cores; ``scenes``: reads the benchmark scenes' cameras (under :func:`b3dgs.data_root`)."""

    command: tuple[str, ...]
    tables: tuple[str, ...]
    copy: tuple[str, ...] = ()
    slow: bool = False
    scenes: bool = False


def _extra(name: str, policies: str, within: str = "", runs: str = "", archive: str = "active_view_runs",
           against: str = "") -> Rebuild:
    """A bench.active_view_extra table: its rows' archive (``runs``, default ``<name>_runs``) paired with the rows
    of ``archive`` (default the committed campaign's; ``against``: only those policies)."""
    return Rebuild(("bench.active_view_extra", "--new", f"{{res}}/{runs or name + '_runs'}", "--archive",
                    f"{{res}}/{archive}", "--policies", *policies.split(),
                    *(("--within", *within.split()) if within else ()),
                    *(("--against", *against.split()) if against else ()),
                    "--name", name, "--results-root", "{out}"), (name,), slow=True, scenes=True)


_GEO = "info_gain_geometry info_gain_geometry+greedy_conditioned"
_SCHEDULE = ("bench.schedule", "--table-only", "--out", "{tmp}/schedule", "--results-root", "{out}")

#: the rebuilds, by name; the arguments are those the committed tables were made with (docs, scripts/campaign.sh,
#: and what each .json records: policies, variants, seeds)
REBUILDS: dict[str, Rebuild] = {
    "report": Rebuild(("bench.studies", "--report-only", "--uq", "--out", "{tmp}/bench", "--archive", "{res}/runs",
                       "--report", "{out}/report"), ("report/report",), slow=True, scenes=True),
    "active_view": Rebuild(("bench.active_view", "--aggregate-only", "--study-out", "{tmp}/study",
                            "--archive", "{res}/active_view_runs", "--results-root", "{out}"),
                           ("active_view", "active_view_8to16"), slow=True, scenes=True),
    "active_view_sh": _extra("active_view_sh", "sh native_sh sh+diverse native_plus_sh"),
    "active_view_ig": _extra("active_view_ig", "info_gain+greedy_conditioned cover info_gain_params+greedy_conditioned "
                                               "info_gain info_gain+diverse info_gain@standard", within="cover"),
    "active_view_counts": _extra("active_view_counts", "native_fisher3"),
    # issue 42's centre term (scripts/geometry_rows.sh): against the campaign, and against issue 42's own rows
    "active_view_geo": _extra("active_view_geo", _GEO, within=_GEO),
    "active_view_geo_ig": _extra("active_view_geo_ig", _GEO, runs="active_view_geo_runs", archive="active_view_ig_runs",
                                 against="info_gain info_gain+greedy_conditioned info_gain+diverse "
                                         "info_gain_params+greedy_conditioned cover"),
    "active_view_schedule": Rebuild(("bench.active_view_schedule", "--dir", "{res}/active_view_schedule",
                                     "--results-root", "{out}/active_view_schedule"),
                                    ("active_view_schedule/compare",)),
    "claims": Rebuild(("bench.claims", "--results", "{res}", "--results-root", "{out}"),
                      ("claims", "claims_two_scenes")),
    "compression": Rebuild(("bench.compression", "--aggregate-only", "--out", "{tmp}/compression",
                            "--archive", "{tmp}/compression_runs", "--results-root", "{out}"), ("compression",),
                           copy=("compression_runs",)),  # the bench syncs its --out back into --archive
    "count_cost": Rebuild(("bench.count_cost", "--table-only", "--results-root", "{out}"), ("count_cost",),
                          copy=("count_cost.json",)),  # the .json is the measurement; the table is made from it
    "counts": Rebuild(("bench.counts", "--table-only", "--seeds", "0", "1", "2", "--alone", "sh", "native_plus_sh",
                       "--archive", "{res}/runs",
                       "--results-root", "{out}"), ("counts",), slow=True),
    "suggest": Rebuild(("bench.suggest", "--table-only", "--archive", "{res}/suggest_runs", "--results-root", "{out}"),
                        ("suggest",)),
    "ood_sector": Rebuild(("bench.ood_sector", "--table-only", "--archive", "{res}/ood_sector_runs",
                           "--results-root", "{out}"), ("ood_sector",)),
    "schedule": Rebuild((*_SCHEDULE, "--archive", "{res}/schedule_runs"), ("schedule",)),
    "dp_cadence": Rebuild(("bench.dp_cadence", "--seeds", "0", "1", "--table-only", "--out", "{tmp}/dp_cadence",
                           "--results-root", "{out}", "--archive", "{res}/dp_cadence_runs"), ("dp_cadence",)),
    "schedule_models": Rebuild((*_SCHEDULE, "--models", "standard", "niw", "dpmm", "--seeds", "0",
                                "--variant", "dash=schedule=dash", "--archive", "{res}/schedule_models_runs",
                                "--name", "schedule_models", "--base-model", "standard",
                                "--import", "dash={res}/schedule_runs/{scene}/{model}/dash/s{seed}",
                                "--import", "constant={res}/schedule_runs/{scene}/{model}/constant/s{seed}",
                                "--import", "constant={res}/runs/{scene}/{model}/s{seed}", "--reference", "constant"),
                               ("schedule_models",)),
    "schedule_screen3": Rebuild((*_SCHEDULE, "--scenes", "fox", "flower", "--seeds", "0", "--jobs", "1",
                                 "--variant", "constant=schedule=constant", "--variant", "dash=schedule=dash",
                                 "--variant", "trim2=schedule=dash schedule.keep_below=2.0",
                                 "--archive", "{res}/schedule_screen3_runs", "--name", "schedule_screen3"),
                                ("schedule_screen3",)),
}

_MEASURED = "a measurement (times on the machine it ran on): no archive to aggregate, only a rerun remeasures it"
#: committed tables (a .md with a sibling .json) that no command rebuilds from an archive, and why
NOT_REBUILDABLE: dict[str, str] = {
    "active_view_pre_campaign": "the earlier study's rows were not archived (only per-scene study.md/json and plots "
                                "in active_view_pre_campaign/); made by older code that trains the same picks to "
                                "other numbers (docs/studies.md)",
    "active_resolution": "scores candidates from phase-1 checkpoints (bench.active_resolution), which are not archived",
    "device_h200": "a GPU profile (bench.device_profile report) whose .md was edited by hand after the report; its "
                   "inputs were saved as train_cuda_h200*.json, not the train_cuda.json the report reads",
    "fma": _MEASURED + " (bench.build_ab: CPU times of two extension builds)",
    "host_syncs": "counted while training (bench.host_syncs); the per-model counts it resumes from are not archived",
    "lanes": "counted on an instrumented build; its trained cases need their checkpoints (bench.lanes)",
    "posterior": "trained runs (bench.posterior), and from before the quick-protocol change (docs/studies.md)",
    "reliability": "the outcome of running each bad input's command (bench.reliability); nothing to aggregate",
    "render": _MEASURED + " (bench.render)",
    "schedule_screen": "its runs were not archived (no schedule_screen_runs/): a screen whose table alone was kept",
    "schedule_screen2": "its runs were not archived (no schedule_screen2_runs/): a screen whose table alone was kept",
    "speed_ab": _MEASURED + " (bench.speed_ab: two checkouts side by side)",
    "step_profile": _MEASURED + " (bench.step_profile)",
    "train": "trained runs with their wall-clock curves (bench.train); " + _MEASURED,
    "uq": "scores trained checkpoints (bench.uq), which the archive does not keep",
    "uq_count_scale": "re-scores trained NIW checkpoints (bench.uq_count_scale), which the archive does not keep",
    "uq_count_scale_default": "re-scores trained NIW checkpoints (bench.uq_count_scale), which the archive does not "
                              "keep",
    "uq_sampling": _MEASURED + " (bench.uq_sampling)",
    "viewer": _MEASURED + " (bench.viewer: frame times)",
}

#: .json keys (paths from the top) a rebuild may change, with the reason: they say where the aggregation ran or wrote,
#: not what it found
TOLERATED: dict[str, str] = {
    "/machine": "bench.common.machine() of the machine that wrote the file (Python, torch, threads, CPU), recorded "
                "again by a rebuild (compression, schedule*)",
    "/config/out": "the report's own output folder (report.json), which a rebuild moves to its temporary root",
}
#: strings naming a file under a checkout's bench/results/ (the report's run paths, /work/main/bench/results/runs/...)
#: are compared from ``bench/results/`` on: the part before it records where the checkout was, not a result
CHECKOUT_MARK = "/bench/results/"


def committed_tables(results: Path = RESULTS) -> list[str]:
    """Every committed table under ``results``: a ``.md`` with a sibling ``.json`` (top level and one folder down),
    leaving out the per-scene copies under ``active_view*/<scene>/`` that the study tables write."""
    names = []
    for md in sorted(results.glob("*.md")) + sorted(results.glob("*/*.md")):
        rel = md.relative_to(results).with_suffix("")
        if md.with_suffix(".json").is_file():
            names.append(rel.as_posix())
    return names


def first_md_difference(a: str, b: str) -> Optional[str]:
    """The first line where the committed text ``a`` and the rebuilt ``b`` differ, or None."""
    la, lb = a.splitlines(), b.splitlines()
    for i, (x, y) in enumerate(zip(la, lb), 1):
        if x != y:
            return f".md line {i}: committed {x[:160]!r}, rebuilt {y[:160]!r}"
    if len(la) != len(lb):
        return f".md: committed {len(la)} lines, rebuilt {len(lb)}"
    return None


#: floats this close (relative) count as equal: the last bits of float64 LAPACK / BLAS results (the SVD that makes
#: each loaded pose exactly orthonormal) depend on the CPU kind's kernels, and a table derived from them may carry
#: those bits. A result differs at 1e-7 or more; the .md tables are compared as text, exactly.
ROUNDOFF = 1e-12


def first_json_difference(a, b, path: str = "", roundoff: Optional[list] = None) -> Optional[str]:
    """The first key path where the parsed JSON ``a`` (committed) and ``b`` (rebuilt) differ, or None; floats within
    :data:`ROUNDOFF` are equal, each such pair appended to ``roundoff`` (when given) as (path, committed, rebuilt)."""
    if isinstance(a, dict) and isinstance(b, dict):
        for k in list(a) + [k for k in b if k not in a]:
            if k not in b:
                return f".json {path}/{k}: only in the committed file"
            if k not in a:
                return f".json {path}/{k}: only in the rebuilt file"
            d = first_json_difference(a[k], b[k], f"{path}/{k}", roundoff)
            if d:
                return d
        return None
    if isinstance(a, list) and isinstance(b, list):
        for i, (x, y) in enumerate(zip(a, b)):
            d = first_json_difference(x, y, f"{path}/{i}", roundoff)
            if d:
                return d
        return None if len(a) == len(b) else f".json {path}: committed {len(a)} items, rebuilt {len(b)}"
    if isinstance(a, float) and isinstance(b, float) and a != b and math.isclose(a, b, rel_tol=ROUNDOFF):
        if roundoff is not None:
            roundoff.append((path or "/", a, b))
        return None
    if a != b or type(a) is not type(b):
        return f".json {path or '/'}: committed {json.dumps(a)[:160]}, rebuilt {json.dumps(b)[:160]}"
    return None


def _comparable(x, results: Path, path: str = ""):
    """``x`` without the :data:`TOLERATED` keys, its paths under a checkout from ``bench/results/`` on."""
    if isinstance(x, dict):
        return {k: _comparable(v, results, f"{path}/{k}") for k, v in x.items() if f"{path}/{k}" not in TOLERATED}
    if isinstance(x, list):
        return [_comparable(v, results, f"{path}/{i}") for i, v in enumerate(x)]
    if isinstance(x, str):
        if x.startswith(str(results) + "/"):
            return "bench/results/" + x[len(str(results)) + 1:]
        if CHECKOUT_MARK in x and x.startswith("/"):
            return "bench/results/" + x.split(CHECKOUT_MARK, 1)[1]
    return x


def compare(name: str, results: Path, rebuilt: Path, roundoff: Optional[list] = None) -> Optional[str]:
    """None when ``rebuilt/<name>.{md,json}`` equal ``results/<name>.{md,json}``, else the first difference (the
    floats equal only within :data:`ROUNDOFF` go to ``roundoff``)."""
    for suffix in (".md", ".json"):
        if not (results / f"{name}{suffix}").is_file():
            return f"no committed {name}{suffix} in {results}"
        if not (rebuilt / f"{name}{suffix}").is_file():
            return f"the rebuild wrote no {name}{suffix}"
    d = first_md_difference((results / f"{name}.md").read_text(), (rebuilt / f"{name}.md").read_text())
    if d:
        return d
    a, b = (_comparable(json.loads((r / f"{name}.json").read_text()), results) for r in (results, rebuilt))
    return first_json_difference(a, b, roundoff=roundoff)


def _shown(path: Path) -> str:
    """A path as a command names it: relative to the checkout when inside it (as the committed tables record it)."""
    try:
        return path.resolve().relative_to(ROOT).as_posix()
    except ValueError:
        return str(path)


def command(rb: Rebuild, results: Path, out: Path, tmp: Path) -> list[str]:
    """``rb``'s command line with its placeholders filled in."""
    res, out, tmp = _shown(results), str(out), str(tmp)
    return ["python", "-m", *(a.replace("{res}", res).replace("{out}", out).replace("{tmp}", tmp) for a in rb.command)]


def missing_scenes() -> Optional[str]:
    """Why the rebuilds that read the benchmark scenes cannot run here, or None."""
    from b3dgs import data_root

    root = Path(data_root())
    return None if root.is_dir() else (f"needs the benchmark scenes under {root}, which does not exist "
                                       "(fix: set B3DGS_DATA to the scenes' folder or B3DGS_SHARED to its parent)")


def run(name: str, rb: Rebuild, results: Path, out: Path) -> list[dict]:
    """Runs one rebuild into ``out`` and compares its tables; one result per table."""
    shown = " ".join(a if " " not in a else repr(a) for a in command(rb, results, Path("OUT"), Path("TMP")))
    why = missing_scenes() if rb.scenes else None
    if why:
        return [{"table": t, "rebuild": name, "command": shown, "identical": False, "difference": why, "seconds": 0.0}
                for t in rb.tables]
    tmp = Path(tempfile.mkdtemp(prefix=f"reproduce-{name}-"))
    try:
        for rel in rb.copy:
            src = results / rel
            (shutil.copytree if src.is_dir() else shutil.copy2)(src, (out if src.is_file() else tmp) / rel)
        _, _, module, *argv = command(rb, results, out, tmp)
        cmd, env = bench_child(module.removeprefix("bench."), *argv)
        t0 = time.perf_counter()
        proc = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True)
        secs = time.perf_counter() - t0
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    rows = []
    for t in rb.tables:
        if proc.returncode != 0:
            tail = (proc.stderr.strip().splitlines() or ["(no output)"])[-1]
            diff = f"the command failed (exit {proc.returncode}): {tail[:300]}"
        else:
            diff = compare(t, results, out, roundoff := [])
        note = None
        if diff is None and roundoff:
            worst = max(abs(x - y) / max(abs(x), abs(y)) for _, x, y in roundoff)
            note = f"{len(roundoff)} float(s) equal to round-off (max relative {worst:.1e}; first {roundoff[0][0]})"
        rows.append({"table": t, "rebuild": name, "command": shown, "identical": diff is None, "difference": diff or note,
                     "seconds": round(secs, 1)})
    return rows


def markdown(rows: list[dict], skipped: dict[str, str]) -> str:
    """The result table, then the tables not rebuilt and why."""
    cell = lambda s: str(s).replace("|", "\\|")  # noqa: E731
    lines = ["| table | command | identical | first difference | s |", "|---|---|---|---|---|"]
    lines += [f"| {r['table']} | `{cell(r['command'])}` | {'yes' if r['identical'] else '**no**'} | "
              f"{cell(r['difference'] or '')} | {r['seconds']} |" for r in rows]
    if skipped:
        lines += ["", "Not rebuilt:", ""] + [f"- {t}: {why}" for t, why in skipped.items()]
    return "\n".join(lines) + "\n"


def main(argv: Optional[list[str]] = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", nargs="+", default=None, help="tables or rebuilds by name (default: all)")
    ap.add_argument("--skip-slow", action="store_true", help="leave out the rebuilds marked slow")
    ap.add_argument("--results", default=str(RESULTS), help="the committed results (default bench/results)")
    ap.add_argument("--out", default=None, help="keep the rebuilt tables and reproduce.md here (default: a temp dir)")
    ap.add_argument("--list", action="store_true", help="list the tables and their commands; rebuild nothing")
    ap.add_argument("--jobs", type=int, default=1,
                    help="rebuilds run at once (each is one process with its own temp dir; the tables do not depend "
                         "on it; 2 on a 2-core machine takes about half the time)")
    args = ap.parse_args(argv)
    results = Path(args.results).resolve()
    known = {t for rb in REBUILDS.values() for t in rb.tables}
    unknown = sorted(set(args.only or []) - known - set(REBUILDS) - set(NOT_REBUILDABLE))
    if unknown:
        names = ", ".join(sorted(known | set(NOT_REBUILDABLE)))
        ap.error(f"--only {' '.join(unknown)}: no such table (one of {names})")
    asked = {n: rb for n, rb in REBUILDS.items()
             if args.only is None or n in args.only or set(rb.tables) & set(args.only)}
    chosen = {n: rb for n, rb in asked.items() if not (args.skip_slow and rb.slow)}
    skipped = {t: why for t, why in NOT_REBUILDABLE.items() if args.only is None or t in args.only}
    skipped.update({t: "slow (--skip-slow)" for n, rb in asked.items() if n not in chosen for t in rb.tables})
    if args.list:
        for n, rb in REBUILDS.items():
            print(f"{', '.join(rb.tables)}: {' '.join(command(rb, results, Path('OUT'), Path('TMP')))}"
                  + (" (slow)" if rb.slow else ""))
        print("\n".join(f"{t}: not rebuilt: {why}" for t, why in NOT_REBUILDABLE.items()))
        return 0
    out = Path(args.out).resolve() if args.out else Path(tempfile.mkdtemp(prefix="reproduce-"))
    for root in {RESULTS.resolve(), results}:
        if out == root or root in out.parents:
            ap.error(f"--out {out} is inside the committed results {root}: pass a folder outside it")
    out.mkdir(parents=True, exist_ok=True)
    if args.jobs < 1:
        ap.error(f"--jobs {args.jobs}: pass 1 or more")
    rows = []
    try:
        with ThreadPoolExecutor(max_workers=args.jobs) as pool:  # each rebuild is a subprocess: threads only wait
            for n, rb in chosen.items():
                print(f"rebuilding {', '.join(rb.tables)} ...", flush=True)
            for got in pool.map(lambda item: run(item[0], item[1], results, out), chosen.items()):
                rows += got  # in the listed order, whatever order they finish in
                for r in got:
                    said = "DIFFERS: " + r["difference"] if not r["identical"] else \
                        "identical" + (f", {r['difference']}" if r["difference"] else "")
                    print(f"  {r['table']}: {said} ({r['seconds']} s)", flush=True)
        text = markdown(rows, skipped)
        (out / "reproduce.md").write_text(text)
        print(text)
    finally:
        if not args.out:
            shutil.rmtree(out, ignore_errors=True)
    bad = [r["table"] for r in rows if not r["identical"]]
    if bad:
        print(f"bench.reproduce: {len(bad)} of {len(rows)} tables differ from the committed ones: {', '.join(bad)}",
              file=sys.stderr)
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())

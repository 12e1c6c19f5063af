"""The compression ladder (``b3dgs-study compress``) on the canonical standard runs of the shared scenes.

    python -m bench.compression                          # ethiopian_head + fox, seeds 0 1 2 (as far as bases exist)
    python -m bench.compression --seeds 0 --jobs 2       # one base per scene, the two scenes side by side
    python -m bench.compression --aggregate-only         # only rebuild the tables and plots

Base runs are ``outputs/bench/<scene>/standard/s<seed>`` (``bench/studies.py`` trains them). One subprocess per
base run (``--jobs`` at a time, ``threads=1`` each); every row is resumable, so an interrupted run of this script
picks up where it stopped. Finished rows are copied to ``--archive`` (default bench/results/compression_runs/,
committed) after each base and restored from it at the start, so a ladder spread over sessions resumes (with its base
runs at the same paths: train them with ``python -m bench.studies --studies canonical --methods standard``). Writes ``bench/results/compression.{json,md}`` and ``bench/results/compression/``
(the study's plots).
"""
from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from bench.common import RESULTS, ROOT, machine, restore, sync_results, write_results

NAME = "compression"

# The paper's keep-ratio table (13 scenes x 3 seeds, 30k base + 2k fine-tune per round, GPU): PSNR.
PAPER = {0.55: {"opacity": 26.049, "gradient": 25.702, "dp_mass": 26.124, "posterior_importance": 26.092},
         0.35: {"opacity": 25.898, "gradient": 24.789, "dp_mass": 25.793, "posterior_importance": 25.856},
         0.20: {"opacity": 25.403, "gradient": 22.120, "dp_mass": 25.373, "posterior_importance": 25.477},
         0.10: {"opacity": 24.951, "gradient": 19.549, "dp_mass": 24.779, "posterior_importance": 24.956}}
PAPER_NOTE = ("paper: posterior − opacity +0.042 / −0.042 / +0.074 / +0.004 dB at 55 / 35 / 20 / 10 % keep; matched "
              "PUP beats the best continuation score at every keep ratio (+1.297 dB at nominal 20 %, 26/26 wins)")


def run_base(base: Path, out: Path, extra: list[str], archive: Path | None = None, every_s: float = 60.0) -> float:
    logs = out / "logs"
    logs.mkdir(parents=True, exist_ok=True)
    cmd = [sys.executable, "-m", "b3dgs.study.cli", "compress", f"base_runs=[{base}]", f"out_dir={out}",
           "threads=1", "plots=false", "progress_bar=false", *extra]
    t0 = time.time()
    name = f"{base.parent.parent.name}_{base.name}"
    with open(logs / f"{name}.log", "a") as log:
        r = subprocess.Popen(cmd, cwd=ROOT, stdout=log, stderr=subprocess.STDOUT)
        while True:  # rows finished so far reach the archive every every_s seconds, not only at the end
            try:
                r.wait(timeout=every_s)
                break
            except subprocess.TimeoutExpired:
                if archive is not None:
                    sync_results(out, archive, ARCHIVED)
    if r.returncode != 0:
        print(f"{name}: failed (exit {r.returncode}); see {logs / (name + '.log')}", flush=True)
    else:
        print(f"{name}: done in {time.time() - t0:.0f} s", flush=True)
    return time.time() - t0


#: the ladder's small result files (meta, each base's base.json, each row's result.json): what the archive keeps
ARCHIVED = ("meta.json", "*/s*/base.json", "*/s*/protocol.json", "*/s*/*_k*/result.json")


def aggregate(out: Path, root: Path = RESULTS) -> dict:
    from b3dgs.report.document import markdown_table
    from b3dgs.study.compression import write_report

    s = write_report(out, plots=True)
    dst = root / NAME
    dst.mkdir(parents=True, exist_ok=True)
    for png in (out / "plots").glob("*.png"):
        shutil.copy2(png, dst / png.name)
    lines = [(out / "compression.md").read_text().replace("](plots/", "](compression/"), "",
             f"## Next to the paper (13 scenes, 30k base; ours: {len(s['scenes'])} scenes, 3k base, 300 fine-tune steps per "
             "round)", "",
             *markdown_table(["Keep %", "score", "ours PSNR", "paper PSNR"],
                             [[str(int(round(k * 100))), name, "—" if mine is None else f"{mine:.3f}", f"{v:.3f}"]
                              for k, ref in PAPER.items() for name, v in ref.items()
                              for mine in [s["cells"].get(f"{name}@{k}", {}).get("psnr")]])]
    lines += ["", PAPER_NOTE, "",
              "Absolute PSNR is not comparable (other scenes, resolution and budgets); the comparison is the ordering "
              "of scores and the sign of the differences."]
    write_results(NAME, {"machine": machine(), "summary": s, "paper": {str(k): v for k, v in PAPER.items()}},
                  "\n".join(lines) + "\n", root=root)
    return s


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", nargs="+", default=["ethiopian_head", "fox"])
    ap.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    ap.add_argument("--bench", default=str(ROOT / "outputs" / "bench"), help="where the base runs are")
    ap.add_argument("--out", default=str(ROOT / "outputs" / "compression"))
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--aggregate-only", action="store_true")
    ap.add_argument("--results-root", default=str(RESULTS), help="where the table and plots go (default bench/results)")
    ap.add_argument("--extra", nargs="*", default=[], help="extra overrides for b3dgs-study compress")
    ap.add_argument("--archive", default=None,
                    help="copy of every finished row's result.json (and base.json) for resuming across machines; "
                         "default bench/results/compression_runs (committed) with the default --out, else <out>/archive")
    args = ap.parse_args()
    out = Path(args.out)
    if args.archive is None:  # smoke runs elsewhere never write into the committed archive
        args.archive = str(RESULTS / "compression_runs") if args.out == ap.get_default("out") else str(out / "archive")
    archive = Path(args.archive)
    restore(archive, out, ARCHIVED, "finished rows and bases")
    if not args.aggregate_only:
        bases = [Path(args.bench) / sc / "standard" / f"s{sd}" for sd in args.seeds for sc in args.scenes]
        missing = [str(b) for b in bases if not (b / "metrics.json").exists()]
        if missing:
            print(f"skipping {len(missing)} base runs that are not finished: {missing}", flush=True)
        bases = [b for b in bases if (b / "metrics.json").exists()]
        def one(b):
            run_base(b, out, list(args.extra), archive)
            sync_results(out, archive, ARCHIVED)  # after each base: its finished rows are safe in the archive

        with ThreadPoolExecutor(max_workers=max(1, args.jobs)) as ex:
            list(ex.map(one, bases))
    sync_results(out, archive, ARCHIVED)
    s = aggregate(out, Path(args.results_root))
    print(json.dumps({"rows": s["n_rows"], "scenes": s["scenes"]}), flush=True)
    print(f"wrote {Path(args.results_root) / (NAME + '.md')}", flush=True)


if __name__ == "__main__":
    main()

"""The paper's bounded studies at the quick protocol, resumably, then ``b3dgs-report`` over all runs.

    python -m bench.studies                          # the grid of conf/report.yaml `studies` (days on 2 cores)
    python -m bench.studies --studies canonical --uq --jobs 2 --threads 1   # the 7-scene x 3-seed canonical grid
    python -m bench.studies --jobs 2 --threads 1                # two runs at once, one thread each (2 cores)
    python -m bench.studies --studies sparse --scenes fox --seeds 0
    python -m bench.studies --scenes synthetic --seeds 0 --budgets 8 all --max-steps 100 --out /tmp/b --report /tmp/b/report

Scenes: any configured scene; the protocol is ``experiment=study``. Studies (grids from conf/report.yaml): canonical
(standard / NIW / DPMM, ``outputs/bench/<scene>/<method>/s<seed>``, shared with bench/posterior.py and bench/uq.py;
``--uq`` adds uq.json), sparse (``data.train_indices`` = ``select_evenly`` of the budget; a budget not below a scene's
train-view count is skipped) and initcap (``model.init_max_points``). A sparse or init-cap run that is the same training
run as an earlier one (NIW only observes training) is not retrained: it gets the twin's metrics with
``training_shared_with`` (``--no-share`` trains it). A run dir with metrics.json is finished and reused; finished runs'
small files are archived to ``--archive`` (default bench/results/runs/, committed), so a campaign resumes from the
repository, and the report (``--report``) is built from the archive. docs/studies.md has the results.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from omegaconf import OmegaConf

from b3dgs.io import write_json
from bench.common import (QUICK, RESULTS, ROOT, archive_files, bench_child, compose, model_overrides, n_train_views,
                          read_json, scene_names, scene_overrides, steps_overrides, threads_overrides, train_run)

STUDIES = OmegaConf.load(ROOT / "conf" / "report.yaml").studies


def plan(args) -> list[tuple[Path, list[str], str]]:
    """(run dir, overrides, study) for every run of the requested studies."""
    from b3dgs.data.scene import select_evenly

    protocol = QUICK + steps_overrides(args.max_steps, evals=12)
    out = Path(args.out)
    jobs = []
    for scene in args.scenes:
        base = scene_overrides(scene) + protocol + list(args.extra)
        n_train = n_train_views(base) if "sparse" in args.studies else None
        for seed in args.seeds:
            common = base + [f"seed={seed}"]
            if "canonical" in args.studies or ("sparse" in args.studies and "all" in args.budgets):
                for m in args.methods:
                    jobs.append((out / scene / m / f"s{seed}", common + model_overrides(m), "canonical"))
            budgets = [b for b in args.budgets if b != "all"] if "sparse" in args.studies else []
            if seed == args.seeds[0] and any(int(b) >= n_train for b in budgets):
                print(f"{scene}: {n_train} train views; sparse budgets "
                      f"{', '.join(b for b in budgets if int(b) >= n_train)} skipped (not sparser than 'all')", flush=True)
            for b in [b for b in budgets if int(b) < n_train]:
                idx = select_evenly(n_train, int(b))
                for m in STUDIES.sparse.methods:
                    jobs.append((out / "sparse" / f"b{b}" / scene / m / f"s{seed}",
                                 common + [*model_overrides(m), f"data.train_indices=[{','.join(map(str, idx))}]"],
                                 "sparse"))
            if "initcap" in args.studies:
                for m in STUDIES.initcap.methods:
                    jobs.append((out / "initcap" / f"c{args.cap}" / scene / m / f"s{seed}",
                                 common + [*model_overrides(m), f"model.init_max_points={args.cap}"],
                                 "initcap"))
    unique: dict = {}
    for j in jobs:
        unique.setdefault(j[0], j)
    return list(unique.values())


def training_signature(overrides: list[str]) -> str:
    """:func:`b3dgs.study.rounds.training_signature` of the run these overrides compose."""
    from b3dgs.study.rounds import training_signature as signature

    return signature(compose("train", [*overrides, "trainer.default_root_dir=."]))


def twins(jobs, studies=("sparse", "initcap")) -> dict[Path, Path]:
    """run dir -> the earlier run dir of the same study whose training is the same run (e.g. NIW and
    standard: NIW only observes training). Canonical runs are always trained (their NIW posterior feeds
    uq.json); the bounded studies read PSNR, SSIM, LPIPS and counts only."""
    sig: dict[str, Path] = {}
    out = {}
    for run_dir, overrides, study in jobs:
        if study not in studies:
            continue
        first = sig.setdefault(study + training_signature(overrides), run_dir)
        if first != run_dir:
            out[run_dir] = first
    return out


def write_shared(run_dir: Path, overrides: list[str], twin: Path) -> dict:
    """A run dir for a run that is the same training run as ``twin`` (:meth:`b3dgs.lifecycle.Run.share_training`):
    its own composed config, twin's curve and metrics with ``training_shared_with`` naming the twin; no checkpoint."""
    from b3dgs.lifecycle import Run

    return Run(compose("train", [*overrides, f"trainer.default_root_dir={run_dir}"]), run_dir).share_training(twin)


def uq_regimes(names: list[str], samples: int, seed: int) -> dict:
    """The regimes of ``conf/uq/<name>.yaml`` with conf/report.yaml's ``uq_settings`` on top (``samples`` for the
    sampling ones)."""
    from hydra.utils import instantiate

    from b3dgs.train import CONF_DIR

    cfg = OmegaConf.create({"uq": {"samples": samples}, "seed": seed})
    for n in names:
        cfg = OmegaConf.merge(cfg, OmegaConf.load(Path(CONF_DIR) / "uq" / f"{n}.yaml"),
                              {n: STUDIES.get("uq_settings", {}).get(n, {})})
    return {n: instantiate(cfg[n]) for n in names}


def merge_uq(path: Path, new: dict) -> dict:
    """uq.json at path with the regimes of ``new`` added (atomically); both must score the same views."""
    have = read_json(path, {})
    old_meta, new_meta = have.get("_meta", {}), new.get("_meta", {})
    for key in ("views", "seed"):
        if key in old_meta and old_meta[key] != new_meta.get(key):
            raise RuntimeError(f"{path}: the new regimes score other {key} ({new_meta.get(key)}) than the file's "
                               f"({old_meta[key]}); delete the file to recompute every regime")
    merged = {**{k: v for k, v in have.items() if k != "_meta"}, **{k: v for k, v in new.items() if k != "_meta"},
              "_meta": {**old_meta, **new_meta}}
    write_json(path, merged)
    return merged


def ensure_uq(run_dir: Path, method: str, samples: int, seed: int) -> None:
    """uq.json for a canonical run with every regime conf/report.yaml asks of its method: only the missing ones are
    computed (a regime added to conf/report.yaml later is merged into the file, the others are kept)."""
    ensure_regimes(run_dir, list(STUDIES.uq_regimes.get(method, ["proxy"])), samples, seed)


def ensure_regimes(run_dir: Path, names: list[str], samples: int, seed: int) -> None:
    """run_dir's uq.json with every regime of ``names``: those it lacks are computed and merged in."""
    from b3dgs.eval import evaluate_uq

    todo = [n for n in names if n not in read_json(run_dir / "uq.json", {})]
    if not todo:
        return
    with tempfile.TemporaryDirectory(dir=run_dir, prefix=".uq.") as tmp:  # its plots and TensorBoard files: dropped
        res = evaluate_uq([str(run_dir)], uq_regimes(todo, samples, seed), seed=seed, panels=0, out_dir=Path(tmp))
    merge_uq(run_dir / "uq.json", res)


def missing_regimes(run_dir: Path, method: str) -> list[str]:
    """The regimes conf/report.yaml asks of method that run_dir's uq.json lacks (all of them without one)."""
    have = read_json(run_dir / "uq.json", {})
    return [n for n in STUDIES.uq_regimes.get(method, ["proxy"]) if n not in have]


def ensemble_members(args, scene: str) -> list[Path]:
    """The standard canonical runs of scene forming its deep ensemble (conf/report.yaml ``ensemble_seeds``)."""
    return [Path(args.out) / scene / "standard" / f"s{s}" for s in STUDIES.ensemble_seeds]


def ensure_ensemble(members: list[Path], out_dir: Path) -> bool:
    """``out_dir/uq.json`` of the deep ensemble of ``members`` (EnsembleUQ over their checkpoints), unless it exists
    for exactly these members. False when a member is not finished here (no checkpoint to load)."""
    from b3dgs.eval import evaluate_uq

    f = out_dir / "uq.json"
    if f.is_file() and json.loads(f.read_text()).get("ensemble", {}).get("runs") == [str(m) for m in members]:
        return True
    if not all((m / "metrics.json").is_file() and (m / "checkpoints").is_dir() for m in members):
        return False
    evaluate_uq([str(m) for m in members], uq_regimes(["ensemble"], 0, 0), seed=0, panels=3, out_dir=out_dir)
    return True


def archive_ensemble(args, scene: str) -> Path:
    """The ensemble's uq.json into the archive, its members named by their archive dirs (so the report, built from
    the archive, attaches it to the first member)."""
    members = ensemble_members(args, scene)
    res = json.loads((Path(args.out) / scene / "ensemble" / "uq.json").read_text())
    res["ensemble"]["runs"] = [str(archive_dir(args, m).resolve()) for m in members]
    dest = Path(args.archive) / scene / "ensemble" / "uq.json"
    dest.parent.mkdir(parents=True, exist_ok=True)
    write_json(dest, res)
    return dest


ARCHIVED = ("config.yaml", "metrics.json", "curve.json", "uq.json")


def archive_dir(args, run_dir: Path) -> Path:
    """Where run_dir's small files are archived: the same path relative to --out, under --archive."""
    return Path(args.archive) / run_dir.relative_to(Path(args.out))


def archived(args, run_dir: Path, study: str) -> bool:
    """The run is finished in the archive (with its uq.json when --uq asks for one)."""
    a = archive_dir(args, run_dir)
    return (a / "metrics.json").is_file() and not (args.uq and study == "canonical" and not (a / "uq.json").is_file())


def archive(args, run_dir: Path) -> None:
    """Copies run_dir's small files into the archive atomically (:func:`bench.common.archive_files`)."""
    archive_files(run_dir, archive_dir(args, run_dir), ARCHIVED)


def uq_subprocess(run_dir: Path, method: str, samples: int, seed: int, threads: int | None) -> None:
    """ensure_uq in its own process (runs of a --jobs pool stay isolated, and killable)."""
    if missing_regimes(run_dir, method):
        _child(["--uq-one", str(run_dir), method, str(samples), str(seed)], threads, f"uq.json of {run_dir}")


def _child(argv: list[str], threads: int | None, what: str) -> None:
    cmd, env = bench_child("studies", *argv, *(["--threads", str(threads)] if threads else []))
    res = subprocess.run(cmd, capture_output=True, text=True, env=env)
    if res.returncode != 0:
        raise RuntimeError(f"{what} failed:\n{res.stderr[-4000:]}")


def main() -> None:
    if len(sys.argv) > 1 and sys.argv[1] in ("--uq-one", "--uq-ensemble"):  # internal: see uq_subprocess
        import torch

        argv = sys.argv[2:]
        if "--threads" in argv:
            torch.set_num_threads(int(argv[argv.index("--threads") + 1]))
            argv = argv[:argv.index("--threads")]
        if sys.argv[1] == "--uq-one":
            ensure_uq(Path(argv[0]), argv[1], int(argv[2]), int(argv[3]))
        else:
            ensure_ensemble([Path(a) for a in argv[1:]], Path(argv[0]))
        return
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--studies", nargs="+", default=["canonical", "sparse", "initcap"],
                    choices=["canonical", "sparse", "initcap"])
    ap.add_argument("--scenes", nargs="+", default=list(STUDIES.scenes), choices=scene_names(),
                    help="configured scenes (conf/scene/<name>.yaml)")
    ap.add_argument("--seeds", type=int, nargs="+", default=list(STUDIES.seeds))
    ap.add_argument("--methods", nargs="+", default=list(STUDIES.canonical_methods), help="canonical methods")
    ap.add_argument("--budgets", nargs="+", default=[str(b) for b in STUDIES.sparse.budgets])
    ap.add_argument("--cap", type=int, default=int(STUDIES.initcap.cap))
    ap.add_argument("--max-steps", type=int, default=None, help="override the quick protocol's 3000 steps (smoke tests)")
    ap.add_argument("--uq", action="store_true", help="add uq.json to canonical runs (OOD study)")
    ap.add_argument("--uq-samples", type=int, default=50)
    ap.add_argument("--out", default="outputs/bench")
    ap.add_argument("--report", default=str(RESULTS / "report"))
    ap.add_argument("--archive", default=None,
                    help="copy of each finished run's small files (resume across machines; report input); default "
                         "bench/results/runs (committed) with the default --out, else <out>/archive")
    ap.add_argument("--extra", nargs="*", default=[], help="extra Hydra overrides for every run")
    ap.add_argument("--dry-run", action="store_true", help="list the runs (and whether they are finished) only")
    ap.add_argument("--report-only", action="store_true", help="train nothing: the report of the archived runs")
    ap.add_argument("--jobs", type=int, default=1, help="runs trained at once (each a subprocess)")
    ap.add_argument("--threads", type=int, default=None, help="torch threads per run (e.g. --jobs 2 --threads 1)")
    ap.add_argument("--no-share", dest="share", action="store_false",
                    help="train sparse/initcap runs that are the same training run as another (NIW = standard) anyway")
    args = ap.parse_args()
    if args.archive is None:  # smoke runs elsewhere never write into the committed archive
        args.archive = str(RESULTS / "runs") if args.out == ap.get_default("out") else str(Path(args.out) / "archive")
    jobs = plan(args)
    # twins composes every run's config (most of a --report-only's time): a report trains nothing, so shares nothing
    sharing = args.share and (args.dry_run or not args.report_only)
    shared = twins(jobs) if sharing else {}
    todo = [j for j in jobs if not archived(args, j[0], j[2])]
    print(f"{len(jobs)} runs, {len(jobs) - len(todo)} finished, {len(todo)} to do" + (
        f" ({len([j for j in todo if j[0] in shared])} of them the same training run as another: shared)"
        if sharing else ""), flush=True)
    if args.dry_run:
        for run_dir, _, study in jobs:
            print(("done " if archived(args, run_dir, study) else "todo ") + str(run_dir)
                  + (f" (shares {shared[run_dir]})" if run_dir in shared else ""))
        return
    threads = threads_overrides(args.threads)
    if args.report_only:
        jobs = [j for j in jobs if archived(args, j[0], j[2])]
        print(f"report of the {len(jobs)} archived runs", flush=True)

    def one(job):
        run_dir, overrides, study = job
        if archived(args, run_dir, study):
            return None
        m = train_run(run_dir, overrides + threads)
        print(f"{study:9s} {run_dir}: PSNR {m['psnr']:.3f}, {m['train_time_s']:.1f} s", flush=True)
        if args.uq and study == "canonical":
            uq_subprocess(run_dir, m["method"], args.uq_samples, int(m["seed"]), args.threads)
            print(f"{study:9s} {run_dir}: uq.json", flush=True)
        archive(args, run_dir)
        return m

    def add_regimes(run_dir):
        """An archived run whose uq.json lacks a regime added since: the missing ones, from its checkpoint here."""
        a = archive_dir(args, run_dir)
        m = json.loads((a / "metrics.json").read_text())
        uq_subprocess(run_dir, m["method"], args.uq_samples, int(m["seed"]), args.threads)
        archive(args, run_dir)
        print(f"canonical {run_dir}: uq.json with {', '.join(missing_regimes(a, m['method'])) or 'every regime'}",
              flush=True)

    stale = [run_dir for run_dir, _, study in jobs if args.uq and not args.report_only and study == "canonical"
             and (m := read_json(archive_dir(args, run_dir) / "metrics.json")) and (run_dir / "metrics.json").is_file()
             and missing_regimes(archive_dir(args, run_dir), m["method"])]
    if stale:
        print(f"{len(stale)} archived runs lack a regime of conf/report.yaml: adding it", flush=True)
        with ThreadPoolExecutor(max_workers=max(1, args.jobs)) as ex:
            list(ex.map(add_regimes, stale))
    with ThreadPoolExecutor(max_workers=max(1, args.jobs)) as ex:  # each run is its own subprocess
        list(ex.map(one, [j for j in jobs if j[0] not in shared and not args.report_only]))  # list(): a failed run raises here
    for run_dir, overrides, study in jobs:  # after every twin has finished
        if run_dir in shared and not archived(args, run_dir, study):
            twin = shared[run_dir]
            write_shared(run_dir, overrides, twin if (twin / "metrics.json").is_file() else archive_dir(args, twin))
            archive(args, run_dir)
            print(f"{study:9s} {run_dir}: same training run as {shared[run_dir]} (shared)", flush=True)
    ensembles = []
    if "canonical" in args.studies and "standard" in args.methods and len(STUDIES.ensemble_seeds) >= 2:
        for scene in args.scenes:  # the per-scene deep ensemble, once all its members are finished here
            dest = Path(args.archive) / scene / "ensemble" / "uq.json"
            if args.uq and not args.report_only and not dest.is_file():
                members = ensemble_members(args, scene)
                if all(m in {j[0] for j in jobs} for m in members) and all((m / "checkpoints").is_dir() for m in members):
                    _child(["--uq-ensemble", str(Path(args.out) / scene / "ensemble"), *map(str, members)],
                           args.threads, f"the ensemble of {scene}")
                    archive_ensemble(args, scene)
                    print(f"ensemble  {scene}: uq.json of {len(members)} standard runs", flush=True)
            if dest.is_file():
                ensembles.append(dest)
    from b3dgs.report.app import build_report

    # exactly the grid's runs: outputs/bench also holds other benchmarks' runs of the same scene, method and
    # seed (e.g. niw_calib), which the report would rightly refuse as duplicates
    runs = [str(archive_dir(args, j[0])) for j in jobs if archive_dir(args, j[0]).is_dir()] + [str(e) for e in ensembles]
    cfg = compose("report", [f"runs=[{','.join(runs)}]", f"out={args.report}"])
    paths = build_report(cfg)
    print(f"report: {paths['md']}")


if __name__ == "__main__":
    main()

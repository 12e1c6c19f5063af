"""Shared helpers for the benchmarks: scenes and protocol (from b3dgs's config), medians, JSON + table output.

``bench/`` is a package, run as ``python -m bench.<name>`` from the repository root (or with it on ``PYTHONPATH``);
its modules import each other as ``bench.<module>`` only and leave ``sys.path`` alone (tests/test_bench_imports.py).
"""
from __future__ import annotations

import importlib.util
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Callable, Sequence

from b3dgs.device import machine, machine_kind
from b3dgs.io import atomic_path, write_json
from b3dgs.upgrade import FAMILY_POSTERIOR_UNRECORDED

ROOT = Path(__file__).resolve().parents[1]  # the checkout this bench/ belongs to
RESULTS = Path(__file__).resolve().parent / "results"


def median_ms(fn: Callable[[], None], repeats: int = 7, warmup: int = 2, device=None) -> float:
    """Median wall time of ``fn`` in ms (CUDA work is waited for on ``device``)."""
    from b3dgs.device import timed_clock

    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        t0 = timed_clock(device)
        fn()
        times.append((timed_clock(device) - t0) * 1000)
    return statistics.median(times)


def table(rows: Sequence[dict], cols: Sequence[str]) -> str:
    """A Markdown table of ``rows`` (dicts) over ``cols`` (b3dgs.report.document.markdown_table)."""
    from b3dgs.report.document import markdown_table

    def fmt(v):
        if isinstance(v, float):
            return f"{v:.4g}" if abs(v) < 1e4 else f"{v:.0f}"
        return str(v)

    return "\n".join(markdown_table(cols, [[fmt(r.get(c, "")) for c in cols] for r in rows]))


def write_results(name: str, payload: dict, text: str, root: Path = RESULTS, echo: bool = True) -> Path:
    """``<root>/<name>.json`` and ``.md``, written atomically (default root: bench/results); prints the text."""
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    write_json(root / f"{name}.json", payload)
    with atomic_path(root / f"{name}.md") as tmp:
        tmp.write_text(text + "\n")
    if echo:
        print(text)
    return root / f"{name}.json"


def read_json(path: Path, default=None):
    """The JSON in file ``path``, or ``default`` where there is no such file."""
    return json.loads(Path(path).read_text()) if Path(path).is_file() else default


def pyplot():
    """matplotlib.pyplot on the Agg backend (files only, no display)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def steps_overrides(max_steps: int | None, evals: int = 4) -> list[str]:
    """``trainer.max_steps`` (smoke tests) with ``evals`` evaluations along it; nothing for None."""
    return [f"trainer.max_steps={max_steps}", f"trainer.eval_every={max(1, max_steps // evals)}"] if max_steps else []


def threads_overrides(threads: int | None) -> list[str]:
    return [f"threads={threads}"] if threads else []


# The benchmark scenes are b3dgs's named scenes, conf/scene/<name>.yaml (loader + folder under the data root, see
# b3dgs.data_root), plus those of installed packages (b3dgs.conf entry points): a scene is added with one YAML file.
# The study protocol is conf/experiment/study.yaml (256 px, 3000 steps, no logger, progress bar or renders).
QUICK = ["experiment=study"]
SEVEN = ["ethiopian_head", "fox", "lego", "fern", "flower", "dtu_scan24", "dtu_scan65"]  # conf/report.yaml's scenes
#: the held-out-sector split (bench.ood_sector, bench.suggest): a contiguous 1/8 of the cameras and every 8th of the rest
SECTOR_SPLIT = ["data.test_split=sector+interleaved", "data.test_fraction=0.125"]
# The posterior blocks each model had when the committed benchmarks and studies ran: conf/experiment/archived_posterior.yaml
# (the study's table of them). The scripts that extend them pass these explicitly (model_overrides), so a later change
# of a model's default blocks (conf/model/<name>.yaml) cannot change what an archived row means; the active-view study
# pins its families with that preset (ARCHIVED_FAMILY_POSTERIOR, an override of b3dgs-study active).
ARCHIVED_POSTERIOR = FAMILY_POSTERIOR_UNRECORDED
ARCHIVED_FAMILY_POSTERIOR = "experiment=archived_posterior"


def model_overrides(model: str) -> list[str]:
    """``model=<model>`` with its archived posterior blocks pinned (``posterior=[...]``) where it has them."""
    blocks = ARCHIVED_POSTERIOR.get(model)
    return [f"model={model}"] + ([] if blocks is None else [f"posterior=[{','.join(blocks)}]"])


def scene_names() -> list[str]:
    """The configured scenes: ``scene/<name>.yaml`` in b3dgs's conf dir and in every installed package's."""
    from b3dgs.confs import conf_roots

    return sorted({p.stem for root in conf_roots() for p in (root / "scene").glob("*.yaml")})


def compose(config_name: str, overrides: Sequence[str]):
    """b3dgs's config ``config_name`` (train, study, report, ...) composed with ``overrides``."""
    from hydra.core.global_hydra import GlobalHydra

    from b3dgs.study.active import compose_config

    GlobalHydra.instance().clear()
    return compose_config(config_name, list(overrides))


def n_train_views(overrides: Sequence[str]) -> int:
    """Train views of the scene these overrides select (reads the scene's cameras once)."""
    from b3dgs.data.scene import poses_only
    from b3dgs.lifecycle import data_module

    with poses_only():
        return len(data_module(compose("train", [o for o in overrides if o.startswith(("data", "scene="))]).data)
                   .scene.train)


def plain_overrides(overrides: Sequence[str]) -> list[str]:
    """``overrides`` with each ``scene=`` / ``experiment=`` spelled out as the group choices and values its file sets
    (``data=transforms``, ``data.path=/abs/fox``, ...), which a checkout from before those groups understands too."""
    from omegaconf import OmegaConf

    from b3dgs.confs import load_option
    from b3dgs.protocol import flatten

    cfg = compose("train", [*overrides, "trainer.default_root_dir=."])
    out: list[str] = []
    for o in overrides:
        group, _, name = o.partition("=")
        option = load_option(group, name) if group in ("scene", "experiment") else None
        if option is None:
            out.append(o)
            continue
        for d in option.get("defaults") or []:
            out += [f"{k[len('override /'):]}={v}" for k, v in (d.items() if isinstance(d, dict) else ())
                    if k.startswith("override /")]
        out += [f"{k}={json.dumps(OmegaConf.to_object(v) if OmegaConf.is_config(v) else v)}"
                for k in flatten({k: v for k, v in option.items() if k != "defaults"})
                for v in [OmegaConf.select(cfg, k)]]
    return out


def load_file(path: Path):
    """The Python module in file ``path``, loaded without changing ``sys.path``."""
    spec = importlib.util.spec_from_file_location(Path(path).stem, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def restore(archive: Path, out: Path, patterns: Sequence[str], what: str = "files of finished rows") -> int:
    """Copies the archive's files that ``out`` lacks into it (:func:`sync_results`): archived rows count as finished."""
    n = sync_results(archive, out, patterns, only_missing=True) if Path(archive).is_dir() else 0
    if n:
        print(f"restored {n} {what} from {archive}", flush=True)
    return n


def archived_files(root: Path, patterns: Sequence[str]) -> list[Path]:
    """The files under root matching the glob patterns, relative to root, sorted."""
    return sorted({p.relative_to(root) for pat in patterns for p in root.glob(pat) if p.is_file()})


def sync_results(src: Path, dst: Path, patterns: Sequence[str], only_missing: bool = False) -> int:
    """Copies a study's small result files (``patterns`` under src) to dst atomically (a unique temporary file renamed
    into place, so overlapping syncs are safe); returns how many changed. A committed archive of them lets a study
    spread over sessions resume: restored rows count as finished."""
    try:  # an archive inside the study dir (the default <study-out>/archive) is never copied into itself
        inner = Path(dst).resolve().relative_to(Path(src).resolve()).parts
    except ValueError:
        inner = None
    n = 0
    for rel in archived_files(src, patterns):
        if inner and rel.parts[:len(inner)] == inner:
            continue
        target = dst / rel
        if target.exists() and (only_missing or target.read_bytes() == (src / rel).read_bytes()):
            continue
        with atomic_path(target) as tmp:
            shutil.copy2(src / rel, tmp)
        n += 1
    return n


class PeriodicSync:
    """``with PeriodicSync(src, dst, patterns):`` runs :func:`sync_results` every ``every_s`` seconds in a background
    thread while the block runs, and once more at its end: an interrupted session keeps every row finished so far."""

    def __init__(self, src: Path, dst: Path, patterns: Sequence[str], every_s: float = 60.0):
        self.args, self.every_s, self.stop = (src, dst, patterns), every_s, threading.Event()
        self.thread = threading.Thread(target=self._loop, daemon=True)

    def _loop(self) -> None:
        while not self.stop.wait(self.every_s):
            sync_results(*self.args)

    def __enter__(self) -> "PeriodicSync":
        self.thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop.set()
        self.thread.join()
        sync_results(*self.args)


def bench_child(name: str, *argv: str) -> tuple[list[str], dict[str, str]]:
    """The command and environment that run ``python -m bench.<name> argv...`` in a child process from any working
    directory: this checkout goes first on ``PYTHONPATH``, so the child imports this ``bench`` and ``b3dgs``."""
    path = os.pathsep.join([str(ROOT), *[p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p]])
    return [sys.executable, "-m", f"bench.{name}", *argv], dict(os.environ, PYTHONPATH=path)


def shared_dir() -> Path:
    return Path(os.environ.get("B3DGS_SHARED", ROOT.parent / "shared"))


def fresh_dir(d: Path) -> Path:
    """``d`` emptied: removed with what it holds, made again."""
    if d.exists():
        shutil.rmtree(d)
    d.mkdir(parents=True)
    return d


def archive_files(run_dir: Path, dest: Path, names: Sequence[str]) -> None:
    """Copies the files ``names`` of ``run_dir`` that exist into ``dest``, atomically: a temporary folder beside it,
    renamed into place (an earlier ``dest`` is replaced), so an archive never holds half a run."""
    dest.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{dest.name}.", dir=dest.parent))
    for name in names:
        if (run_dir / name).is_file():
            shutil.copy2(run_dir / name, tmp / name)
    if dest.exists():
        shutil.rmtree(dest)
    tmp.rename(dest)


def train_run(run_dir: Path, overrides: list[str], timeout_s: int = 3600, force: bool = False) -> dict:
    """Train one configuration in a subprocess (isolated, killable) unless ``run_dir`` already holds
    a finished run; returns its metrics.json. Benchmarks are therefore resumable."""
    metrics = run_dir / "metrics.json"
    if metrics.exists() and not force:
        return json.loads(metrics.read_text())
    # an interrupted run dir resumes where it stopped; force starts it afresh
    cmd = [sys.executable, "-m", "b3dgs.train", *overrides, f"hydra.run.dir={run_dir}",
           "overwrite=true" if force else "resume=auto"]
    t0 = time.perf_counter()
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s)
    if res.returncode != 0:
        raise RuntimeError(f"training failed ({' '.join(overrides)}):\n{res.stderr[-4000:]}")
    out = json.loads(metrics.read_text())
    out["wall_s"] = round(time.perf_counter() - t0, 2)
    return out


def check_same_parameters(metrics: dict, archived: Path, what: str) -> None:
    """Refuse a retrained run whose parameters differ from the archived run it stands in for (``archived``: that run's
    metrics.json; nothing to check when it is absent or records no hash): the archive's later pieces were computed
    from the archived parameters. Training reproduces its bits on the same kind of machine only, so the one line
    names both machines."""
    from b3dgs.errors import B3dgsError

    if not archived.is_file():
        return
    old = json.loads(archived.read_text())
    want = (old.get("checkpoint") or {}).get("params_sha256")
    got = (metrics.get("checkpoint") or {}).get("params_sha256")
    if want is None or got == want:
        return

    def kind(m) -> str:
        return machine_kind(m) if m else "a machine not recorded"

    raise B3dgsError(f"{what}: retrained parameters {got} differ from the archived run's {want} "
                     f"({archived}); it trained on {kind(old.get('machine'))}, this is {kind(machine())}",
                     "resume on a machine of the kind that trained the archive (training reproduces its bits there "
                     "only), or start afresh with another --archive")


def scene_overrides(scene: str) -> list[str]:
    """The Hydra overrides of benchmark scene ``scene`` (one of :func:`scene_names`)."""
    names = scene_names()
    if scene not in names:
        from b3dgs.errors import B3dgsError

        raise B3dgsError(f"unknown benchmark scene {scene!r}",
                         f"pass one of {', '.join(names)}, or add conf/scene/{scene}.yaml")
    return [f"scene={scene}"]


def ensure_lpips(run_dir: Path, metrics: dict) -> dict:
    """Fill in LPIPS for a finished run that was trained before the weights were available, by re-rendering its test
    views from the checkpoint (through the run: :meth:`b3dgs.lifecycle.Run.amend_metrics`)."""
    if metrics.get("lpips") is not None:
        return metrics
    from b3dgs.lifecycle import Run
    from b3dgs.metrics.lpips import get_lpips
    from b3dgs.metrics.views import evaluate_views
    from b3dgs.runs import load_run

    model, reason = get_lpips()
    if model is None:
        return metrics
    run = load_run(run_dir)
    ev = evaluate_views(run.module, run.scene.test, lpips_model=model, with_ssim=False)
    by_name = {r["name"]: r["lpips"] for r in ev["per_view"]}
    per_view = [{**r, "lpips": by_name[r["name"]]} if r["name"] in by_name else r for r in metrics.get("per_view", [])]
    update = {"lpips": ev["lpips"], "lpips_reason": None, "per_view": per_view}
    Run(run_dir=run_dir).amend_metrics(update, prog="bench")
    return {**metrics, **update}

"""Bad, extreme and damaged inputs: what ``b3dgs-train`` / ``b3dgs-eval`` now say about each.

Every row runs the real command in a subprocess (its own process group, a wall-clock timeout and a
6 GiB address-space limit, so a hang or a memory blow-up is recorded instead of taking the machine
down) and keeps its exit code and the one line it prints: the ``<prog>: error: ...`` line for a
refused input, the warning or the final ``Done:`` line for an accepted one.

Scenario rows (issue 20: concurrent trainings, signals, kills inside the final writes, finished runs,
stored results reused or pooled, multiruns) run several commands; their row keeps the decisive command's
exit code and line and says what was checked besides (``expect`` names the outcome: ``refused``,
``accepted`` or ``interrupted`` with exit 130 / 143). The third-pass rows check that no result is lost or
misattributed: ``b3dgs-eval`` run after run and at once on one run, into another run's folder, on a running run
and over mismatched ensemble members; ``overwrite=true`` next to files b3dgs did not write (compared byte for
byte); a resume with another renderer; gsplat or several devices on the CPU.

Damaged scenes are built under ``outputs/bench/reliability/fixtures`` from copies of the shared
scenes (never written to). Results go to ``bench/results/reliability.{json,md}``, rewritten
atomically after every row; rows already measured are skipped unless ``--force``.

    python -m bench.reliability [--force] [--only ID ...] [--timeout 180]
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Optional

import numpy as np

from bench.common import RESULTS, ROOT, fresh_dir, load_file, read_json, shared_dir, write_results
# the test callback that kills a run at a chosen point (children run from the checkout's root and import it)
kill_args = load_file(ROOT / "tests" / "kill_hooks.py").kill_args

WORK = ROOT / "outputs" / "bench" / "reliability"
FIX = WORK / "fixtures"
MEM_LIMIT = 6 * 2**30
# short, small runs for the rows that are expected to train
SHORT = ["trainer.max_steps=2", "trainer.eval_every=1", "trainer.checkpoint_every=1", "trainer.enable_progress_bar=false",
         "logger=none", "trainer.save_renders=false", "data.max_side=64"]


def _fox_variant(name: str, edit) -> Path:
    """A copy of the fox scene's transforms.json (images linked, not copied) changed by ``edit(meta, dir)``."""
    d = fresh_dir(FIX / name)
    (d / "images").symlink_to(shared_dir() / "data" / "fox" / "images")
    meta = json.loads((shared_dir() / "data" / "fox" / "transforms.json").read_text())
    edit(meta, d)
    (d / "transforms.json").write_text(json.dumps(meta))
    return d


def _set(**kw):
    def edit(meta, d):
        for k, v in kw.items():
            if v is None:
                meta.pop(k, None)
            else:
                meta[k] = v
    return edit


def _mixed_sizes(proportional: bool):
    """Every other frame downscaled (x1/2, or to a different aspect ratio), and no w/h in the file."""
    def edit(meta, d):
        from PIL import Image

        from b3dgs.data.images import save_png

        meta.pop("w", None)
        meta.pop("h", None)
        (d / "small").mkdir()
        for i, fr in enumerate(meta["frames"]):
            if i % 2:
                src = shared_dir() / "data" / "fox" / fr["file_path"]
                with Image.open(src) as im:
                    size = (im.width // 2, im.height // 2) if proportional else (im.width // 2, im.height // 3)
                    small = np.asarray(im.convert("RGB").resize(size, Image.Resampling.BOX))
                name = f"small/{Path(fr['file_path']).stem}.png"
                save_png(d / name, small)
                fr["file_path"] = name
    return edit


def _tiny_scene(meta, d):
    for fr in meta["frames"]:
        m = np.asarray(fr["transform_matrix"], dtype=float)
        m[:3, 3] *= 1e-4
        fr["transform_matrix"] = m.tolist()


def _colmap_variant(name: str, file: str, keep) -> Path:
    d, head = fresh_dir(FIX / name), shared_dir() / "data" / "ethiopian_head"
    (d / "sparse").mkdir()
    shutil.copytree(head / "sparse" / "0", d / "sparse" / "0")
    (d / "images").symlink_to(head / "images")
    p = d / "sparse" / "0" / file
    data = p.read_bytes()
    p.chmod(0o644)
    p.write_bytes(data[: keep(len(data))])
    return d


def _run_dir(name: str, ckpt: bytes | None) -> Path:
    """A run dir holding a config.yaml and, if given, a checkpoints/last.ckpt with these bytes."""
    d = fresh_dir(FIX / name)
    (d / "checkpoints").mkdir()
    (d / "config.yaml").write_text("seed: 0\n")
    if ckpt is not None:
        (d / "checkpoints" / "last.ckpt").write_bytes(ckpt)
    return d


def _fixture_file(name: str, data: bytes) -> Path:
    p = FIX / name
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_bytes(data)
    return p


def _bad_ckpt() -> Path:
    return _fixture_file("truncated.ckpt", b"PK\x03\x04" + bytes(range(256)) * 4)


# ------------------------------------------------------------------------------------ issue 20 scenarios
TINY = ["+data.n_views=8", "data.max_side=16", "trainer.max_steps=4", "trainer.eval_every=100", "trainer.checkpoint_every=2",
        "trainer.checkpoint_every_s=0", "trainer.enable_progress_bar=false", "logger=none", "threads=1"]


def _popen(module: str, args: list[str], env: Optional[dict] = None, cwd: Path = ROOT,
           limit=True) -> subprocess.Popen:
    """``python -m module args`` with its output captured, in its own process group under the memory limit (``limit``:
    True, or the function to run in the child before it starts; False: neither)."""
    env = env or {k: v for k, v in os.environ.items() if k != "HYDRA_FULL_ERROR"}
    return subprocess.Popen([sys.executable, "-m", module, *args], cwd=cwd, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, preexec_fn=_limit if limit is True else limit or None)


def _wait(proc: subprocess.Popen, timeout: int) -> tuple[Optional[int], str, str]:
    """(exit code, stdout, stderr) of ``proc``; exit code None when it ran past ``timeout`` s (its group killed)."""
    try:
        out, err = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        return None, *proc.communicate()
    return proc.returncode, out, err


def _run(module: str, args: list[str], timeout: int = 300, **kw) -> tuple[int, str, str]:
    rc, out, err = _wait(_popen(module, args, **kw), timeout)
    return (-1, out, err + f"\nTIMEOUT after {timeout} s") if rc is None else (rc, out, err)


def _fresh(name: str) -> Path:
    return fresh_dir(WORK / "scenarios" / name)


def _files(d: Path) -> dict:
    return {str(p.relative_to(d)): (p.stat().st_mtime_ns, p.stat().st_size) for p in sorted(d.rglob("*")) if p.is_file()}


def _finished_run(d: Path, *extra: str) -> Path:
    rc, out, err = _run("b3dgs.train", [*TINY, *extra, f"hydra.run.dir={d}"])
    if rc != 0:
        raise RuntimeError(f"fixture run failed: {err[-500:]}")
    return d


def sc_concurrent() -> dict:
    """Two trainings on one run dir: the first is stopped (SIGSTOP by its own test hook) at step 1, holding it."""
    d = _fresh("concurrent") / "run"
    first = _popen("b3dgs.train", [*TINY, f"hydra.run.dir={d}", *kill_args(step=1, sig="STOP")],
                   limit=False)
    os.waitpid(first.pid, os.WUNTRACED)
    try:
        before = _files(d)
        rc, out, err = _run("b3dgs.train", [*TINY, "seed=1", f"hydra.run.dir={d}"])
        untouched = _files(d) == before
    finally:
        os.kill(first.pid, signal.SIGCONT)
    first.communicate(timeout=300)
    ok = rc == 2 and untouched and first.returncode == 0 and (d / "metrics.json").exists()
    return {"exit_code": rc, "message": _message("train", rc, out, err), "ok": ok,
            "checked": f"the first run finished (exit {first.returncode}), the refused one changed nothing"}


def sc_default_dirs() -> dict:
    """Two trainings with the default run dir, started together in one folder: two run dirs."""
    d = _fresh("default_dirs")
    procs = [_popen("b3dgs.train", [*TINY, "model.sh_degree=1"], cwd=d) for _ in range(2)]
    res = [(p.wait(timeout=300), *p.communicate()) for p in procs]
    runs = sorted(d.glob("outputs/train/*/metrics.json"))
    rc = max(r[0] for r in res)
    return {"exit_code": rc, "message": _message("train", res[-1][0], res[-1][1], res[-1][2]),
            "ok": rc == 0 and len(runs) == 2, "checked": f"{len(runs)} run dirs with metrics.json"}


def sc_signal(sig: str, code: int) -> dict:
    d = _fresh(f"sig{sig}") / "run"
    rc, out, err = _run("b3dgs.train", [*TINY, f"hydra.run.dir={d}", *kill_args(step=3, sig=sig)])
    import torch

    step = torch.load(d / "checkpoints" / "last.ckpt", weights_only=False)["global_step"] if (d / "checkpoints" / "last.ckpt").exists() else None
    rc2, out2, err2 = _run("b3dgs.train", [*TINY, "resume=auto", f"hydra.run.dir={d}"])
    line = [ln for ln in err.splitlines() if ln.strip()][-1:] or [""]
    return {"exit_code": rc, "message": line[0], "ok": rc == code and step == 3 and rc2 == 0 and line[0].endswith(
        "resume with resume=auto"), "checked": f"last.ckpt at step {step}; resume=auto then finished (exit {rc2})"}


def sc_final_ctrl_c() -> dict:
    d = _fresh("final_ctrl_c") / "run"
    rc, out, err = _run("b3dgs.train", [*TINY, f"hydra.run.dir={d}", *kill_args(point="final", sig="INT")])
    rc2, _, _ = _run("b3dgs.train", [*TINY, "resume=auto", f"hydra.run.dir={d}"])
    line = [ln for ln in err.splitlines() if ln.strip()][-1:] or [""]
    return {"exit_code": rc, "message": line[0], "ok": rc == 130 and rc2 == 0 and (d / "metrics.json").exists(),
            "checked": f"resume=auto then finished the evaluation (exit {rc2})"}


def sc_kill_final_write(point: str) -> dict:
    """kill -9 inside a final write (temp file written, not renamed), then resume=auto: the same metrics.json."""
    base = _fresh(f"kill_{point}")
    dens = ["trainer.max_steps=8", "strategy.refine_start=2", "strategy.refine_every=2", "strategy.refine_stop=7",
            "strategy.grad_threshold=1e-9"]  # densify, so that the restored counters are not empty
    ref = _finished_run(base / "ref", *dens)
    d = base / "cut"
    rc0, _, _ = _run("b3dgs.train", [*TINY, *dens, f"hydra.run.dir={d}", *kill_args(point=f"write:{point}")])
    stale = [p.name for p in d.rglob("*.tmp")]
    rc, out, err = _run("b3dgs.train", [*TINY, *dens, "resume=auto", f"hydra.run.dir={d}"])
    a, b = (json.loads((x / "metrics.json").read_text()) for x in (ref, d))
    timing = ("train_time_s", "render_fps", "block_time_s")
    same = {k: v for k, v in a.items() if k not in timing} == {k: v for k, v in b.items() if k not in timing}
    ok = rc0 == -9 and bool(stale) and rc == 0 and same and not list(d.rglob("*.tmp")) and bool(b.get("added"))
    return {"exit_code": rc, "message": _message("train", rc, out, err), "ok": ok,
            "checked": f"killed (exit {rc0}) leaving {stale}; after resume metrics.json equal to an uninterrupted "
                       f"run's (timings aside): {same}; temp files removed; added={b.get('added')}"}


def sc_finished_resume() -> dict:
    d = _finished_run(_fresh("finished") / "run")
    before = _files(d)
    rc, out, err = _run("b3dgs.train", [*TINY, "resume=auto", f"hydra.run.dir={d}"])
    lines = [ln.split("] - ", 1)[-1] for ln in (out + err).splitlines() if "finished run" in ln]
    return {"exit_code": rc, "message": lines[0] if lines else _message("train", rc, out, err),
            "ok": rc == 0 and _files(d) == before, "checked": "no file of the run dir rewritten"}


def sc_refused_leaves_nothing() -> dict:
    d = _fresh("refused") / "run"
    d.mkdir()
    (d / "config.yaml").write_text("seed: 0\n")
    rc, out, err = _run("b3dgs.train", [*TINY, f"hydra.run.dir={d}"])
    left = sorted(p.name for p in d.iterdir())
    return {"exit_code": rc, "message": _message("train", rc, out, err), "ok": rc == 2 and left == ["config.yaml"],
            "checked": f"run dir holds {left} (no .hydra/, no train.log)"}


def sc_joblib() -> dict:
    d = _fresh("joblib")
    rc, out, err = _run("b3dgs.train", ["-m", "hydra/launcher=joblib", "hydra.launcher.n_jobs=2", "model.sh_degree=0,1", *TINY,
                                        f"hydra.sweep.dir={d}"], limit=False)
    runs = sorted(d.glob("*/metrics.json"))
    return {"exit_code": rc, "message": f"{len(runs)} of 2 jobs finished: " + ", ".join(r.parent.name for r in runs),
            "ok": rc == 0 and len(runs) == 2, "checked": "both run dirs hold metrics.json"}


def sc_multirun_bad_seed() -> dict:
    d = _fresh("multirun_bad_seed")
    rc, out, err = _run("b3dgs.train", ["-m", "seed=-1,1", *TINY, f"hydra.sweep.dir={d}"])
    runs = sorted(d.glob("*/metrics.json"))
    return {"exit_code": rc, "message": _message("train", rc, out, err), "ok": rc == 2 and len(runs) == 1,
            "checked": f"the job after it ran: {[r.parent.name for r in runs]}"}


def sc_study_reuse() -> dict:
    d = _fresh("study_reuse")
    study = ["data=synthetic", "data.max_side=16", "+data.n_views=24", "renderer=cpu", "trainer.max_steps=6",
             "trainer.checkpoint_every_s=0", "initial_views=4", "acquire=2", "seeds=[0]", "policies=[uniform]",
             "family_baselines=[]", "threads=1", "plots=false", "oracle=false", f"out_dir={d}"]
    rc0, _, err0 = _run("b3dgs.study.active", study)
    rc, out, err = _run("b3dgs.study.active", study + ["initial_views=3", "trainer.max_steps=9"])
    return {"exit_code": rc, "message": _message("study", rc, out, err), "ok": rc0 == 0 and rc == 2,
            "checked": f"first study exit {rc0}"}


def sc_report_pool() -> dict:
    d = _fresh("report_pool")
    _finished_run(d / "a")
    _finished_run(d / "b", "seed=1", "trainer.max_steps=6")
    rc, out, err = _run("b3dgs.report.app", [f"runs={d}/*", f"out={d / 'report'}"])
    rc2, _, err2 = _run("b3dgs.report.app", [f"runs={d}/*", f"out={d / 'report'}", "group_by=[trainer.max_steps]"])
    return {"exit_code": rc, "message": _message("report", rc, out, err), "ok": rc == 2 and rc2 == 0,
            "checked": f"with group_by=[trainer.max_steps]: exit {rc2}"}


def sc_eval_twice() -> dict:
    d = _finished_run(_fresh("eval_twice") / "run")
    rc, out, err = _run("b3dgs.eval", [f"run=[{d},{d}/.]", "uq=[ensemble]", f"hydra.run.dir={d.parent / 'eval'}"])
    return {"exit_code": rc, "message": _message("eval", rc, out, err), "ok": rc == 2, "checked": ""}


def sc_eval_elsewhere() -> dict:
    """b3dgs-eval from another folder on a run trained with a relative data.path."""
    from omegaconf import OmegaConf

    base = _fresh("eval_elsewhere")
    scene = base / "scene"
    shutil.copytree(_fox_variant("eval_elsewhere_fox", _set()), scene, symlinks=True)
    work = base / "work"
    work.mkdir()
    (work / "scene").symlink_to(scene)
    rc0, _, err0 = _run("b3dgs.train", ["data=transforms", "data.path=scene", "data.max_images=8", *SHORT,
                                        f"hydra.run.dir={base / 'run'}"], cwd=work)
    rc, out, err = _run("b3dgs.eval", [f"run={base / 'run'}", "uq=[proxy]", "max_views=1", "panels=0",
                                       f"hydra.run.dir={base / 'eval'}"], cwd=base)
    wrote = (base / "run" / "uq.json").exists()
    data_path = str(OmegaConf.load(base / "run" / "config.yaml").data.path).replace(str(ROOT) + "/", "")
    msg = f"uq.json written: {wrote}" if rc == 0 else _message("eval", rc, out, err)
    return {"exit_code": rc, "message": msg, "ok": rc0 == 0 and rc == 0 and wrote,
            "checked": f"config.yaml data.path = {json.dumps(data_path)}"}


def sc_png16() -> dict:
    """Two 16-bit frames holding the same raw value 200, one with a bright pixel: loaded as the same intensity."""
    from PIL import Image

    from b3dgs.data.images import load_image

    d = _fresh("png16")
    vals = []
    for name, peak in (("dark", 200), ("bright", 60000)):
        a = np.full((4, 4), 200, dtype=np.uint16)
        a[0, 0] = peak
        Image.fromarray(a).save(d / f"{name}.png")
        vals.append(float(load_image(d / f"{name}.png")[1, 1, 0]))
    return {"exit_code": 0, "message": f"raw 200 loads as {vals[0]:.6f} and {vals[1]:.6f} (200/65535 = {200 / 65535:.6f})",
            "ok": all(abs(v - 200 / 65535) < 1e-7 for v in vals), "checked": "b3dgs.data.images.load_image"}


def sc_get_photo_scene() -> dict:
    """``b3dgs-data get dtu_scan24`` into an empty data root with the shipped registry entry, only its host replaced by
    a loopback server (tests/loopback.py) serving a zip shaped as the entry's GitHub archive, of the shared copy's 49
    photos: its SfM layout step, then ``scene=dtu_scan24`` finds the scene."""
    import io
    import zipfile

    import yaml

    from b3dgs import datasets

    loopback = load_file(ROOT / "tests" / "loopback.py")
    d = _fresh("get_photo_scene")
    photos = sorted((shared_dir() / "data" / "dtu_scan24" / "images").iterdir())
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as z:
        for i, ph in enumerate(photos):  # NeuF's monosdf_DTU/scan24 names: <index>_rgb.png, beside other files
            z.writestr(f"NeuF-ebe501d/data/monosdf_DTU/scan24/{i:06d}_rgb.png", ph.read_bytes())
            z.writestr(f"NeuF-ebe501d/data/monosdf_DTU/scan24/{i:06d}_depth.npy", b"")
    with loopback.serve() as srv:
        reg = yaml.safe_load(datasets.REGISTRY_FILE.read_text())
        src = reg["dtu_scan24"]["sources"][0]
        path = "/" + src["url"].split("://", 1)[1].partition("/")[2]
        src["url"], srv.files[path] = srv.url + path, buf.getvalue()
        (d / "registry.yaml").write_text(yaml.safe_dump(reg))
        env = {k: v for k, v in os.environ.items() if k != "HYDRA_FULL_ERROR"}
        env.update({"B3DGS_DATA": str(d / "root"), datasets.REGISTRY_ENV: str(d / "registry.yaml")})
        rc, out, err = _wait(_popen("b3dgs.datasets", ["get", "dtu_scan24"], env=env, limit=False), 600)
    lines = [ln for ln in (out + err).splitlines() if ln.startswith(("dtu_scan24: ready", "b3dgs-data: error",
                                                                     "b3dgs-process: error"))]
    scene = d / "root" / "dtu_scan24"
    made = sorted(p.name for p in scene.iterdir()) if scene.is_dir() else []
    return {"exit_code": rc, "message": lines[-1] if lines else (err or out)[-300:],
            "ok": rc == 0 and made == ["images", "sparse"], "checked": f"the scene folder holds {made}"}


TRUNCATED_METRICS = '{"psnr": 2'


def _eval_run_with(name: str, file: str, text: str) -> Path:
    """A finished tiny run with ``file`` overwritten by ``text``."""
    d = FIX / name
    shutil.rmtree(d, ignore_errors=True)
    _finished_run(d)
    (d / file).write_text(text)
    return d


# ------------------------------------------------------------------------- third pass: results, run dirs
EVAL_SIDE = ["data.max_side=32"]  # LPIPS needs 31 px
EVAL_FAST = ["uq.samples=3", "max_views=2", "panels=1"]


def _eval(args: list[str], where: Path) -> tuple[int, str, str]:
    return _run("b3dgs.eval", [*args, *EVAL_FAST, f"hydra.run.dir={where}"])


def _regimes(path: Path) -> list[str]:
    return sorted(k for k in read_json(path, {}) if not k.startswith("_"))


def _last_line(out: str, err: str) -> str:
    """The last log line (progress bars aside)."""
    lines = [ln.split("] - ", 1)[-1] for ln in (out + "\n" + err).replace("\r", "\n").splitlines() if "] - " in ln]
    return lines[-1] if lines else ""


def sc_eval_keeps_regimes() -> dict:
    """uq=[proxy], then uq=[constant], then run=[A,B] uq=[ensemble]: A keeps both, the ensemble has its own folder."""
    base = _fresh("eval_keeps")
    a, b = _finished_run(base / "A", *EVAL_SIDE), _finished_run(base / "B", *EVAL_SIDE, "seed=1")
    rcs = [_eval([f"run={a}", f"uq=[{u}]"], base / "ev")[0] for u in ("proxy", "constant")]
    rc, out, err = _eval([f"run=[{a},{b}]", "uq=[ensemble]"], base / "ev")
    ens = base / "ensemble_A+B" / "uq.json"
    return {"exit_code": rc, "message": _last_line(out, err), "ok": rcs == [0, 0] and rc == 0 and _regimes(a / "uq.json")
            == ["constant", "proxy"] and _regimes(ens) == ["ensemble"],
            "checked": f"A/uq.json holds {_regimes(a / 'uq.json')}, ensemble_A+B/uq.json {_regimes(ens)}"}


def sc_eval_concurrent() -> dict:
    """Two b3dgs-eval on one run at once (uq=[proxy] and uq=[constant])."""
    base = _fresh("eval_concurrent")
    a = _finished_run(base / "A", *EVAL_SIDE)
    procs = [_popen("b3dgs.eval", [f"run={a}", f"uq=[{u}]", *EVAL_FAST, f"hydra.run.dir={base / u}"])
             for u in ("proxy", "constant")]
    res = [(p.wait(timeout=300), *p.communicate()) for p in procs]
    rc = max(r[0] for r in res)
    return {"exit_code": rc, "message": _last_line(res[-1][1], res[-1][2]),
            "ok": rc == 0 and _regimes(a / "uq.json") == ["constant", "proxy"],
            "checked": f"both exit 0; A/uq.json holds {_regimes(a / 'uq.json')}"}


def sc_eval_other_run() -> dict:
    """b3dgs-eval run=A out=B, then b3dgs-report runs=B: B's row must not show A's uncertainty (b3dgs-eval now refuses
    out= another run's dir up front; a uq.json put there by hand is still left out of the report)."""
    base = _fresh("eval_other_run")
    a, b = _finished_run(base / "A", *EVAL_SIDE), _finished_run(base / "B", *EVAL_SIDE, "seed=1")
    rc0, out0, err0 = _eval([f"run={a}", "uq=[proxy]", f"out={b}"], base / "ev")
    if rc0 == 2 and "is the run dir of another run" in err0:
        rc1, _, _ = _eval([f"run={a}", "uq=[proxy]", f"out={base / 'A_uq'}"], base / "ev")  # elsewhere, then by hand
        if rc1 == 0:
            shutil.copy(base / "A_uq" / "uq.json", b / "uq.json")
    rc, out, err = _run("b3dgs.report.app", [f"runs={b}", f"out={base / 'report'}"])
    rows = json.loads((base / "report" / "report.json").read_text())["runs"] if rc == 0 else []
    flagged = [ln.split("] - ", 1)[-1] for ln in (out + err).splitlines() if "left out of the report" in ln]
    refused = _message("eval", rc0, out0, err0) if rc0 == 2 else None
    ok = rc0 in (0, 2) and rc == 0 and bool(flagged) and all(not r["uq_regimes"] for r in rows)
    return {"exit_code": rc, "message": (refused + " / " if refused else "")
            + (flagged[0] if flagged else _message("report", rc, out, err)), "ok": ok,
            "checked": f"B's report row has uq regimes {[r['uq_regimes'] for r in rows]}"}


def sc_eval_running() -> dict:
    """b3dgs-eval on a run that is still training (stopped by its own test hook at step 1)."""
    d = _fresh("eval_running") / "run"
    first = _popen("b3dgs.train", [*TINY, *EVAL_SIDE, f"hydra.run.dir={d}", *kill_args(step=1, sig="STOP")], limit=False)
    os.waitpid(first.pid, os.WUNTRACED)
    try:
        rc, out, err = _eval([f"run={d}", "uq=[proxy]"], d.parent / "ev")
    finally:
        os.kill(first.pid, signal.SIGCONT)
    first.communicate(timeout=300)
    return {"exit_code": rc, "message": _message("eval", rc, out, err), "ok": rc == 2 and "still training" in err,
            "checked": f"the training then finished (exit {first.returncode})"}


def sc_ensemble_mismatch(extra: list[str]) -> dict:
    base = _fresh("ensemble_mismatch_" + extra[0].split("=")[0].replace(".", "_"))
    a, b = _finished_run(base / "A", *EVAL_SIDE), _finished_run(base / "B", *EVAL_SIDE, "seed=1", *extra)
    rc, out, err = _eval([f"run=[{a},{b}]", "uq=[ensemble]"], base / "ev")
    return {"exit_code": rc, "message": _message("eval", rc, out, err), "ok": rc == 2 and not (a / "uq.json").exists()
            and not list(base.glob("ensemble_*")), "checked": "nothing written"}


USER_FILES = {"config.yaml": b"model: resnet50\n", "checkpoints/resnet_epoch90.ckpt": b"\x00resnet weights",
              "renders/figure1.png": b"\x89PNG figure 1"}


def _user_files(d: Path, names=USER_FILES) -> dict:
    for name, data in names.items():
        (d / name).parent.mkdir(parents=True, exist_ok=True)
        (d / name).write_bytes(data)
    return {k: (d / k).read_bytes() for k in names}


def _all_bytes(d: Path) -> dict:
    return {str(p.relative_to(d)): p.read_bytes() for p in sorted(d.rglob("*")) if p.is_file()}


def sc_overwrite_foreign() -> dict:
    """overwrite=true on a folder of someone else's config.yaml, checkpoints/ and renders/."""
    d = _fresh("overwrite_foreign") / "work"
    _user_files(d)
    before = _all_bytes(d)
    rc, out, err = _run("b3dgs.train", [*TINY, "overwrite=true", f"hydra.run.dir={d}"])
    return {"exit_code": rc, "message": _message("train", rc, out, err), "ok": rc == 2 and _all_bytes(d) == before,
            "checked": "every file byte for byte"}


def sc_overwrite_user_files() -> dict:
    """overwrite=true on a b3dgs run dir into whose renders/ and checkpoints/ a user put files of their own."""
    d = _finished_run(_fresh("overwrite_run") / "run")
    mine = _user_files(d, {k: v for k, v in USER_FILES.items() if k != "config.yaml"})
    rc, out, err = _run("b3dgs.train", [*TINY, "overwrite=true", "seed=1", f"hydra.run.dir={d}"])
    kept = {k: (d / k).read_bytes() for k in mine if (d / k).exists()} == mine
    seed = json.loads((d / "metrics.json").read_text())["seed"] if (d / "metrics.json").exists() else None
    return {"exit_code": rc, "message": _message("train", rc, out, err), "ok": rc == 0 and kept and seed == 1,
            "checked": f"the user's files byte for byte: {kept}; metrics.json of the new run (seed {seed})"}


def sc_run_dir_dot() -> dict:
    """`hydra.run.dir=.` in a folder whose renders/ holds a user's file."""
    d = _fresh("run_dir_dot")
    _user_files(d, {"renders/figure1.png": USER_FILES["renders/figure1.png"]})
    before = _all_bytes(d)
    rc, out, err = _run("b3dgs.train", [*TINY, "hydra.run.dir=."], cwd=d)
    return {"exit_code": rc, "message": _message("train", rc, out, err).replace(str(d), "<folder>"),
            "ok": rc == 2 and _all_bytes(d) == before, "checked": "the folder byte for byte"}


def sc_resume_renderer() -> dict:
    """SIGTERM a renderer=cpu run after its first checkpoint, then `resume=auto renderer=torch`."""
    d = _fresh("resume_renderer") / "run"
    rc0, _, _ = _run("b3dgs.train", [*TINY, "renderer=cpu", f"hydra.run.dir={d}", *kill_args(step=3, sig="TERM")])
    config = (d / "config.yaml").read_text() if (d / "config.yaml").exists() else None
    rc, out, err = _run("b3dgs.train", [*TINY, "resume=auto", "renderer=torch", f"hydra.run.dir={d}"])
    same = config is not None and (d / "config.yaml").read_text() == config
    rc2, _, _ = _run("b3dgs.train", [*TINY, "resume=auto", "renderer=cpu", f"hydra.run.dir={d}"])
    return {"exit_code": rc, "message": _message("train", rc, out, err),
            "ok": rc0 == 143 and rc == 2 and same and rc2 == 0 and (d / "metrics.json").exists(),
            "checked": f"stopped with exit {rc0}; config.yaml kept the C++ renderer; resume=auto renderer=cpu then "
                       f"finished (exit {rc2})"}


def rows() -> list[dict]:
    """(id, what, app, overrides or a fixture builder returning them, expected outcome)."""
    S = shared_dir() / "data"
    fox = ["data=transforms", "data.max_images=8"]
    head = ["data=colmap", "data.max_images=8"]
    R = []

    def add(rid, what, args, expect="refused", app="train"):
        R.append({"id": rid, "what": what, "app": app, "args": args, "expect": expect})

    # --- config values (refused before the scene loads)
    add("plus_typo", "`+trainer.max_stpes=50` (typo added with +)", ["+trainer.max_stpes=50"])
    add("plus_typo_strategy", "`+strategy.refine_evry=5`", ["+strategy.refine_evry=5"])
    add("plus_typo_data", "`+data.nviews=16`", ["+data.nviews=16"])
    add("plus_top_level", "`+foo=1` (unknown top-level key)", ["+foo=1"])
    add("posterior_dup", "`posterior=[niw,niw]`", ["posterior=[niw,niw]"])
    add("unknown_block", "`+posterior.bogus.x=1`", ["+posterior.bogus.x=1"])
    add("max_side_0", "`data.max_side=0`", ["data.max_side=0"])
    add("max_side_neg", "`data.max_side=-3`", ["data.max_side=-3"])
    add("background_data", "`data.background=[2,-1,0.5]`", ["data.background=[2,-1,0.5]"])
    add("background_model", "`model.background=[2,-1,0.5]`", ["model.background=[2,-1,0.5]"])
    add("test_every_neg", "`data.test_every=-1`", ["data.test_every=-1"])
    add("init_opacity_1", "`model.init_opacity=1.0` (crashed in write_ply after training)", ["model.init_opacity=1.0"])
    add("sh_degree_4", "`model.sh_degree=4`", ["model.sh_degree=4"])
    add("lr_negative", "`model.lr_means=-1`", ["model.lr_means=-1"])
    add("max_steps_str", "`trainer.max_steps=abc`", ["trainer.max_steps=abc"])
    add("max_steps_0", "`trainer.max_steps=0`", ["trainer.max_steps=0"])
    add("refine_every_0", "`strategy.refine_every=0`", ["strategy.refine_every=0"])
    add("niw_kappa_neg", "`model=niw posterior.niw.kappa0=-1`", ["model=niw", "posterior.niw.kappa0=-1"])
    add("renderer_near_0", "`renderer.near=0`", ["renderer.near=0"])
    add("no_such_option", "`trainer=nope` (no such option)", ["trainer=nope"])
    add("colmap_no_path", "`data=colmap` without data.path", ["data=colmap"])
    add("path_missing", "`data=transforms data.path=/nonexistent`", ["data=transforms", "data.path=/nonexistent/scene"])
    add("resume_missing", "`resume=/nonexistent/last.ckpt`", ["resume=/nonexistent/last.ckpt"])
    add("resume_damaged", "`resume=` a truncated checkpoint", lambda: [f"resume={_bad_ckpt()}"])
    # --- cameras (transforms.json)
    add("focal_zero", "`fl_x = fl_y = 0` in transforms.json",
        lambda: fox + [f"data.path={_fox_variant('focal_zero', _set(fl_x=0.0, fl_y=0.0))}"])
    add("focal_negative", "negative focal in transforms.json",
        lambda: fox + [f"data.path={_fox_variant('focal_neg', _set(fl_x=-343.88, fl_y=-343.6))}"])
    add("pp_outside", "principal point outside the image (cx=1000)",
        lambda: fox + [f"data.path={_fox_variant('pp_outside', _set(cx=1000.0))}"])
    add("mixed_sizes", "mixed image sizes (x1/2) without w/h: intrinsics scaled",
        lambda: fox + SHORT + [f"data.path={_fox_variant('mixed', _mixed_sizes(True))}"], expect="accepted")
    add("mixed_sizes_bad", "mixed image sizes of another aspect ratio without w/h",
        lambda: fox + [f"data.path={_fox_variant('mixed_bad', _mixed_sizes(False))}"])
    add("tiny_extent", "a scene of extent ~4e-4 with `normalize=false`",
        lambda: fox + ["data.normalize=false", f"data.path={_fox_variant('tiny', _tiny_scene)}"])
    # --- COLMAP files
    add("points3d_truncated", "`points3D.bin` truncated (pycolmap hung, 12.7 GB)",
        lambda: head + [f"data.path={_colmap_variant('p3d', 'points3D.bin', lambda n: n // 2)}"])
    add("images_cut_10", "`images.bin` cut by 10 bytes (loaded silently)",
        lambda: head + [f"data.path={_colmap_variant('img10', 'images.bin', lambda n: n - 10)}"])
    add("cameras_10_bytes", "`cameras.bin` cut to 10 bytes",
        lambda: head + [f"data.path={_colmap_variant('cam10', 'cameras.bin', lambda n: 10)}"])
    add("colmap_wrong_folder", "`data=colmap` on a transforms scene", head + [f"data.path={S / 'fox'}"])
    # --- accepted inputs that used to crash
    add("test_every_0", "`data.test_every=0` (Done line crashed on None)", ["data.test_every=0", "+data.n_views=8",
                                                                           *SHORT], expect="accepted")
    # --- b3dgs-eval
    add("eval_samples_1", "`b3dgs-eval uq.samples=1`", lambda: [f"run={_run_dir('run_ok', None)}", "uq.samples=1"],
        app="eval")
    add("eval_not_run_dir", "`b3dgs-eval run=/nonexistent`", ["run=/nonexistent"], app="eval")
    add("eval_no_ckpt", "`b3dgs-eval` on a run dir without a checkpoint",
        lambda: [f"run={_run_dir('run_no_ckpt', None)}"], app="eval")
    add("eval_damaged_ckpt", "`b3dgs-eval` on a run dir with a damaged last.ckpt",
        lambda: [f"run={_run_dir('run_bad_ckpt', b'PK garbage')}"], app="eval")
    add("eval_ensemble_one", "`b3dgs-eval uq=[ensemble]` with one run",
        lambda: [f"run=[{_run_dir('run_one', None)}]", "uq=[ensemble]"], app="eval")

    # --- issue 20: inputs
    for rid, args, note in [("seed_neg", ["seed=-1"], ""), ("seed_2_32", [f"seed={2**32}"], " (2^32)"),
                            ("init_scale_0", ["model.init_scale=0"], " (trained, then failed at the PLY write)"),
                            ("init_scale_neg", ["model.init_scale=-1"], " (blamed on learning rates)"),
                            ("percent_dense_neg", ["strategy.percent_dense=-1"], " (accepted)"),
                            ("plus_twice", ["+data.n_views=8", "+data.n_views=9"], " (reported as unknown)"),
                            ("plus_existing", ["+seed=3"], " (key already there; reported as unknown)")]:
        add(rid, f"`{' '.join(args)}`{note}", args)
    add("run_dir_file", "`hydra.run.dir=` a file", lambda: [f"hydra.run.dir={_a_file()}"])
    add("run_dir_below_file", "`hydra.run.dir=` below a file", lambda: [f"hydra.run.dir={_a_file()}/run"])
    add("disk_full", "disk full while writing the checkpoint (simulated: `ulimit -f 64`)", TINY + ["fsize"])
    add("huge_resolution", "`+data.resolution=30000` synthetic (MemoryError)", ["+data.n_views=8", "+data.resolution=30000",
                                                                                 "data.max_side=null"])
    add("transforms_non_numeric", "`fl_x: \"abc\"` in one frame of transforms.json",
        lambda: fox + [f"data.path={_fox_variant('non_numeric', lambda m, d: m['frames'][3].update(fl_x='abc'))}"])
    add("eval_metrics_truncated", "`b3dgs-eval` on a run whose metrics.json is truncated",
        lambda: [f"run={_eval_run_with('run_trunc_metrics', 'metrics.json', TRUNCATED_METRICS)}", "uq=[proxy]"], app="eval")
    add("eval_config_corrupt", "`b3dgs-eval` on a run whose config.yaml is corrupt",
        lambda: [f"run={_eval_run_with('run_bad_cfg', 'config.yaml', 'data: [unclosed')}", "uq=[proxy]"], app="eval")
    add("eval_out_file", "`b3dgs-eval out=` a file", lambda: [f"run={_run_dir('run_out', None)}", f"out={_a_file()}"], app="eval")
    add("study_acquire_0", "`b3dgs-study active acquire=0` (\"max_images must be positive\" after phase 1)",
        ["data=synthetic", "+data.n_views=24", "acquire=0"], app="study.active")
    add("study_initial_0", "`b3dgs-study active initial_views=0`", ["data=synthetic", "+data.n_views=24", "initial_views=0"],
        app="study.active")

    # --- issue 20: scenarios
    def scen(rid, what, fn, expect="refused"):
        R.append({"id": rid, "what": what, "app": "train", "args": [], "expect": expect, "scenario": fn})

    scen("concurrent_one_dir", "two `b3dgs-train` on one run dir at once (both ran, one result lost)", sc_concurrent)
    scen("default_dirs_same_second", "two `b3dgs-train` with the default run dir started together", sc_default_dirs,
         "accepted")
    scen("sigterm", "SIGTERM during training (exit 0, no message)", lambda: sc_signal("TERM", 143), "interrupted")
    scen("sigint", "SIGINT (Ctrl-C) during training", lambda: sc_signal("INT", 130), "interrupted")
    scen("ctrl_c_final_eval", "Ctrl-C during the final evaluation (traceback)", sc_final_ctrl_c, "interrupted")
    scen("kill9_ply_write", "kill -9 inside the PLY write, then `resume=auto` (counters emptied, .tmp left)",
         lambda: sc_kill_final_write("point_cloud.ply"), "accepted")
    scen("kill9_metrics_write", "kill -9 inside the metrics.json write, then `resume=auto`",
         lambda: sc_kill_final_write("metrics.json"), "accepted")
    scen("resume_finished", "`resume=auto` on a finished run (rewrote metrics.json)", sc_finished_resume, "accepted")
    scen("refused_leaves_nothing", "a refused run (dir holds a run) left .hydra/ and train.log", sc_refused_leaves_nothing)
    scen("joblib_n_jobs_2", "joblib multirun `n_jobs=2` over `model.sh_degree=0,1`", sc_joblib, "accepted")
    scen("multirun_bad_seed", "multirun `seed=-1,1` (the job after the bad one never ran)", sc_multirun_bad_seed)
    scen("study_other_settings", "`b3dgs-study active` again into one out_dir with other initial_views / max_steps "
         "(old rows reused)", sc_study_reuse)
    scen("report_mixed_protocols", "`b3dgs-report` over runs of 4 and 6 steps (pooled as seeds)", sc_report_pool)
    scen("eval_ensemble_twice", "`b3dgs-eval uq=[ensemble]` with one run twice (zero spread)", sc_eval_twice)
    scen("eval_other_cwd", "`b3dgs-eval` from another folder, run trained with a relative data.path", sc_eval_elsewhere,
         "accepted")
    scen("get_photo_scene", "`b3dgs-data get dtu_scan24` (a registry scene made by SfM) into an empty data root "
         "(refused at its SfM step: b3dgs-process would not take a name conf/scene/ has)", sc_get_photo_scene,
         "accepted")
    scen("png16_scaling", "16-bit PNGs: one raw value in a dark and in a bright frame (0.784 vs 0.003)", sc_png16,
         "accepted")

    # --- third pass: results never lost, run dirs, renderers, devices
    scen("eval_keeps_regimes", "`uq=[proxy]`, then `uq=[constant]`, then `run=[A,B] uq=[ensemble]` (A kept only "
         "the last regime; the ensemble replaced A's)", sc_eval_keeps_regimes, "accepted")
    scen("eval_concurrent", "two `b3dgs-eval` on one run at once (one result lost)", sc_eval_concurrent, "accepted")
    scen("eval_out_other_run", "`b3dgs-eval run=A out=B`, then `b3dgs-report runs=B` (B's row showed A's AUSE and "
         "ECE)", sc_eval_other_run, "accepted")
    scen("eval_running_run", "`b3dgs-eval` on a run still training (fix said resume=auto)", sc_eval_running)
    scen("ensemble_other_model", "`run=[standard, niw] uq=[ensemble]` (accepted, NLL 378159)",
         lambda: sc_ensemble_mismatch(["model=niw"]))
    scen("ensemble_other_steps", "`run=[4-step, 6-step] uq=[ensemble]` (accepted)",
         lambda: sc_ensemble_mismatch(["trainer.max_steps=6"]))
    scen("overwrite_foreign", "`overwrite=true` on a folder of a user's config.yaml, checkpoints/resnet_epoch90.ckpt "
         "and renders/figure1.png (both files deleted)", sc_overwrite_foreign)
    scen("overwrite_user_files", "`overwrite=true` on a b3dgs run dir holding a user's files in renders/ and "
         "checkpoints/", sc_overwrite_user_files, "accepted")
    scen("run_dir_dot", "`hydra.run.dir=.` in a folder whose renders/ holds a user's file (accepted; a later "
         "overwrite=true deleted it)", sc_run_dir_dot)
    scen("resume_other_renderer", "SIGTERM after the first checkpoint, then `resume=auto renderer=torch` after a C++ "
         "start (accepted: 34.472 vs 34.424 dB)", sc_resume_renderer)
    add("gsplat_on_cpu", "`renderer=gsplat` on a CPU-only machine (\"unexpected error (a bug)\", exit 1)",
        ["renderer=gsplat", *TINY])
    add("devices_2_cpu", "`trainer.devices=2` on the CPU (a child fought its parent for the lock, left config.yaml)",
        ["trainer.devices=2", *TINY])
    add("max_gaussians_below_init", "`strategy.max_gaussians=100`, below the initial Gaussians (no warning)",
        ["strategy.max_gaussians=100", *TINY], expect="accepted")
    return R


def _a_file() -> Path:
    return _fixture_file("a_file", b"not a folder\n")


def _limit() -> None:
    os.setsid()
    resource.setrlimit(resource.RLIMIT_AS, (MEM_LIMIT, MEM_LIMIT))


def _message(app: str, rc: int, out: str, err: str) -> str:
    prog = f"b3dgs-{app}"
    lines = [ln.strip() for ln in (err + "\n" + out).replace("\r", "\n").splitlines() if ln.strip()]
    for ln in lines:
        if ln.startswith(f"{prog}: error:"):
            return ln
    if rc == 0:
        warn = [ln for ln in lines if "[WARNING]" in ln and "b3dgs" in ln]
        done = [ln for ln in lines if "Done:" in ln]
        pick = warn[:1] + done[-1:]
        return " / ".join(ln.split("] - ", 1)[-1] for ln in pick)
    return (lines[-1] if lines else "")[:400]


def run_scenario(row: dict) -> dict:
    t0 = time.perf_counter()
    res = row["scenario"]()
    msg = str(res["message"]).replace(str(ROOT) + "/", "")
    if res.get("checked"):
        msg += f" [checked: {str(res['checked']).replace(str(ROOT) + '/', '')}]"
    return {"id": row["id"], "input": row["what"], "command": "scenario " + row["id"], "expect": row["expect"],
            "exit_code": res["exit_code"], "message": msg, "lines_on_stderr": None,
            "seconds": round(time.perf_counter() - t0, 1), "ok": bool(res["ok"])}


def _limit_fsize() -> None:
    _limit()
    resource.setrlimit(resource.RLIMIT_FSIZE, (64 * 1024, 64 * 1024))


def run_row(row: dict, timeout: int) -> dict:
    if "scenario" in row:
        return run_scenario(row)
    args = row["args"]() if callable(row["args"]) else list(row["args"])
    preexec = _limit
    if "fsize" in args:
        args, preexec = [a for a in args if a != "fsize"], _limit_fsize
    run_dir = WORK / "runs" / row["id"]
    shutil.rmtree(run_dir, ignore_errors=True)
    app = "study" if row["app"].startswith("study") else row["app"]
    given = any(a.startswith("hydra.run.dir=") for a in args)
    where = [f"out_dir={run_dir}"] if app == "study" else [] if given else [f"hydra.run.dir={run_dir}"]
    t0 = time.perf_counter()
    rc, out, err = _wait(_popen(f"b3dgs.{row['app']}", [*args, *where], limit=preexec), timeout)
    secs = time.perf_counter() - t0
    msg = f"TIMEOUT after {timeout} s" if rc is None else _message(app, rc, out, err)
    ok = (rc == 2 and msg.startswith(f"b3dgs-{app}: error:")) if row["expect"] == "refused" else rc == 0
    shown = [a.replace(str(ROOT) + "/", "").replace(str(shared_dir()), "shared") for a in args]
    return {"id": row["id"], "input": row["what"], "command": f"b3dgs-{app} " + " ".join(shown),
            "expect": row["expect"], "exit_code": rc, "message": msg.replace(str(ROOT) + "/", ""),
            "lines_on_stderr": len([ln for ln in err.splitlines() if ln.strip()]), "seconds": round(secs, 1), "ok": ok}


def write(results: dict) -> None:
    order = [r["id"] for r in rows()]
    done = [results[i] for i in order if i in results]
    from b3dgs.report.document import markdown_table

    lines = ["# Reliability: bad inputs and what b3dgs now says", "",
             f"Generated by `python -m bench.reliability` ({len(done)} rows, {sum(r['ok'] for r in done)} as expected: "
             "refused with one line and exit code 2, accepted with exit code 0, or interrupted with exit code 130 / "
             "143 and one line). Scenario rows (several commands) say in [checked: ...] what was verified besides "
             "the exit code and line shown.", ""]
    lines += markdown_table(["#", "input", "exit", "one-line message", "s"],
                            [[str(k), r["input"], f"{r['exit_code']}{'' if r['ok'] else ' **(unexpected)**'}",
                              r["message"], str(r["seconds"])] for k, r in enumerate(done, 1)])
    write_results("reliability", {"rows": done, "n": len(done), "n_ok": sum(r["ok"] for r in done)}, "\n".join(lines),
                  echo=False)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--force", action="store_true", help="re-run rows already in reliability.json")
    ap.add_argument("--only", nargs="*", default=None, help="row ids to run")
    ap.add_argument("--timeout", type=int, default=180, help="seconds per row")
    a = ap.parse_args()
    path = RESULTS / "reliability.json"
    results = {r["id"]: r for r in json.loads(path.read_text())["rows"]} if path.exists() else {}
    for row in rows():
        if (a.only is not None and row["id"] not in a.only) or (row["id"] in results and not a.force):
            continue
        res = run_row(row, a.timeout)
        results[row["id"]] = res
        write(results)  # after every row: an interrupted run resumes where it stopped
        print(f"{res['id']:>22} rc={res['exit_code']} {res['seconds']:>6}s {'ok ' if res['ok'] else 'BAD'} {res['message'][:150]}",
              flush=True)
    write(results)


if __name__ == "__main__":
    main()

"""Bad, extreme and damaged inputs: what ``b3dgs-train`` / ``b3dgs-eval`` now say about each.

Every row runs the real command in a subprocess (its own process group, a wall-clock timeout and a
6 GiB address-space limit, so a hang or a memory blow-up is recorded instead of taking the machine
down) and keeps its exit code and the one line it prints: the ``<prog>: error: ...`` line for a
refused input, the warning or the final ``Done:`` line for an accepted one.

Damaged scenes are built under ``outputs/bench/reliability/fixtures`` from copies of the shared
scenes (never written to). Results go to ``bench/results/reliability.{json,md}``, rewritten
atomically after every row; rows already measured are skipped unless ``--force``.

    python bench/reliability.py [--force] [--only ID ...] [--timeout 180]
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

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from bench.common import RESULTS, shared_dir  # noqa: E402
from b3dgs.io import atomic_path, write_json  # noqa: E402

WORK = ROOT / "outputs" / "bench" / "reliability"
FIX = WORK / "fixtures"
MEM_LIMIT = 6 * 2**30
# short, small runs for the rows that are expected to train
SHORT = ["trainer.max_steps=2", "trainer.eval_every=1", "trainer.checkpoint_every=1", "trainer.progress_bar=false",
         "logger=none", "trainer.save_renders=false", "data.max_side=64"]


def _fox_meta() -> dict:
    return json.loads((shared_dir() / "data" / "fox" / "transforms.json").read_text())


def _fox_variant(name: str, edit) -> Path:
    """A copy of the fox scene's transforms.json (images linked, not copied) changed by ``edit(meta, dir)``."""
    d = FIX / name
    if d.exists():
        shutil.rmtree(d)
    d.mkdir(parents=True)
    (d / "images").symlink_to(shared_dir() / "data" / "fox" / "images")
    meta = _fox_meta()
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
    d = FIX / name
    if d.exists():
        shutil.rmtree(d)
    head = shared_dir() / "data" / "ethiopian_head"
    (d / "sparse").mkdir(parents=True)
    shutil.copytree(head / "sparse" / "0", d / "sparse" / "0")
    (d / "images").symlink_to(head / "images")
    p = d / "sparse" / "0" / file
    data = p.read_bytes()
    p.chmod(0o644)
    p.write_bytes(data[: keep(len(data))])
    return d


def _run_dir(name: str, ckpt: bytes | None) -> Path:
    """A run dir holding a config.yaml and, if given, a checkpoints/last.ckpt with these bytes."""
    d = FIX / name
    if d.exists():
        shutil.rmtree(d)
    (d / "checkpoints").mkdir(parents=True)
    (d / "config.yaml").write_text("seed: 0\n")
    if ckpt is not None:
        (d / "checkpoints" / "last.ckpt").write_bytes(ckpt)
    return d


def _bad_ckpt() -> Path:
    p = FIX / "truncated.ckpt"
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_bytes(b"PK\x03\x04" + bytes(range(256)) * 4)
    return p


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
    return R


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


def run_row(row: dict, timeout: int) -> dict:
    args = row["args"]() if callable(row["args"]) else list(row["args"])
    run_dir = WORK / "runs" / row["id"]
    if run_dir.exists():
        shutil.rmtree(run_dir)
    cmd = [sys.executable, "-m", f"b3dgs.{row['app']}", *args, f"hydra.run.dir={run_dir}"]
    env = {k: v for k, v in os.environ.items() if k != "HYDRA_FULL_ERROR"}
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=_limit)
    try:
        out, err = proc.communicate(timeout=timeout)
        rc = proc.returncode
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        out, err = proc.communicate()
        rc = None
    secs = time.perf_counter() - t0
    msg = f"TIMEOUT after {timeout} s" if rc is None else _message(row["app"], rc, out, err)
    ok = (rc == 2 and msg.startswith(f"b3dgs-{row['app']}: error:")) if row["expect"] == "refused" else rc == 0
    shown = [a.replace(str(ROOT) + "/", "").replace(str(shared_dir()), "shared") for a in args]
    return {"id": row["id"], "input": row["what"], "command": f"b3dgs-{row['app']} " + " ".join(shown),
            "expect": row["expect"], "exit_code": rc, "message": msg.replace(str(ROOT) + "/", ""),
            "lines_on_stderr": len([ln for ln in err.splitlines() if ln.strip()]), "seconds": round(secs, 1), "ok": ok}


def write(results: dict) -> None:
    order = [r["id"] for r in rows()]
    done = [results[i] for i in order if i in results]
    write_json(RESULTS / "reliability.json", {"rows": done, "n": len(done), "n_ok": sum(r["ok"] for r in done)})
    esc = lambda s: str(s).replace("|", "\\|")  # noqa: E731
    lines = ["# Reliability: bad inputs and what b3dgs now says", "",
             f"Generated by `python bench/reliability.py` ({len(done)} rows, {sum(r['ok'] for r in done)} as expected: "
             "refused with one line and exit code 2, or accepted with exit code 0).", "",
             "| # | input | exit | one-line message | s |", "|---|---|---|---|---|"]
    for k, r in enumerate(done, 1):
        flag = "" if r["ok"] else " **(unexpected)**"
        lines.append(f"| {k} | {esc(r['input'])} | {r['exit_code']}{flag} | {esc(r['message'])} | {r['seconds']} |")
    RESULTS.mkdir(parents=True, exist_ok=True)
    with atomic_path(RESULTS / "reliability.md") as tmp:
        tmp.write_text("\n".join(lines) + "\n")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--force", action="store_true", help="re-run rows already in reliability.json")
    ap.add_argument("--only", nargs="*", default=None, help="row ids to run")
    ap.add_argument("--timeout", type=int, default=180, help="seconds per row")
    a = ap.parse_args()
    path = RESULTS / "reliability.json"
    results = {r["id"]: r for r in json.loads(path.read_text())["rows"]} if path.exists() else {}
    for row in rows():
        if a.only is not None and row["id"] not in a.only:
            continue
        if row["id"] in results and not a.force:
            continue
        res = run_row(row, a.timeout)
        results[row["id"]] = res
        write(results)  # after every row: an interrupted run resumes where it stopped
        print(f"{res['id']:>22} rc={res['exit_code']} {res['seconds']:>6}s {'ok ' if res['ok'] else 'BAD'} {res['message'][:150]}",
              flush=True)
    write(results)


if __name__ == "__main__":
    main()

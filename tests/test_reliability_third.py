"""Third reliability pass: b3dgs-eval never loses a result (regimes merged under a lock, ensembles in their own
folder), overwrite=true removes only what b3dgs wrote (the run manifest), a resume refuses another renderer, the
report uses only the uq.json regimes of its own run, and one-line refusals (gsplat or several devices on the CPU,
fix texts that are true)."""
import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch
import yaml
from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra

from b3dgs.errors import B3dgsError, format_error
from b3dgs.train import CONF_DIR
from tests.inproc import train_here

ROOT = Path(__file__).resolve().parents[1]
TINY = ["data=synthetic", "+data.n_views=8", "data.max_side=32", "trainer.max_steps=4", "trainer.eval_every=100",
        "trainer.checkpoint_every=2", "trainer.enable_progress_bar=false", "logger=none", "threads=1"]


def run_train(run_dir: Path, overrides: list[str]) -> dict:
    return train_here(run_dir, [*TINY, *overrides])


def snapshot(d: Path) -> dict:
    return {str(p.relative_to(d)): p.read_bytes() for p in sorted(d.rglob("*")) if p.is_file()}


def _cli(module: str, args: list[str], **kw) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k != "HYDRA_FULL_ERROR"}
    return subprocess.run([sys.executable, "-m", module, *args], capture_output=True, text=True, timeout=600,
                          cwd=ROOT, env=env, **kw)


# ------------------------------------------------------------------------------------------ overwrite
def test_overwrite_removes_only_what_b3dgs_wrote(tmp_path):
    """A folder of someone else's files (config.yaml, checkpoints/, renders/) is refused for a new run, for
    overwrite=true and for resume=auto, and stays byte for byte; in a b3dgs run dir (and in one written before run
    manifests) overwrite=true replaces the run and leaves the user's files in renders/ and checkpoints/ alone."""
    user = tmp_path / "user"
    for name, data in (("config.yaml", b"model: resnet\n"), ("checkpoints/resnet_epoch90.ckpt", b"\x00weights"),
                       ("renders/figure1.png", b"\x89PNG figure")):
        (user / name).parent.mkdir(parents=True, exist_ok=True)
        (user / name).write_bytes(data)
    before = snapshot(user)
    for extra in ([], ["overwrite=true"], ["resume=auto"]):
        with pytest.raises(B3dgsError, match=r"is not empty and holds no b3dgs run \(checkpoints/resnet_epoch90.ckpt, "
                                             r"config.yaml, renders/figure1.png\)"):
            run_train(user, extra)
        assert snapshot(user) == before

    run = tmp_path / "run"
    run_train(run, ["trainer.keep_checkpoints=true"])
    assert json.loads((run / ".b3dgs-run.json").read_text())["b3dgs_run"] == 2
    assert sorted(p.name for p in (run / "checkpoints").iterdir()) == ["last.ckpt", "step2.ckpt", "step4.ckpt"]
    mine = {"renders/figure1.png": b"\x89PNG figure", "checkpoints/resnet_epoch90.ckpt": b"\x00weights",
            "notes.txt": b"mine"}
    for name, data in mine.items():
        (run / name).write_bytes(data)
    with pytest.raises(ValueError, match="already holds a run"):
        run_train(run, [])
    for legacy in (False, True):
        if legacy:  # a run dir written before manifests: recognised by its config.yaml and metrics.json
            (run / ".b3dgs-run.json").unlink()
        m = run_train(run, ["overwrite=true", "seed=1"])
        assert m["seed"] == 1 and (run / ".b3dgs-run.json").is_file()
        assert {k: (run / k).read_bytes() for k in mine} == mine
        assert sorted(p.name for p in (run / "checkpoints").iterdir()) == ["last.ckpt", "resnet_epoch90.ckpt"]
        assert sorted(p.name for p in (run / "renders").iterdir()) == sorted(
            ["figure1.png"] + [f"{v['name']}.png" for v in m["per_view"]])


# ------------------------------------------------------------------------------------------ resume
def test_resume_refuses_another_renderer(tmp_path):
    """resume=auto renderer=torch after a C++ start is refused before anything is written, from the renderer
    recorded in the checkpoint or (checkpoints written before it) from the run's config.yaml."""
    d = tmp_path / "run"
    run_train(d, ["renderer=cpu"])
    ck = torch.load(d / "checkpoints" / "last.ckpt", weights_only=False)
    assert ck["b3dgs"]["identity"]["renderer"]["_target_"].endswith("CPURenderer")
    config = (d / "config.yaml").read_text()
    want = (r"resume: the checkpoint .*last.ckpt does not match this run: it was trained with renderer=cpu, this run "
            r"uses renderer=torch \(fix: pass renderer=cpu, or start afresh")
    with pytest.raises(B3dgsError, match=want):
        run_train(d, ["renderer=torch", "resume=auto"])
    with pytest.raises(B3dgsError, match=r"its renderer.near is 0.01, this run's 0.02 \(fix: pass renderer.near=0.01"):
        run_train(d, ["renderer=cpu", "renderer.near=0.02", "resume=auto"])
    assert run_train(d, ["renderer=cpu", "resume=auto"])["steps"] == 4  # the same renderer: accepted
    del ck["b3dgs"]["identity"]["renderer"]  # as written before the renderer was recorded
    torch.save(ck, d / "checkpoints" / "last.ckpt")
    with pytest.raises(B3dgsError, match=want):
        run_train(d, ["renderer=torch", "resume=auto"])
    assert (d / "config.yaml").read_text() == config


def test_check_devices_and_max_gaussians_warning(caplog):
    from b3dgs.lifecycle import check_devices, warn_disabled_options

    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        for devices, refused in (("2", True), ("[0,1]", True), ("-1", True), ("1", False), ("auto", False)):
            cfg = compose(config_name="train", overrides=["renderer=cpu", f"trainer.devices={devices}"])
            if refused:
                with pytest.raises(B3dgsError, match=r"asks for several training processes on the CPU, .*"
                                                     r"\(fix: pass trainer.devices=1"):
                    check_devices(cfg)
            else:
                check_devices(cfg)
    module = SimpleNamespace(strategy=SimpleNamespace(max_gaussians=100), num_gaussians=3874)
    with caplog.at_level("WARNING", logger="b3dgs.train"):
        warn_disabled_options(module)
        warn_disabled_options(SimpleNamespace(strategy=SimpleNamespace(max_gaussians=None), num_gaussians=3874))
    assert [r.getMessage() for r in caplog.records] == [
        "strategy.max_gaussians=100 is below the 3874 initial Gaussians: no Gaussian is ever added (densification by "
        "clone and split is off; only pruning changes the count) (fix: raise strategy.max_gaussians above 3874, or "
        "lower model.init_max_points)"]


@pytest.mark.skipif(torch.cuda.is_available(), reason="the CPU-only message")
def test_gsplat_and_several_devices_on_the_cpu_are_one_line(tmp_path):
    from b3dgs.render.renderers import GsplatRenderer

    with pytest.raises(RuntimeError) as e:
        GsplatRenderer().check_available()
    assert format_error(e.value) == ("renderer=gsplat needs a CUDA GPU, and none is visible here (fix: pass "
                                     "renderer=cpu or renderer=auto, which picks the C++ CPU backend here)")
    for arg, text in (("renderer=gsplat", "renderer=gsplat needs a CUDA GPU"),
                      ("trainer.devices=2", "trainer.devices=2 asks for several training processes on the CPU")):
        d = tmp_path / arg.split("=")[0]
        p = _cli("b3dgs.train", [*TINY, arg, f"hydra.run.dir={d}"])
        lines = [ln for ln in p.stderr.splitlines() if ln.strip()]
        assert p.returncode == 2 and len(lines) == 1 and lines[0].startswith(f"b3dgs-train: error: {text}"), p.stderr
        assert not d.exists()


def test_fix_texts_name_the_real_default():
    from b3dgs.validation import validate_config

    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        for over, default in ((["trainer.max_steps=abc"], 3000), (["trainer=quick", "trainer.max_steps=abc"], 300)):
            cfg = compose(config_name="train", overrides=over, return_hydra_config=True)
            with pytest.raises(B3dgsError, match=rf"\(fix: pass trainer.max_steps=<int>, like its default {default}\)"):
                validate_config(cfg)


# ------------------------------------------------------------------------------------------ eval
@pytest.fixture(scope="module")
def two_runs(tmp_path_factory):
    base = tmp_path_factory.mktemp("runs")
    run_train(base / "A", ["data.n_views=16"])  # two test views
    run_train(base / "B", ["data.n_views=16", "seed=1"])
    return base / "A", base / "B"


def _regimes(*names):
    from b3dgs_plugins.uq.constant import ConstantUQ
    from b3dgs_plugins.uq.ensemble import EnsembleUQ
    from b3dgs_plugins.uq.proxy import ProxyUQ

    make = {"proxy": lambda: ProxyUQ(samples=3), "constant": ConstantUQ, "ensemble": EnsembleUQ}
    return {n: make[n]() for n in names}


def test_eval_adds_regime_by_regime_and_ensembles_go_to_their_own_folder(two_runs, tmp_path):
    from b3dgs.eval import evaluate_uq

    a, b = two_runs
    evaluate_uq([str(a)], _regimes("proxy"), max_views=2, panels=1)
    evaluate_uq([str(a)], _regimes("constant"), max_views=2, panels=2)
    evaluate_uq([str(a), str(b)], _regimes("ensemble"), max_views=2, panels=1)
    uq = json.loads((a / "uq.json").read_text())
    assert sorted(uq) == ["_meta", "constant", "proxy"]
    assert uq["proxy"]["panels"] == ["uq/proxy_view_000.png"] and len(uq["constant"]["panels"]) == 2
    assert uq["proxy"]["run_checkpoints"] == [json.loads((a / "metrics.json").read_text())["checkpoint"]["params_sha256"]]
    assert {p.name for p in (a / "uq").iterdir()} == {"proxy_view_000.png", "constant_view_000.png",
                                                      "constant_view_008.png", "sparsification.png", "reliability.png"}
    ens = a.parent / "ensemble_A+B"
    assert sorted(json.loads((ens / "uq.json").read_text())) == ["_meta", "ensemble"]
    assert (ens / "uq" / "ensemble_view_000.png").is_file() and not list(ens.glob(".uq-staging*"))
    # a regime evaluated again replaces its entry and its panels together
    evaluate_uq([str(a)], _regimes("constant"), max_views=2, panels=1)
    uq = json.loads((a / "uq.json").read_text())
    assert sorted(uq) == ["_meta", "constant", "proxy"] and uq["constant"]["panels"] == ["uq/constant_view_000.png"]
    assert not (a / "uq" / "constant_view_008.png").exists()
    # asked with out=: the ensemble goes into A's uq.json too
    evaluate_uq([str(a), str(b)], _regimes("ensemble"), max_views=2, panels=0, out_dir=a)
    assert sorted(json.loads((a / "uq.json").read_text())) == ["_meta", "constant", "ensemble", "proxy"]
    manifest = json.loads((a / ".b3dgs-run.json").read_text())["files"]
    assert "uq/proxy_view_000.png" in manifest and "uq.json" in manifest


def test_two_evals_at_once_keep_both_regimes(two_runs, tmp_path):
    """Two b3dgs-eval processes on one run at once: both regimes are in its uq.json; the last line says where."""
    import shutil

    a = tmp_path / "A"
    shutil.copytree(two_runs[0], a, ignore=shutil.ignore_patterns("uq*", "tb_uq", ".uq*"))
    env = {k: v for k, v in os.environ.items() if k != "HYDRA_FULL_ERROR"}
    procs = [subprocess.Popen([sys.executable, "-m", "b3dgs.eval", f"run={a}", f"uq=[{u}]", "uq.samples=3",
                               "max_views=2", "panels=1", f"hydra.run.dir={tmp_path / ('ev_' + u)}"], cwd=ROOT, env=env,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for u in ("proxy", "constant")]
    for p, u in zip(procs, ("proxy", "constant")):
        out, err = p.communicate(timeout=600)
        assert p.returncode == 0, err[-2000:]
        last = [ln for ln in out.splitlines() if ln.strip()][-1]
        assert last.endswith(f"Wrote {u} to {a / 'uq.json'} (plots in {a / 'uq'})"), out[-1000:]
    assert sorted(json.loads((a / "uq.json").read_text())) == ["_meta", "constant", "proxy"]
    assert {"proxy_view_000.png", "constant_view_000.png"} <= {p.name for p in (a / "uq").iterdir()}


def test_merge_waits_for_the_lock(tmp_path):
    from filelock import FileLock

    from b3dgs.uq.store import LOCK_NAME, merge_into

    (tmp_path / "uq.json").write_text(json.dumps({"proxy": {"ece": 0.1}, "_meta": {"seed": 0}}))
    lock = FileLock(str(tmp_path / LOCK_NAME))
    lock.acquire()
    t = threading.Thread(target=merge_into, args=(tmp_path, {"constant": {"ece": 0.2, "panels": []}}, {"seed": 1}, None))
    t.start()
    time.sleep(0.5)
    assert t.is_alive()  # waiting for the other evaluation to finish its write
    lock.release()
    t.join(30)
    merged = json.loads((tmp_path / "uq.json").read_text())
    assert merged == {"proxy": {"ece": 0.1}, "constant": {"ece": 0.2, "panels": []}, "_meta": {"seed": 1}}


def test_eval_refuses_a_running_run_and_mismatched_members(two_runs, tmp_path):
    import shutil

    from b3dgs.eval import refuse_running
    from b3dgs.rundir import run_dir_lock
    from b3dgs.uq.store import check_members

    a, b = two_runs
    busy = tmp_path / "busy"
    with run_dir_lock(busy):
        with pytest.raises(B3dgsError, match=rf"the run {busy} is still training \(b3dgs-train pid {os.getpid()} "
                                             r"holds it\) \(fix: wait for that training to finish"):
            refuse_running([busy])
    refuse_running([a])
    check_members([a, b])

    def variant(name, cfg_edit=None, steps=None):
        d = tmp_path / name
        shutil.copytree(b, d, ignore=shutil.ignore_patterns("checkpoints", "renders", "uq*", "tb_uq"))
        cfg = yaml.safe_load((d / "config.yaml").read_text())
        if cfg_edit:
            cfg_edit(cfg)
        (d / "config.yaml").write_text(yaml.safe_dump(cfg))
        if steps is not None:
            m = json.loads((d / "metrics.json").read_text())
            m["steps"] = steps
            (d / "metrics.json").write_text(json.dumps(m))
        return d

    niw = variant("niw", lambda c: c["model"].update(name="niw"))
    longer = variant("longer", lambda c: c["trainer"].update(max_steps=8))
    scene = variant("scene", lambda c: c["data"].update(name="other"))
    steps = variant("steps", steps=3)
    for d, text in ((niw, 'model.name: "standard" in .*A, "niw" in .*niw'), (longer, "trainer.max_steps: 4 in"),
                    (scene, 'data.name: "synthetic" in .*A, "other"'), (steps, "different step counts: 4 in .*A, 3 in")):
        with pytest.raises(B3dgsError, match=rf"the ensemble members (differ in|trained for) .*{text}.*\(fix: pass run= "
                                             r"runs that differ only in seed"):
            check_members([a, d])
    with pytest.raises(B3dgsError, match="hold the same model"):
        check_members([b, variant("copy", lambda c: c.update(seed=5))])


# ------------------------------------------------------------------------------------------ report
def test_report_uses_only_the_uq_of_its_own_run(tmp_path, caplog):
    from b3dgs.report.collect import load_runs
    from tests.test_report import write_run

    entry = {"per_view": [], "ause_rmse": 0.02, "ece": 0.05, "cov95": 0.9}
    a = write_run(tmp_path / "A", "sceneA", "standard", 0, 20.0)
    b = write_run(tmp_path / "B", "sceneA", "standard", 1, 21.0)
    c = write_run(tmp_path / "C", "sceneA", "standard", 2, 22.0)
    for d, digest in ((a, "aaaa"), (b, "bbbb"), (c, "cccc")):
        m = json.loads((d / "metrics.json").read_text())
        m["checkpoint"] = {"global_step": 300, "num_gaussians": 1000, "params_sha256": digest}
        (d / "metrics.json").write_text(json.dumps(m))
    (a / "uq.json").write_text(json.dumps({"proxy": {**entry, "runs": [str(a)], "run_checkpoints": ["aaaa"]}}))
    # b3dgs-eval run=A out=B: A's uncertainty in B's folder
    (b / "uq.json").write_text(json.dumps({"proxy": {**entry, "runs": [str(a)], "run_checkpoints": ["aaaa"]},
                                           "constant": {**entry, "runs": [str(b)], "run_checkpoints": ["bbbb"]}}))
    # written before digests: a regime naming another existing run is left out, one naming a moved run is kept
    (c / "uq.json").write_text(json.dumps({"proxy": {**entry, "runs": [str(a)]},
                                           "constant": {**entry, "runs": ["/moved/away/C"]}}))
    with caplog.at_level("WARNING", logger="b3dgs.report.collect"):
        runs, _ = load_runs(str(tmp_path / "*"))
    uq = {r.path.name: sorted(r.uq) for r in runs}
    assert uq == {"A": ["proxy"], "B": ["constant"], "C": ["constant"]}
    msgs = [r.getMessage() for r in caplog.records]
    assert any(m.startswith(f"{b}: its uq.json regimes proxy score the run {a}, not this one: left out") for m in msgs)
    assert any(m.startswith(f"{c}: its uq.json regimes proxy score the run {a}") for m in msgs)


def test_run_files_match_whole_path_components(tmp_path):
    """Manifest patterns match one path component each: a user's checkpoints/step1/x.ckpt or renders/figure.png
    is not b3dgs's; a folder without a manifest is listed (up to a limit) as someone else's."""
    from b3dgs.rundir import MANIFEST_NAME, foreign_files, remove_run_files, run_dir_kind, run_files

    for name in ("checkpoints/last.ckpt", "checkpoints/step12.ckpt", "checkpoints/step1/x.ckpt", "renders/view_000.png",
                 "renders/figure.png", "uq/proxy_view_000.png", "uq/proxy_mine.png", "notes/config.yaml"):
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / name).write_text("x")
    (tmp_path / "metrics.json").write_text(json.dumps({"per_view": [{"name": "view_000.png"}]}))
    (tmp_path / "uq.json").write_text(json.dumps({"proxy": {"panels": ["uq/proxy_view_000.png"]}}))
    assert run_dir_kind(tmp_path) == "foreign" and run_files(tmp_path) == []
    assert len(foreign_files(tmp_path, limit=3)) == 3
    (tmp_path / MANIFEST_NAME).write_text(json.dumps({"b3dgs_run": 1, "writes": ["metrics.json", "checkpoints/last.ckpt",
                                                                                 "checkpoints/step[0-9]*.ckpt", "uq.json"]}))
    assert run_dir_kind(tmp_path) == "run"
    assert run_files(tmp_path) == ["checkpoints/last.ckpt", "checkpoints/step12.ckpt", "metrics.json",
                                   "renders/view_000.png", "uq.json", "uq/proxy_view_000.png"]
    remove_run_files(tmp_path)
    left = sorted(str(p.relative_to(tmp_path)) for p in tmp_path.rglob("*") if p.is_file())
    assert left == [MANIFEST_NAME, "checkpoints/step1/x.ckpt", "notes/config.yaml", "renders/figure.png",
                    "uq/proxy_mine.png"]


def test_a_damaged_manifest_is_refused_before_eval_or_render_write_anything(two_runs, tmp_path):
    """A truncated .b3dgs-run.json: b3dgs-eval and b3dgs-render exit 2 with one line, and nothing new is in the run
    dir (before, they wrote uq.json, panels and frames, then failed on the manifest; issue 46 §7)."""
    import shutil

    a = tmp_path / "A"
    shutil.copytree(two_runs[0], a, ignore=shutil.ignore_patterns("uq*", "tb_uq", ".uq*", "render"))
    (a / ".b3dgs-run.json").write_text('{"b3dgs_run": 1, "wri')
    before = snapshot(a)
    for module, args in (("b3dgs.eval", [f"run={a}", "uq=[constant]", "max_views=1"]),
                         ("b3dgs.render_cli", [f"run={a}", "path=test", "frames=2"])):
        res = _cli(module, args)
        lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
        assert res.returncode == 2 and len(lines) == 1 and "run manifest" in lines[0] and "damaged" in lines[0], \
            res.stderr[-2000:]
        assert "fix: pass out=DIR" in lines[0], lines[0]
        assert snapshot(a) == before, module

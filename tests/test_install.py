"""A non-editable install works away from the checkout: the wheel carries ``conf/`` (as ``b3dgs/conf``) and
the plugins (as ``b3dgs_plugins``), and the installed ``b3dgs-train`` composes and trains from another folder.
Run dirs and checkpoints that name the plugins by their old top-level package ``plugins.`` still load."""
import os
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

from b3dgs.checkpoint import identity_mismatch
from b3dgs.upgrade import upgrade_targets

REPO = Path(__file__).resolve().parents[1]


def _tracked_copy(dst: Path) -> Path:
    """The files git tracks (and untracked ones it does not ignore), copied to ``dst``: a build leaves no
    ``build/`` or ``*.egg-info`` in the checkout, and a stale one cannot leak into the wheel."""
    names = subprocess.run(["git", "ls-files", "-co", "--exclude-standard"], cwd=REPO, capture_output=True,
                           text=True, check=True).stdout.split("\n")
    for name in filter(None, names):
        src, out = REPO / name, dst / name
        if src.is_symlink():
            out.parent.mkdir(parents=True, exist_ok=True)
            out.symlink_to(os.readlink(src))
        elif src.is_file():
            out.parent.mkdir(parents=True, exist_ok=True)
            out.write_bytes(src.read_bytes())
    return dst


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    if subprocess.run(["git", "rev-parse"], cwd=REPO, capture_output=True).returncode != 0:
        pytest.skip("not a git checkout (the wheel is built from the files git tracks)")
    tmp = tmp_path_factory.mktemp("wheel")
    src = _tracked_copy(tmp / "src")
    res = subprocess.run([sys.executable, "-m", "pip", "wheel", str(src), "--no-deps", "--no-build-isolation",
                          "-q", "-w", str(tmp / "dist")], capture_output=True, text=True, timeout=600, cwd=tmp)
    assert res.returncode == 0, res.stderr[-2000:]
    (whl,) = (tmp / "dist").glob("b3dgs-*.whl")
    return whl


def test_wheel_carries_conf_and_plugins(wheel):
    names = set(zipfile.ZipFile(wheel).namelist())
    conf = {p.relative_to(REPO / "conf").as_posix() for p in (REPO / "conf").rglob("*.yaml")}
    assert {f"b3dgs/conf/{c}" for c in conf} <= names, "a conf/ file is missing from the wheel"
    for root, name in (("b3dgs", "b3dgs"), ("plugins", "b3dgs_plugins"), ("hydra_plugins", "hydra_plugins")):
        own = {f"{name}/{p.relative_to(REPO / root).as_posix()}" for p in (REPO / root).rglob("*.py")
               if "__pycache__" not in p.parts}
        assert own <= names, f"missing from the wheel: {sorted(own - names)[:5]}"
    assert not any(n.startswith("plugins/") for n in names), "plugins must install as b3dgs_plugins, not plugins"
    assert {"b3dgs/render/csrc/ext.cpp", "b3dgs/render/csrc/kernels.h"} <= names


@pytest.fixture(scope="module")
def venv(wheel, tmp_path_factory) -> Path:
    """A fresh venv (torch and the other dependencies from this interpreter's site-packages) holding the
    wheel, non-editable."""
    root = tmp_path_factory.mktemp("venv")
    subprocess.run([sys.executable, "-m", "venv", "--system-site-packages", str(root)], check=True, timeout=300)
    res = subprocess.run([str(root / "bin" / "python"), "-m", "pip", "install", "-q", "--no-deps", "--no-index",
                          str(wheel)], capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr[-2000:]
    return root


def _outside(venv: Path, args: list[str], cwd: Path, timeout: int = 300) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "HYDRA_FULL_ERROR")}
    return subprocess.run(args, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)


@pytest.mark.slow
def test_installed_train_composes_and_trains_outside_the_checkout(venv, tmp_path):
    where = _outside(venv, [str(venv / "bin" / "python"), "-c",
                            "import b3dgs, b3dgs_plugins; print(b3dgs.conf_dir()); print(b3dgs_plugins.__file__)"],
                     tmp_path)
    assert where.returncode == 0, where.stderr[-2000:]
    conf, plugins = where.stdout.split()
    assert conf.startswith(str(venv)) and plugins.startswith(str(venv)), where.stdout  # not the checkout's
    job = _outside(venv, [str(venv / "bin" / "b3dgs-train"), "--cfg", "job", "model=niw"], tmp_path)
    assert job.returncode == 0, job.stderr[-2000:]
    assert "_target_: b3dgs_plugins.strategy.default.AdaptiveDensityControl" in job.stdout
    assert "_target_: b3dgs_plugins.posterior.niw.NIWBlock" in job.stdout
    run = tmp_path / "run"
    res = _outside(venv, [str(venv / "bin" / "b3dgs-train"), "trainer=quick", "trainer.max_steps=50",
                          "trainer.eval_every=25", "trainer.enable_progress_bar=false", "logger=none", "model=niw",
                          f"hydra.run.dir={run}"], tmp_path, timeout=600)
    assert res.returncode == 0, res.stderr[-3000:]
    assert (run / "metrics.json").is_file() and (run / "point_cloud.ply").is_file()


def test_old_plugin_class_paths_still_load():
    old = {"strategy": {"_target_": "plugins.strategy.default.AdaptiveDensityControl", "refine_every": 100},
           "posterior": {"niw": {"_target_": "plugins.posterior.niw.NIWBlock"}}, "other": ["plugins.x", 1]}
    new = upgrade_targets(old)
    assert new["strategy"]["_target_"] == "b3dgs_plugins.strategy.default.AdaptiveDensityControl"
    assert new["posterior"]["niw"]["_target_"] == "b3dgs_plugins.posterior.niw.NIWBlock"
    assert new["other"] == ["plugins.x", 1]  # only _target_ values are class paths
    assert old["strategy"]["_target_"].startswith("plugins.")  # the input is left as it was
    saved = {"model": "niw", "posterior": old["posterior"], "strategy": old["strategy"], "hparams": {}}
    assert identity_mismatch(saved, upgrade_targets(saved)) is None

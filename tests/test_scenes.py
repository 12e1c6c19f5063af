"""Scenes and protocols as config: ``conf/scene/<name>.yaml`` (loader + folder under ``data_root``),
``conf/experiment/{study,smoke}.yaml``; bench/ reads them (``bench.common``) and takes any configured scene.

The seven benchmark scenes compose exactly the configs the campaigns ran with (``data=<loader> data.path=...`` plus
the old bench/common.py QUICK overrides), and their ``data`` nodes equal those of the archived runs."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra
from omegaconf import OmegaConf

from b3dgs.rundir import save_config
from b3dgs.train import CONF_DIR
from tests.fake_package import install_conf_package
from tests.test_data import _blender_scene

ROOT = Path(__file__).resolve().parents[1]
ARCHIVE = ROOT / "bench" / "results" / "runs"
#: the loaders of the benchmark scenes as bench/common.py SCENES had them before they became config
LOADERS = {"ethiopian_head": "colmap", "fox": "transforms", "lego": "blender", "fern": "colmap", "flower": "colmap",
           "dtu_scan24": "colmap", "dtu_scan65": "colmap"}
OLD_QUICK = ["data.max_side=256", "trainer.max_steps=3000", "trainer.enable_progress_bar=false", "logger=none",
             "trainer.save_renders=false"]


def _compose(overrides, config_name="train"):
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        cfg = compose(config_name=config_name, overrides=[*overrides, "trainer.default_root_dir=."])
    return OmegaConf.to_container(cfg, resolve=True)


@pytest.mark.parametrize("scene", sorted(LOADERS))
@pytest.mark.parametrize("model", ["standard", "niw"])
def test_scene_and_study_protocol_compose_the_campaign_config(scene, model):
    root = "/data/root"
    old = _compose([f"data={LOADERS[scene]}", f"data.path={root}/{scene}", *OLD_QUICK, f"model={model}", "seed=2",
                    f"data_root={root}"])
    new = _compose([f"scene={scene}", "experiment=study", f"model={model}", "seed=2", f"data_root={root}"])
    # the study protocol shows its progress bar since issue 44, a setting that changes no result
    from b3dgs.protocol import run_protocol

    assert run_protocol(new) == run_protocol(old)
    assert (old["trainer"].pop("enable_progress_bar"), new["trainer"].pop("enable_progress_bar")) == (False, True)
    assert new == old
    assert new["data"]["path"] == f"{root}/{scene}" and new["data"]["name"] == scene
    study_old = _compose([f"data={LOADERS[scene]}", f"data.path={root}/{scene}", f"data_root={root}"], "study")
    assert _compose([f"scene={scene}", f"data_root={root}"], "study") == study_old


@pytest.mark.parametrize("scene", sorted(LOADERS))
def test_the_archived_runs_data_nodes_are_reproduced(scene, tmp_path):
    archived = ARCHIVE / scene / "standard" / "s0" / "config.yaml"
    if not archived.is_file():
        pytest.skip(f"no archived run at {archived}")
    want = yaml.safe_load(archived.read_text())["data"]
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        cfg = compose(config_name="train", overrides=[f"scene={scene}", "experiment=study", "model=standard",
                                                      f"data_root={Path(want['path']).parent}",
                                                      "trainer.default_root_dir=."])
    save_config(cfg, tmp_path / "config.yaml")
    got = yaml.safe_load((tmp_path / "config.yaml").read_text())["data"]
    want["path"] = str(Path(want["path"]).resolve())
    # settings added since, at the values that reproduce the archived runs (b3dgs.upgrade.RUN_DEFAULTS)
    from b3dgs.upgrade import RUN_DEFAULTS

    added = {k[len("data."):]: v for k, v in RUN_DEFAULTS.items() if k.startswith("data.") and k[len("data."):] not in want}
    assert {k: got.pop(k) for k in added} == added
    assert got == want


def test_data_root_comes_from_the_environment(monkeypatch):
    from b3dgs import data_root

    monkeypatch.setenv("B3DGS_DATA", "/x/data")
    assert data_root() == "/x/data" and _compose(["scene=fox"])["data"]["path"] == "/x/data/fox"
    monkeypatch.delenv("B3DGS_DATA")
    monkeypatch.setenv("B3DGS_SHARED", "/y/shared")
    assert data_root() == str(Path("/y/shared/data"))
    assert _compose(["scene=fox", "data_root=/z"])["data"]["path"] == "/z/fox"


def test_the_smoke_protocol_and_its_old_name():
    smoke = _compose(["trainer=smoke"])
    assert _compose(["trainer=quick"]) == smoke == _compose(["experiment=smoke"])
    assert smoke["trainer"]["max_steps"] == 300


def test_data_root_is_not_a_setting_of_a_run():
    from b3dgs.protocol import run_protocol

    a, b = _compose(["scene=fox", "data_root=/a"]), _compose(["scene=fox", "data_root=/b"])
    assert run_protocol(a) == run_protocol(b)


def test_train_scene_fox_runs(tmp_path):
    """``b3dgs-train scene=fox`` (a few steps at a small size)."""
    from b3dgs import data_root

    if not (Path(data_root()) / "fox").is_dir():
        pytest.skip(f"no fox scene in {data_root()}")
    res = subprocess.run([sys.executable, "-m", "b3dgs.train", "scene=fox", "trainer.max_steps=2", "data.max_side=32",
                          "trainer.eval_every=2", "trainer.enable_progress_bar=false", "logger=none", "threads=1",
                          "trainer.save_renders=false", f"hydra.run.dir={tmp_path / 'run'}"],
                         capture_output=True, text=True, timeout=600, cwd=ROOT)
    assert res.returncode == 0, res.stderr[-2000:]
    cfg = yaml.safe_load((tmp_path / "run" / "config.yaml").read_text())
    assert cfg["data"]["kind"] == "transforms" and Path(cfg["data"]["path"]).name == "fox"


def test_a_scene_added_by_one_yaml_is_a_benchmark_scene(tmp_path, monkeypatch):
    """A scene in a folder of its own plus one YAML file (here shipped by an installed package, the b3dgs.conf entry
    point): ``python -m bench.studies --scenes mine`` plans it (the sparse budgets load it to count its views)."""
    data = tmp_path / "data"
    (data / "mine").mkdir(parents=True)
    _blender_scene(data / "mine")
    pkgs = tmp_path / "pkgs"
    pkgs.mkdir()
    install_conf_package(pkgs, monkeypatch, "b3dgs_ext_scene", "scene", "unused", "", {
        "mine": "# @package _global_\ndefaults:\n  - override /data: blender\ndata:\n  path: ${data_root}/mine\n"})
    env = dict(os.environ, B3DGS_DATA=str(data),
               PYTHONPATH=os.pathsep.join(filter(None, [str(pkgs), str(ROOT), os.environ.get("PYTHONPATH")])))
    res = subprocess.run([sys.executable, "-m", "bench.studies", "--scenes", "mine", "--studies", "canonical",
                          "sparse", "--seeds", "0", "--methods", "standard", "--budgets", "1", "all", "--dry-run",
                          "--out", str(tmp_path / "out")], capture_output=True, text=True, timeout=600, cwd=ROOT,
                         env=env)
    assert res.returncode == 0, res.stderr[-2000:]
    assert f"todo {tmp_path / 'out' / 'mine' / 'standard' / 's0'}" in res.stdout
    assert f"todo {tmp_path / 'out' / 'sparse' / 'b1' / 'mine' / 'standard' / 's0'}" in res.stdout
    res = subprocess.run([sys.executable, "-m", "bench.studies", "--scenes", "theirs", "--dry-run"], cwd=ROOT, env=env,
                         capture_output=True, text=True, timeout=600)
    assert res.returncode == 2 and "mine" in res.stderr  # argparse names the configured scenes

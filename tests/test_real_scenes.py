"""The real scenes of ../shared/data load with their protocol conventions (a few views at a small size each).

lego: NeRF-synthetic, alpha composited on white (data=blender). fern, flower: the COLMAP model with its points
(data=colmap); data=llff gives the same cameras without points. DTU: COLMAP. Every test skips without its scene.
"""
from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra
from omegaconf import OmegaConf

from conftest import SHARED
from test_data import _llff_scene, inside, project

from b3dgs.data import load_scene
from b3dgs.data.colmap import read_colmap
from b3dgs.data.llff import read_llff
from b3dgs.data.scene import check_layout, split_indices
from b3dgs.data.transforms import read_transforms
from b3dgs.errors import B3dgsError
from b3dgs.train import CONF_DIR
from b3dgs.validation import validate_config

REPO = Path(__file__).resolve().parents[1]
DATA = SHARED / "data"
SEVEN = ["ethiopian_head", "fox", "lego", "fern", "flower", "dtu_scan24", "dtu_scan65"]


def needs(*scenes):
    missing = [s for s in scenes if not (DATA / s).is_dir()]
    return pytest.mark.skipif(bool(missing), reason=f"{', '.join(missing)} not in {DATA}")


def compose_train(overrides):
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        return compose(config_name="train", overrides=overrides)


def bench_module(name):
    import importlib

    return importlib.import_module(f"bench.{name}")


# ---------------------------------------------------------------------------------------------- lego


@needs("lego")
def test_lego_alpha_on_background_and_opengl_poses():
    kw = dict(max_side=32, max_images=3, test_every=0, normalize=False)
    white = load_scene("transforms", str(DATA / "lego"), background=(1.0, 1.0, 1.0), **kw)
    black = load_scene("transforms", str(DATA / "lego"), background=(0.0, 0.0, 0.0), **kw)
    fx = 0.5 * 800 / math.tan(0.5 * 0.6911112070083618) * 32 / 800
    for w, b in zip(white.train, black.train):
        assert w.image.shape == (32, 32, 3)
        assert torch.allclose(w.image[0, 0], torch.ones(3)) and torch.allclose(b.image[0, 0], torch.zeros(3))
        d = w.image - b.image  # = 1 - alpha, the same in every channel
        assert float(d.min()) > -1e-5 and float(d.max()) < 1 + 1e-5
        assert torch.allclose(d[..., 0], d[..., 2], atol=1e-5)
        assert 0.05 < float((d[..., 0] < 1e-3).float().mean()) < 0.9  # the opaque object covers part of the view
        assert float(w.K[0, 0]) == pytest.approx(fx, rel=1e-5) and float(w.K[0, 2]) == pytest.approx(16.0)
        # OpenGL c2w -> OpenCV: the object at the world origin is in front of the camera, near the image centre
        uv, z = project(w, torch.zeros(1, 3))
        assert float(z[0]) > 2.0 and float((uv[0] - 16.0).abs().max()) < 4.0


@needs("lego")
def test_lego_held_out_split_and_white_protocol():
    names = [f.name for f in read_transforms(DATA / "lego")[0]]  # headers only: no image is decoded
    train, test = split_indices(len(names), 8)
    assert len(names) == 100 and len(test) == 13 and len(train) == 87
    assert [names[i] for i in test[:3]] == ["train/r_0.png", "train/r_16.png", "train/r_23.png"]  # sorted by name
    cfg = compose_train(["data=blender", f"data.path={DATA / 'lego'}"])
    validate_config(cfg)
    assert cfg.data.kind == "transforms"
    assert list(cfg.data.background) == list(cfg.model.background) == [1.0, 1.0, 1.0]  # images and renders alike
    with pytest.raises(B3dgsError, match=r"model.background.*differs from data.background"):
        validate_config(compose_train(["data=blender", f"data.path={DATA / 'lego'}", "model.background=[0,0,0]"]))
    from b3dgs.study.active import compose_config, family_config  # the active-view study's models follow its data too

    study = family_config(compose_config("study", ["data=blender", f"data.path={DATA / 'lego'}"]), "niw", 0)
    assert OmegaConf.to_container(study.model, resolve=True)["background"] == [1.0, 1.0, 1.0]


# ---------------------------------------------------------------------------------------------- fern, flower


@needs("fern", "flower")
@pytest.mark.parametrize("scene,n_points", [("fern", 4069), ("flower", 9697)])
def test_llff_scenes_colmap_and_llff_agree(scene, n_points):
    kw = dict(max_side=32, max_images=4, test_every=0, normalize=False)
    col = load_scene("colmap", str(DATA / scene), **kw)
    llff = load_scene("llff", str(DATA / scene), **kw)
    assert [c.name for c in col.train] == [c.name for c in llff.train]
    for a, b in zip(col.train, llff.train):
        assert torch.allclose(a.K, b.K, atol=1e-3) and torch.allclose(a.viewmat, b.viewmat, atol=1e-4)
    assert col.points.shape == (n_points, 3) and llff.points is None  # data=llff: random initialisation
    for cam in col.train:
        uv, z = project(cam, col.points)
        assert float(inside(cam, uv, z).float().mean()) > 0.5  # forward-facing: most points in every view


@needs("fern", "flower")
@pytest.mark.parametrize("scene", ["fern", "flower"])
def test_llff_bounds_bracket_the_sfm_depths(scene):
    """poses_bounds.npy's near/far (used only for the focus depth: no NDC) hold the COLMAP points' depths."""
    frames, bounds = read_llff(DATA / scene)
    points = read_colmap(DATA / scene)[1]
    assert len(frames) == len(bounds) and np.all(bounds[:, 0] > 0) and np.all(bounds[:, 1] > bounds[:, 0])
    for f, (near, far) in list(zip(frames, bounds))[::5]:
        z = points @ f.viewmat[2, :3] + f.viewmat[2, 3]
        lo, hi = np.percentile(z, [5, 95])
        assert 0.8 * near < lo and hi < 1.2 * far


# ---------------------------------------------------------------------------------------------- DTU


@needs("dtu_scan24", "dtu_scan65")
@pytest.mark.parametrize("scene,size,fx,n_points", [("dtu_scan24", (384, 384), 925.6, 2627),
                                                    ("dtu_scan65", (800, 600), 1446.2, 3644)])
def test_dtu_colmap(scene, size, fx, n_points):
    assert len(read_colmap(DATA / scene)[0]) == 49  # every view registered: 7 held out (0, 8, ..., 48)
    s = load_scene("colmap", str(DATA / scene), max_side=64, max_images=4, test_every=0)
    r = 64 / max(size)
    cam = s.train[0]
    assert (cam.width, cam.height) == (round(size[0] * r), round(size[1] * r))
    assert float(cam.K[0, 0]) == pytest.approx(fx * r, rel=2e-3)
    assert s.points.shape == (n_points, 3)
    for cam in s.train:  # object-centric: most points in front of, and inside, every view (the crop cuts some)
        uv, z = project(cam, s.points)
        assert float(inside(cam, uv, z).float().mean()) > 0.6


# ---------------------------------------------------------------------------------------------- wrong format


def test_wrong_format_names_the_right_one(tmp_path):
    (tmp_path / "poses_bounds.npy").write_bytes(b"")
    with pytest.raises(B3dgsError, match=r"data=colmap: .* holds a llff scene \(fix: pass data=llff\)"):
        load_scene("colmap", str(tmp_path))
    with pytest.raises(B3dgsError, match="scene path not found"):
        load_scene("llff", str(tmp_path / "nope"))
    (tmp_path / "empty").mkdir()
    with pytest.raises(FileNotFoundError):  # a folder of no known format: the loader names the missing file
        load_scene("llff", str(tmp_path / "empty"))


def test_llff_bounds_must_be_ordered(tmp_path):
    _llff_scene(tmp_path, n=3, res=8)
    pb = np.load(tmp_path / "poses_bounds.npy")
    pb[1, 15:] = (5.0, 2.0)  # far < near
    np.save(tmp_path / "poses_bounds.npy", pb)
    with pytest.raises(B3dgsError, match=r"rows \[1\] have near/far bounds .* \(fix: regenerate"):
        load_scene("llff", str(tmp_path))


@needs(*SEVEN)
def test_layout_of_the_shared_scenes():
    with pytest.raises(B3dgsError, match=r"holds a transforms scene \(fix: pass data=transforms"):
        check_layout("llff", DATA / "lego")
    with pytest.raises(B3dgsError, match=r"fix: pass data=colmap"):
        check_layout("transforms", DATA / "dtu_scan65")
    for kind in ("colmap", "llff"):
        check_layout(kind, DATA / "fern")  # both formats: no error


# ---------------------------------------------------------------------------------------------- the grid


@needs(*SEVEN)
def test_seven_scene_protocol_composes():
    """conf/report.yaml's studies name the seven scenes; each one's bench overrides compose and validate."""
    common = bench_module("common")
    studies = OmegaConf.load(REPO / "conf" / "report.yaml").studies
    assert list(studies.scenes) == SEVEN and list(studies.seeds) == [0, 1, 2]
    assert common.QUICK == ["experiment=study"]
    for scene in SEVEN:
        cfg = compose_train(common.scene_overrides(scene) + common.QUICK)
        validate_config(cfg)
        assert cfg.data.max_side == 256 and cfg.data.test_every == 8
        assert list(cfg.model.background) == ([1.0] * 3 if scene == "lego" else [0.0] * 3)
    with pytest.raises(B3dgsError, match="unknown benchmark scene"):
        common.scene_overrides("legoo")


@needs("fern")
def test_sparse_budgets_above_the_train_views_are_skipped(tmp_path):
    studies = bench_module("studies")
    args = argparse.Namespace(studies=["sparse"], scenes=["fern"], seeds=[0], methods=["standard"],
                              budgets=["8", "16", "32", "all"], cap=1000, max_steps=None, out=str(tmp_path), extra=[])
    dirs = {str(d.relative_to(tmp_path)) for d, _, _ in studies.plan(args)}
    assert "sparse/b16/fern/standard/s0" in dirs and not any("/b32/" in d for d in dirs)  # 17 train views
    assert "fern/standard/s0" in dirs  # the budget "all"

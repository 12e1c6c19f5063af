"""``data.path=DIR`` alone reads that folder in its own format (issue 52 §1, issue 55): it used to train the built-in
synthetic scene and exit 0, with the path recorded in config.yaml and never read."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation

from b3dgs.data.images import save_png
from b3dgs.data.scene import SceneSettings, check_scene_settings, infer_data_option, infer_data_override
from b3dgs.data.synthetic import load_synthetic
from b3dgs.errors import B3dgsError

ENV = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1]), "HYDRA_FULL_ERROR": ""}


def _num(*xs) -> str:
    return " ".join(repr(float(x)) for x in xs)


def write_colmap_text(root: Path, n_views: int = 8, side: int = 32) -> Path:
    """A COLMAP text model (PINHOLE, ``sparse/0``) and PNGs of the procedural scene: a scene made here, no files."""
    raw = load_synthetic(n_views=n_views, resolution=side, n_points=200)
    sparse, images = root / "sparse" / "0", root / "images"
    sparse.mkdir(parents=True)
    images.mkdir()
    cam = raw.cameras[0]
    fx, fy, cx, cy = (float(cam.K[0, 0]), float(cam.K[1, 1]), float(cam.K[0, 2]), float(cam.K[1, 2]))
    (sparse / "cameras.txt").write_text(f"1 PINHOLE {cam.width} {cam.height} {_num(fx, fy, cx, cy)}\n")
    lines = []
    for i, c in enumerate(raw.cameras, start=1):
        w2c = c.viewmat.double().numpy()
        qx, qy, qz, qw = Rotation.from_matrix(w2c[:3, :3]).as_quat()
        t = w2c[:3, 3]
        lines += [f"{i} {_num(qw, qx, qy, qz, *t)} 1 view_{i:03d}.png", ""]
        save_png(images / f"view_{i:03d}.png", c.image.numpy())
    (sparse / "images.txt").write_text("\n".join(lines) + "\n")
    pts = raw.points[:100]
    cols = (np.clip(raw.point_colors[:100], 0, 1) * 255).round().astype(int)
    (sparse / "points3D.txt").write_text("".join(
        f"{j + 1} {_num(*p)} {c[0]} {c[1]} {c[2]} 0.5\n" for j, (p, c) in enumerate(zip(pts, cols))))
    return root


def _layout(root: Path, files: list[str]) -> Path:
    for name in files:
        (root / name).parent.mkdir(parents=True, exist_ok=True)
        (root / name).write_bytes(b"")
    return root


@pytest.mark.parametrize("files,option", [
    (["sparse/0/cameras.bin", "sparse/0/images.bin", "sparse/0/points3D.bin", "images/a.png"], "colmap"),
    (["sparse/cameras.txt", "sparse/images.txt", "sparse/points3D.txt"], "colmap"),
    (["transforms.json", "images/a.png"], "transforms"),
    (["transforms_train.json", "transforms_test.json", "train/r_0.png"], "blender"),
    (["poses_bounds.npy", "images/a.png"], "llff"),
    (["poses_bounds.npy", "sparse/0/cameras.bin", "sparse/0/images.bin", "sparse/0/points3D.bin"], "colmap"),
])
def test_the_folder_names_its_format(tmp_path, files, option):
    assert infer_data_option(_layout(tmp_path, files))[0] == option


def test_a_blender_split_file_reads_as_blender_and_names_its_folder(tmp_path):
    """data.path=lego/transforms_train.json: Blender's alpha-on-white format (as its folder is) and the scene name lego
    (it was transforms_train.json, the name reports group runs by); a split file beside a transforms.json stays one."""
    from omegaconf import OmegaConf

    import b3dgs  # noqa: F401 - registers the resolvers

    lego = _layout(tmp_path / "lego", ["transforms_train.json", "transforms_test.json", "train/r_0.png"])
    assert infer_data_option(lego / "transforms_train.json")[0] == "blender"
    assert infer_data_option(lego / "transforms_test.json")[0] == "blender"
    both = _layout(tmp_path / "ns", ["transforms.json", "transforms_train.json", "images/a.png"])
    assert infer_data_option(both / "transforms_train.json")[0] == "transforms"
    assert infer_data_option(_layout(tmp_path / "own", ["cams.json"]) / "cams.json")[0] == "transforms"
    for path, name in ((lego / "transforms_train.json", "lego"), (lego, "lego"), (f"{lego}/", "lego"), (None, "scene")):
        cfg = OmegaConf.create({"path": None if path is None else str(path), "name": "${b3dgs.basename:${path}}"})
        assert cfg.name == name, path


def test_a_folder_of_photos_only_names_b3dgs_process(tmp_path):
    for root in (_layout(tmp_path / "flat", ["a.jpg", "b.jpg"]), _layout(tmp_path / "nested", ["images/a.png"])):
        with pytest.raises(B3dgsError) as e:
            infer_data_option(root)
        assert "photos but no camera poses" in str(e.value) and "b3dgs-process images=" in e.value.fix
        with pytest.raises(B3dgsError, match="b3dgs-process"):  # an explicit data= is checked against it too
            check_scene_settings("colmap", root, SceneSettings(), {})
    with pytest.raises(B3dgsError, match="holds no scene"):
        infer_data_option(_layout(tmp_path / "empty", ["notes.txt"]))
    with pytest.raises(B3dgsError, match="does not exist"):
        infer_data_option(tmp_path / "nope")


def test_a_path_inside_a_scene_or_above_several_names_the_scene_folder(tmp_path):
    """A file of a scene, its COLMAP model or its image folder names the scene folder; a data root names its scenes."""
    scene = _layout(tmp_path / "data" / "garden", ["sparse/0/cameras.bin", "sparse/0/images.bin",
                                                   "sparse/0/points3D.bin", "images/a.png", "poses_bounds.npy"])
    _layout(tmp_path / "data" / "fox", ["transforms.json", "images/a.png"])
    for inside in ("poses_bounds.npy", "sparse/0", "sparse", "sparse/0/cameras.bin", "images", "images/a.png"):
        with pytest.raises(B3dgsError) as e:
            infer_data_option(scene / inside)
        assert f"inside the scene folder {scene}" in str(e.value), inside
        assert e.value.fix == f"pass the folder: data.path={scene}"
    with pytest.raises(B3dgsError) as e:
        infer_data_option(tmp_path / "data")
    assert "holds 2 scene folders (fox, garden), not a scene" in str(e.value)
    assert e.value.fix.endswith(f"data.path={tmp_path / 'data' / 'fox'}")
    assert infer_data_option(tmp_path / "data" / "fox" / "transforms.json")[0] == "transforms"  # a .json stays a scene
    assert infer_data_option(scene)[0] == "colmap"


def test_each_refusal_names_the_option_the_folder_came_as(tmp_path):
    """b3dgs-suggest's candidates=DIR reads a folder as data.path does; every refusal names candidates=, and none offers
    data=FORMAT (which candidates= does not take)."""
    scene = _layout(tmp_path / "data" / "garden", ["poses_bounds.npy", "images/a.png"])
    _layout(tmp_path / "data" / "fox", ["transforms.json", "images/a.png"])
    cases = [tmp_path / "nope", scene / "images", tmp_path / "data", _layout(tmp_path / "empty", ["notes.txt"]),
             _layout(tmp_path / "photos", ["a.jpg"])]
    for path in cases:
        with pytest.raises(B3dgsError) as e:
            infer_data_option(path, key="candidates")
        assert str(e.value).startswith(f"candidates={path}"), path
        assert "data.path" not in str(e.value) and "data=" not in (e.value.fix or ""), path
        assert "candidates=" in e.value.fix, path


def test_synthetic_with_a_path_is_refused_naming_the_folders_format(tmp_path):
    _layout(tmp_path, ["transforms.json"])
    with pytest.raises(B3dgsError) as e:
        check_scene_settings("synthetic", tmp_path, SceneSettings(), {})
    assert "reads no folder" in str(e.value) and "data=transforms" in e.value.fix


def test_the_override_is_added_only_when_no_format_or_scene_is_named(tmp_path, capsys):
    colmap = _layout(tmp_path / "c", ["sparse/0/cameras.txt", "sparse/0/images.txt", "sparse/0/points3D.txt"])
    nerf = _layout(tmp_path / "t", ["transforms.json"])
    assert infer_data_override("b3dgs-train", [f"data.path={colmap}", "seed=1"]) == \
        ["data=colmap", f"data.path={colmap}", "seed=1"]
    assert "reading it with data=colmap" in capsys.readouterr().err
    for argv in (["data=llff", f"data.path={colmap}"], ["scene=fox", f"data.path={colmap}"], ["seed=1"],
                 ["data.path=${data_root}/fox"], ["data.path=/data/café shots"]):
        assert infer_data_override("b3dgs-train", argv) == argv
    quoted = f"data.path='{colmap}'"
    assert infer_data_override("b3dgs-train", [quoted]) == ["data=colmap", quoted]
    assert infer_data_override("b3dgs-train", ["-m", f"data.path={colmap},{colmap}"])[1] == "data=colmap"
    comma = [f"data.path={colmap},1"]  # without -m: a folder named "c,1", or a sweep: Hydra's words say which
    assert infer_data_override("b3dgs-train", comma) == comma
    with pytest.raises(B3dgsError, match="different formats"):
        infer_data_override("b3dgs-train", ["-m", f"data.path={colmap},{nerf}"])


def test_a_home_folder_path_is_read_or_its_fix_writes_it_out(tmp_path, monkeypatch):
    """zsh leaves ``data.path=~/scene`` unexpanded and Hydra cannot read ``~``: the fix writes the home folder out; the
    quoted form (``data.path='~/scene'``) is read from the home folder (it said "does not exist" before)."""
    from b3dgs.data.datamodule import SceneDataModule
    from b3dgs.errors import _parse_fix

    monkeypatch.setenv("HOME", str(tmp_path))
    write_colmap_text(tmp_path / "scenes" / "mine")
    assert _parse_fix("data.path=~/scenes/mine") == \
        f"write the home folder out: data.path={tmp_path}/scenes/mine (Hydra cannot read ~)"
    dm = SceneDataModule("colmap", "~/scenes/mine", max_side=None)
    assert dm.path == str(tmp_path / "scenes" / "mine")
    dm.setup()
    assert len(dm.scene.train) + len(dm.scene.test) == 8


def test_data_path_alone_trains_that_colmap_scene(tmp_path):
    """The newcomer's command: ``b3dgs-train data.path=DIR`` (a COLMAP scene made here) trains DIR, not the synthetic
    scene; config.yaml and metrics.json say so."""
    scene = write_colmap_text(tmp_path / "kitchen")
    run = tmp_path / "run"
    res = subprocess.run([sys.executable, "-m", "b3dgs.train", f"data.path={scene}", "trainer.max_steps=6",
                          "logger=none", "renderer=torch", f"hydra.run.dir={run}"],
                         capture_output=True, text=True, timeout=300, cwd=tmp_path, env=ENV)
    assert res.returncode == 0, res.stderr[-3000:]
    assert "reading it with data=colmap" in res.stderr
    cfg = yaml.safe_load((run / "config.yaml").read_text())
    assert cfg["data"]["kind"] == "colmap" and cfg["data"]["path"] == str(scene)
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["scene"] == "kitchen" and metrics["num_train_views"] + metrics["num_test_views"] == 8


def test_data_path_to_photos_only_is_one_line_and_writes_nothing(tmp_path):
    photos = tmp_path / "photos"
    photos.mkdir()
    save_png(photos / "a.png", np.zeros((8, 8, 3)))
    res = subprocess.run([sys.executable, "-m", "b3dgs.train", f"data.path={photos}", f"hydra.run.dir={tmp_path / 'r'}"],
                         capture_output=True, text=True, timeout=120, cwd=tmp_path, env=ENV)
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert res.returncode == 2 and len(lines) == 1 and "b3dgs-process" in lines[0], res.stderr[-2000:]
    assert not (tmp_path / "r").exists()


def test_a_run_read_where_its_scene_moved_finds_it_or_names_data_path(tmp_path, monkeypatch, caplog):
    """A run dir read on another machine (its scene folder elsewhere): the commands that load a run read the folder of
    the same name under this machine's data root, or ``data.path=DIR``; a folder holding another scene, or none, is
    refused in one line naming ``data.path``."""
    from b3dgs.runs import load_run

    scene, run = write_colmap_text(tmp_path / "a" / "kitchen"), tmp_path / "run"
    res = subprocess.run([sys.executable, "-m", "b3dgs.train", f"data.path={scene}", "trainer.max_steps=6",
                          "logger=none", "renderer=torch", f"hydra.run.dir={run}"],
                         capture_output=True, text=True, timeout=300, cwd=tmp_path, env=ENV)
    assert res.returncode == 0, res.stderr[-3000:]
    moved = tmp_path / "b" / "kitchen"
    moved.parent.mkdir()
    scene.rename(moved)
    monkeypatch.setenv("B3DGS_DATA", str(tmp_path / "b"))
    with caplog.at_level("WARNING"):
        loaded = load_run(run)
    assert loaded.cfg.data.path == str(moved) and f"reading {moved}" in caplog.text
    other = write_colmap_text(tmp_path / "c" / "kitchen", n_views=6)
    with pytest.raises(B3dgsError, match="is not the scene .* was trained on") as e:
        load_run(run, data_path=other)
    assert "data.path=DIR" in e.value.fix
    monkeypatch.setenv("B3DGS_DATA", str(tmp_path / "c" / "none"))
    with pytest.raises(B3dgsError, match=f"scene folder {scene} is not on this machine") as e:
        load_run(run)
    assert "data.path=DIR" in e.value.fix
    # the command's own data.path= (here b3dgs-export, with no data root holding the scene)
    res = subprocess.run([sys.executable, "-m", "b3dgs.export", f"run={run}", f"data.path={moved}",
                          f"out={tmp_path / 'x.ply'}"], capture_output=True, text=True, timeout=300, cwd=tmp_path,
                         env={**ENV, "B3DGS_DATA": str(tmp_path / "c" / "none")})
    assert res.returncode == 0 and (tmp_path / "x.ply").is_file(), res.stderr[-2000:]
    # a run trained on a transforms file: the file of the same folder name under the data root
    from omegaconf import OmegaConf

    from b3dgs.runs import locate_scene

    lego = _layout(tmp_path / "d" / "lego", ["transforms_train.json"])
    monkeypatch.setenv("B3DGS_DATA", str(tmp_path / "d"))
    cfg = OmegaConf.create({"data": {"path": "/elsewhere/lego/transforms_train.json"}})
    assert locate_scene(cfg, run / "config.yaml") == str(lego / "transforms_train.json") == cfg.data.path


def test_a_named_scene_missing_from_the_data_root_names_b3dgs_data_get(tmp_path, monkeypatch):
    """scene=fox on a fresh clone: the fix is to fetch it by name, into the data root; any other missing folder keeps
    the plain fix."""
    from b3dgs import datasets
    from b3dgs.data.scene import missing_scene_fix

    root = tmp_path / "root"
    monkeypatch.setenv("B3DGS_DATA", str(root))
    (tmp_path / "registry.yaml").write_text(yaml.safe_dump({"mine": {"group": "test", "sources": []}}))
    monkeypatch.setenv(datasets.REGISTRY_ENV, str(tmp_path / "registry.yaml"))
    with pytest.raises(B3dgsError, match="does not exist") as e:
        infer_data_option(root / "mine")
    assert e.value.fix.startswith(f"fetch it: b3dgs-data get mine (into {root})")
    assert missing_scene_fix(tmp_path / "elsewhere" / "mine") == "pass data.path=PATH to an existing scene folder"
    assert missing_scene_fix(root / "yours") == "pass data.path=PATH to an existing scene folder"
    with pytest.raises(B3dgsError, match="b3dgs-data get mine"):  # a named scene's data= and data.path, as scene=mine
        check_scene_settings("transforms", root / "mine", SceneSettings(), {})

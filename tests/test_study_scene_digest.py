"""A study notices that its data changed (issue 55 §3): each scene folder of a study records the digest of the images,
poses and split its rows were made from, and a resume on other data is refused in one line naming what changed."""
from __future__ import annotations

import json

import numpy as np
import pytest
from b3dgs.data.images import save_png
from b3dgs.errors import B3dgsError
from b3dgs.protocol import check_stored_scene, scene_digest

from test_data_path import write_colmap_text


def _study(out, scene):
    from b3dgs.study.active import ActiveStudy, compose_config

    cfg = compose_config("study", [
        "data=colmap", f"data.path={scene}", "data.max_side=32", "renderer=cpu", "trainer.max_steps=30",
        "initial_views=3", "acquire=2", "seeds=[0]", "policies=[farthest]", "family_baselines=[]",
        "oracle=false", "plots=false", f"out_dir={out}"])
    cfg.trainer.default_root_dir = str(out / "run")  # resolved outside a Hydra job: the run dir is a literal
    return ActiveStudy(cfg)


def test_a_resumed_study_on_changed_images_is_refused_naming_them(tmp_path):
    scene = write_colmap_text(tmp_path / "kitchen", n_views=12)
    first = _study(tmp_path / "study", scene)
    recorded = json.loads((first.out / "scene.json").read_text())["digest"]
    assert set(recorded) == {"images", "poses", "split"}
    assert _study(tmp_path / "study", scene).scene_digest == recorded  # the same data: resumes
    for png in sorted((scene / "images").iterdir()):  # every image of the scene changes between two runs
        save_png(png, np.full((32, 32, 3), 0.25))
    with pytest.raises(B3dgsError) as e:
        _study(tmp_path / "study", scene)
    assert "holds rows made from other data: the scene's images changed" in str(e.value)
    assert "another out_dir" in e.value.fix
    assert json.loads((first.out / "scene.json").read_text())["digest"] == recorded  # nothing rewritten


def test_the_digest_names_each_part_that_changed(tmp_path):
    from b3dgs.data.scene import load_scene

    a = load_scene("synthetic", None, max_side=16, n_views=8, normalize=False)
    check_stored_scene(tmp_path, a, fix="pass another out_dir")
    moved = load_scene("synthetic", None, max_side=16, n_views=8, test_every=4, normalize=False)  # the same views, another split
    with pytest.raises(B3dgsError, match="the scene's split changed since"):
        check_stored_scene(tmp_path, moved, fix="pass another out_dir")
    a.train[0].viewmat[0, 3] += 0.5
    d = scene_digest(a)
    assert d["poses"] != json.loads((tmp_path / "scene.json").read_text())["digest"]["poses"]
    with pytest.raises(B3dgsError, match="poses changed"):
        check_stored_scene(tmp_path, d, fix="pass another out_dir")

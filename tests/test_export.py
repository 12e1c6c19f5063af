"""Exports in the scene's own frame: the similarity transform of Gaussians, the PLY a run writes (standard 3DGS
names, read by plyfile), the normalisation saved in metrics.json and the checkpoint, and on ethiopian_head the
PLY's centres in the COLMAP frame of its SfM points."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from conftest import SHARED
from test_train import QUICK, run_train

from b3dgs.data.scene import SceneTransform
from b3dgs.ply import read_ply, standard_property_names, transform_gaussians, write_splats


def _rot(q: torch.Tensor) -> torch.Tensor:
    w, x, y, z = (q / q.norm(dim=-1, keepdim=True)).unbind(-1)
    return torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
                        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
                        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1).reshape(-1, 3, 3)


def _splats(n: int, k: int, seed: int = 0) -> dict:
    g = torch.Generator().manual_seed(seed)
    return {"means": torch.randn(n, 3, generator=g, dtype=torch.float64),
            "scales": torch.randn(n, 3, generator=g, dtype=torch.float64) - 3,
            "quats": torch.randn(n, 4, generator=g, dtype=torch.float64),
            "opacities": torch.randn(n, generator=g, dtype=torch.float64),
            "sh0": torch.randn(n, 1, 3, generator=g, dtype=torch.float64),
            "shN": torch.randn(n, k, 3, generator=g, dtype=torch.float64)}


def test_similarity_maps_centres_scales_and_rotations_consistently():
    """x -> s R x + t maps every covariance Σ to s² R Σ Rᵀ; the inverse transform brings the Gaussians back."""
    sp = _splats(50, 0)
    theta = 0.7
    R = np.array([[math.cos(theta), -math.sin(theta), 0.0], [math.sin(theta), math.cos(theta), 0.0], [0.0, 0.0, 1.0]])
    tf = SceneTransform(2.5, tuple(map(tuple, R)), (1.0, -2.0, 0.5))
    m, s, q = transform_gaussians(sp["means"], sp["scales"], sp["quats"], tf.scale, tf.rotation, tf.translation)
    assert torch.allclose(m, torch.from_numpy(tf.apply(sp["means"].numpy())))
    assert torch.allclose(s, sp["scales"] + math.log(2.5))

    def cov(scales, quats):
        Rg = _rot(quats)
        return Rg @ torch.diag_embed(torch.exp(2 * scales)) @ Rg.transpose(1, 2)

    Rt = torch.from_numpy(R)
    assert torch.allclose(cov(s, q), 2.5 ** 2 * Rt @ cov(sp["scales"], sp["quats"]) @ Rt.T, atol=1e-12)
    inv = tf.inverse()
    m2, s2, q2 = transform_gaussians(m, s, q, inv.scale, inv.rotation, inv.translation)
    assert torch.allclose(m2, sp["means"]) and torch.allclose(s2, sp["scales"])
    assert torch.allclose(cov(s2, q2), cov(sp["scales"], sp["quats"]), atol=1e-12)
    assert SceneTransform.from_dict(json.loads(json.dumps(tf.to_dict()))) == tf


def test_ply_in_the_scene_frame_round_trips_through_plyfile(tmp_path):
    from plyfile import PlyData

    sp = {k: v.float() for k, v in _splats(40, 15, seed=1).items()}
    tf = SceneTransform.from_normalisation(np.array([3.0, -1.0, 10.0]), 0.1)
    path = write_splats(tmp_path / "pc.ply", sp, tf.inverse(), extra={"niw_pos_var": torch.rand(40)},
                        comments=["frame: test"])
    ply = PlyData.read(str(path))
    names = list(ply["vertex"].data.dtype.names)
    assert names == standard_property_names(15) + ["niw_pos_var"] and "frame: test" in ply.comments
    back = read_ply(path)
    assert torch.allclose(back["means"].double(), torch.from_numpy(tf.inverse().apply(sp["means"].double().numpy())),
                          rtol=1e-6, atol=1e-4)
    assert torch.allclose(back["scales_log"], sp["scales"] + math.log(10.0), atol=1e-5)
    assert torch.equal(back["quats"], sp["quats"]) and torch.equal(back["shN"], sp["shN"])
    # and back into the training frame: the model's own Gaussians
    m, s, _ = transform_gaussians(back["means"].double(), back["scales_log"].double(), back["quats"], tf.scale,
                                  tf.rotation, tf.translation)
    assert torch.allclose(m.float(), sp["means"], atol=1e-5) and torch.allclose(s.float(), sp["scales"], atol=1e-5)
    with pytest.raises(ValueError, match="SH coefficients"):  # view-dependent colour cannot be turned here
        write_splats(tmp_path / "r.ply", sp, SceneTransform(1.0, ((0.0, -1.0, 0.0), (1.0, 0.0, 0.0), (0.0, 0.0, 1.0))))


def test_run_writes_its_normalisation_and_a_ply_in_the_scene_frame(tmp_path):
    from b3dgs.runs import load_run

    m = run_train(tmp_path, QUICK + ["trainer.max_steps=5", "trainer.eval_every=5", "trainer.save_renders=false"])
    tf = SceneTransform.from_dict(m["scene_transform"])
    ck = torch.load(tmp_path / "checkpoints" / "last.ckpt", weights_only=False)
    assert SceneTransform.from_dict(ck["scene_transform"]) == tf and tf.scale != 1.0
    means = ck["state_dict"]["splats.means"].double().numpy()
    ply = read_ply(tmp_path / "point_cloud.ply")
    assert np.allclose(ply["means"].double().numpy(), tf.inverse().apply(means), atol=1e-4)
    assert np.allclose(ply["scales_log"].numpy(), ck["state_dict"]["splats.scales"].numpy() - math.log(tf.scale), atol=1e-5)
    assert load_run(tmp_path).scene.transform == tf  # the reloaded scene has the same normalisation


@pytest.mark.skipif(not (SHARED / "data" / "ethiopian_head").is_dir(), reason="ethiopian_head not in shared/data")
def test_ethiopian_head_ply_lies_in_the_colmap_frame(tmp_path):
    """A short run's PLY centres lie in the box of the scene's SfM points as COLMAP wrote them (not in the
    normalised frame, which spans a few units where COLMAP's spans tens)."""
    from plyfile import PlyData

    from b3dgs.data.colmap import read_colmap

    path = SHARED / "data" / "ethiopian_head"
    run_train(tmp_path, ["data=colmap", f"data.path={path}", "data.max_side=32", "data.max_images=16",
                         "trainer.max_steps=10", "trainer.eval_every=10", "trainer.save_renders=false",
                         "trainer.enable_progress_bar=false", "logger=none", "strategy.refine_start=1000"])
    _, points, _ = read_colmap(path)
    lo, hi = np.percentile(points, 1, axis=0), np.percentile(points, 99, axis=0)
    v = PlyData.read(str(tmp_path / "point_cloud.ply"))["vertex"].data
    xyz = np.stack([v["x"], v["y"], v["z"]], axis=1).astype(np.float64)
    assert {"opacity", "scale_0", "rot_0", "f_dc_0"} <= set(v.dtype.names)
    inside = ((xyz >= lo - 0.05 * (hi - lo)) & (xyz <= hi + 0.05 * (hi - lo))).all(axis=1).mean()
    assert inside > 0.9, inside  # the Gaussians start at the SfM points and moved little in 10 steps
    span = np.percentile(xyz, 99, axis=0) - np.percentile(xyz, 1, axis=0)
    assert np.allclose(span, hi - lo, rtol=0.25), (span, hi - lo)
    assert np.allclose(np.median(xyz, axis=0), np.median(points, axis=0), atol=0.05 * np.linalg.norm(hi - lo))

"""``experiment=paper``: the paper's protocol (30k steps, full resolution, its image-folder policy, the staged posterior
schedule) composes for every model with the paper's numbers; ``data.images_dir`` picks, checks and loads an image folder
(a downscaled one too); a long CPU run is warned about with its expected time."""
import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra
from omegaconf import OmegaConf

from b3dgs.data.images import save_png
from b3dgs.data.scene import FrameSpec, load_scene
from b3dgs.errors import B3dgsError
from b3dgs.train import CONF_DIR

#: the paper's numbers (Sec. 3.3, Appendix "Canonical benchmark setup" and its schedule table, "Dataset handling") and
#: the official 3DGS 30k optimizer the paper trains around; a drift in any of them fails here
PAPER = {
    "trainer.max_steps": 30000, "data.max_side": None, "data.test_every": 8, "schedule._target_": "b3dgs.schedule.ConstantSchedule",
    "model.sh_degree": 3, "model.sh_increase_every": 1000, "model.lambda_dssim": 0.2, "model.init_max_points": None,
    "model.lr_means": 1.6e-4, "model.lr_means_final": 1.6e-6, "model.lr_scales": 5e-3, "model.lr_quats": 1e-3,
    "model.lr_opacities": 5e-2, "model.lr_sh0": 2.5e-3, "model.lr_shN": 1.25e-4,
}
ADC = {"strategy.refine_start": 500, "strategy.refine_stop": 15000, "strategy.refine_every": 100,
       "strategy.reset_every": 3000, "strategy.grad_threshold": 2e-4, "strategy.percent_dense": 0.01,
       "strategy.max_gaussians": None}
MCMC = {"strategy.refine_start": 500, "strategy.refine_stop": 25000, "strategy.refine_every": 100,
        "strategy.cap_max": 1_000_000}
NIW = {"posterior.niw.t_niw": 0, "posterior.niw.kappa0": 0.01, "posterior.niw.nu0": 5.0}
STAGES = {  # the canonical 30k DPMM row: DP (CAVI every 50) and noise from 5k, opacity / colour from 15k
    **NIW, "posterior.dp.t_dp": 5000, "posterior.dp.cavi_every": 50, "posterior.dp.alpha": 5.0,
    "posterior.noise.t_noise": 5000, "posterior.opacity.t_post": 15000, "posterior.color.t_post": 15000}
EXPECTED = {"standard": {**PAPER, **ADC}, "niw": {**PAPER, **ADC, **NIW}, "dpmm": {**PAPER, **ADC, **STAGES},
            "mcmc": {**PAPER, **MCMC, "model.init_opacity": 0.5}}


def compose_train(overrides):
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        return compose(config_name="train", overrides=overrides, return_hydra_config=True)


@pytest.mark.parametrize("model", sorted(EXPECTED))
def test_paper_protocol_composes_with_the_papers_numbers(model):
    from b3dgs.validation import validate_config

    cfg = compose_train(["scene=fox", f"model={model}", "experiment=paper", "data_root=/data/root"])
    got = {k: OmegaConf.select(cfg, k) for k in EXPECTED[model]}
    assert got == EXPECTED[model]
    assert sorted(cfg.get("posterior") or {}) == sorted({k.split(".")[1] for k in EXPECTED[model] if k.startswith("posterior.")})
    assert cfg.data.images_dir is None  # fox: neither Mip-NeRF 360 nor a format with image folders
    validate_config(cfg, app="train")  # every node checks (keys, types, ranges; plugins build and validate)


def test_other_protocols_keep_their_strategy_numbers():
    """The experiment's strategy settings (conf/experiment/strategy/paper_<strategy>.yaml) reach no other protocol:
    they keep the class's defaults with the quick protocol's preset (conf/strategy/preset/quick_default.yaml)."""
    from b3dgs.confs import field_defaults

    default = OmegaConf.load(Path(CONF_DIR) / "strategy" / "default.yaml")
    quick = OmegaConf.load(Path(CONF_DIR) / "strategy" / "preset" / "quick_default.yaml")
    expect = {"_target_": default._target_, **field_defaults(default._target_), **OmegaConf.to_container(quick)}
    for extra in ([], ["experiment=study"], ["experiment=smoke"]):
        cfg = compose_train(["model=dpmm", *extra])
        assert OmegaConf.to_container(cfg.strategy) == expect
        assert cfg.data.images_dir is None and cfg.posterior.dp.t_dp == cfg.trainer.max_steps // 6


@pytest.mark.parametrize("data,name,folder", [
    ("colmap", "bicycle", "images_4"), ("colmap", "treehill", "images_4"), ("llff", "garden", "images_4"),
    ("colmap", "room", "images_2"), ("colmap", "bonsai", "images_2"), ("colmap", "truck", None),
    ("colmap", "drjohnson", None), ("transforms", "bicycle", None), ("blender", "lego", None)])
def test_the_image_folder_policy(data, name, folder):
    cfg = compose_train([f"data={data}", f"data.path=/x/{name}", "experiment=paper"])
    assert cfg.data.images_dir == folder
    assert compose_train([f"data={data}", f"data.path=/x/{name}", "experiment=paper",
                          "data.images_dir=images_8"]).data.images_dir == "images_8"
    assert compose_train([f"data={data}", f"data.path=/x/{name}"]).data.images_dir is None


@pytest.mark.parametrize("name,folder", [("bicycle", "images_4"), ("room", "images_2"), ("truck", None)])
def test_a_fetched_paper_scene_by_name_gets_the_folder_policy(name, folder):
    """b3dgs-data get NAME, then scene=NAME experiment=paper: the COLMAP loader on <data_root>/NAME, in the paper's
    image folder."""
    from b3dgs import data_root

    cfg = compose_train([f"scene={name}", "experiment=paper"])
    assert (cfg.data.kind, cfg.data.path, cfg.data.images_dir) == ("colmap", f"{data_root()}/{name}", folder)


def _colmap_with_folders(root: Path) -> None:
    """A one-view PINHOLE model (64x48, fx = fy = 50) with images/ and a half-size images_2/ (and a odd images_3/)."""
    from test_data import _write_colmap

    _write_colmap(root, "PINHOLE", [50.0, 50.0, 32.0, 24.0], 64, 48, np.full((48, 64, 3), 0.5))
    for folder, (w, h) in {"images_2": (32, 24), "images_3": (32, 40)}.items():
        (root / folder).mkdir()
        save_png(root / folder / "a.png", np.full((h, w, 3), 0.5))


def test_images_shrunk_after_colmap_ran_are_read_with_k_scaled(tmp_path, caplog):
    """images/ replaced by a uniform half-size copy (the model still says 64x48): read at the files' size, K scaled, one
    log line (the official 3DGS code reads any size); a size that is no uniform downscale stays refused. The same for a
    transforms.json whose w/h are those of the images before they were shrunk."""
    import logging

    _colmap_with_folders(tmp_path)
    save_png(tmp_path / "images" / "a.png", np.full((24, 32, 3), 0.5))
    with caplog.at_level(logging.INFO, logger="b3dgs.data.scene"):
        cam = load_scene("colmap", str(tmp_path), test_every=0, normalize=False).train[0]
    assert (cam.width, cam.height) == (32, 24)
    assert torch.allclose(cam.K, torch.tensor([[25.0, 0, 16], [0, 25, 12], [0, 0, 1]]))
    assert "1 of 1 images in" in caplog.text and "a.png: 32x24, camera 64x48" in caplog.text
    save_png(tmp_path / "images" / "a.png", np.full((40, 32, 3), 0.5))
    with pytest.raises(B3dgsError, match=r"a\.png is 32x40 but its camera says 64x48"):
        load_scene("colmap", str(tmp_path), test_every=0)
    nerf = tmp_path / "nerf"
    (nerf / "images").mkdir(parents=True)
    save_png(nerf / "images" / "a.png", np.full((24, 32, 3), 0.5))
    (nerf / "transforms.json").write_text(json.dumps({"fl_x": 50.0, "fl_y": 50.0, "cx": 32.0, "cy": 24.0, "w": 64,
                                                      "h": 48, "frames": [{"file_path": "images/a.png",
                                                                           "transform_matrix": np.eye(4).tolist()}]}))
    cam = load_scene("transforms", str(nerf), test_every=0, normalize=False).train[0]
    assert (cam.width, cam.height) == (32, 24)
    assert torch.allclose(cam.K, torch.tensor([[25.0, 0, 16], [0, 25, 12], [0, 0, 1]]))
    # nerfstudio's images_N (--downscale-factor): data.images_dir reads the file of the same name there
    (nerf / "images_2").mkdir()
    save_png(nerf / "images" / "a.png", np.full((48, 64, 3), 0.5))
    save_png(nerf / "images_2" / "a.png", np.full((24, 32, 3), 0.25))
    cam = load_scene("transforms", str(nerf), test_every=0, normalize=False, images_dir="images_2").train[0]
    assert (cam.width, cam.height) == (32, 24) and float(cam.image.mean()) == pytest.approx(0.25, abs=0.01)
    assert torch.allclose(cam.K, torch.tensor([[25.0, 0, 16], [0, 25, 12], [0, 0, 1]]))
    meta = json.loads((nerf / "transforms.json").read_text())
    del meta["w"], meta["h"]
    (nerf / "transforms.json").write_text(json.dumps(meta))  # the size comes from the full-size image then
    cam = load_scene("transforms", str(nerf), test_every=0, normalize=False, images_dir="images_2").train[0]
    assert torch.allclose(cam.K, torch.tensor([[25.0, 0, 16], [0, 25, 12], [0, 0, 1]]))
    (nerf / "images" / "a.png").unlink()
    with pytest.raises(B3dgsError, match=r"data\.images_dir=images_2 scales the intrinsics .* no w and h"):
        load_scene("transforms", str(nerf), test_every=0, images_dir="images_2")


def test_images_dir_loads_a_downscaled_folder_and_refuses_what_it_cannot(tmp_path):
    from b3dgs.data.datamodule import SceneDataModule

    _colmap_with_folders(tmp_path)
    full = load_scene("colmap", str(tmp_path), test_every=0, normalize=False)
    half = SceneDataModule(kind="colmap", path=str(tmp_path), test_every=0, normalize=False, images_dir="images_2").scene
    cam = half.train[0]
    assert (cam.width, cam.height) == (32, 24) and (full.train[0].width, full.train[0].height) == (64, 48)
    assert torch.allclose(cam.K, torch.tensor([[25.0, 0, 16], [0, 25, 12], [0, 0, 1]]))
    with pytest.raises(B3dgsError, match=r"a\.png is 32x40 but its camera says 64x48"):  # not a uniform downscale
        load_scene("colmap", str(tmp_path), test_every=0, images_dir="images_3")
    with pytest.raises(B3dgsError, match=r"has no folder images_4 \(fix: .*\(images, images_2, images_3\)\)"):
        SceneDataModule(kind="colmap", path=str(tmp_path), images_dir="images_4")
    with pytest.raises(B3dgsError, match=r"data=synthetic has no image folder setting.*data\.images_dir=null"):
        SceneDataModule(kind="synthetic", images_dir="images_2")
    for bad in ("/abs/images", "../images", ""):
        with pytest.raises(B3dgsError, match="must be the name of a folder inside data.path"):
            SceneDataModule(kind="colmap", path=str(tmp_path), images_dir=bad)


def test_a_long_cpu_run_is_warned_with_its_expected_time():
    from b3dgs.lifecycle import CPU_SECONDS_PER_PIXEL_STEP, warn_long_cpu_run

    def scene(w, h, n=100):
        return SimpleNamespace(train=[SimpleNamespace(width=w, height=h)] * n)

    cpu, gpu = SimpleNamespace(device=torch.device("cpu"), name="cpu"), SimpleNamespace(device="cuda:0", name="gsplat")
    msg = warn_long_cpu_run(scene(1237, 822), cpu, 30000)  # bicycle's images_4, the paper's 30k steps
    hours = 30000 * 1237 * 822 * CPU_SECONDS_PER_PIXEL_STEP / 3600
    assert msg is not None and f"at least ~{hours:.1f} h" in msg and "CUDA GPU" in msg and "1237x822" in msg
    assert warn_long_cpu_run(scene(1237, 822), gpu, 30000) is None
    assert warn_long_cpu_run(scene(256, 144), cpu, 3000) is None  # the study protocol: minutes


def test_a_gpu_run_at_the_cpu_image_size_is_warned(caplog):
    """b3dgs-train data.path=DIR on a GPU trains at the CPU default's 256 px: said, with experiment=paper as the fix;
    not on the CPU, not under a chosen experiment, not where the files are no larger than the cap."""
    from b3dgs.lifecycle import warn_cpu_size_on_gpu

    def scene(w, h):
        return SimpleNamespace(train=[SimpleNamespace(width=w, height=h)] * 3)

    cpu, gpu = SimpleNamespace(device=torch.device("cpu")), SimpleNamespace(device="cuda:0")
    msg = warn_cpu_size_on_gpu(scene(256, 192), gpu, 256, None)
    assert msg is not None and "data.max_side=256" in msg and "experiment=paper" in msg and msg in caplog.text
    assert warn_cpu_size_on_gpu(scene(256, 192), cpu, 256, None) is None
    assert warn_cpu_size_on_gpu(scene(256, 192), gpu, 256, "study") is None
    assert warn_cpu_size_on_gpu(scene(200, 150), gpu, 256, None) is None
    assert warn_cpu_size_on_gpu(scene(1600, 1200), gpu, None, None) is None


def test_downscaling_at_load_is_said_once_with_the_setting(tmp_path, caplog):
    from b3dgs.data.scene import FrameSpec, materialize

    save_png(tmp_path / "a.png", np.zeros((60, 80, 3), np.uint8))
    K = np.array([[50.0, 0, 40], [0, 50.0, 30], [0, 0, 1]])
    frames = [FrameSpec(name="a.png", path=tmp_path / "a.png", K=K, viewmat=np.eye(4), width=80, height=60)]
    with caplog.at_level("INFO"):
        cams = materialize(frames, max_side=40)
    assert (cams[0].width, cams[0].height) == (40, 30)
    assert "images downscaled to a longest side of 40 px (data.max_side" in caplog.text and "80x60 -> 40x30" in caplog.text
    caplog.clear()
    with caplog.at_level("INFO"):
        materialize(frames, max_side=None)
    assert "downscaled" not in caplog.text


def test_paper_protocol_trains_a_few_steps_on_the_synthetic_scene(tmp_path):
    """experiment=paper end to end on the CPU, cut to 20 steps (the full run is a GPU's: docs/user-guide.md)."""
    from test_train import run_train

    m = run_train(tmp_path, ["experiment=paper", "model=dpmm", "+data.n_views=8", "trainer.max_steps=20",
                             "trainer.enable_progress_bar=false", "logger=none", "trainer.save_renders=false"])
    cfg = OmegaConf.load(tmp_path / "config.yaml")
    assert m["steps"] == 20 and cfg.data.max_side is None and cfg.strategy.refine_stop == 15000
    assert m["num_train_views"] == 7 and np.isfinite(m["psnr"])


def test_a_smaller_copy_of_the_images_is_hinted_when_max_side_shrinks_them(tmp_path, caplog):
    """data.max_side that halves the files, with a uniform images_N copy still at least that large: one log line
    names data.images_dir=images_N (not applied: its resampling differs). No hint for a copy that is no uniform
    downscale (images_3 here), one smaller than max_side, or no shrinking."""
    import logging

    from b3dgs.data.scene import hint_smaller_copies

    _colmap_with_folders(tmp_path)
    with caplog.at_level(logging.INFO, logger="b3dgs.data.scene"):
        load_scene("colmap", str(tmp_path), test_every=0, max_side=16)
    hint = ("data.max_side=16 shrinks 64-px images from images/; images_2/ holds copies 2x smaller: "
            "data.images_dir=images_2 loads them faster (its resampling differs, so the pixels do too)")
    assert hint in caplog.text
    frames = [FrameSpec("a.png", tmp_path / "images" / "a.png", np.eye(3), np.eye(4), 64, 48)]
    assert hint_smaller_copies(tmp_path / "images", frames, 16) == hint
    assert hint_smaller_copies(tmp_path / "images", frames, 40) is None  # images_2 (32 px) would be upscaled
    assert hint_smaller_copies(tmp_path / "images", frames, 64) is None and \
        hint_smaller_copies(tmp_path / "images", frames, None) is None
    (tmp_path / "images_2" / "a.png").unlink()
    save_png(tmp_path / "images_2" / "a.png", np.full((30, 40, 3), 0.5))  # not 1/2 of 64x48
    assert hint_smaller_copies(tmp_path / "images", frames, 16) is None

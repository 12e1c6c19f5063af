"""Training schedules (``schedule=constant|dash``): the frequency criterion, the levels, the downsampled
cameras, the primitive budget, the pixel-unit conversions of the posterior blocks, and a dash training run
that resumes bit for bit."""

import pytest
import torch

from b3dgs.data.scene import load_scene
from b3dgs.schedule import ConstantSchedule, DashSchedule, band_energy, mean_spectrum


def _scene(n_views=12, side=64):
    return load_scene("synthetic", None, n_views=n_views, resolution=side, seed=0)


def test_band_energy_is_monotone_and_total_at_scale_one():
    spec = mean_spectrum([c.image for c in _scene().train])
    total = float(spec.sum())
    assert band_energy(spec, 1.0) == pytest.approx(total, rel=1e-12)
    vals = [band_energy(spec, s) for s in (1.0, 1.5, 2.0, 3.0, 4.0, 8.0)]
    assert all(a >= b for a, b in zip(vals, vals[1:])), vals
    assert vals[-1] < vals[0]


def test_dash_levels_rise_to_full_resolution_at_full_res_at():
    sc = _scene()
    d = DashSchedule(full_res_at=0.5, levels=8, min_side=11)
    d.initialize(sc.train, max_steps=1000)
    s = d.summary()["levels"]
    scales, starts = [lv["scale"] for lv in s], [lv["from_step"] for lv in s]
    assert scales[0] > 1.0 and scales[-1] == 1.0
    assert all(a > b for a, b in zip(scales, scales[1:]))
    assert starts[0] == 0 and starts[-1] == 500 and all(a <= b for a, b in zip(starts, starts[1:]))
    assert d.scale(0) == pytest.approx(scales[0], abs=1e-4) and d.scale(499) > 1.0 and d.scale(500) == 1.0 and d.scale(999) == 1.0
    # the start keeps 1/start_energy_factor of every view's spectrum, and never goes below min_side pixels
    for c in sc.train:
        spec = mean_spectrum([c.image])
        assert band_energy(spec, scales[0]) >= band_energy(spec, 1.0) / d.start_energy_factor - 1e-9
    assert min(sc.train[0].width, sc.train[0].height) / d.scale(0) >= d.min_side - 1e-9


def test_dash_camera_is_cached_per_level_and_scales_intrinsics():
    sc = _scene()
    cam = sc.train[0]
    d = DashSchedule(full_res_at=0.5, levels=4, min_side=11)
    d.initialize(sc.train, max_steps=100)
    c0 = d.camera(cam, 0)
    s = d.scale(0)
    assert (c0.width, c0.height) == (round(cam.width / s), round(cam.height / s))
    assert d.camera(cam, 1) is c0  # resized once per level, not every step
    # a world point projects to the same place relative to the image size (pixel-centre-at-0.5 convention)
    X = torch.tensor([0.05, -0.02, 0.0, 1.0])
    def pix(c):
        x = (c.viewmat @ X)[:3]
        u = c.K @ (x / x[2])
        return u[0] / c.width, u[1] / c.height
    for a, b in zip(pix(cam), pix(c0)):
        assert float(a) == pytest.approx(float(b), abs=1e-5)
    # the image is the area average (exact box filter for a factor of 2)
    half = cam.resized(cam.width // 2, cam.height // 2)
    ref = cam.image.reshape(cam.height // 2, 2, cam.width // 2, 2, 3).mean(dim=(1, 3))
    assert torch.allclose(half.image, ref, atol=1e-6)
    assert d.camera(cam, 99) is cam  # full resolution: the camera itself
    assert ConstantSchedule().camera(cam, 0) is cam


def test_budget_fraction_and_scheduled_cap():
    from b3dgs.plugin import Plugin

    sc = _scene()
    d = DashSchedule(full_res_at=0.5, levels=6, min_side=11, budget=True, keep=1.0)
    d.initialize(sc.train, max_steps=1000)
    fr = [d.step_info(t)["budget_fraction"] for t in range(0, 500, 25)]
    assert all(0 < f < 1 for f in fr) and fr[0] < 0.2 and fr[-1] > 0.5
    assert all(a <= b + 1e-12 for a, b in zip(fr, fr[1:]))
    assert "budget_fraction" not in d.step_info(500)  # full resolution: the strategy's own cap
    assert Plugin.scheduled_cap(50000, 1000, {}) == 50000  # schedule=constant: the strategy's own cap
    assert Plugin.scheduled_cap(50000, 1000, {"budget_fraction": 0.5}) == 1000 + 24500
    assert Plugin.scheduled_cap(None, 1000, {"budget_fraction": 1.0}) == 6000
    assert "budget_fraction" not in DashSchedule(budget=False).step_info(0)
    assert "keep_fraction" not in d.step_info(999) and DashSchedule(keep=0.5).step_info(0)["keep_fraction"] == 0.5
    assert DashSchedule().keep == 0.45 and not DashSchedule().budget  # the defaults of conf/schedule/dash.yaml
    early = DashSchedule(full_res_at=0.5, levels=6, min_side=11, keep=0.5, keep_below=2.0)
    early.initialize(sc.train, max_steps=1000)
    first = min(t for t in range(1000) if "keep_fraction" in early.step_info(t))
    assert 0 < first < 500 and early.scale(first) <= 2.0 < early.scale(first - 1)  # from the first level at <= 2
    assert DashSchedule(keep=0.5).keep_below == 1.0  # the default trims at full resolution, as before


def test_density_statistics_are_resolution_consistent():
    """The strategy accumulates the 2-D mean gradient in NDC units (pixel gradient x half the image size) and the
    screen radius as a fraction of the long side: a half-resolution view with the same NDC gradient and the
    same relative footprint adds exactly what the full view adds."""
    from b3dgs_plugins.strategy.default import AdaptiveDensityControl

    strat = AdaptiveDensityControl(refine_start=10 ** 6, refine_stop=2 * 10 ** 6)
    splats = {"means": torch.zeros(3, 3)}
    grads, radii = torch.tensor([[3e-6, 4e-6], [0.0, 1e-5], [2e-6, 0.0]]), torch.tensor([4.0, 8.0, 0.0])
    out = []
    for factor in (1, 2):
        st = strat.initialize_state(splats=splats, scene=None, info={})
        info = {"per_gaussian": {"means2d_grad": (grads * factor)[None], "radii": (radii / factor)[None]},
                "width": 128 // factor, "height": 96 // factor}
        strat.step_post_backward(splats=splats, optimizers={}, state=st, step=1, info=info)
        out.append(st)
    for k in ("grad2d", "count", "max_radii"):
        assert torch.allclose(out[0][k], out[1][k]), k


def test_dp_and_niw_counts_are_in_full_resolution_pixels():
    """A step at half resolution adds the same DP usage / NIW count as the full-resolution step it stands for."""
    from types import SimpleNamespace

    from b3dgs_plugins.posterior.dp import DPBlock

    blk = DPBlock(t_dp=10 ** 6)
    splats = {"means": torch.zeros(4, 3)}
    ws = torch.tensor([[100.0, 40.0, 0.0, 8.0]])
    res = []
    for rs in (1.0, 0.5):
        st = blk.initialize_state(splats=splats, scene=SimpleNamespace(train=[0] * 10), info={})
        info = {"per_gaussian": {"weight_sum": ws * rs * rs}, "num_train_views": 10}
        if rs != 1.0:
            info["resolution_scale"] = rs
        blk.step_post_backward(splats=splats, optimizers={}, state=st, step=0, info=info)
        res.append(st["usage"])
    assert torch.allclose(res[0], res[1])


def test_schedule_group_is_validated():
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    from b3dgs.errors import B3dgsError
    from b3dgs.train import CONF_DIR
    from b3dgs.validation import validate_config

    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        cfg = compose(config_name="train", overrides=["schedule=dash", "schedule.full_res_at=1.5"])
        with pytest.raises(B3dgsError, match=r"schedule.full_res_at must be in \[0, 1\]"):
            validate_config(cfg)
        cfg = compose(config_name="train", overrides=["schedule=dash", "+schedule.full_res=0.4"])
        with pytest.raises(B3dgsError, match=r"full_res_at"):
            validate_config(cfg)
        validate_config(compose(config_name="train", overrides=["schedule=constant"]))


def test_dash_training_learns_resumes_exactly_and_refuses_another_schedule(tmp_path):
    """A short dash run trains at rising resolution (levels recorded in metrics.json), trims to half its Gaussians at
    full resolution (schedule.keep=0.5) and never grows back, and a resume from its mid-run checkpoint ends bit for bit like the uninterrupted run; resuming it with
    schedule=constant is refused with the schedule named."""
    import json

    from tests.test_train import QUICK, run_train

    over = QUICK + ["trainer.max_steps=120", "trainer.eval_every=60", "trainer.checkpoint_every=60",
                    "trainer.keep_checkpoints=true", "trainer.save_renders=false", "schedule=dash",
                    "schedule.levels=4", "schedule.min_side=11", "schedule.keep=0.5", "strategy.refine_start=20",
                    "strategy.refine_every=20", "strategy.refine_stop=100"]
    a = tmp_path / "a"
    m = run_train(a, over)
    assert m["psnr"] > 15.0
    # the trim at full resolution (step 60) kept half the Gaussians, by usage, and the count never grew back
    ck = torch.load(a / "checkpoints" / "last.ckpt", weights_only=False)
    trimmed = int(ck["b3dgs"]["states"]["strategy"]["trimmed_cap"])
    assert m["removed"].get("budget", 0) > 0 and m["num_gaussians"] <= trimmed
    lv = m["schedule"]["levels"]
    assert m["schedule"]["name"] == "dash" and lv[0]["scale"] > 1 and lv[-1] == {"scale": 1.0, "from_step": 60}
    b = tmp_path / "b"
    b.mkdir()
    import shutil

    shutil.copytree(a / "checkpoints", b / "checkpoints")
    shutil.copy(a / "config.yaml", b / "config.yaml")
    with pytest.raises(ValueError, match=r"schedule"):
        run_train(b, [o for o in over if not o.startswith("schedule")] + ["resume=" + str(b / "checkpoints" / "step60.ckpt")])
    m2 = run_train(b, over + ["resume=" + str(b / "checkpoints" / "step60.ckpt")])
    assert m2["checkpoint"]["params_sha256"] == m["checkpoint"]["params_sha256"]
    assert json.loads((a / "metrics.json").read_text())["num_gaussians"] == m2["num_gaussians"]

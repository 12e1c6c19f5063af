"""b3dgs-suggest (issue 54): candidate poses that look at the scene from outside its core, no suggestion behind a
forward-facing capture, n above the candidates, a standard run (no posterior block) and a one-camera scene, candidates=
in each format (3DGS cameras.json, nerfstudio path, scene folder), the per-pixel information map against a float64
brute force, b3dgs-render of the suggested path, one-line refusals that write nothing, and reruns that replace only
their own files."""
from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra
from omegaconf import OmegaConf

from b3dgs.errors import B3dgsError
from b3dgs.render_cli import _look_at
from b3dgs.train import CONF_DIR
from b3dgs.types import Camera

ROOT = Path(__file__).resolve().parents[1]
ENV = {**os.environ, "PYTHONPATH": f"{ROOT}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}
SMALL = ["generate.azimuths=6", "generate.elevations=2", "generate.distances=1", "generate.jitter_per_camera=1",
         "targets.azimuths=6", "targets.elevations=1", "score_max_side=16", "preview_max_side=24"]
TRAIN = [sys.executable, "-m", "b3dgs.train", "data.max_side=32", "+data.n_views=16", "+data.n_points=600",
         "model.sh_degree=1", "model.sh_increase_every=5",
         "logger=none", "trainer.enable_progress_bar=false"]


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """A standard run (no posterior block) of the synthetic hemisphere, and one trained on a single camera."""
    base = tmp_path_factory.mktemp("suggest")
    jobs = {"std": TRAIN + ["trainer.max_steps=30", "trainer.eval_every=30"],
            "one": TRAIN + ["trainer.max_steps=12", "trainer.eval_every=12", "data.train_indices=[0]"]}
    procs = {k: subprocess.Popen(v + [f"hydra.run.dir={base / k}"], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                                 text=True, cwd=ROOT, env=ENV) for k, v in jobs.items()}
    for k, p in procs.items():
        _, err = p.communicate(timeout=600)
        assert p.returncode == 0, err[-3000:]
    return {k: base / k for k in jobs}


def cfg_of(run, *overrides):
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        return compose(config_name="suggest", overrides=[f"run={run}", *SMALL, *overrides])


def run_suggest(run, *overrides) -> dict:
    from b3dgs.suggest import suggest

    return suggest(cfg_of(run, *overrides))


def cli(*args):
    return subprocess.run([sys.executable, "-m", "b3dgs.suggest", *args], capture_output=True, text=True, timeout=600,
                          cwd=ROOT, env=ENV)


def manifest_files(run: Path) -> set:
    from b3dgs.rundir import MANIFEST_NAME

    return set(json.loads((run / MANIFEST_NAME).read_text())["files"])


def ring_camera(name, az, el, side=12, radius=3.0, target=(0.0, 0.0, 0.0)):
    pos = np.asarray(target) + radius * np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
    K = torch.tensor([[14.0, 0, side / 2], [0, 14.0, side / 2], [0, 0, 1]])
    view = _look_at(pos, np.asarray(target, float), np.array([0.0, 0.0, 1.0]))
    return Camera(name, K, torch.from_numpy(view).float(), side, side)


# ---------------------------------------------------------------------------------------------- candidates
def test_forward_facing_capture_gets_only_frontal_candidates():
    from b3dgs.suggest import frontal, generate_candidates, scene_frame

    gen = OmegaConf.create({"azimuths": 24, "elevations": 3, "distances": 2, "margin_deg": 10.0, "jitter_per_camera": 2,
                            "jitter_scale": 0.15})
    # LLFF-like: cameras in a small cap around +x, all looking at the origin
    llff = [ring_camera(f"f{i}", az, el) for i, (az, el) in enumerate([(-0.2, 0.0), (0.0, 0.1), (0.2, -0.05), (0.1, 0.2)])]
    fr = scene_frame(llff)
    assert fr["forward"] and fr["axis"][0] > 0.95
    raw, fr = generate_candidates(llff, gen)
    kept = frontal(raw, fr)
    assert 0 < len(kept) < len(raw)  # the ring behind the capture is dropped
    limit = -math.sin(math.radians(10.0))
    dots = [float((c.center.double().numpy() - fr["centre"]) @ fr["axis"]) / float(np.linalg.norm(
        c.center.double().numpy() - fr["centre"])) for c in kept]
    assert min(dots) >= limit - 1e-9
    assert max(dots) > 0.9 and min(dots) < 0.2  # the frontal half-space, not only the capture's cap
    # a full orbit is not forward-facing: candidates all around
    orbit = [ring_camera(f"o{i}", a, 0.2) for i, a in enumerate(np.linspace(0, 2 * math.pi, 8, endpoint=False))]
    raw, fr = generate_candidates(orbit, gen)
    assert not fr["forward"] and len(frontal(raw, fr)) == len(raw)


def test_candidates_look_at_the_scene_from_outside_its_core(runs):
    from b3dgs.acquisition import ScoringContext
    from b3dgs.runs import load_run
    from b3dgs.suggest import core_radius, filter_candidates, frontal, generate_candidates

    run = load_run(runs["std"])
    gen = cfg_of(runs["std"]).generate
    raw, fr = generate_candidates(run.scene.train, gen, 0)
    centre = fr["centre"]
    inside = ring_camera("inside", 0.3, 0.1, radius=0.01, target=tuple(centre))  # at the centre: in the core
    r_core = core_radius(run.module, fr, 0.5)
    assert r_core > 0.05
    ctx = ScoringContext([run.module], run.scene.train, 16, run.scene.extent, 0)
    kept, dropped = filter_candidates(frontal(raw, fr) + [inside], ctx, fr, r_core, 0.05)
    assert dropped["inside_core"] >= 1 and "inside" not in {c.name for c in kept} and len(kept) >= 10
    for c in kept:
        pos = c.center.double().numpy()
        assert np.linalg.norm(pos - centre) > r_core
        p = c.viewmat.double().numpy() @ np.append(centre, 1.0)  # the centre in the camera: ahead, inside the image
        u, v = (c.K.double().numpy() @ p[:3])[:2] / p[2]
        assert p[2] > 0 and 0 <= u <= c.width and 0 <= v <= c.height, c.name


# ---------------------------------------------------------------------------------------------- the command
def test_suggest_writes_ranked_cameras_previews_plot_and_render_reads_the_path(runs):
    from b3dgs.render_cli import render

    run = runs["std"]
    rec = run_suggest(run, "n=3")
    out = run / "suggest"
    assert rec["returned"] == 3 and rec["batch"] == "greedy_conditioned" and rec["targets"] == 6
    names = {"cameras.json", "path.json", "suggest.json", "plot.png", "preview_01.png", "preview_02.png",
             "preview_03.png"}
    assert {p.name for p in out.iterdir()} == names
    assert {f"suggest/{n}" for n in names} <= manifest_files(run)
    rec = json.loads((out / "suggest.json").read_text())
    sug = rec["suggestions"]
    assert [s["rank"] for s in sug] == [1, 2, 3] and len({s["name"] for s in sug}) == 3
    # greedy_conditioned: the first pick is the best first score; each score is conditioned on the earlier picks
    assert sug[0]["first_score"] == max(rec["scores"].values())
    assert all(s["score"] <= s["first_score"] * (1 + 1e-9) for s in sug)
    for s in sug:  # each preview's map sums to its (conditioned) score
        assert s["information_map_sum"] == pytest.approx(s["score"], rel=1e-3)
    cams = json.loads((out / "cameras.json").read_text())
    assert [c["img_name"] for c in cams] == ["suggest_01", "suggest_02", "suggest_03"]
    assert {"position", "rotation", "fx", "fy", "width", "height", "id"} <= set(cams[0])
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        w = render(compose(config_name="render", overrides=[f"run={run}", f"path={out / 'path.json'}", "video=false"]))
    assert len(w["frames"]) == 3
    # b3dgs-view draws them as frusta labelled by rank, first in its camera list
    from b3dgs.viewer.run import open_run

    viewed = open_run(run)
    assert [c.name for c in viewed.suggested] == ["suggest_01", "suggest_02", "suggest_03"]
    for c, s in zip(viewed.suggested, sug):
        assert np.allclose(c.viewmat.double().numpy(), np.asarray(s["viewmat"]), atol=1e-6)
    try:
        import viser  # noqa: F401
    except ImportError:
        return
    from b3dgs.viewer.server import ViewerApp, ViewerSettings

    app = ViewerApp(viewed, ViewerSettings(port=0))
    try:
        assert [(lbl, k) for lbl, _, k in app._cameras][:2] == [("suggested #1: suggest_01", "suggested"),
                                                               ("suggested #2: suggest_02", "suggested")]
    finally:
        app.stop()


def test_rerun_replaces_only_its_own_files(runs):
    run = runs["std"]
    run_suggest(run, "n=3")
    mine = run / "suggest" / "notes.txt"
    mine.write_text("my notes")
    rec = run_suggest(run, "n=1", "policy=farthest")
    out = run / "suggest"
    assert {p.name for p in out.iterdir()} == {"cameras.json", "path.json", "suggest.json", "plot.png",
                                               "preview_01.png", "notes.txt"}
    assert mine.read_text() == "my notes" and rec["batch"] == "own" and rec["targets"] == 0
    listed = {f for f in manifest_files(run) if f.startswith("suggest/")}
    assert "suggest/preview_02.png" not in listed and "suggest/notes.txt" not in listed


def test_n_above_the_candidates_and_the_candidate_file_formats(runs, tmp_path):
    """A 3DGS cameras.json and a nerfstudio path (both written by b3dgs-suggest) read back as the suggested poses;
    n=8 of 3 candidates gives 3; a scene folder's poses (in the scene's own frame) read back into the run's frame."""
    from b3dgs.data.images import save_png
    from b3dgs.data.scene import scene_transform
    from b3dgs.runs import load_run
    from b3dgs.suggest import _move, read_candidates

    run = runs["std"]
    run_suggest(run, "n=3", "policy=cover")
    rec = json.loads((run / "suggest" / "suggest.json").read_text())
    for name in ("cameras.json", "path.json"):
        f = tmp_path / name
        f.write_bytes((run / "suggest" / name).read_bytes())
        loaded = load_run(run)
        cams = read_candidates(str(f), loaded.scene)
        assert len(cams) == 3
        for c, s in zip(cams, rec["suggestions"]):
            assert np.allclose(c.viewmat.double().numpy(), np.asarray(s["viewmat"]), atol=1e-4), name
        got = run_suggest(run, "n=8", f"candidates={f}", "policy=farthest", "out=" + str(tmp_path / f"o_{name}"))
        assert got["requested"] == 8 and got["returned"] == 3 and got["candidates"]["source"] == str(f)
    # a scene folder (transforms.json) holding the run's test poses in the scene's own frame
    scene = load_run(run).scene
    own = _move(scene.test, scene_transform(scene).inverse())
    folder = tmp_path / "other"
    (folder / "images").mkdir(parents=True)
    frames = []
    for i, c in enumerate(own):
        save_png(folder / "images" / f"v{i}.png", np.zeros((c.height, c.width, 3), np.uint8))
        c2w = c.camtoworld.double().numpy() @ np.diag([1.0, -1, -1, 1])  # OpenCV -> OpenGL
        frames.append({"file_path": f"images/v{i}.png", "transform_matrix": c2w.tolist()})
    K = own[0].K.double().numpy()
    (folder / "transforms.json").write_text(json.dumps({
        "fl_x": K[0, 0], "fl_y": K[1, 1], "cx": K[0, 2], "cy": K[1, 2], "w": own[0].width, "h": own[0].height,
        "frames": frames}))
    cams = read_candidates(str(folder), scene)
    assert len(cams) == len(scene.test)
    with pytest.raises(B3dgsError, match=f"candidates={folder / 'images'} is a folder inside the scene folder") as e:
        read_candidates(str(folder / "images"), scene)  # the loader's words, naming the key it came as
    assert e.value.fix == f"pass the folder: candidates={folder}"
    for c, t in zip(sorted(cams, key=lambda c: c.name), scene.test):
        assert np.allclose(c.viewmat.double().numpy(), t.viewmat.double().numpy(), atol=1e-4)


def test_one_camera_scene_is_forward_facing_and_gets_nothing_from_behind(runs):
    run = runs["one"]
    rec = run_suggest(run, "n=4")
    assert rec["forward_facing"] and rec["returned"] >= 1
    assert rec["candidates"]["dropped"]["behind_forward_capture"] > 0
    axis = np.asarray(rec["axis"])
    assert all(float(np.asarray(s["direction"]) @ axis) >= -math.sin(math.radians(10.0)) - 1e-9
               for s in rec["suggestions"])


def test_bad_input_is_one_line_and_writes_nothing(runs, tmp_path):
    run = runs["std"]
    before = {p.name: p.stat().st_mtime_ns for p in (run / "suggest").iterdir()} if (run / "suggest").exists() else {}
    res = cli(f"run={run}", *SMALL, f"candidates={tmp_path / 'nope.json'}")
    assert res.returncode == 2, res.stderr[-2000:]
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("b3dgs-suggest: error:") and "no such file" in lines[0], res.stderr
    assert "(fix:" in lines[0]
    bad = tmp_path / "bad.json"
    bad.write_text('{"frames": []}')
    for args, words in (([f"candidates={bad}"], "neither a 3DGS camera list nor a nerfstudio camera_path"),
                        (["n=0"], "n=0 must be an integer >= 1"),
                        (["policy=oracle"], "ground truth"), (["policy=nonsense"], "unknown acquisition option"),
                        (["policy=farthest", "batch=greedy_conditioned"], "builds its batch itself"),
                        (["min_coverage=2"], "min_coverage=2")):
        with pytest.raises(B3dgsError, match=words):
            run_suggest(run, *args)
    after = {p.name: p.stat().st_mtime_ns for p in (run / "suggest").iterdir()} if (run / "suggest").exists() else {}
    assert after == before


def test_info_gain_on_a_degree_0_run_is_refused_in_one_line(runs, monkeypatch):
    from b3dgs.module import SplatModule

    monkeypatch.setattr(SplatModule, "active_sh_degree", lambda self, step=None: 0)
    with pytest.raises(B3dgsError, match="SH degree 0.*policy=cover or farthest"):
        run_suggest(runs["std"], "out=" + str(runs["std"] / "deg0"))
    assert not (runs["std"] / "deg0").exists()
    # cover still suggests there; the previews say the map is missing instead of drawing an empty one
    out = runs["std"] / "deg0_cover"
    run_suggest(runs["std"], "policy=cover", "n=2", "out=" + str(out))
    rec = json.loads((out / "suggest.json").read_text())
    assert rec["information_map"].startswith("no information map: ") and "SH degree 0" in rec["information_map"]
    assert [s["information_map_sum"] for s in rec["suggestions"]] == [None, None]
    assert (out / "preview_01.png").is_file()


# ---------------------------------------------------------------------------------------------- the information map
class _Tiny:
    """A few random Gaussians (SH degree 1) and a renderer: what a ScoringContext and the map read of a model."""

    from b3dgs.module import SplatModule

    prepare_posterior, view_sums = SplatModule.prepare_posterior, SplatModule.view_sums  # the view pass, as a run's
    del SplatModule

    def __init__(self, splats, renderer):
        from types import SimpleNamespace

        self.splats, self.renderer, self.bg = splats, renderer, torch.zeros(3)
        self.hparams = SimpleNamespace(seed=0)

    def active_sh_degree(self):
        return 1

    def params(self):
        return dict(self.splats)

    def device_camera(self, c):
        return c

    def render_camera(self, c, params=None, **kw):
        return self.renderer.render(params if params is not None else self.splats, c, sh_degree=kw.pop("sh_degree", 1),
                                    background=self.bg, **kw)


def test_information_map_is_exact_against_a_float64_brute_force():
    """Each pixel's share m_p = Σ_k g_k w_kp / Σ_p' w_kp', with g_k = 3 tr((Λ_k⁻¹ − (Λ_k + J_kc)⁻¹) G_k) from explicit
    float64 inverses and every w_kp from one-hot colour renders; the map sums to info_gain's score."""
    from b3dgs.acquisition import ScoringContext
    from b3dgs.render.projection import rgb_to_sh0, sh_basis
    from b3dgs.render.renderers import make_renderer
    from b3dgs.study.active import load_policy
    from b3dgs.suggest import information_map, sh_gain_per_gaussian
    from b3dgs_plugins.acquisition.info_gain import InfoGainPolicy

    g = torch.Generator().manual_seed(0)
    N = 30
    splats = {"means": (torch.rand(N, 3, generator=g) - 0.5) * 1.2, "quats": torch.randn(N, 4, generator=g),
              "scales": torch.full((N, 3), math.log(0.2)), "opacities": torch.zeros(N),
              "sh0": torch.randn(N, 1, 3, generator=g) * 0.5, "shN": torch.randn(N, 15, 3, generator=g) * 0.2}
    r = make_renderer("auto")
    m = _Tiny(splats, r)
    train = []
    for i, az in enumerate([0.0, 0.7, 1.4, 2.1]):
        c = ring_camera(f"t{i}", az, 0.3)
        train.append(c.with_image((m.render_camera(c).rgb + 0.05 * torch.randn(12, 12, 3, generator=g)).clamp(0, 1)))
    cand = [ring_camera("c0", 3.5, 0.2), ring_camera("c1", 4.5, 0.6)]
    pool = cand + [ring_camera(f"x{i}", a, 0.1) for i, a in enumerate([3.0, 4.0, 5.0])]
    ctx = ScoringContext([m], train, None, 1.0, 0)
    pol = load_policy("info_gain")[1]  # composed as the study composes it: with its SH block
    assert isinstance(pol, InfoGainPolicy)
    score = float(pol.score(ctx, pool)[0])
    rows, gk = sh_gain_per_gaussian(pol, ctx, pool, cand[0])
    _, mp = information_map(m, cand[0], rows, gk)

    def weights(c):  # (N, H*W) float64: Gaussian k's compositing weight at each pixel, three Gaussians per render
        w = torch.zeros(N, c.height * c.width, dtype=torch.float64)
        for j in range(0, N, 3):
            col = torch.zeros(N, 3)
            for ch in range(min(3, N - j)):
                col[j + ch, ch] = 1.0
            p = {**splats, "sh0": rgb_to_sh0(col)[:, None, :], "shN": torch.zeros_like(splats["shN"])}
            out = r.render(p, c, sh_degree=0, background=torch.zeros(3)).rgb.double().reshape(-1, 3)
            for ch in range(min(3, N - j)):
                w[j + ch] = out[:, ch]
        return w

    mu = splats["means"].double()

    def info(c, s2):
        w = weights(c)
        y = sh_basis(1, torch.nn.functional.normalize(mu - c.center.double(), dim=-1))
        return ((w ** 2).sum(1) / s2)[:, None, None] * y[:, :, None] * y[:, None, :], w

    s2 = sum(float((m.render_camera(c).rgb.double() - c.image.double()).square().sum()) for c in train) / sum(
        c.image.numel() for c in train)
    lam = torch.eye(4, dtype=torch.float64).expand(N, 4, 4) + sum(info(c, s2)[0] for c in train)
    G = sum(info(c, s2)[0] for c in pool)
    J, w = info(cand[0], s2)
    gbf = 3 * torch.einsum("nij,nji->n", torch.linalg.inv(lam) - torch.linalg.inv(lam + J), G)
    Wk = w.sum(1)
    mbf = (gbf[:, None] * w / torch.where(Wk > 0, Wk, 1)[:, None]).sum(0).reshape(12, 12)
    full = torch.zeros(N, dtype=torch.float64)
    full[rows] = gk
    assert torch.allclose(full, gbf, rtol=1e-5, atol=1e-6 * float(gbf.abs().max()))
    assert float((mbf - mp).abs().max()) <= 1e-5 * float(mbf.max())
    assert float(mp.sum()) == pytest.approx(score, rel=1e-5) and float(gbf.sum()) == pytest.approx(score, rel=1e-5)
    assert float(mbf.max()) > 10 * float(mbf[mbf > 0].min())  # a map with structure, not a constant

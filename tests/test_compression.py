"""Compression ladder: pruning scores on known answers (PUP's Fisher against a float64 Jacobian), exact keep
counts, the study end to end on a tiny run with resume, and one-line errors for bad input."""
import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from torch import nn

from b3dgs.acquisition import ScoringContext
from b3dgs.compression import keep_top, position_grad_norm, spatial_fisher, usage_counts
from b3dgs.study.compression import round_targets
from b3dgs.train import CONF_DIR
from b3dgs.types import Camera

ROOT = Path(__file__).resolve().parents[1]
ALL = ["random", "opacity", "gradient", "dp_mass", "posterior_importance", "pup"]


def _score(name, **kw):
    from b3dgs.study.compression import load_pruning

    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        s = load_pruning(name)
    for k, v in kw.items():
        setattr(s, k, v)
    return s


def _tiny_model(double=False, points=12, side=8, views=8):
    from b3dgs.data.scene import load_scene
    from b3dgs.lifecycle import build_module, build_plugins

    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        cfg = compose("train", ["renderer=torch", f"model.init_max_points={points}", "model.init_num_random=0",
                                "model.sh_degree=1"])
    scene = load_scene("synthetic", None, max_side=side, n_views=views)
    strategy, blocks = build_plugins(cfg)
    m = build_module(cfg, strategy, blocks)
    m.init_from_scene(scene)
    if double:
        m.splats = nn.ParameterDict({k: nn.Parameter(v.detach().double()) for k, v in m.splats.items()})
        m.bg = m.bg.double()
    m._loaded_step = 10_000
    return m, scene


def test_keep_top_counts_ties_and_nan():
    s = torch.tensor([1.0, 3.0, 3.0, float("nan"), 2.0, 3.0])
    m = keep_top(s, 3)
    assert m.tolist() == [False, True, True, False, False, True]
    assert keep_top(s, 2).tolist() == [False, True, True, False, False, False]  # ties: lower index first
    assert keep_top(s, 6).all() and not keep_top(s, 0).any()
    assert keep_top(s, 5)[3].item() is False  # NaN ranks last
    with pytest.raises(ValueError, match=r"\(N,\)"):
        keep_top(s.reshape(2, 3), 1)


def test_round_targets_land_on_the_keep_ratio():
    assert round_targets(1000, 0.1, 1) == [100]
    t = round_targets(1000, 0.1, 2)
    assert t[-1] == 100 and t[0] == round(1000 * 0.1 ** 0.5)
    assert round_targets(3, 0.01, 2)[-1] == 1  # never zero Gaussians
    with pytest.raises(ValueError, match="keep"):
        round_targets(10, 1.5, 1)


def test_pup_fisher_matches_float64_jacobian():
    """Exact mode (stride >= side, per channel) against the per-pixel, per-channel Jacobian over means and
    log-scales in float64: F_k = Σ_{p,c} J_k Jᵀ_k (6×6 per Gaussian)."""
    m, scene = _tiny_model(double=True)
    cams = [Camera(c.name, c.K.double(), c.viewmat.double(), c.width, c.height, c.image.double())
            for c in scene.train[:2]]
    ctx = ScoringContext([m], cams, score_max_side=None)
    F = spatial_fisher({"ctx": ctx}, stride=64, per_channel=True)
    base = {k: v.detach().clone() for k, v in m.params().items()}
    n = base["means"].shape[0]
    ref = torch.zeros(n, 6, 6, dtype=torch.float64)
    for cam in cams:
        def f(means, scales):
            p = dict(base, means=means, scales=scales)
            return m.render_camera(cam, params=p).rgb.reshape(-1)

        Jm, Js = torch.autograd.functional.jacobian(f, (base["means"], base["scales"]))
        J = torch.cat([Jm, Js], dim=-1)  # (P*C, N, 6)
        ref += torch.einsum("pni,pnj->nij", J, J)
    assert ref.abs().max() > 0
    torch.testing.assert_close(F, ref, rtol=1e-9, atol=1e-12)
    # the strided (fast) mode keeps the magnitude
    approx = spatial_fisher({"ctx": ctx}, stride=2, per_channel=True)
    tr = torch.diagonal(approx, dim1=-2, dim2=-1).sum()
    assert 0.5 < float(tr / torch.diagonal(ref, dim1=-2, dim2=-1).sum()) < 4.0


def test_scores_rank_what_they_claim():
    m, scene = _tiny_model(points=40, side=16)
    ctx = ScoringContext([m], scene.train, score_max_side=None)
    # push Gaussian 0 far behind every camera: no pixel sees it
    with torch.no_grad():
        m.splats["means"][0] = torch.tensor([0.0, 0.0, 1.0e4])
    info = {"ctx": ctx, "cache": {}, "generator": torch.Generator().manual_seed(0)}
    n = m.num_gaussians
    u = usage_counts(info)
    assert u.shape == (n,) and u.dtype == torch.float64 and u[0] == 0 and u.sum() > 0
    assert usage_counts(info) is u  # cached: two scores of one model state pay once
    outs = {}
    for name in ALL:
        state = {}
        s = _score(name).score(splats=m.params(), optimizers=None, state=state, step=0, info=info)
        assert s.shape == (n,) and torch.isfinite(s).all(), name
        outs[name] = (s, state)
    # the unseen Gaussian ranks last for every measurement-based score
    for name in ("gradient", "dp_mass", "posterior_importance", "pup"):
        assert int(torch.argmin(outs[name][0])) == 0, name
    assert outs["pup"][1]["clamped"] >= 1  # its zero Fisher block was clamped, and counted
    # DP weight is monotone in usage (stick-breaking ordered by usage)
    e_pi, order = outs["dp_mass"][0], torch.argsort(u, descending=True)
    assert torch.all(e_pi[order][:-1] >= e_pi[order][1:] - 1e-15)
    g = position_grad_norm(info)
    assert g[0] == 0 and g.sum() > 0
    torch.testing.assert_close(outs["opacity"][0], torch.sigmoid(m.splats["opacities"].detach().double()))


def _train_base(tmp_path: Path) -> Path:
    run = tmp_path / "base"
    res = subprocess.run([sys.executable, "-m", "b3dgs.train", "trainer=quick", "trainer.max_steps=40",
                          "trainer.eval_every=1000", "logger=none", "trainer.enable_progress_bar=false",
                          "trainer.save_renders=false", "data.max_side=32", "threads=1", f"hydra.run.dir={run}"],
                         capture_output=True, text=True, cwd=ROOT, timeout=600)
    assert res.returncode == 0, res.stderr[-2000:]
    return run


def test_study_end_to_end_resumes_and_writes_tables(tmp_path):
    run = _train_base(tmp_path)
    out = tmp_path / "cmp"
    args = [sys.executable, "-m", "b3dgs.study.cli", "compress", f"base_runs=[{run}]", f"out_dir={out}",
            "strategies=[opacity,posterior_importance,pup]", "keep=[0.5,0.2]", "finetune_steps=5", "threads=1",
            "score_max_side=16", "progress_bar=false", "plots=true"]
    res = subprocess.run(args, capture_output=True, text=True, cwd=ROOT, timeout=600)
    assert res.returncode == 0, res.stderr[-3000:]
    n_base = json.loads((run / "metrics.json").read_text())["num_gaussians"]
    rows = sorted(p for p in (out / "synthetic" / "s0").glob("*_k*/result.json") if "finetune_only" not in str(p))
    assert len(rows) == 6
    from b3dgs.rundir import run_files  # the base run's evaluation is a record of the scene-seed folder (Run.record)
    assert run_files(out / "synthetic" / "s0") == ["base.json"]
    # the fine-tune-only control: the rounds of fine-tuning the scores get (all 2 here), nothing pruned
    ctl = json.loads((out / "synthetic" / "s0" / "finetune_only_r2_k100" / "result.json").read_text())
    assert ctl["keep"] == 1.0 and ctl["num_gaussians"] == n_base and len(ctl["per_round"]) == 2 and ctl["control"]
    assert "Fine-tune-only controls" in (out / "compression.md").read_text()
    assert res.stdout.strip().splitlines()[-1] == f"b3dgs-study: wrote {out} (compression.md)"
    from b3dgs.ply import read_ply

    base_ply = read_ply(run / "point_cloud.ply")
    for p in rows:
        r = json.loads(p.read_text())
        assert r["num_gaussians"] == round(n_base * r["keep"])  # the ladder lands exactly
        ply = read_ply(p.parent / "point_cloud.ply")  # each row keeps its pruned model, in the base PLY's frame
        assert len(ply["means"]) == r["num_gaussians"]
        lo, hi = base_ply["means"].min(0).values, base_ply["means"].max(0).values
        assert ((ply["means"] >= lo - 0.1 * (hi - lo)) & (ply["means"] <= hi + 0.1 * (hi - lo))).all(1).float().mean() > 0.95
        assert len(r["per_round"]) == r["rounds"] == 2
        assert r["psnr"] is not None and r["time_s"] >= r["finetune_s"] > 0
    s = json.loads((out / "compression.json").read_text())
    assert {(p["a"], p["b"]) for p in s["pairs"]} == {("posterior_importance", "opacity"), ("pup", "posterior_importance"),
                                                      ("pup", "opacity")}
    md = (out / "compression.md").read_text()
    assert "posterior_importance − opacity" in md and (out / "plots" / "ladder.png").stat().st_size > 1000
    # resume: nothing is recomputed (row files untouched), the tables are rebuilt
    stamps = {p: p.stat().st_mtime_ns for p in rows}
    res = subprocess.run(args, capture_output=True, text=True, cwd=ROOT, timeout=600)
    assert res.returncode == 0, res.stderr[-3000:]
    assert {p: p.stat().st_mtime_ns for p in rows} == stamps
    # other fine-tune settings into the same out_dir: refused in one line, the rows are not reused
    res = subprocess.run([a for a in args if not a.startswith("finetune_steps=")] + ["finetune_steps=7"],
                         capture_output=True, text=True, cwd=ROOT, timeout=600)
    assert res.returncode == 2 and "holds results of other settings (finetune_steps: 5 there, 7 here)" in res.stderr, \
        res.stderr[-2000:]


def test_bad_input_is_one_line(tmp_path):
    for extra, needle in ((["base_runs=[/nonexistent/run]"], "no finished base runs"),
                          (["base_runs=[/nonexistent/run]", "strategies=[nope]"], "unknown pruning option"),
                          ):
        res = subprocess.run([sys.executable, "-m", "b3dgs.study.cli", "compress", f"out_dir={tmp_path}", *extra],
                             capture_output=True, text=True, cwd=ROOT, timeout=300)
        assert res.returncode == 2
        err = [ln for ln in res.stderr.strip().splitlines() if ln.startswith("b3dgs-study: error:")]
        assert len(err) == 1, res.stderr[-2000:]
        if needle:
            assert needle in err[0], err[0]
    res = subprocess.run([sys.executable, "-m", "b3dgs.study.cli", "squash"], capture_output=True, text=True, cwd=ROOT)
    assert res.returncode == 2 and "compress" in res.stderr

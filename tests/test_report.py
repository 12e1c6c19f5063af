"""b3dgs-report: statistics wrappers on known answers, grouping by config, a report from small synthetic
run dirs, the CLI's one-line errors, and (slow) a real short training run and a headless-browser check."""
import json
import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import yaml
from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra

from b3dgs.report.collect import ReportError, load_runs
from b3dgs.report.ood import label_views, support_scores
from b3dgs.report.stats import bootstrap_ci, paired_stats, pareto_front, sign_flip_p, time_to_fraction
from b3dgs.train import CONF_DIR

ROOT = Path(__file__).resolve().parents[1]
# a small procedural scene: 24 views, every 4th a test view (6), 32 px
DATA = {"_target_": "b3dgs.data.datamodule.SceneDataModule", "kind": "synthetic", "path": None, "max_side": 32,
        "test_every": 4, "train_indices": None, "normalize": True, "background": [0.0, 0.0, 0.0],
        "max_images": None, "n_views": 24}
TEST_VIEWS = [f"view_{i:03d}" for i in range(0, 24, 4)]


# ------------------------------------------------------------------------------------------ statistics
def test_sign_flip_all_positive_n6_gives_the_floor():
    d = [0.1, 0.2, 0.05, 0.3, 0.01, 0.4]
    assert sign_flip_p(d) == pytest.approx(2 / 64)
    assert sign_flip_p(d, "greater") == pytest.approx(1 / 64)
    r = paired_stats(d)
    assert r["p_floor"] == pytest.approx(2 / 64) and r["p_two_sided"] == pytest.approx(r["p_floor"])
    assert (r["wins"], r["losses"], r["ties"]) == (6, 0, 0)


def test_sign_flip_symmetric_pair_and_single_unit():
    assert sign_flip_p([1.0, -1.0]) == pytest.approx(1.0)  # flips give means {0, 0, 1, -1}
    # three units, one negative: the statistic 1/3*(3+2-1)=4/3 is reached or exceeded by 2 of 8 patterns
    assert sign_flip_p([3.0, 2.0, -1.0], "greater") == pytest.approx(2 / 8)
    assert sign_flip_p([0.5]) is None


def test_bootstrap_bca_percentile_fallback_and_degenerate():
    rng = np.random.default_rng(1)
    d = rng.normal(0.03, 0.02, size=13)
    bca = bootstrap_ci(d, bca_min_n=6)
    assert bca["method"] == "BCa" and bca["low"] < d.mean() < bca["high"]
    few = bootstrap_ci([0.1, 0.3], bca_min_n=6)
    assert few["method"] == "percentile" and "too few" in few["reason"]
    assert 0.1 <= few["low"] <= few["high"] <= 0.3
    assert bootstrap_ci([0.2])["low"] is None
    assert bootstrap_ci([0.2, 0.2, 0.2])["method"] == "degenerate"


def test_paired_direction_for_lower_is_better():
    r = paired_stats([-0.01, -0.02, 0.005], higher_is_better=False)
    assert (r["wins"], r["losses"]) == (2, 1)
    assert r["p_one_sided"] == pytest.approx(sign_flip_p([-0.01, -0.02, 0.005], "less"))


def test_pareto_front_and_time_to_fraction():
    # cost, value: (1, 10) and (2, 12) are non-dominated, (3, 11) is dominated by (2, 12)
    assert pareto_front([3, 1, 2], [11, 10, 12]) == [1, 2]
    pts = [{"train_time_s": 0.0, "psnr": 10.0}, {"train_time_s": 10.0, "psnr": 20.0}, {"train_time_s": 20.0, "psnr": 20.0}]
    assert time_to_fraction(pts, 0.95) == pytest.approx(9.5)
    assert time_to_fraction(pts[:1], 0.95) is None


# ------------------------------------------------------------------------------------------ fixtures
MODEL_BLOCKS = {"niw": ["niw"], "dpmm": ["niw", "dp", "noise", "opacity", "color"]}  # conf/model/<name>.yaml


def write_run(path: Path, scene: str, method: str, seed: int, psnr: float, *, lpips=0.2, t=100.0, n=1000,
              fps=100.0, data=None, study=None, init_max_points=100000, uq=None, max_steps=300, posterior=None) -> Path:
    """A run dir shaped like b3dgs-train's: config.yaml, metrics.json (done marker), curve.json, uq.json;
    ``posterior``: its blocks (default: the model's own)."""
    path.mkdir(parents=True, exist_ok=True)
    blocks = MODEL_BLOCKS.get(method, []) if posterior is None else posterior
    cfg = {"posterior": {b: {} for b in blocks}, "data": {**DATA, "name": scene, **(data or {})},
           "model": {"_target_": "b3dgs.module.SplatModule", "name": method, "init_max_points": init_max_points},
           "trainer": {"max_steps": max_steps, "eval_every": 100}, "seed": seed, "threads": None, "resume": None}
    if study:
        cfg["study"] = {"name": study}
    (path / "config.yaml").write_text(yaml.safe_dump(cfg, sort_keys=False))
    pts = [{"step": s, "train_time_s": t * s / max_steps, "psnr": psnr - 6.0 * (1 - s / max_steps) ** 2,
            "num_gaussians": n} for s in range(100, max_steps + 1, 100)]
    (path / "curve.json").write_text(json.dumps({"x": "train_time_s", "points": pts}))
    if uq is not None:
        (path / "uq.json").write_text(json.dumps(uq))
    metrics = {"method": method, "scene": scene, "seed": seed, "steps": max_steps, "psnr": psnr, "ssim": 0.9,
               "lpips": lpips, "lpips_reason": None, "num_gaussians": n, "train_time_s": t, "render_fps": fps,
               "renderer": "cpu", "num_train_views": 18, "num_test_views": 6,
               "per_view": [{"name": v, "psnr": psnr} for v in TEST_VIEWS]}
    (path / "metrics.json").write_text(json.dumps(metrics))
    return path


def report_cfg(runs, out, *extra):
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        return compose(config_name="report", overrides=[f"runs={runs}", f"out={out}", *extra])


# ------------------------------------------------------------------------------------------ grouping
def test_grouping_reads_the_config_not_folder_names(tmp_path):
    # folder names lie on purpose: the config decides
    write_run(tmp_path / "niw_s5", "sceneA", "standard", 1, 20.0)
    write_run(tmp_path / "x" / "y", "sceneB", "niw", 2, 21.0)
    write_run(tmp_path / "sparse8", "sceneA", "niw", 0, 18.0, data={"train_indices": [0, 5, 10]})
    write_run(tmp_path / "cap", "sceneA", "niw", 0, 19.0, init_max_points=500)
    (tmp_path / "unfinished").mkdir()
    (tmp_path / "unfinished" / "config.yaml").write_text((tmp_path / "niw_s5" / "config.yaml").read_text())
    hyd = tmp_path / "niw_s5" / ".hydra"
    hyd.mkdir()
    (hyd / "config.yaml").write_text("a: 1\n")
    runs, unfinished = load_runs(str(tmp_path / "**"))
    keys = {r.key for r in runs}
    assert keys == {("canonical", None, "sceneA", "standard", 1), ("canonical", None, "sceneB", "niw", 2),
                    ("sparse", 3, "sceneA", "niw", 0), ("initcap", 500, "sceneA", "niw", 0)}
    assert [p.name for p in unfinished] == ["unfinished"]
    # a folder (no glob) is searched below
    assert len(load_runs(str(tmp_path))[0]) == 4


def test_methods_are_labelled_by_what_ran(tmp_path, monkeypatch):
    """posterior=[niw,dp] on the standard model is its own method (not a duplicate of standard); the paired plot
    of two identical methods says so instead of drawing a 1e-17 axis; the default pair is not niw − standard."""
    from b3dgs.report.app import build_report

    for scene in ("sceneA", "sceneB"):
        write_run(tmp_path / "runs" / scene / "std", scene, "standard", 0, 20.0)
        write_run(tmp_path / "runs" / scene / "nd", scene, "standard", 0, 20.0, posterior=["niw", "dp"])
        write_run(tmp_path / "runs" / scene / "dpmm", scene, "dpmm", 0, 20.5)
    runs, _ = load_runs(str(tmp_path / "runs" / "**"))
    assert sorted({r.method for r in runs}) == ["dpmm", "niw+dp", "standard"]
    cfg = report_cfg(f"{tmp_path / 'runs'}/**", tmp_path / "rep")
    assert cfg.pair is None  # the default: dpmm − standard where both ran
    data = json.loads(build_report(cfg)["json"].read_text())
    assert set(data["canonical"]["table"]) == {"standard", "niw+dp", "dpmm"}
    assert (data["canonical"]["paired"][0]["a"], data["canonical"]["paired"][0]["b"]) == ("dpmm", "standard")
    assert data["canonical"]["paired"][0]["mean"] == pytest.approx(0.5)
    from b3dgs.report import plots
    from b3dgs.report.analysis import paired

    same = [paired(runs, "niw+dp", "standard", "psnr")]
    assert same[0]["per_scene"] == {"sceneA": 0.0, "sceneB": 0.0}
    drawn = []
    monkeypatch.setattr(plots, "_save", lambda fig, path: drawn.extend(fig.axes))
    plots.plot_paired(same, tmp_path / "same.png")
    assert "Δ = 0 in all 2 scenes" in drawn[0].texts[0].get_text() and not drawn[0].get_yticks().size


def test_block_time_share_is_derived_from_the_run_itself():
    from b3dgs.report.collect import Run

    r = Run(Path("x"), {}, {"train_time_s": 200.0, "block_time_s": {"niw": 2.0, "dp": 1.0}})
    assert r.value("block_time_pct") == pytest.approx(1.5)
    assert Run(Path("x"), {}, {"train_time_s": 100.0, "block_time_s": {}}).value("block_time_pct") == 0.0
    assert Run(Path("x"), {}, {"train_time_s": 0.0, "block_time_s": {}}).value("block_time_pct") is None
    assert Run(Path("x"), {}, {"train_time_s": 5.0}).value("block_time_pct") is None
    # a count's pass over the training views after training counts as block time (of a longer run)
    r = Run(Path("x"), {}, {"train_time_s": 200.0, "block_time_s": {"niw": 2.0}, "posterior_pass_s": 8.0})
    assert r.value("block_time_pct") == pytest.approx(100 * 10 / 208)


def test_duplicate_keys_error_or_newest(tmp_path):
    write_run(tmp_path / "a", "sceneA", "standard", 0, 20.0)
    time.sleep(0.05)
    write_run(tmp_path / "b", "sceneA", "standard", 0, 22.0)
    with pytest.raises(ReportError, match="share"):
        load_runs(str(tmp_path / "*"))
    runs, _ = load_runs(str(tmp_path / "*"), on_duplicate="newest")
    assert len(runs) == 1 and runs[0].metrics["psnr"] == 22.0


def test_no_runs_is_a_one_line_error(tmp_path):
    pattern = str(tmp_path / "nothing" / "**")
    res = subprocess.run([sys.executable, "-m", "b3dgs.report.app", f"runs={pattern}", f"out={tmp_path / 'r'}"],
                         capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert res.returncode == 2
    err = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert len(err) == 1 and pattern in err[0] and "runs=" in err[0] and "Traceback" not in res.stderr
    assert not (tmp_path / "r").exists()  # a refused report leaves no folder and no empty app.log


# ------------------------------------------------------------------------------------------ OOD
def test_support_scores_match_camera_geometry():
    from b3dgs.data.scene import load_scene

    s = support_scores({**DATA, "name": "sceneA"})
    scene = load_scene("synthetic", None, max_side=32, test_every=4, n_views=24)
    train = np.stack([c.center.numpy() for c in scene.train])
    assert sorted(s) == TEST_VIEWS
    for c in scene.test:
        assert s[c.name] == pytest.approx(np.linalg.norm(train - c.center.numpy(), axis=1).min() / scene.extent, rel=1e-5)
    lab = label_views([0.1, 0.2, 0.3, 0.4, 0.5, 0.6], 1 / 3)
    assert lab.tolist() == [0, 0, -1, -1, 1, 1]
    with pytest.raises(ReportError):
        label_views([0.1, 0.2], 0.5)


# ------------------------------------------------------------------------------------------ report
def synthetic_bench(root: Path) -> dict:
    """Three scenes, unbalanced seeds, NIW better by known per-scene deltas; uq.json whose NIW uncertainty
    grows with the support score (a perfect OOD detector) and whose standard one shrinks with it; sparse
    (budgets 2, 4) and init-cap (500 points) runs."""
    support = support_scores({**DATA, "name": "sceneA"})  # the three scenes share the geometry
    rising = {"per_view": [{"name": v, "mean_var": support[v]} for v in TEST_VIEWS], "ause_rmse": 0.02, "ece": 0.05,
              "cov95": 0.9}
    falling = {"per_view": [{"name": v, "mean_var": 1.0 / support[v]} for v in TEST_VIEWS], "ause_rmse": 0.03,
               "ece": 0.06, "cov95": 0.8}
    base = {"sceneA": 20.0, "sceneB": 25.0, "sceneC": 30.0}
    delta = {"sceneA": 0.1, "sceneB": 0.2, "sceneC": 0.3}
    seeds = {"sceneA": [0, 1, 2], "sceneB": [0], "sceneC": [0, 1]}
    for scene, ss in seeds.items():
        for s in ss:
            write_run(root / scene / "standard" / f"s{s}", scene, "standard", s, base[scene] + 0.01 * s, t=100.0,
                      n=1000, fps=100.0, uq={"proxy": falling, "_meta": {}})
            write_run(root / scene / "niw" / f"s{s}", scene, "niw", s, base[scene] + 0.01 * s + delta[scene],
                      lpips=0.19, t=102.0, n=1100, fps=95.0, uq={"proxy": rising, "_meta": {}})
        for b in (2, 4):
            for m in ("standard", "niw"):
                write_run(root / "sparse" / scene / m / f"b{b}", scene, m, 0, base[scene] - 8 + b,
                          data={"train_indices": list(range(b))})
        for m, d in (("standard", 0.0), ("niw", 0.05)):
            write_run(root / "initcap" / scene / m, scene, m, 0, base[scene] - 1 + d, init_max_points=500)
    return {"base": base, "delta": delta, "seeds": seeds}


def test_report_from_synthetic_runs(tmp_path):
    truth = synthetic_bench(tmp_path / "runs")
    out = tmp_path / "report"
    from b3dgs.report.app import build_report

    paths = build_report(report_cfg(f"{tmp_path / 'runs'}/**", out, "pair=[niw,standard]"))
    data = json.loads(paths["json"].read_text())
    # canonical: macro mean of per-scene seed means (not the pooled mean over runs)
    std = data["canonical"]["table"]["standard"]
    seed_means = [truth["base"][s] + 0.01 * np.mean(ss) for s, ss in truth["seeds"].items()]
    assert std["psnr"] == pytest.approx(np.mean(seed_means))
    assert std["n_scenes"] == 3 and std["n_runs"] == 6 and std["ause_rmse"] == pytest.approx(0.03)
    # paired: niw − standard per scene = the known deltas; 3 scenes all positive -> p = floor = 2/8
    p = {r["metric"]: r for r in data["canonical"]["paired"]}
    assert p["psnr"]["per_scene"] == pytest.approx(truth["delta"])
    assert p["psnr"]["mean"] == pytest.approx(0.2)
    assert p["psnr"]["p_two_sided"] == pytest.approx(0.25) and p["psnr"]["p_floor"] == pytest.approx(0.25)
    assert p["psnr"]["ci"]["method"] == "percentile"  # 3 scenes < bca_min_n
    assert p["lpips"]["wins"] == 3
    # OOD: rising uncertainty detects OOD perfectly, falling uncertainty never does
    rows = data["ood"]["rows"]
    assert rows["niw (proxy)"]["auroc"] == pytest.approx(1.0) and rows["niw (proxy)"]["gap"] > 0
    assert rows["standard (proxy)"]["auroc"] == pytest.approx(0.0)
    # sparse study: budgets 2, 4 and 'all' (the canonical runs)
    assert list(data["studies"]["sparse"]) == ["2", "4", "all"]
    assert data["studies"]["sparse"]["4"]["niw"]["psnr"] == pytest.approx(np.mean([v - 4 for v in truth["base"].values()]))
    # init cap (recognised from model.init_max_points): paired niw − standard = +0.05 on every scene
    cap = {r["metric"]: r for r in data["studies"]["initcap"]["500"]["paired"]}
    assert cap["psnr"]["mean"] == pytest.approx(0.05) and cap["psnr"]["wins"] == 3
    # curves and time to target from curve.json
    cv = data["canonical"]["curves"]["psnr"]["sceneA"]["standard"]
    assert cv["n_seeds"] == 3 and len(cv["t"]) == 3 and cv["sem"][0] is not None
    assert data["canonical"]["time_to_target"]["standard"]["t95"] < 100.0
    # every figure exists, is a PNG, and is embedded in the HTML; tables are in both documents
    html = paths["html"].read_text()
    md = paths["md"].read_text()
    assert data["figures"] and len(re.findall(r'<img src="data:image/png;base64,', html)) == len(data["figures"])
    for f in data["figures"]:
        assert (out / f).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        assert f"]({f})" in md
    assert html.count("<table>") == len(re.findall(r"^\|---", md, re.M)) >= 6
    assert "p floor" in md and "percentile" in md


# ------------------------------------------------------------------------------------------ slow
@pytest.mark.slow
def test_report_on_real_short_training_runs(tmp_path):
    res = subprocess.run([sys.executable, "-m", "b3dgs.train", "-m", "trainer=quick", "trainer.max_steps=30",
                          "trainer.eval_every=10", "logger=none", "trainer.enable_progress_bar=false",
                          "trainer.save_renders=false", "data.max_side=48", "model=standard,niw",
                          f"hydra.sweep.dir={tmp_path / 'runs'}", "hydra.sweep.subdir=${model.name}"],
                         capture_output=True, text=True, cwd=ROOT, timeout=600)  # both runs in one process
    assert res.returncode == 0, res.stderr[-2000:]
    res = subprocess.run([sys.executable, "-m", "b3dgs.report.app", f"runs={tmp_path / 'runs'}/**",
                          f"out={tmp_path / 'rep'}"], capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert res.returncode == 0, res.stderr[-2000:]
    data = json.loads((tmp_path / "rep" / "report.json").read_text())
    assert set(data["canonical"]["table"]) == {"standard", "niw"}
    assert data["canonical"]["curves"]["psnr"]["synthetic"]["niw"]["step"] == [10, 20, 30]


CHECK_JS = """<script>window.addEventListener('load', () => {
  const imgs = [...document.images].map(i => i.complete && i.naturalWidth > 0 ? i.naturalWidth : 0);
  const tables = [...document.querySelectorAll('table')].map(t => t.rows.length > 1 && t.offsetHeight > 0 ? t.rows.length : 0);
  const pre = document.createElement('pre'); pre.id = 'check';
  pre.textContent = JSON.stringify({imgs, tables}); document.body.appendChild(pre);
});</script>"""


def chromium() -> str | None:
    return next((shutil.which(n) for n in ("chromium", "chromium-browser") if shutil.which(n)), None)


@pytest.mark.slow
@pytest.mark.skipif(chromium() is None, reason="chromium not installed (apt-get install -y chromium)")
def test_report_html_renders_in_headless_chromium(tmp_path):
    synthetic_bench(tmp_path / "runs")
    from b3dgs.report.app import build_report

    paths = build_report(report_cfg(f"{tmp_path / 'runs'}/**", tmp_path / "report", "pair=[niw,standard]"))
    probe = tmp_path / "probe.html"
    probe.write_text(paths["html"].read_text().replace("</body>", CHECK_JS + "</body>"))
    flags = [chromium(), "--headless", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
             f"--user-data-dir={tmp_path / 'profile'}", "--virtual-time-budget=10000"]
    dom = subprocess.run(flags + ["--dump-dom", probe.as_uri()], capture_output=True, text=True, timeout=120).stdout
    found = re.search(r'<pre id="check">(.*?)</pre>', dom)
    assert found, f"no check output in the DOM: {dom[:500]}"
    check = json.loads(found.group(1).replace("&quot;", '"'))
    n_fig = len(json.loads(paths["json"].read_text())["figures"])
    assert len(check["imgs"]) == n_fig and all(w > 0 for w in check["imgs"]), check
    assert len(check["tables"]) >= 6 and all(n > 1 for n in check["tables"]), check
    shot = Path(os.environ.get("B3DGS_REPORT_SCREENSHOT", tmp_path / "report.png"))
    subprocess.run(flags + ["--window-size=1280,2400", f"--screenshot={shot}", paths["html"].as_uri()],
                   capture_output=True, timeout=120)
    assert shot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_study_grid_shares_runs_that_are_the_same_training_run(tmp_path):
    """bench/studies.py: the init-cap NIW run is the standard run (NIW only observes training), so it is
    written as a shared run dir (its own config, the twin's metrics) and the report says so."""
    out, rep = tmp_path / "b", tmp_path / "rep"
    res = subprocess.run([sys.executable, "-m", "bench.studies", "--studies", "initcap", "--scenes", "synthetic",
                          "--seeds", "0", "--max-steps", "40", "--cap", "200", "--out", str(out), "--report", str(rep),
                          "--jobs", "2", "--threads", "1",
                          "--extra", "data.max_side=32", "renderer=cpu"],
                         capture_output=True, text=True, cwd=ROOT, timeout=900)
    assert res.returncode == 0, res.stderr[-3000:]
    niw = out / "initcap" / "c200" / "synthetic" / "niw" / "s0"
    std = out / "initcap" / "c200" / "synthetic" / "standard" / "s0"
    m = json.loads((niw / "metrics.json").read_text())
    assert m["training_shared_with"] == str(std) and m["method"] == "niw"
    assert not (niw / "checkpoints").exists() and (std / "checkpoints").exists()
    from b3dgs.rundir import read_manifest
    assert "metrics.json" in read_manifest(niw)["files"]  # a run of its own (b3dgs.lifecycle.Run.share_training)
    assert "model:\n" in (niw / "config.yaml").read_text() and "name: niw" in (niw / "config.yaml").read_text()
    assert "same training run as another" in (rep / "report.md").read_text()
    # a run outside the default --out is archived beside it, never into the committed bench/results/runs
    assert (out / "archive" / "initcap" / "c200" / "synthetic" / "niw" / "s0" / "metrics.json").is_file()


@pytest.mark.slow
def test_canonical_grid_uq_regimes_ensemble_and_merge(tmp_path):
    """bench/studies.py --uq: every canonical run gets conf/report.yaml's regimes (native only with a posterior), the
    scene's deep ensemble of the standard seeds is evaluated and archived under its members' archive dirs, the report
    has the uncertainty table; a regime missing from a uq.json is computed alone and merged (the others kept as they
    were)."""
    out, rep = tmp_path / "b", tmp_path / "rep"
    cmd = [sys.executable, "-m", "bench.studies", "--studies", "canonical", "--uq", "--uq-samples", "4", "--scenes",
           "synthetic", "--seeds", "0", "1", "2", "--methods", "standard", "niw", "--max-steps", "20", "--out", str(out),
           "--report", str(rep), "--jobs", "2", "--threads", "1", "--extra", "data.max_side=32", "renderer=cpu",
           "trainer.eval_every=20"]  # one curve point, not one every max_steps // 12 (changes no result)
    res = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT, timeout=900)
    assert res.returncode == 0, res.stderr[-3000:]
    arch = out / "archive" / "synthetic"
    std = json.loads((arch / "standard" / "s0" / "uq.json").read_text())
    assert {"proxy", "constant", "ppu"} <= set(std) and "native" not in std
    assert {"proxy", "constant", "ppu", "native"} <= set(json.loads((arch / "niw" / "s1" / "uq.json").read_text()))
    ens = json.loads((arch / "ensemble" / "uq.json").read_text())["ensemble"]
    assert ens["runs"] == [str((arch / "standard" / f"s{s}").resolve()) for s in (0, 1, 2)]
    md = (rep / "report.md").read_text()
    assert "Uncertainty regimes" in md and "| ensemble of 3 standard runs |" in md and "| niw (native) |" in md
    # drop one regime from a run (here and in the archive): only it is recomputed, the rest is kept byte for byte
    for d in (out / "synthetic" / "niw" / "s2", arch / "niw" / "s2"):
        u = json.loads((d / "uq.json").read_text())
        kept = {k: v for k, v in u.items() if k != "constant"}
        (d / "uq.json").write_text(json.dumps(kept))
    res = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT, timeout=900)
    assert res.returncode == 0, res.stderr[-3000:]
    assert "uq.json with every regime" in res.stdout
    now = json.loads((arch / "niw" / "s2" / "uq.json").read_text())
    assert "constant" in now and all(now[k] == kept[k] for k in ("proxy", "ppu", "native"))


def test_an_ensemble_whose_member_is_not_among_the_runs_is_left_out_with_a_line(tmp_path, caplog):
    """Through load_runs on an archive's layout: an ensemble uq.json naming its members by another checkout's absolute
    paths joins its first member here; one whose first member is not among the runs is left out with a warning line,
    not silently (the silent drop hid that the report rebuilt outside /work/main lost its ensemble rows)."""
    arch = tmp_path / "clone" / "bench" / "results" / "runs"
    for s in (0, 1, 2):
        write_run(arch / "sceneA" / "standard" / f"s{s}", "sceneA", "standard", s, 20.0 + s)
    gone = "/work/elsewhere/bench/results/runs/sceneA/standard"
    ens = {"ensemble": {"cov95": 0.5, "runs": [f"{gone}/s{s}" for s in (0, 1, 2)]}}
    (arch / "sceneA" / "ensemble").mkdir(parents=True)
    (arch / "sceneA" / "ensemble" / "uq.json").write_text(json.dumps(ens))
    runs, _ = load_runs([str(arch / "sceneA" / "standard" / "*"), str(arch / "sceneA" / "ensemble" / "uq.json")])
    assert {r.seed: "ensemble" in r.uq for r in runs} == {0: True, 1: False, 2: False}
    # an ensemble whose first member is not among the runs is left out with a line saying so, not silently
    with caplog.at_level("WARNING"):
        runs, _ = load_runs([str(arch / "sceneA" / "standard" / "s1"), str(arch / "sceneA" / "ensemble" / "uq.json")])
    assert not any("ensemble" in r.uq for r in runs) and "not among the report's runs" in caplog.text


# ------------------------------------------------------------------------------------------ pooling
def test_runs_of_different_protocols_are_refused_not_pooled(tmp_path):
    write_run(tmp_path / "a", "sceneA", "standard", 0, 20.0, max_steps=300)
    write_run(tmp_path / "b", "sceneA", "standard", 1, 21.0, max_steps=600)
    with pytest.raises(ReportError, match=r"seeds of sceneA/standard \(canonical\) differ in trainer.max_steps: "
                                          r"300 in .*a, 600 in .*b .*fix: pass group_by=\[trainer.max_steps\]"):
        load_runs(str(tmp_path / "*"))
    runs, _ = load_runs(str(tmp_path / "*"), group_by=["trainer.max_steps"])
    assert sorted(r.study for r in runs) == ["canonical [trainer.max_steps=300]", "canonical [trainer.max_steps=600]"]
    # another method at another resolution: not one table either
    write_run(tmp_path / "b", "sceneA", "niw", 0, 21.0, data={"max_side": 64})
    with pytest.raises(ReportError, match=r"runs of study canonical differ in data.max_side: (32|64) in .*, (64|32) in"):
        load_runs(str(tmp_path / "*"))


def test_runs_from_before_a_class_rename_pool_with_new_ones(tmp_path):
    """A seed trained before plugins.* became b3dgs_plugins.* (b3dgs.upgrade.RENAMED_TARGETS) is the same protocol."""
    for seed, target in ((0, "plugins.posterior.niw.NIWBlock"), (1, "b3dgs_plugins.posterior.niw.NIWBlock")):
        d = write_run(tmp_path / f"s{seed}", "sceneA", "niw", seed, 20.0 + seed)
        cfg = yaml.safe_load((d / "config.yaml").read_text())
        cfg["posterior"] = {"niw": {"_target_": target}}
        (d / "config.yaml").write_text(yaml.safe_dump(cfg))
    runs, _ = load_runs(str(tmp_path / "*"))
    assert len(runs) == 2 and {r.config["posterior"]["niw"]["_target_"] for r in runs} == {
        "b3dgs_plugins.posterior.niw.NIWBlock"}
    cfg["posterior"]["niw"]["_target_"] = "b3dgs_plugins.posterior.niw.OtherBlock"  # a real difference still refused
    (tmp_path / "s1" / "config.yaml").write_text(yaml.safe_dump(cfg))
    with pytest.raises(ReportError, match="posterior.niw._target_"):
        load_runs(str(tmp_path / "*"))


def test_a_run_without_a_value_is_not_counted():
    from b3dgs.report.analysis import macro_row, per_scene
    from b3dgs.report.collect import Run

    runs = [Run(Path(f"r{s}"), {}, {"psnr": p}, scene="s", method="m", seed=s) for s, p in ((0, 20.0), (1, None))]
    assert per_scene(runs)["s"]["m"] == {"mean": 20.0, "sem": None, "n": 1}
    assert macro_row(runs, "proxy")["n_runs"] == 1


def test_a_run_whose_metrics_disagree_with_its_own_records_is_refused(tmp_path):
    """Issue 46 (class: a result file that disagrees with the run's own records): a metrics.json whose PSNR (or SSIM,
    LPIPS) is not the mean of its per-view values, or not the curve's final point, is refused in one line naming the
    file; the archived run as committed passes."""
    from b3dgs.report.collect import ReportError, read_run

    src = Path(__file__).resolve().parents[1] / "bench" / "results" / "runs" / "fox" / "niw" / "s0"
    run = tmp_path / "s0"
    shutil.copytree(src, run)
    read_run(run)
    m = json.loads((run / "metrics.json").read_text())
    edited = {**m, "psnr": m["psnr"] + 0.5}
    (run / "metrics.json").write_text(json.dumps(edited))
    with pytest.raises(ReportError, match=r"disagrees with its own per-view values: psnr"):
        read_run(run)
    pv = [dict(v) for v in m["per_view"]]
    for v in pv:  # per-view values edited along with it: the curve still tells
        v["psnr"] += 0.5
    (run / "metrics.json").write_text(json.dumps({**edited, "per_view": pv}))
    with pytest.raises(ReportError, match=r"disagrees with its curve: final PSNR"):
        read_run(run)


# ------------------------------------------------------------------------------------------ a user's own runs
def md_table(md: str, caption: str) -> dict[str, dict[str, str]]:
    """{first cell: {header: cell}} of the Markdown table under the bold ``caption`` (its first line starting so)."""
    lines = md.split("\n**" + caption, 1)[1].splitlines()
    start = next(i for i, ln in enumerate(lines) if ln.startswith("| "))
    rows = []
    for ln in lines[start:]:
        if not ln.startswith("|"):
            break
        rows.append([c.strip() for c in ln.strip("|").split(" | ")])
    return {r[0]: dict(zip(rows[0], r)) for r in rows[2:]}


def user_runs(root: Path, methods, scenes=("sceneA", "sceneB"), **kw) -> None:
    """A user's own runs: each method on each scene, seed 0, method i better by 0.1·i dB."""
    for scene in scenes:
        for i, m in enumerate(methods):
            uq = kw.get("uq", {}).get(m)
            write_run(root / scene / m, scene, m, 0, 20.0 + 0.1 * i, uq=uq,
                      **{k: v for k, v in kw.items() if k != "uq"})


def build(runs: str, out: Path, *extra) -> tuple[str, str, dict]:
    from b3dgs.report.app import build_report

    paths = build_report(report_cfg(runs, out, *extra))
    return paths["md"].read_text(), paths["html"].read_text(), json.loads(paths["json"].read_text())


def test_user_runs_split_by_group_by_are_canonical_sections(tmp_path):
    """Issue 44 §7: a user's runs of two protocols, split with group_by, are canonical benchmarks (one section per
    value, headed so), not a 'Study: canonical [...]' after 'No canonical runs (every run belongs to a study)'."""
    for steps in (300, 600):
        user_runs(tmp_path / "runs" / str(steps), ["standard", "niw"], max_steps=steps)
    md, html, data = build(f"{tmp_path / 'runs'}/**", tmp_path / "rep", "group_by=[trainer.max_steps]")
    assert "No canonical runs" not in md and "Study: canonical" not in md and "every run belongs" not in html
    for steps in (300, 600):
        head = f"Canonical benchmark [trainer.max_steps={steps}]"
        assert f"## {head}\n" in md and f"<h2>{head}</h2>" in html
        assert f"## OOD support deficit [trainer.max_steps={steps}]" in md
        assert (tmp_path / "rep" / f"pareto_trainer.max_steps={steps}.png").is_file()
        group = data["canonical_groups"][f"trainer.max_steps={steps}"]["canonical"]
        assert set(group["table"]) == {"standard", "niw"} and group["paired"][0]["mean"] == pytest.approx(0.1)
    assert "split by group_by=['trainer.max_steps']" in md
    assert len(set(data["figures"])) == len(data["figures"])  # one file per group, none overwritten


def test_a_study_without_levels_prints_no_none_level(tmp_path):
    user_runs(tmp_path / "runs", ["standard", "niw"], study="mine")
    md, html, data = build(f"{tmp_path / 'runs'}/**", tmp_path / "rep")
    assert "None" not in md and "None" not in html
    assert "## Study: mine\n" in md and "**Study: mine**" in md and "**Study: mine: paired niw − standard**" in md
    assert md_table(md, "Study: mine**")["niw"]["PSNR ↑"] == "20.100"
    assert data["studies"]["mine"]["None"]["paired"][0]["mean"] == pytest.approx(0.1)


def test_the_default_pair_falls_back_to_the_methods_present(tmp_path):
    """pair=null: the two methods present are paired (niw − standard); with three, the report names the pairs to
    ask for; an explicit pair that did not run stays one line naming what did."""
    user_runs(tmp_path / "two", ["standard", "niw"])
    md, html, data = build(f"{tmp_path / 'two'}/**", tmp_path / "rep2")
    assert "No paired analysis" not in md and "## Paired analysis: niw − standard" in md
    assert "<h3>Paired analysis: niw − standard</h3>" in html
    assert "the two methods present, niw − standard" in md
    assert md_table(md, "niw − standard, scene-level")["psnr"]["Mean Δ"] == "+0.1"
    assert data["canonical"]["paired"][0]["a"] == "niw" and (tmp_path / "rep2" / "paired.png").is_file()

    user_runs(tmp_path / "three", ["standard", "niw", "mcmc"])
    md, _, data = build(f"{tmp_path / 'three'}/**", tmp_path / "rep3")
    assert "Paired analysis:" not in md and "paired" not in data["canonical"]
    assert ("No paired analysis: 3 methods ran (standard, niw, mcmc) and the default dpmm − standard needs both; "
            "choose a pair: pair=[niw,standard], pair=[mcmc,standard], pair=[mcmc,niw].") in md

    md, _, _ = build(f"{tmp_path / 'two'}/**", tmp_path / "rep4", "pair=[dpmm,standard]")
    lines = [ln for ln in md.splitlines() if "paired" in ln.lower()]
    assert lines == ["No paired analysis: pair=['dpmm', 'standard'] needs both methods; found ['standard', 'niw'] "
                     "(choose two with pair=[A,B])."]
    md, _, _ = build(f"{tmp_path / 'two'}/**", tmp_path / "rep5", "pair=[standard,niw]")
    assert "## Paired analysis: standard − niw" in md and "two methods present" not in md
    with pytest.raises(ReportError, match=r"pair=\['niw'\] names 1 methods.*fix: pass pair=\[A,B\]"):
        build(f"{tmp_path / 'two'}/**", tmp_path / "rep6", "pair=[niw]")


def test_uq_columns_show_the_regimes_the_runs_have(tmp_path):
    """A run evaluated with uq=[native] shows its native AUSE / ECE / Cov@95, named in the header, not a dash; runs
    with different regimes get a column group per regime; every run with the configured proxy: as before."""
    summ = lambda a: {"ause_rmse": a, "ece": 0.05, "cov95": 0.9, "per_view": []}  # noqa: E731
    user_runs(tmp_path / "native", ["standard", "niw"],
              uq={"niw": {"native": summ(0.01)}, "standard": {"native": summ(0.02)}})
    md, html, data = build(f"{tmp_path / 'native'}/**", tmp_path / "rep1")
    assert "**Canonical table (AUSE, ECE, Cov@95 from the 'native' uq.json regime)**" in md
    t = md_table(md, "Canonical table")
    assert t["niw"]["AUSE ↓ (native)"] == "0.0100" and t["standard"]["Cov@95 (native)"] == "0.900"
    assert "<th>AUSE ↓ (native)</th>" in html
    assert data["canonical"]["table"]["niw"]["ause_rmse"] == pytest.approx(0.01)

    user_runs(tmp_path / "mixed", ["standard", "niw"],
              uq={"niw": {"native": summ(0.01)}, "standard": {"proxy": summ(0.03)}})
    md, _, data = build(f"{tmp_path / 'mixed'}/**", tmp_path / "rep2")
    assert "**Canonical table (AUSE, ECE, Cov@95 per uq.json regime: proxy, native)**" in md
    t = md_table(md, "Canonical table")
    assert (t["standard"]["AUSE ↓ (proxy)"], t["standard"]["AUSE ↓ (native)"]) == ("0.0300", "—")
    assert (t["niw"]["AUSE ↓ (proxy)"], t["niw"]["AUSE ↓ (native)"]) == ("—", "0.0100")
    assert data["canonical"]["table"]["niw"]["ause_rmse@native"] == pytest.approx(0.01)

    user_runs(tmp_path / "proxy", ["standard", "niw"],
              uq={"niw": {"proxy": summ(0.01), "native": summ(0.04)}, "standard": {"proxy": summ(0.03)}})
    md, _, _ = build(f"{tmp_path / 'proxy'}/**", tmp_path / "rep3")
    t = md_table(md, "Canonical table")
    assert "**Canonical table (AUSE, ECE, Cov@95 from the 'proxy' uq.json regime)**" in md
    assert t["niw"]["AUSE ↓"] == "0.0100" and "AUSE ↓ (native)" not in t["niw"]


def test_an_ensembles_uq_json_finds_its_runs_after_they_were_copied(tmp_path):
    """An archived ensemble uq.json names its members by absolute paths of the machine that wrote it
    (/work/main/bench/results/runs/...); read from another checkout, it joins the run at the same tail of the path
    (before, the ensemble rows were silently left out there), and never a run that only an ambiguous tail matches."""
    import json

    from b3dgs.report.collect import Run, _attach_uq

    runs = [Run(path=(tmp_path / "runs" / sc / "standard" / "s0").resolve(), config={}, metrics={}, scene=sc)
            for sc in ("fox", "lego")]
    for r in runs:
        r.path.mkdir(parents=True)
    summ = {"runs": ["/elsewhere/checkout/bench/results/runs/lego/standard/s0"], "ause": 0.1}
    f = tmp_path / "runs" / "lego" / "ensemble" / "uq.json"
    f.parent.mkdir(parents=True)
    f.write_text(json.dumps({"ensemble": summ}))
    _attach_uq(runs, [f])
    assert runs[1].uq == {"ensemble": summ} and runs[0].uq == {}
    # a relative member path is read from the uq.json's folder
    runs[1].uq = {}
    f.write_text(json.dumps({"ensemble": {**summ, "runs": ["../standard/s0"]}}))
    _attach_uq(runs, [f])
    assert "ensemble" in runs[1].uq
    # a tail that two runs share (a copy of fox's runs elsewhere) joins neither
    runs[1].uq = {}
    runs.append(Run(path=(tmp_path / "copy" / "fox" / "standard" / "s0").resolve(), config={}, metrics={}, scene="fox"))
    runs[2].path.mkdir(parents=True)
    f.write_text(json.dumps({"ensemble": {**summ, "runs": ["/q/fox/standard/s0"]}}))
    _attach_uq(runs, [f])
    assert all(r.uq == {} for r in runs)


def test_runs_from_two_kinds_of_machine_get_a_line_saying_so(tmp_path):
    """metrics.json records the machine; a report pooling runs of two kinds says which, and that times between them
    compare machines too. Runs of one kind, or from before machines were recorded, get no such line."""
    def runs(root, cpus):
        for i, (m, cpu) in enumerate(zip(["standard", "niw"] * 2, cpus)):
            p = write_run(root / f"r{i}", "sceneA" if i < 2 else "sceneB", m, 0, 20.0 + i)
            if cpu is not None:
                met = json.loads((p / "metrics.json").read_text())
                met["machine"] = {"cpu": cpu, "cpu_capability": "AVX2" if "Old" in cpu else "AVX512",
                                  "cuda_device": None}
                (p / "metrics.json").write_text(json.dumps(met))

    runs(tmp_path / "mixed", ["Old Xeon", "New Xeon", "Old Xeon", "New Xeon"])
    md, _, js = build(str(tmp_path / "mixed" / "*"), tmp_path / "rep1")
    md = " ".join(md.split())  # the paragraph is wrapped
    assert "trained on 2 kinds of machine (New Xeon (AVX512): 2 runs; Old Xeon (AVX2): 2 runs)" in md
    assert list(js["machine_kinds"].items()) == [("New Xeon (AVX512)", 2), ("Old Xeon (AVX2)", 2)]
    runs(tmp_path / "one", ["New Xeon"] * 4)
    runs(tmp_path / "old", [None] * 4)
    for name in ("one", "old"):
        md, _, js = build(str(tmp_path / name / "*"), tmp_path / f"rep_{name}")
        assert "kinds of machine" not in md and "machine_kinds" not in js

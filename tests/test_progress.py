"""What a training run shows and is called: the progress bar over global steps (step/max_steps, ETA, integer Gaussian
count, loss, last test PSNR), the summary table at the end of a ``-m`` sweep, and method labels from what ran
(run dir names, metrics.json)."""
from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from b3dgs.labels import method_label

ROOT = Path(__file__).resolve().parents[1]
ENV = {**os.environ, "PYTHONPATH": f"{ROOT}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}


@pytest.mark.parametrize("overrides, label", [
    ([], "standard"), (["model=niw"], "niw"), (["model=dpmm"], "dpmm"), (["model=mcmc"], "mcmc"),
    # one scheme: the base is the model option that ran the most of it, whichever model= asked for it
    (["posterior=[niw,dp]"], "niw+dp"), (["posterior=[niw,dp]", "strategy.max_gaussians=5000"], "niw+dp"),
    (["model=dpmm", "posterior=[niw,dp]"], "niw+dp"), (["posterior=[niw,sh]"], "niw+sh"),
    (["model=niw", "posterior=[niw,sh]"], "niw+sh"), (["model=dpmm", "posterior=[niw,dp,noise,opacity,color,sh]"], "dpmm+sh"),
    (["model=mcmc", "strategy=default"], "mcmc+adc"), (["model=niw", "posterior=[]"], "standard"),
    (["model=mcmc", "posterior=[niw]"], "mcmc+niw"),
    (["schedule=dash"], "standard+dash"), (["model=niw", "strategy=mcmc", "schedule=dash"], "niw+mcmc+dash"),
    # a block setting that changes the method, at a value other than the paper's
    (["model=niw", "posterior.niw.count=fisher"], "niw@fisher"), (["model=niw", "posterior.niw.count=paper"], "niw"),
    (["model=dpmm", "posterior.niw.count=fisher3"], "dpmm@fisher3"),
    (["posterior=[niw,sh]", "posterior.niw.count=weight"], "niw@weight+sh"),
    (["model=mcmc", "posterior=[niw]", "posterior.niw.count=fisher"], "mcmc+niw@fisher"),
])
def test_method_label_says_what_ran(overrides, label):
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra
    from omegaconf import open_dict

    from b3dgs.train import CONF_DIR

    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        cfg = compose(config_name="train", overrides=overrides)
    assert method_label(cfg) == label
    with open_dict(cfg):
        del cfg["schedule"]  # run dirs from before schedules existed ran the constant one
    assert method_label(cfg) == label.replace("+dash", "")
    from hydra.core.override_parser.overrides_parser import OverridesParser

    # a label is part of run dir names, passed back as run=DIR: a plain Hydra override value
    assert OverridesParser.create().parse_override(f"run=x_{label}_s0").value() == f"x_{label}_s0"


def test_archived_runs_keep_their_method_labels():
    """Every archived run (bench/results) is labelled today as its metrics.json says it was when it ran, so the report
    groups archived runs as before."""
    from omegaconf import OmegaConf

    from b3dgs.report.collect import upgrade_targets

    runs = [p.parent for p in sorted((ROOT / "bench" / "results").rglob("config.yaml")) if (p.parent / "metrics.json").is_file()]
    if not runs:
        pytest.skip("no archived runs in bench/results")
    got = {str(r): method_label(upgrade_targets(OmegaConf.to_container(OmegaConf.load(r / "config.yaml"), resolve=False)))
           for r in runs}
    want = {str(r): json.loads((r / "metrics.json").read_text())["method"] for r in runs}
    assert got == want


def test_sweep_shows_steps_eta_and_ends_with_a_summary_table(tmp_path):
    """A 3-seed sweep of standard and posterior=[niw,dp] under the study protocol (experiment=study): the bar counts
    global steps with an ETA in every run, run dirs and metrics.json carry the method label, and the sweep's last lines
    are the mean ± SEM table and where it is."""
    cmd = [sys.executable, "-m", "b3dgs.train", "-m", "experiment=study", "seed=0,1,2", "posterior=[],[niw,dp]", "data.max_side=32",
           "+data.n_views=16", "trainer.max_steps=12", "trainer.eval_every=6", "logger=none",
           "trainer.save_renders=false", f"hydra.sweep.dir={tmp_path}"]
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=900, cwd=ROOT, env=ENV)
    assert res.returncode == 0, res.stderr[-3000:]
    bars = [ln for ln in re.split(r"[\r\n]", res.stdout) if ln.startswith("train ")]
    final = [ln for ln in bars if " 12/12 steps" in ln]
    assert len(final) == 6, bars[-3:]  # each run's last line (the study protocol shows its bar too)
    assert re.search(r"\[\d\d:\d\d<00:00 ETA, +[\d.]+ steps/s, gaussians=3,874, loss=0\.\d{4}, test PSNR=\d+\.\d\d dB, "
                     r"SSIM=0\.\d{4}(, LPIPS=\d\.\d{4})?\]", final[-1]), final[-1]
    assert any(re.search(r" [1-9]/12 steps \[\d\d:\d\d<\d\d:\d\d ETA", ln) for ln in bars)  # an ETA while running
    dirs = sorted(d.name for d in tmp_path.iterdir() if d.is_dir())
    assert [d.split("_", 1)[1] for d in dirs] == ["synthetic_standard_s0", "synthetic_niw+dp_s0",
                                                   "synthetic_standard_s1", "synthetic_niw+dp_s1",
                                                   "synthetic_standard_s2", "synthetic_niw+dp_s2"]
    assert json.loads((tmp_path / dirs[1] / "metrics.json").read_text())["method"] == "niw+dp"
    lines = res.stdout.strip().splitlines()
    assert lines[-1] == f"b3dgs-train: 6 runs in {tmp_path}; summary in {tmp_path / 'summary.md'}"
    rows = [ln for ln in lines if ln.startswith("| synthetic |")]
    assert [r.split(" | ")[1] for r in rows] == ["standard", "niw+dp"]
    assert all("| 3 (0, 1, 2) |" in r and re.search(r"\d+\.\d{3} ± \d+\.\d{3}", r) for r in rows)
    assert "| 3 (0, 1, 2) |" in (tmp_path / "summary.md").read_text()
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert [g["key"]["method"] for g in summary["groups"]] == ["standard", "niw+dp"]


def test_a_log_file_gets_whole_bar_lines_not_a_redraw_per_step(tmp_path):
    """stdout is a pipe here, as in a cluster's log file: the bar is printed as newline-ended lines (the first step,
    every line_every_s seconds, the last), never as one carriage-return redraw per step. The last line shows the final
    evaluation (metrics.json's PSNR and SSIM), not the last periodic one (step 30 of 40 here)."""
    cmd = [sys.executable, "-m", "b3dgs.train", "data.max_side=32", "+data.n_views=16", "trainer.max_steps=40",
           "trainer.eval_every=30", "logger=none", "trainer.save_renders=false", f"hydra.run.dir={tmp_path}"]
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=900, cwd=ROOT, env=ENV)
    assert res.returncode == 0, res.stderr[-3000:]
    assert "\r" not in res.stdout
    bars = [ln for ln in res.stdout.splitlines() if ln.startswith("train ")]
    assert 2 <= len(bars) <= 4, bars  # 40 steps take seconds, not 30 s per extra line
    m = json.loads((tmp_path / "metrics.json").read_text())
    periodic = json.loads((tmp_path / "curve.json").read_text())["points"][0]
    assert periodic["step"] == 30 and f"{periodic['psnr']:.2f}" != f"{m['psnr']:.2f}"
    assert " 1/40 steps [" in bars[0] and sum(" 40/40 steps [" in b for b in bars) == 1, bars
    assert bars[-1].endswith(f"test PSNR={m['psnr']:.2f} dB, SSIM={m['ssim']:.4f}"
                             + ("]" if m["lpips"] is None else f", LPIPS={m['lpips']:.4f}]")), bars


def test_study_and_eval_bars_print_whole_lines_in_a_log_file():
    """b3dgs.progress: the eval / render / compression bars print whole lines when their stream is not a terminal
    (a cluster log): no carriage-return redraws, the last state once, also for a bar a terminal clears (leave=False:
    eval's bars, which stopped at 0/N in a pipe; issue 52). On a terminal it is tqdm's own bar."""
    import io

    from tqdm.std import tqdm as std_tqdm

    from b3dgs.progress import progress

    buf = io.StringIO()
    for _ in progress(range(5), desc="uq native", file=buf, line_every_s=0.0):
        pass
    lines = buf.getvalue().splitlines()
    assert "\r" not in buf.getvalue() and buf.getvalue().endswith("\n")
    assert lines[0].startswith("uq native:   0%") and lines[-1].startswith("uq native: 100%")
    assert sum(ln.startswith("uq native: 100%") for ln in lines) == 1 and len(lines) == 6
    buf = io.StringIO()
    for _ in progress(range(1000), desc="render", file=buf, leave=False):  # 30 s apart: the first and the last line
        pass
    lines = buf.getvalue().splitlines()
    assert len(lines) == 2 and lines[0].startswith("render:   0%") and lines[1].startswith("render: 100%"), lines

    class Tty(io.StringIO):
        def isatty(self):
            return True

    bar = progress(range(3), file=Tty())
    assert type(bar) is std_tqdm
    bar.close()

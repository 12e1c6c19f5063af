"""Issue 52 §6, what a newcomer meets first: every command's ``--help`` (its purpose, three examples, only the groups
it reads), Hydra's sweep hint kept and ``-m`` accepted after the overrides, one line before the first C++ build,
a caption font that has σ, ``setup.sh`` saying what it does, bars that finish in a pipe, and ``experiment=quality``."""
from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
ENV = {**os.environ, "PYTHONPATH": f"{ROOT}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}

# command: (how to start it, the config groups its --help lists)
TRAIN_GROUPS = {"data", "experiment", "logger", "model", "posterior", "renderer", "scene", "schedule", "strategy",
                "trainer"}
COMMANDS = {
    "b3dgs-train": (["b3dgs.train"], TRAIN_GROUPS),
    "b3dgs-eval": (["b3dgs.eval"], {"uq"}),
    "b3dgs-render": (["b3dgs.render_cli"], set()),
    "b3dgs-export": (["b3dgs.export"], set()),
    "b3dgs-view": (["b3dgs.viewer.app"], set()),
    "b3dgs-report": (["b3dgs.report.app"], set()),
    "b3dgs-study active": (["b3dgs.study.cli", "active"], {"data", "experiment", "renderer", "scene", "strategy",
                                                            "trainer"}),
    "b3dgs-study compress": (["b3dgs.study.cli", "compress"], set()),
    "b3dgs-process": (["b3dgs.process"], set()),
}


def _help(args: list[str], cwd: Path) -> str:
    res = subprocess.run([sys.executable, "-m", *args, "--help"], capture_output=True, text=True, timeout=120, cwd=cwd,
                         env=ENV)
    assert res.returncode == 0, res.stderr[-2000:]
    return res.stdout


@pytest.mark.parametrize("prog", list(COMMANDS))
def test_help_gives_purpose_three_examples_and_only_the_groups_read(prog, tmp_path):
    """``--help`` opens with ``<prog>: <purpose>``, then ``Examples:`` and three example lines of that command; the
    config groups it lists are exactly those it reads (none for a command that reads none: no Hydra group dump)."""
    args, groups = COMMANDS[prog]
    out = _help(args, tmp_path)
    lines = out.splitlines()
    assert lines[0].startswith(f"{prog}: ") and len(lines[0]) > len(prog) + 20, lines[:2]
    assert lines[1] == "Examples:" and all(ln.startswith(f"  {prog} ") for ln in lines[2:5]), lines[:6]
    assert not lines[5].startswith(f"  {prog} "), lines[:6]  # three, not more
    section = out.partition("== Configuration groups ==")[2].partition("== Config ==")[0]
    listed = {ln.split(":")[0] for ln in section.splitlines() if re.match(r"^[\w/]+: \w", ln)}
    assert listed == groups, (prog, listed ^ groups)
    assert ("== Configuration groups ==" in out) == bool(groups)
    assert "$" not in out.replace("${", "") and "b3dgs.help" not in out  # the template resolved, nothing left
    assert not any(tmp_path.iterdir())


def test_study_help_without_a_study_names_them_with_examples(tmp_path):
    """``b3dgs-study --help`` (no study yet): exit 0, its purpose, the studies and three examples."""
    lines = _help(["b3dgs.study.cli"], tmp_path).splitlines()
    assert lines[0].startswith("b3dgs-study: ") and "Examples:" in lines
    ex = lines[lines.index("Examples:") + 1:]
    assert len(ex) == 3 and all(ln.startswith("  b3dgs-study ") for ln in ex), ex
    assert {"active", "compress"} <= {ln.split()[0] for ln in lines[2:4]}, lines


def test_a_sweep_without_m_keeps_hydras_hint(tmp_path):
    """``seed=0,1`` without ``-m``: one line whose fix gives the command again with -m first, and the list and string
    readings (it said "correct the config override named above", losing Hydra's hint)."""
    res = subprocess.run([sys.executable, "-m", "b3dgs.train", "seed=0,1", f"hydra.run.dir={tmp_path / 'run'}"],
                         capture_output=True, text=True, timeout=120, cwd=tmp_path, env=ENV)
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert res.returncode == 2 and len(lines) == 1, res.stderr[-2000:]
    assert f"b3dgs-train -m seed=0,1 hydra.run.dir={tmp_path / 'run'}" in lines[0], lines[0]
    assert "seed=[0,1]" in lines[0] and "seed='0,1'" in lines[0], lines[0]
    assert not (tmp_path / "run").exists()


def test_m_after_the_overrides_is_moved_first(tmp_path):
    """``run=a,b -m`` (Hydra's parser answered it with its usage text): the sweep runs, each job's error one line."""
    from b3dgs.errors import multirun_first

    assert multirun_first(["seed=0,1", "-m", "x=1"]) == ["-m", "seed=0,1", "x=1"]
    argv = ["-m", "seed=0,1"]
    assert multirun_first(argv) is argv and multirun_first(["--cfg", "job"]) == ["--cfg", "job"]
    res = subprocess.run([sys.executable, "-m", "b3dgs.export", "run=a,b", "-m"], capture_output=True, text=True,
                         timeout=180, cwd=tmp_path, env=ENV)
    assert "usage:" not in res.stderr and "unrecognized arguments" not in res.stderr, res.stderr[-2000:]
    assert "Launching 2 jobs" in res.stdout + res.stderr, res.stdout[-2000:]
    errors = [ln for ln in res.stderr.splitlines() if ln.startswith("b3dgs-export: error: job ")]
    assert res.returncode == 2 and len(errors) == 2, res.stderr[-2000:]


def test_first_build_says_so_once_and_a_cached_load_says_nothing(tmp_path, monkeypatch, capsys):
    """The C++ kernels' first build prints one stderr line with its expected time and cache folder before compiling;
    a later load of the built module prints nothing (the real build, ~50 s, is faked)."""
    from torch.utils import cpp_extension

    from b3dgs.render import _ext

    monkeypatch.setenv("B3DGS_CACHE", str(tmp_path))
    built = []

    def fake_load(name, build_directory, **_):
        print(capsys.readouterr().err, end="", file=sys.stderr)  # what was said before the build started
        built.append(name)
        (Path(build_directory) / f"{name}.so").write_bytes(b"")
        return "module"

    monkeypatch.setattr(cpp_extension, "load", fake_load)
    monkeypatch.setattr(_ext, "_import_built", lambda path, name: "cached module")
    monkeypatch.setattr(_ext, "_module", None)
    assert _ext.load_extension() == "module" and len(built) == 1
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1 and err[0].startswith("b3dgs: compiling the C++ CPU kernels once (about 1 minute"), err
    assert str(tmp_path) in err[0]
    monkeypatch.setattr(_ext, "_module", None)  # a new process: the .so is there
    assert _ext.load_extension() == "cached module" and len(built) == 1
    assert capsys.readouterr().err == ""


def test_caption_font_draws_sigma_not_the_missing_glyph_box():
    """The render captions' σ ("right: native σ") is drawn as σ: its pixels differ from those of a character no font
    has (the missing-glyph box PIL's built-in font drew for σ)."""
    from b3dgs.render_cli import _caption

    def ink(text):
        img = _caption(28, 40, text).min(axis=2)
        return img < 128

    sigma, missing = ink("σ"), ink("\U0010fffd")
    assert sigma.sum() > 5 and not np.array_equal(sigma, missing)


def test_setup_script_parses_and_says_what_it_does():
    """scripts/setup.sh is valid bash, announces its five steps with their expected times, and suggests a virtual
    environment when none is active (it printed nothing for 95 s)."""
    script = ROOT / "scripts" / "setup.sh"
    assert subprocess.run(["bash", "-n", str(script)], capture_output=True).returncode == 0
    text = script.read_text()
    steps = re.findall(r'say "(\d)/5 ([^"]*)"', text)
    assert sorted({n for n, _ in steps}) == ["1", "2", "3", "4", "5"], steps
    timed = [msg for _, msg in steps if re.search(r"\(about \d+ s", msg)]
    assert len(timed) >= 5, steps
    assert "python -m venv .venv" in text and "VIRTUAL_ENV" in text


@pytest.mark.slow  # a training and an eval in subprocesses (~80 s on 2 busy cores); tests/test_progress.py checks the
# bar itself in a log stream without them
def test_eval_bars_finish_when_piped(tmp_path):
    """b3dgs-eval with its output in a pipe: each regime's bar ends on its final N/N state (it stopped at 0/N)."""
    run = tmp_path / "run"
    tiny = ["data=synthetic", "+data.n_views=16", "data.max_side=32", "trainer.max_steps=2", "trainer.eval_every=100",
            "trainer.enable_progress_bar=false", "logger=none", "threads=1"]
    res = subprocess.run([sys.executable, "-m", "b3dgs.train", *tiny, f"hydra.run.dir={run}"], capture_output=True,
                         text=True, timeout=300, cwd=tmp_path, env=ENV)
    assert res.returncode == 0, res.stderr[-2000:]
    res = subprocess.run([sys.executable, "-m", "b3dgs.eval", f"run={run}", "uq=[constant]", "max_views=2", "panels=0",
                          "threads=1"] , capture_output=True, text=True, timeout=300,
                         cwd=tmp_path, env=ENV)
    assert res.returncode == 0, res.stderr[-2000:]
    bars = [ln for ln in (res.stdout + res.stderr).splitlines() if ln.startswith("uq constant:")]
    assert bars and "2/2" in bars[-1] and "100%" in bars[-1], res.stderr[-2000:]


def test_experiment_quality_is_the_paper_protocol_at_1600_px():
    """experiment=quality: 1600 px, 30k steps, and the official densification of experiment=paper for the chosen
    strategy (conf/experiment/strategy/quality_<strategy>.yaml reuse paper_<strategy>.yaml)."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    from b3dgs import conf_dir

    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=conf_dir(), version_base="1.3"):
        plain = compose(config_name="train", overrides=["data=colmap", "data.path=/x"])
        paper = compose(config_name="train", overrides=["data=colmap", "data.path=/x", "experiment=paper"])
        quality = compose(config_name="train", overrides=["data=colmap", "data.path=/x", "experiment=quality"])
        mcmc = [compose(config_name="train", overrides=["data=colmap", "data.path=/x", f"experiment={e}", "model=mcmc"])
                for e in ("paper", "quality")]
    GlobalHydra.instance().clear()
    assert quality.data.max_side == 1600 and quality.trainer.max_steps == 30000
    assert quality.strategy == paper.strategy and quality.strategy != plain.strategy
    assert quality.strategy.refine_stop == 15000 and quality.strategy.max_gaussians is None
    assert mcmc[1].strategy == mcmc[0].strategy and mcmc[1].strategy.refine_stop == 25000
    assert quality.model == paper.model and quality.data.images_dir == paper.data.images_dir

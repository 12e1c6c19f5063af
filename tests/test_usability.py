"""Small things a user meets: "did you mean" for a misspelt key (at any depth) or option, the warning before a long
run on the pure-PyTorch renderer, ``renderer=auto -> ...`` said once per process, and ``b3dgs-train --help`` listing
only the groups training reads."""
from __future__ import annotations

import logging
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
ENV = {**os.environ, "PYTHONPATH": f"{ROOT}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}


@pytest.mark.parametrize("arg, want", [("trainer.max_stpes=10", "max_steps"), ("trainer.max_step=10", "max_steps"),
                                       ("data.max_sid=10", "max_side"), ("sed=1", "seed")])
def test_misspelt_key_suggests_the_right_one(tmp_path, arg, want):
    res = subprocess.run([sys.executable, "-m", "b3dgs.train", arg], capture_output=True, text=True, timeout=120,
                         cwd=tmp_path, env=ENV)
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert res.returncode == 2 and len(lines) == 1, res.stderr[-2000:]
    assert f"unknown config key {arg.split('=')[0]}; did you mean {want}? (fix: " in lines[0], lines[0]
    assert not any(tmp_path.iterdir())


@pytest.mark.parametrize("config, key, want", [
    ("train", "modle", "model"), ("train", "sede", "seed"), ("train", "traner.max_steps", "trainer.max_steps"),
    ("train", "trainr.max_stps", "trainer.max_steps"), ("train", "trainer.max_stpes", "max_steps"),
    ("train", "posterior.niww.kappa0", "posterior.niw.kappa0"), ("train", "posterior.niw.kapa0", "kappa0"),
    ("train", "strategy.refine_stat", "refine_start"), ("train", "renderer.nearr", "near"),
    ("study", "acquisiton.score_max_sid", "acquisition.score_max_side"), ("eval", "uq.native.samplez", "samples"),
    ("view", "mdoe", "mode"), ("train", "trainer.max_steps", None), ("train", "zzzz.qqq", None)])
def test_did_you_mean_at_any_depth(monkeypatch, config, key, want):
    """Each component of a misspelt key is matched against the keys b3dgs's configs give its node, the top level
    against the running app's own config (``modle`` -> model for b3dgs-train, not b3dgs-view's ``mode``)."""
    from b3dgs import errors

    monkeypatch.setattr(errors, "_APP_CONFIG", config)
    assert errors._key_suggestion(key) == (f"; did you mean {want}?" if want else "")


def test_misspelt_option_and_nested_key_in_one_line(tmp_path):
    for args, want in ((["scene=foxx"], "Could not find 'scene/foxx'; did you mean fox? (fix: pick an existing option"),
                       (["model=niw", "posterior.niww.kappa0=1"],
                        "unknown config key posterior.niww.kappa0; did you mean posterior.niw.kappa0? (fix: ")):
        res = subprocess.run([sys.executable, "-m", "b3dgs.train", *args], capture_output=True, text=True, timeout=120,
                             cwd=tmp_path, env=ENV)
        lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
        assert res.returncode == 2 and len(lines) == 1 and want in lines[0], res.stderr[-2000:]


def test_an_override_with_a_space_or_non_ascii_letters_is_told_to_quote_it(tmp_path):
    """Hydra's grammar cannot read ``data.path=/data/café shots``: the fix shows the quoted form (issue 46 §10)."""
    res = subprocess.run([sys.executable, "-m", "b3dgs.train", "data.path=/data/café shots"], capture_output=True,
                         text=True, timeout=120, cwd=tmp_path, env=ENV)
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert res.returncode == 2 and len(lines) == 1, res.stderr[-2000:]
    want = "(fix: quote the value: \"data.path='/data/café shots'\""
    assert want in lines[0], lines[0]
    from b3dgs.errors import _parse_fix

    assert _parse_fix("trainer.max_steps=1x") == "write overrides as key=value, group=option or +key=value"


def _train_cfg(*overrides):
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    from b3dgs.train import CONF_DIR

    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        return compose(config_name="train", overrides=list(overrides))


def test_torch_renderer_warns_before_a_long_cpu_run(caplog):
    from b3dgs.lifecycle import warn_slow_renderer

    with caplog.at_level(logging.WARNING, logger="b3dgs.train"):
        msg = warn_slow_renderer(_train_cfg("renderer=torch", "renderer.device_name=cpu"))
    assert msg and "renderer=torch trains at about 1 s per step" in msg and "about 50 min" in msg
    assert "renderer=cpu" in msg and msg in caplog.text
    assert warn_slow_renderer(_train_cfg("renderer=torch", "renderer.device_name=cpu", "trainer.max_steps=300")) is None
    assert warn_slow_renderer(_train_cfg("renderer=cpu")) is None


def test_auto_renderer_is_announced_once_per_process(caplog, monkeypatch):
    from b3dgs.render import renderers

    monkeypatch.setattr(renderers, "_SAID", set())  # as in a fresh process
    with caplog.at_level(logging.INFO, logger="b3dgs.render.renderers"):
        for _ in range(3):
            renderers.auto_renderer()
    assert sum("renderer=auto ->" in r.getMessage() for r in caplog.records) == 1


def test_a_scene_file_without_the_global_header_is_refused_not_ignored(tmp_path):
    """conf/scene/mine.yaml without '# @package _global_': its keys land under scene.*, where nothing reads them;
    b3dgs-train used to train the synthetic scene and exit 0 (issue 46 §3). Now one line naming the file and the fix."""
    (tmp_path / "conf" / "scene").mkdir(parents=True)
    # the plain file, and the same with a defaults list (override /data: colmap), which said "unknown config key"
    for body in ("data:\n  path: /nope\n  max_side: 64\n",
                 "defaults:\n  - override /data: colmap\ndata:\n  path: /nope\n"):
        (tmp_path / "conf" / "scene" / "mine.yaml").write_text(body)
        res = subprocess.run([sys.executable, "-m", "b3dgs.train", "scene=mine",
                              f"hydra.searchpath=[file://{tmp_path / 'conf'}]", f"hydra.run.dir={tmp_path / 'run'}"],
                             capture_output=True, text=True, timeout=120, cwd=tmp_path, env=ENV)
        lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
        assert res.returncode == 2 and len(lines) == 1, res.stderr[-2000:]
        assert "scene/mine.yaml is not a global config file" in lines[0] and "@package _global_" in lines[0], lines[0]
    assert not (tmp_path / "run").exists()
    # the same keys given as a +scene.* override: refused too (it trained the synthetic scene; issue 46 §4)
    res = subprocess.run([sys.executable, "-m", "b3dgs.train", "+scene.data.path=/nope",
                          f"hydra.run.dir={tmp_path / 'run'}"], capture_output=True, text=True, timeout=120,
                         cwd=tmp_path, env=ENV)
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert res.returncode == 2 and len(lines) == 1 and "scene.{data} reaches nothing" in lines[0], res.stderr[-2000:]


def test_train_help_lists_only_the_groups_training_reads(tmp_path):
    """uq, acquisition (and acquisition/batch) and pruning are b3dgs-eval's and b3dgs-study's groups: b3dgs-train's
    --help leaves them out and lists the others with their options; the config follows as Hydra prints it."""
    res = subprocess.run([sys.executable, "-m", "b3dgs.train", "--help"], capture_output=True, text=True, timeout=120,
                         cwd=tmp_path, env=ENV)
    assert res.returncode == 0, res.stderr[-2000:]
    head, _, rest = res.stdout.partition("== Config ==")
    head = head.partition("== Configuration groups ==")[2]  # after the purpose line and the examples
    groups = {ln.split(":")[0] for ln in head.splitlines() if ": " in ln and not ln.startswith(" ")}
    assert {"data", "model", "posterior", "renderer", "scene", "schedule", "strategy", "trainer", "logger",
            "experiment"} <= groups, head
    assert not groups & {"uq", "acquisition", "acquisition/batch", "pruning", "hydra", "experiment/strategy"}, head
    # the study-only preset is left out of its group's line, the other presets stay
    experiments = next(ln for ln in head.splitlines() if ln.startswith("experiment: ")).split(": ")[1].split(", ")
    assert "archived_posterior" not in experiments and {"paper", "study", "smoke"} <= set(experiments), head
    assert "model: dpmm, mcmc, niw, standard" in head and "\nstrategy:\n  _target_: " in rest and "b3dgs.help" not in res.stdout
    assert not any(tmp_path.iterdir())


def test_train_refuses_a_study_preset_by_name(tmp_path):
    """experiment=archived_posterior sets family_posterior, which only b3dgs-study reads: b3dgs-train names the
    option and the command it belongs to, instead of "unknown config key family_posterior"."""
    res = subprocess.run([sys.executable, "-m", "b3dgs.train", "experiment=archived_posterior",
                          f"hydra.run.dir={tmp_path / 'run'}"], capture_output=True, text=True, timeout=120,
                         cwd=tmp_path, env=ENV)
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert res.returncode == 2 and len(lines) == 1, res.stderr[-2000:]
    assert "experiment=archived_posterior sets family_posterior" in lines[0] and "b3dgs-study" in lines[0], lines[0]
    assert not (tmp_path / "run").exists()


def test_help_groups_lists_the_apps_groups_less_hidden_groups_and_options(monkeypatch):
    """help_groups(APP, ...): the groups APP's defaults list names; NAME hides a group, NAME=OPTION one option."""
    from b3dgs import confs

    listing = "acquisition: a, b\nacquisition/batch: x\nexperiment: paper, preset, study\nexperiment/strategy: s\n" \
              "hydra/launcher: basic\nmodel: m\n"

    def fake_format(keep):
        return "".join(ln + "\n" for ln in listing.splitlines() if keep(ln.split(":")[0]))

    monkeypatch.setattr(confs, "_format_groups", fake_format)
    monkeypatch.setattr(confs, "app_groups", lambda config: {"experiment", "experiment/strategy", "model"})
    assert confs.help_groups("train", "experiment/strategy", "experiment=preset") == \
        "experiment: paper, study\nmodel: m\n"
    assert confs.help_groups("train") == "experiment: paper, preset, study\nexperiment/strategy: s\nmodel: m\n"
    monkeypatch.undo()
    assert confs.app_groups("eval") == {"uq"} and confs.app_groups("export") == set()
    assert {"data", "model", "experiment", "experiment/strategy"} <= confs.app_groups("train")
    assert not confs.app_groups("train") & {"uq", "acquisition", "pruning", "hydra", "_self_"}


def test_eval_help_lists_only_the_uq_group(tmp_path):
    """b3dgs-eval reads one group, uq (the run's model, data and renderer come from its checkpoint): its --help lists
    only that group, with its options."""
    res = subprocess.run([sys.executable, "-m", "b3dgs.eval", "--help"], capture_output=True, text=True, timeout=120,
                         cwd=tmp_path, env=ENV)
    assert res.returncode == 0, res.stderr[-2000:]
    head, _, rest = res.stdout.partition("== Config ==")
    head = head.partition("== Configuration groups ==")[2]  # after the purpose line and the examples
    groups = {ln.split(":")[0] for ln in head.splitlines() if ": " in ln and not ln.startswith(" ")}
    assert groups == {"uq"}, head
    assert "native_plus_sh" in head and "\nrun: ???" in rest and "b3dgs.help" not in res.stdout
    assert not any(tmp_path.iterdir())

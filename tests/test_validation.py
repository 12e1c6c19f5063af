"""Config validation before the scene loads, one-line errors, and the quiet-log filters."""
from __future__ import annotations

import logging
import subprocess
import sys
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra

from b3dgs.errors import B3dgsError, _HarmlessInfoFilter, format_error
from b3dgs.train import CONF_DIR
from b3dgs.validation import check_checkpoint, validate_config

REPO = Path(__file__).resolve().parents[1]


def cfg_of(overrides, config_name="train"):
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        return compose(config_name=config_name, overrides=overrides, return_hydra_config=True)


def options(group):
    return sorted(p.stem for p in (Path(CONF_DIR) / group).glob("*.yaml"))


@pytest.mark.parametrize("over", [[f"model={m}"] for m in options("model")] + [[f"renderer={r}"] for r in options("renderer")]
                         + [["trainer=quick", "+data.n_views=16", "data.test_every=0"]])
def test_shipped_configs_pass(over):
    validate_config(cfg_of(over))


BAD = [  # (overrides, text the one-line message must contain)
    (["+trainer.max_stpes=50"], "did you mean max_steps"),
    (["+strategy.refine_evry=5"], "strategy.refine_evry"),
    (["+data.nviews=16"], "did you mean n_views"),
    (["+model.lr_mean=1"], "model.lr_mean"),
    (["+foo=1"], "unknown config key foo"),
    (["posterior=[niw,niw]"], "niw more than once"),
    (["model.background=[0,0]"], "model.background"),
    (["data=colmap"], "data.path is not set"),
    (["model.init_opacity=1.0"], "model.init_opacity"),
    (["model.sh_degree=4"], "model.sh_degree"),
    (["model.lambda_dssim=2"], "model.lambda_dssim"),
    (["model.lr_means=-1"], "model.lr_means"),
    (["trainer.max_steps=0"], "trainer.max_steps"),
    (["trainer.max_steps=abc"], "an integer"),
    (["trainer.enable_progress_bar=maybe"], "true or false"),
    (["strategy.refine_every=0"], "strategy.refine_every"),
    (["model=niw", "posterior.niw.kappa0=-1"], "posterior.niw.kappa0"),
    (["model=niw", "+model.posterior.niw.kappa0=1"], "model.posterior is not read"),  # trained with 0.01 (issue 46 §4)
    (["+model.max_steps=10"], "pass trainer.max_steps=N instead of model.max_steps"),
    (["+posterior.bogus.x=1"], "posterior.bogus"),
    (["seed=abc"], "seed"),
    (["seed=-1"], "seed=-1 is invalid: it must be an integer in [0, 2^32)"),
    ([f"seed={2**32}"], "seed=4294967296 is invalid"),
    (["model.init_scale=0"], "model.init_scale=0 is invalid: it must be a positive number"),
    (["model.init_scale=-1"], "model.init_scale=-1 is invalid"),
    (["strategy.percent_dense=-1"], "strategy.percent_dense=-1 is invalid"),
    (["threads=0"], "threads"),
    (["resume=/nonexistent/last.ckpt"], "no such checkpoint"),
]


@pytest.mark.parametrize("over,text", BAD, ids=[" ".join(o) for o, _ in BAD])
def test_bad_values_refused_with_a_fix(over, text):
    with pytest.raises(B3dgsError) as ei:
        validate_config(cfg_of(over))
    msg = str(ei.value)
    assert text in msg
    assert "(fix: " in msg and "\n" not in msg


BUILT = [  # (overrides, node, text): values the renderer or the data module refuses itself (its validate) when built
    (["data.max_side=0"], "data", "data.max_side=0 is invalid: it must be an integer >= 1 or null"),
    (["data.max_side=-3"], "data", "data.max_side=-3 is invalid"),
    (["data.background=[2,-1,0.5]"], "data", "data.background=[2,-1,0.5] is invalid"),
    (["data.test_every=-1"], "data", "data.test_every=-1 is invalid"),
    (["data.train_indices=[1,1]"], "data", "data.train_indices=[1,1] is invalid"),
    (["data.calib_every=1"], "data", "data.calib_every=1 is invalid"),
    (["data=transforms", "data.path=/nonexistent/scene"], "data", "data.path=/nonexistent/scene does not exist"),
    (["+data.n_views=0"], "data", "data.n_views=0 is invalid: it must be an integer >= 1"),  # the loader's own
    (["+data.resolution=-2"], "data", "data.resolution=-2 is invalid"),
    (["renderer.near=0"], "renderer", "renderer.near=0 is invalid: it must be a positive number"),
    (["renderer.near=0"], "data", "data.near_plane=0 is invalid"),  # ${renderer.near}: its fix names renderer.near
    (["renderer=torch", "renderer.device_name=tpu"], "renderer", "renderer.device_name=tpu is not a device"),
    (["renderer=gsplat", "renderer.tile_size=0"], "renderer", "renderer.tile_size=0 is invalid"),
    (["renderer=gsplat", "renderer.eps2d=-1"], "renderer", "renderer.eps2d=-1 is invalid"),
]


@pytest.mark.parametrize("over,node,text", BUILT, ids=[f"{' '.join(o)} {n}" for o, n, _ in BUILT])
def test_renderer_and_data_refuse_their_own_bad_values_when_built(over, node, text):
    """Keys and types pass validate_config; the component's validate refuses the value when Hydra builds it, with
    the line b3dgs-train prints (Hydra's InstantiationException wraps it; format_error reads through)."""
    from hydra.utils import instantiate

    cfg = cfg_of(over)
    validate_config(cfg)
    with pytest.raises(Exception) as ei:
        instantiate(cfg[node])
    msg = format_error(ei.value)
    assert msg is not None and text in msg and "(fix: " in msg and "\n" not in msg, msg
    if node == "data" and "near_plane" in text:
        assert "renderer.near" in msg


@pytest.mark.parametrize("over,text", [(["+data.n_views=0"], "data.n_views=0 is invalid"),
                                       (["renderer=torch", "renderer.device_name=tpu"],
                                        "renderer.device_name=tpu is not a device")])
def test_cli_refuses_a_bad_renderer_or_data_value_in_one_line(tmp_path, over, text):
    res = _cli(*over, "+data.n_views=4", "data.max_side=16", "trainer.max_steps=2", "logger=none",
               f"hydra.run.dir={tmp_path}/run") if "n_views=0" not in over[0] else \
        _cli(*over, "data.max_side=16", "trainer.max_steps=2", "logger=none", f"hydra.run.dir={tmp_path}/run")
    assert res.returncode == 2, res.stderr[-2000:]
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert lines == [lines[0]] and lines[0].startswith(f"b3dgs-train: error: {text}") and "(fix: " in lines[0], lines
    assert not (tmp_path / "run").exists()  # a refused run leaves nothing


def test_eval_checks(tmp_path):
    with pytest.raises(B3dgsError, match="uq.samples=1"):
        validate_config(cfg_of([f"run={tmp_path}", "uq.samples=1"], "eval"), app="eval")
    with pytest.raises(B3dgsError, match="not a b3dgs run dir"):
        validate_config(cfg_of([f"run={tmp_path}"], "eval"), app="eval")
    (tmp_path / "config.yaml").write_text("seed: 0\n")
    with pytest.raises(B3dgsError, match="last.ckpt does not exist"):
        validate_config(cfg_of([f"run={tmp_path}"], "eval"), app="eval")
    with pytest.raises(B3dgsError, match="needs >= 2 run dirs"):
        validate_config(cfg_of([f"run=[{tmp_path}]", "uq=[ensemble]"], "eval"), app="eval")


def test_damaged_checkpoint_is_named(tmp_path):
    import torch

    good = tmp_path / "good.ckpt"
    torch.save({"state_dict": {"x": torch.zeros(1000)}}, good)
    check_checkpoint(good, "fix")
    bad = tmp_path / "bad.ckpt"
    bad.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    with pytest.raises(B3dgsError, match=r"bad\.ckpt is damaged"):
        check_checkpoint(bad, "fix")
    with pytest.raises(B3dgsError, match="damaged"):
        validate_config(cfg_of([f"resume={bad}"]))


def test_format_error_known_and_unknown():
    assert format_error(B3dgsError("p", "f")) == "p (fix: f)"
    assert format_error(FileNotFoundError("no such file x")).startswith("no such file x (fix:")
    assert format_error(RuntimeError("boom")) is None  # a bug keeps its traceback
    assert format_error(ValueError("raised by a library")) is None  # not raised by b3dgs's own code


def test_harmless_lightning_info_dropped():
    f = _HarmlessInfoFilter()
    rec = lambda m: logging.LogRecord("lightning.pytorch.utilities.rank_zero", logging.INFO, "", 0, m, None, None)  # noqa: E731
    assert not f.filter(rec("💡 Tip: For seamless cloud logging ... litlogger"))
    assert not f.filter(rec("GPU available: False, used: False"))
    assert f.filter(rec("Restoring states from the checkpoint path at x.ckpt"))


def test_quiet_log_leaves_lightning_unimported_and_its_lines_printed_once():
    """quiet_known_noise before Lightning is imported (a command that refuses before it trains): it does not import
    Lightning; when Lightning is imported later its console handler is removed then, so a Lightning line reaches
    stderr once (through the root handler), not twice."""
    code = ("import logging, sys\n"
            "logging.basicConfig(format='root: %(message)s')\n"
            "from b3dgs.errors import quiet_known_noise\n"
            "quiet_known_noise()\n"
            "assert 'lightning' not in sys.modules\n"
            "import lightning\n"
            "logging.getLogger('lightning.pytorch.core').warning('a lightning line')\n")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, cwd=REPO)
    assert res.returncode == 0, res.stderr[-2000:]
    assert [ln for ln in res.stderr.splitlines() if "a lightning line" in ln] == ["root: a lightning line"], res.stderr


def _cli(*args):
    import os

    env = {k: v for k, v in os.environ.items() if k != "HYDRA_FULL_ERROR"}
    return subprocess.run([sys.executable, "-m", "b3dgs.train", *args], capture_output=True, text=True, timeout=300,
                          cwd=REPO, env=env)


def test_cli_one_line_error_and_debug(tmp_path):
    res = _cli("+trainer.max_stpes=50", f"hydra.run.dir={tmp_path}/a")
    assert res.returncode == 2, res.stderr[-2000:]
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert lines == [lines[0]] and lines[0].startswith("b3dgs-train: error: unknown config key trainer.max_stpes")
    assert "(fix: " in lines[0]
    res = _cli("trainer=nope", f"hydra.run.dir={tmp_path}/b")  # Hydra's composition error, one line too
    assert res.returncode == 2 and res.stderr.strip().count("\n") == 0, res.stderr
    assert "trainer/nope" in res.stderr
    res = _cli("data.max_side=0", "b3dgs.debug=true", f"hydra.run.dir={tmp_path}/c")
    assert res.returncode != 0 and "Traceback" in res.stderr and "data.max_side=0" in res.stderr


def test_io_and_memory_errors_are_one_line(monkeypatch):
    import errno

    from b3dgs import errors

    full = OSError(errno.ENOSPC, "No space left on device", "/runs/a/point_cloud.ply")
    monkeypatch.setattr(errors, "_APP_CONFIG", None)  # no app: both keys
    assert format_error(full) == ("cannot write /runs/a/point_cloud.ply: no space left on the device (fix: free disk "
                                  "space, or pass hydra.run.dir / out= on another disk)")
    for app, key in (("train", "hydra.run.dir=DIR"), ("render", "out=DIR"), ("suggest", "out=DIR")):  # the app's own
        monkeypatch.setattr(errors, "_APP_CONFIG", app)
        assert format_error(OSError(errno.EROFS, "Read-only file system", "/x")).endswith(
            f"(fix: pass {key} to a writable folder)"), app
    monkeypatch.setattr(errors, "_APP_CONFIG", None)
    assert "read-only" in format_error(OSError(errno.EROFS, "Read-only file system", "/x"))
    assert format_error(MemoryError()).startswith("ran out of memory (fix: lower data.max_side or data.resolution")
    assert "disk is full" in format_error(RuntimeError("PytorchStreamWriter failed writing file data/0: file write failed"))
    assert format_error(OSError(errno.ECONNRESET, "reset")) is None  # not a known problem: a traceback


def test_plus_key_given_twice_or_existing(monkeypatch):
    from hydra.errors import ConfigCompositionException

    for argv, want in ((["+data.n_views=8", "+data.n_views=9"], "data.n_views is given 2 times (+data.n_views=8 "
                        "+data.n_views=9) (fix: pass it once)"),
                       (["+seed=3"], "+seed adds a key the config already has (fix: pass seed=VALUE without the +)")):
        monkeypatch.setattr(sys, "argv", ["b3dgs-train", *argv])
        with pytest.raises(ConfigCompositionException) as ei:
            cfg_of(argv)
        assert format_error(ei.value) == want


def test_eval_refuses_one_run_twice_and_an_out_file(tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.yaml").write_text("seed: 0\n")
    with pytest.raises(B3dgsError, match=r"names the run .*run twice .*fix: pass each run dir once"):
        validate_config(cfg_of([f"run=[{run},{tmp_path}/./run]", "uq=[ensemble]"], "eval"), app="eval")
    (tmp_path / "f").write_text("x")
    with pytest.raises(B3dgsError, match=r"out=.*f is a file"):
        validate_config(cfg_of([f"run={run}", f"out={tmp_path / 'f'}"], "eval"), app="eval")


def test_damaged_run_files_are_one_line(tmp_path):
    from b3dgs.runs import load_run

    (tmp_path / "checkpoints").mkdir()
    (tmp_path / "checkpoints" / "last.ckpt").write_bytes(b"x")
    (tmp_path / "config.yaml").write_text("data: [unclosed\n")
    with pytest.raises(ValueError, match=r"config.yaml is damaged or not a b3dgs run config .*fix: train the run again"):
        load_run(tmp_path)
    # a run of an older version: data.path relative to where it was trained
    (tmp_path / "config.yaml").write_text("data: {path: scenes/fox}\nmodel: {name: standard}\n")
    with pytest.raises(ValueError, match=r"data.path=scenes/fox, relative to the folder the run was trained in"):
        load_run(tmp_path)


def test_config_stores_data_path_absolute(tmp_path, monkeypatch):
    from omegaconf import OmegaConf

    from b3dgs.rundir import save_config

    monkeypatch.chdir(tmp_path)
    cfg = cfg_of(["data=transforms", "data.path=scenes/fox", f"trainer.default_root_dir={tmp_path}"])
    save_config(cfg, tmp_path / "config.yaml")
    assert OmegaConf.load(tmp_path / "config.yaml").data.path == str(tmp_path / "scenes" / "fox")


def test_a_value_out_of_range_names_the_default_to_pass():
    """The fix of a core value out of range names its default, read from the config file that declares it."""
    from b3dgs.schema import apply_rules

    for values, fix in (({"trainer.max_steps": 0}, "pass trainer.max_steps=3000 (the default of conf/trainer/default.yaml)"),
                        ({"model.sh_degree": 7}, "pass model.sh_degree=3 (the default of conf/model/standard.yaml)"),
                        ({"trainer.curve_max_views": 0}, "pass trainer.curve_max_views=null (the default of "
                                                         "conf/trainer/default.yaml)")):
        with pytest.raises(B3dgsError) as e:
            apply_rules(values)
        assert e.value.fix == fix


def test_an_unknown_option_in_a_list_names_the_nearest_and_the_options():
    """uq=[nativ] (a list of options): Hydra's "Could not load 'uq/nativ'" names no option; the line does."""
    from hydra.errors import MissingConfigException

    msg = format_error(MissingConfigException("In 'eval': Could not load 'uq/nativ'.", missing_cfg_file="uq/nativ"))
    assert msg.startswith("uq=nativ is not an option of uq; did you mean native? (fix: pick an existing option: ")
    assert " proxy " in msg and " ensemble " in msg

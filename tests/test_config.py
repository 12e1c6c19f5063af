"""Every option of every config group composes, and its components build."""
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra
from hydra.utils import instantiate
from omegaconf import OmegaConf

from b3dgs.lifecycle import build_plugins
from b3dgs.train import CONF_DIR

EVAL_GROUPS = {"uq"}  # groups of the b3dgs-eval app (conf/eval.yaml)
STUDY_GROUPS = {"acquisition"}  # groups of the b3dgs-study app (conf/study.yaml; tests/test_acquisition.py builds each)
COMPRESS_GROUPS = {"pruning"}  # groups of b3dgs-study compress (conf/compress.yaml; built below)
GROUPS = sorted(p.name for p in Path(CONF_DIR).iterdir()
                if p.is_dir() and p.name not in {"hydra"} | EVAL_GROUPS | STUDY_GROUPS | COMPRESS_GROUPS)


def options(group):
    return sorted(p.stem for p in (Path(CONF_DIR) / group).glob("*.yaml"))


def compose_cfg(overrides, config_name="train"):
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        return compose(config_name=config_name, overrides=overrides, return_hydra_config=True)


CASES = [(g, o) for g in GROUPS for o in options(g)]


@pytest.mark.parametrize("group,option", CASES, ids=[f"{g}={o}" for g, o in CASES])
def test_every_option_composes_and_builds(group, option, tmp_path):
    overrides = [f"{group}={option}" if group != "posterior" else f"posterior=[{option}]"]
    if group == "data" and option != "synthetic":
        overrides.append(f"data.path={tmp_path}")
    cfg = compose_cfg(overrides)
    OmegaConf.resolve(cfg.hydra)  # interpolations in run dirs resolve
    strategy, blocks = build_plugins(cfg)
    strategy.validate()
    for blk in blocks.values():
        blk.validate(max_steps=int(cfg.trainer.max_steps))
    if group == "data":
        dm = instantiate(cfg.data)
        assert dm.kind == {"blender": "transforms"}.get(option, option)  # blender: transforms, on white
    if group == "model":
        from b3dgs.lifecycle import build_module

        module = build_module(cfg, strategy, blocks)
        assert module.hparams.name == cfg.model.name
    if group == "logger" and cfg.get("logger"):
        instantiate(cfg.logger, save_dir=str(tmp_path))


def test_model_selects_posterior_blocks():
    assert not compose_cfg(["model=standard"]).get("posterior")
    if "niw" in options("model"):
        assert list(compose_cfg(["model=niw"]).posterior.keys()) == ["niw"]
    if "dpmm" in options("model"):
        cfg = compose_cfg(["model=dpmm"])
        assert "niw" in cfg.posterior and "dp" in cfg.posterior
        # the command line wins over the model's choice
        assert list(compose_cfg(["model=dpmm", "posterior=[niw]"]).posterior.keys()) == ["niw"]
        assert not compose_cfg(["model=dpmm", "posterior=[]"]).get("posterior")


def test_bad_values_fail_clearly():
    cfg = compose_cfg(["strategy.refine_every=0"])
    strategy, _ = build_plugins(cfg)
    with pytest.raises(ValueError, match="refine_every"):
        strategy.validate()
    cfg = compose_cfg(["model.lambda_dssim=2"])
    from b3dgs.lifecycle import build_module

    with pytest.raises(ValueError, match="lambda_dssim"):
        build_module(cfg, *build_plugins(cfg))


@pytest.mark.parametrize("option", options("uq"))
def test_every_uq_option_builds(option):
    from b3dgs.eval import regimes_from_cfg

    cfg = compose_cfg(["run=/nonexistent", f"uq=[{option}]", "uq.samples=7"], config_name="eval")
    regimes = regimes_from_cfg(cfg)
    assert list(regimes) == [option]
    if hasattr(regimes[option], "samples") and option in ("native", "proxy"):
        assert regimes[option].samples == 7


def test_eval_needs_a_regime():
    from b3dgs.eval import regimes_from_cfg

    with pytest.raises(ValueError, match="uq="):
        regimes_from_cfg(compose_cfg(["run=/x", "uq=[]"], config_name="eval"))


@pytest.mark.parametrize("option", options("pruning"))
def test_every_pruning_option_builds(option):
    from b3dgs.compression import PruningScore
    from b3dgs.study.compression import load_pruning

    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        score = load_pruning(option)
    assert isinstance(score, PruningScore) and score.rounds >= 1

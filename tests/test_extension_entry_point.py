"""An installed package adds a config option through the `b3dgs.conf` entry point, without touching b3dgs."""
import sys

from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra

from b3dgs.lifecycle import build_plugins
from b3dgs.train import CONF_DIR
from tests.fake_package import install_conf_package


def test_external_package_adds_a_strategy(tmp_path, monkeypatch):
    install_conf_package(tmp_path, monkeypatch, "b3dgs_ext_demo", "strategy", "strat", '''
        from dataclasses import dataclass
        from b3dgs.plugin import Plugin

        @dataclass
        class NeverDensify(Plugin):
            """A user's strategy that only counts steps."""
            label: str = "demo"
    ''', {"never": "_target_: b3dgs_ext_demo.strat.NeverDensify\nlabel: external\n"})
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        cfg = compose(config_name="train", overrides=["strategy=never"])
    strategy, _ = build_plugins(cfg)
    assert type(strategy).__name__ == "NeverDensify" and strategy.label == "external"
    sys.modules.pop("b3dgs_ext_demo", None)

"""An installed package adds a config option through the `b3dgs.conf` entry point, without touching b3dgs."""
import importlib
import sys
import textwrap

from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra

from b3dgs.train import CONF_DIR, build_plugins


def test_external_package_adds_a_strategy(tmp_path, monkeypatch):
    pkg = tmp_path / "b3dgs_ext_demo"
    (pkg / "conf" / "strategy").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "conf" / "__init__.py").write_text("")
    (pkg / "conf" / "strategy" / "__init__.py").write_text("")
    (pkg / "strat.py").write_text(textwrap.dedent('''
        from dataclasses import dataclass
        from b3dgs.plugin import Plugin

        @dataclass
        class NeverDensify(Plugin):
            """A user's strategy that only counts steps."""
            label: str = "demo"
    '''))
    (pkg / "conf" / "strategy" / "never.yaml").write_text("_target_: b3dgs_ext_demo.strat.NeverDensify\nlabel: external\n")
    dist = tmp_path / "b3dgs_ext_demo-0.1.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: b3dgs-ext-demo\nVersion: 0.1\n")
    (dist / "entry_points.txt").write_text("[b3dgs.conf]\nb3dgs_ext_demo = b3dgs_ext_demo.conf\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    importlib.invalidate_caches()
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        cfg = compose(config_name="train", overrides=["strategy=never"])
    strategy, _ = build_plugins(cfg)
    assert type(strategy).__name__ == "NeverDensify" and strategy.label == "external"
    sys.modules.pop("b3dgs_ext_demo", None)

"""Issue 46: every key of a composed config reaches a component or is refused. For b3dgs-train and b3dgs-eval,
validate_config checks every node of the composed config (a misspelt key added under any node is refused); for the
other apps, run_cli refuses a ``+key`` that no config file of the app gives, except under the nodes listed here that
take any key (free-form mappings and ``_target_`` nodes, whose classes decide when they are built)."""
import pytest
from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra
from omegaconf import DictConfig

from b3dgs.confs import added_key_problem
from b3dgs.errors import B3dgsError
from b3dgs.train import CONF_DIR
from b3dgs.validation import validate_config

TYPO = "zz_not_a_key"


def _compose(name, overrides=()):
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        return compose(config_name=name, overrides=list(overrides))


def _nodes(cfg, prefix=""):
    """Dotted paths of every mapping node (the root as "") and of every leaf key, outside hydra."""
    nodes, leaves = [prefix], []
    for k in cfg.keys():
        if str(k) == "hydra":
            continue
        path = f"{prefix}.{k}" if prefix else str(k)
        v = cfg._get_node(k)
        if isinstance(v, DictConfig):
            n, lv = _nodes(v, path)
            nodes += n
            leaves += lv
        else:
            leaves.append(path)
    return nodes, leaves


@pytest.mark.parametrize("app,base", [("train", ["data=synthetic", "model=dpmm"]),
                                      ("eval", ["run=/nonexistent/run", "uq=[native,proxy,sh]"])])
def test_validated_apps_refuse_a_key_added_under_any_node(app, base):
    cfg = _compose(app, base)
    nodes, leaves = _nodes(cfg)
    assert len(leaves) > 20
    for node in nodes:
        key = f"{node}.{TYPO}" if node else TYPO
        bad = _compose(app, [*base, f"+{key}=1"])
        with pytest.raises(B3dgsError, match=TYPO):
            validate_config(bad, app=app)


#: per app, the nodes that take any key (a free-form mapping or a _target_ node); every other node refuses one
FREE = {
    "render": set(),
    "export": set(),
    "process": set(),
    "view": set(),
    "report": set(),
    "study": {"policy_settings", "callbacks", "data", "renderer", "strategy", "trainer", "acquisition.batch_settings"},
    "compress": {"strategy_settings"},
    "suggest": {"policy_settings"},
}


@pytest.mark.parametrize("app", sorted(FREE))
def test_other_apps_refuse_a_plus_key_nothing_reads(app):
    cfg = _compose(app)
    nodes, leaves = _nodes(cfg)
    for leaf in leaves:  # every key the app's config gives is accepted as +key (or ++key)
        assert added_key_problem(leaf, app) is None, leaf
    free = set()
    for node in nodes:
        key = f"{node}.{TYPO}" if node else TYPO
        problem = added_key_problem(key, app)
        if problem is None:
            free.add(node)
        else:
            assert TYPO in problem[0] and problem[1].startswith("remove it")
    assert free == FREE[app]


def test_cli_refuses_unread_plus_key_in_one_line(tmp_path):
    """b3dgs-export +fromat=ply: one line, exit 2, with the key that exists."""
    import subprocess
    import sys

    res = subprocess.run([sys.executable, "-m", "b3dgs.export", f"run={tmp_path}", "+fromat=ply"],
                         capture_output=True, text=True, timeout=120)
    assert res.returncode == 2, res.stderr
    line = res.stderr.strip().splitlines()[-1]
    assert "+fromat" in line and "did you mean format" in line and len(res.stderr.strip().splitlines()) == 1

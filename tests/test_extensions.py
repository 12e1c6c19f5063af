"""One test per extension kind of docs/extending.md: an option added by a package outside b3dgs (a throw-away package
with its own ``conf/`` declared through the ``b3dgs.conf`` entry point, ``tests/fake_package.py``), used through
the same config path as b3dgs's own options, without touching the core. (Strategies:
``tests/test_extension_entry_point.py``; acquisition policies: ``tests/test_acquisition.py``.)"""
import sys

import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra

from b3dgs.errors import format_error
from b3dgs.lifecycle import build_renderer
from b3dgs.train import CONF_DIR
from b3dgs.validation import validate_config
from tests.fake_package import install_conf_package
from tests.inproc import train_here

TINY = ["data.max_side=16", "+data.n_views=6", "trainer.enable_progress_bar=false", "logger=none",
        "trainer.eval_every=100", "trainer.save_renders=false", "threads=1"]


@pytest.fixture
def package(tmp_path, monkeypatch):
    """``package(name, group, module, source, options)``: installs it; removed from sys.modules afterwards."""
    names = []

    def make(name, group, module, source, options):
        names.append(name)
        install_conf_package(tmp_path / "site", monkeypatch, name, group, module, source, options)

    (tmp_path / "site").mkdir()
    yield make
    for n in names:
        for m in [m for m in sys.modules if m == n or m.startswith(n + ".")]:
            sys.modules.pop(m)
    GlobalHydra.instance().clear()


def _compose(config_name, overrides):
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        return compose(config_name=config_name, overrides=overrides, return_hydra_config=config_name == "train")


def _train(tmp_path, overrides):
    return train_here(tmp_path, [*TINY, *overrides])


def test_outside_package_adds_a_posterior_block(package, tmp_path):
    package("b3dgs_ext_block", "posterior", "blocks", '''
        from dataclasses import dataclass
        from typing import ClassVar
        import torch
        from b3dgs.plugin import PosteriorBlock

        @dataclass
        class VisitCount(PosteriorBlock):
            needs_weights: ClassVar[bool] = True
            changes_training: ClassVar[bool] = False
            per_gaussian_state: ClassVar[tuple] = ("visits",)
            label: str = "v"

            def initialize_state(self, *, splats, scene, info):
                return {"visits": torch.zeros(splats["means"].shape[0], device=splats["means"].device),
                        "steps": torch.zeros((), device=splats["means"].device)}

            def step_post_backward(self, *, splats, optimizers, state, step, info):
                state["visits"] += (info["per_gaussian"]["weight_sum"].sum(0) > 0).float()
                state["steps"] += 1

            def summary(self, *, state):
                return {"steps": int(state["steps"]), "rows": int(state["visits"].shape[0])}
    ''', {"visits": "visits:\n  _target_: b3dgs_ext_block.blocks.VisitCount\n  label: outside\n"})
    m = _train(tmp_path / "run", ["posterior=[visits]", "trainer.max_steps=12", "strategy.refine_start=2",
                                  "strategy.refine_every=4", "strategy.refine_stop=11", "strategy.grad_threshold=1e-9"])
    assert m["num_gaussians"] > 0
    ck = torch.load(tmp_path / "run" / "checkpoints" / "last.ckpt", weights_only=False)
    visits = ck["b3dgs"]["states"]["visits"]["visits"]
    assert visits.shape[0] == ck["state_dict"]["splats.means"].shape[0] == m["num_gaussians"]  # followed densification
    assert float(ck["b3dgs"]["states"]["visits"]["steps"]) == 12


def test_outside_package_adds_a_pruning_score(package):
    from b3dgs.compression import keep_top
    from b3dgs.study.compression import load_pruning

    package("b3dgs_ext_prune", "pruning", "scores", '''
        from dataclasses import dataclass
        from b3dgs.compression import PruningScore

        @dataclass
        class Volume(PruningScore):
            def score(self, *, splats, optimizers, state, step, info):
                return splats["scales"].detach().sum(-1)
    ''', {"volume": "_target_: b3dgs_ext_prune.scores.Volume\nrounds: 2\n"})
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        score = load_pruning("volume")
    assert type(score).__name__ == "Volume" and score.rounds == 2
    scales = torch.tensor([[0.0, 0, 0], [1.0, 1, 1], [-1.0, -1, -1]])
    s = score.score(splats={"scales": scales}, optimizers=None, state={}, step=0, info={})
    assert keep_top(s, 1).tolist() == [False, True, False]


def test_outside_package_adds_a_uq_regime(package):
    from b3dgs.eval import regimes_from_cfg
    from b3dgs.uq.regime import UQRegime

    package("b3dgs_ext_uq", "uq", "regimes", '''
        from dataclasses import dataclass
        from typing import ClassVar
        import torch
        from b3dgs.uq.regime import Predictive, UQRegime

        @dataclass
        class Flat(UQRegime):
            has_epistemic: ClassVar[bool] = False
            level: float = 0.01

            def predict(self, camera, generator=None):
                mean = torch.zeros(camera.height, camera.width, 3)
                flat = torch.full(mean.shape[:2], self.level)
                return Predictive(mean, flat, torch.zeros_like(flat), self.level)
    ''', {"flat": "flat:\n  _target_: b3dgs_ext_uq.regimes.Flat\n  level: 0.5\n"})
    cfg = _compose("eval", ["run=/nonexistent", "uq=[flat,constant]"])
    regimes = regimes_from_cfg(cfg)
    assert list(regimes) == ["flat", "constant"] and isinstance(regimes["flat"], UQRegime)
    assert regimes["flat"].level == 0.5


def test_outside_package_adds_a_renderer(package, tmp_path):
    package("b3dgs_ext_render", "renderer", "rend", '''
        from dataclasses import dataclass
        from typing import ClassVar
        from b3dgs.render.renderers import TorchRenderer

        @dataclass
        class CountingTorch(TorchRenderer):
            name: ClassVar[str] = "counting"
            calls = 0

            def render(self, params, camera, **kw):
                type(self).calls += 1
                return super().render(params, camera, **kw)
    ''', {"counting": "_target_: b3dgs_ext_render.rend.CountingTorch\nnear: 0.01\n"})
    cfg = _compose("train", [*TINY, "renderer=counting", "trainer.max_steps=3",
                             f"trainer.default_root_dir={tmp_path}"])
    validate_config(cfg)
    renderer = build_renderer(cfg.renderer)
    assert type(renderer).__name__ == "CountingTorch" and renderer.device.type == "cpu"
    m = _train(tmp_path / "run", ["renderer=counting", "trainer.max_steps=3"])
    assert m["renderer"]["name"] == "counting" and type(renderer).calls >= 3


def test_outside_package_adds_a_data_loader(package, tmp_path):
    package("b3dgs_ext_data", "data", "loaders", '''
        from b3dgs.data.synthetic import load_synthetic
        from b3dgs.errors import B3dgsError

        def load_small(*, n_views=8, max_side=None, background=(0.0, 0.0, 0.0), max_images=None):
            return load_synthetic(n_views=n_views, resolution=16, max_side=max_side, background=background,
                                  max_images=max_images)

        def check_small(*, n_views=8, **_):
            if not (isinstance(n_views, int) and n_views >= 2):
                raise B3dgsError(f"data.n_views={n_views} is invalid: it must be an integer >= 2", "pass data.n_views=8")

        load_small.validate = check_small   # called with the extra data.* keys when the data module is built
    ''', {"small": "defaults:\n  - synthetic\n  - _self_\nname: small\nkind: b3dgs_ext_data.loaders:load_small\n"})
    cfg = _compose("train", ["data=small", "+data.n_views=5", "data.test_every=0", f"trainer.default_root_dir={tmp_path}"])
    validate_config(cfg)
    from hydra.utils import instantiate

    dm = instantiate(cfg.data)
    dm.setup("fit")
    assert dm.scene.name == "small" and len(dm.scene.train) == 5 and dm.scene.train[0].width == 16
    bad = _compose("train", ["data=small", "+data.n_view=5", f"trainer.default_root_dir={tmp_path}"])
    with pytest.raises(ValueError, match="unknown config key data.n_view; did you mean n_views"):
        validate_config(bad)
    one = _compose("train", ["data=small", "+data.n_views=1", f"trainer.default_root_dir={tmp_path}"])
    validate_config(one)  # keys and types are right; the loader's own validate refuses the value when the data is built
    with pytest.raises(Exception) as ei:
        instantiate(one.data)
    assert format_error(ei.value) == "data.n_views=1 is invalid: it must be an integer >= 2 (fix: pass data.n_views=8)"


def test_acquisition_family_is_any_model_option():
    from b3dgs.errors import B3dgsError
    from b3dgs_plugins.acquisition.uniform import UniformPolicy

    for family in ("standard", "niw", "dpmm", "mcmc"):
        UniformPolicy(family=family).validate()
    with pytest.raises(B3dgsError, match="family='nope' is not a model option"):
        UniformPolicy(family="nope").validate()


def _doc_blocks(heading_file: str) -> str:
    """The code block of docs/extending.md whose first line is ``# <heading_file>``, as written there."""
    import re
    from pathlib import Path

    text = (Path(__file__).resolve().parents[1] / "docs" / "extending.md").read_text()
    blocks = re.findall(r"```(?:python|yaml)\n(.*?)```", text, flags=re.S)
    found = [b for b in blocks if b.startswith(f"# {heading_file}\n")]
    assert len(found) == 1, f"docs/extending.md has {len(found)} blocks headed {heading_file}"
    return found[0]


def test_docs_view_pass_example_runs(package, tmp_path):
    """The extending doc's block with a view-pass sum of its own, run as written there: one plugin file and one YAML
    file, no core change. The mean distance it exports lies between the nearest and farthest training camera of
    every Gaussian the views saw, and its summary is the median of the exported values."""
    from b3dgs.data import load_scene
    from b3dgs.ply import read_ply

    source = _doc_blocks("its_pkg/distance.py").replace("its_pkg", "b3dgs_ext_dist")
    yaml = _doc_blocks("its_pkg/conf/posterior/distance.yaml").replace("its_pkg", "b3dgs_ext_dist")
    package("b3dgs_ext_dist", "posterior", "distance", source, {"distance": yaml})
    run = tmp_path / "run"
    m = _train(run, ["posterior=[distance]", "trainer.max_steps=8"])
    ply = read_ply(run / "point_cloud.ply")
    dist = torch.as_tensor(ply["extra"]["view_distance"]).double()
    ck = torch.load(run / "checkpoints" / "last.ckpt", weights_only=False)
    means = ck["state_dict"]["splats.means"].double()
    assert dist.shape[0] == means.shape[0] == m["num_gaussians"]
    scene = load_scene("synthetic", None, max_side=16, n_views=6)
    centres = torch.stack([c.center.double() for c in scene.train])
    d = torch.cdist(means, centres)
    seen = dist > 0
    assert int(seen.sum()) > 0.5 * means.shape[0]
    tol = 1e-4 * d.max()
    assert bool((dist[seen] >= d.min(1).values[seen] - tol).all() and (dist[seen] <= d.max(1).values[seen] + tol).all())
    assert m["posterior"]["distance"]["median_distance"] == pytest.approx(float(dist.float().median()), rel=1e-5)


def test_module_names_no_block():
    """The LightningModule asks no block for anything by name: no identifier or string in b3dgs/module.py names a
    shipped posterior block, its option or its view-pass sums (blocks declare what they need; issue 45)."""
    import io
    import re
    import tokenize
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    banned = {"fisher", "fisher_probes", "sh_information", "sq_err", "n_values"}
    for f in (root / "plugins" / "posterior").glob("*.py"):
        banned.add(f.stem.lower())
        banned |= {ln[6:].split("(")[0].split(":")[0].strip().lower() for ln in f.read_text().splitlines() if ln.startswith("class ")}
    banned |= {f.stem.lower() for f in (root / "conf" / "posterior").glob("*.yaml")}
    banned.discard("__init__")
    found = []
    for tok in tokenize.generate_tokens(io.StringIO((root / "b3dgs" / "module.py").read_text()).readline):
        if tok.type == tokenize.NAME and tok.string.lower() in banned:
            found.append((tok.start[0], tok.string))
        elif tok.type == tokenize.STRING:
            words = {w.lower() for w in re.findall(r"[A-Za-z_][A-Za-z_0-9]*", tok.string)}
            if tok.string.lstrip("rbfuRBFU").startswith(('"""', "'''")):
                continue  # docstrings may explain
            found += [(tok.start[0], w) for w in words & banned]
    assert found == [], f"b3dgs/module.py names blocks or their sums: {found}"


def test_an_option_two_packages_give_is_refused(package, capsys):
    """Issue 46 (class: an input one name could mean two ways): a package that adds conf/model/niw.yaml, an option
    b3dgs has, would be taken or ignored silently by Hydra's search path; every CLI refuses it in one line naming both
    files. An option of a new name is fine."""
    from b3dgs.confs import option_clashes
    from b3dgs.errors import run_cli

    assert option_clashes() == []
    package("b3dgs_ext_clash", "model", "m", "X = 1\n", {"niw": "name: niw\n", "niw_mine": "name: niw_mine\n"})
    clashes = option_clashes()
    assert [name for name, _ in clashes] == ["model/niw"] and len(clashes[0][1]) == 2
    with pytest.raises(SystemExit) as ei:
        run_cli("b3dgs-render", lambda: None, argv=[], config="render")
    assert ei.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "model/niw is given by 2 files" in err[0] and "(fix: rename one of them" in err[0]

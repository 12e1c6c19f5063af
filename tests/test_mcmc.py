"""3DGS-MCMC strategy (plugins/strategy/mcmc.py): relocation formula, ops bookkeeping, noise gate, training."""
import math
from dataclasses import dataclass
from typing import ClassVar

import pytest
import torch
from hydra import compose, initialize_config_dir
from torch import nn

from b3dgs.ops import TopologyOps
from b3dgs.plugin import Plugin
from b3dgs.train import CONF_DIR
from b3dgs_plugins.strategy.mcmc import MCMCStrategy, relocation


@pytest.mark.parametrize("n", [1, 2, 3, 5, 8])
def test_relocation_keeps_centre_opacity_and_the_1d_integral(n):
    """1 - (1 - o')^n = o, and the composited 1-D profile 1 - (1 - o' g_{s'})^n integrates to o s √(2π)."""
    o = torch.tensor([0.02, 0.3, 0.7, 0.97], dtype=torch.float64)
    s = torch.tensor([[0.5, 1.0, 2.0]] * 4, dtype=torch.float64)
    o2, s2 = relocation(o, s, torch.full((4,), n))
    assert torch.allclose(1 - (1 - o2) ** n, o, atol=1e-12)
    x = torch.linspace(-40, 40, 400001, dtype=torch.float64)
    for j in range(4):
        prof = 1 - (1 - o2[j] * torch.exp(-x ** 2 / (2 * s2[j, 0] ** 2))) ** n
        integral = torch.trapezoid(prof, x)
        assert math.isclose(float(integral), float(o[j] * s[j, 0]) * math.sqrt(2 * math.pi), rel_tol=1e-6)
    if n == 1:
        assert torch.allclose(o2, o) and torch.allclose(s2, s)


def test_relocation_refuses_bad_shapes():
    with pytest.raises(ValueError, match="relocation"):
        relocation(torch.rand(3), torch.rand(3, 2), torch.ones(3, dtype=torch.long))


def _toy(n=40, seed=0):
    g = torch.Generator().manual_seed(seed)
    splats = nn.ParameterDict({
        "means": nn.Parameter(torch.randn(n, 3, generator=g)), "quats": nn.Parameter(torch.randn(n, 4, generator=g)),
        "scales": nn.Parameter(torch.randn(n, 3, generator=g) - 3), "opacities": nn.Parameter(torch.randn(n, generator=g)),
        "sh0": nn.Parameter(torch.randn(n, 1, 3, generator=g)), "shN": nn.Parameter(torch.randn(n, 3, 3, generator=g))})
    opt = torch.optim.Adam([{"params": [p], "name": k, "lr": 1e-3} for k, p in splats.items()])
    loss = sum((p ** 2).sum() for p in splats.values())
    loss.backward()
    opt.step()
    states = {"core": {"ids": torch.arange(n), "parent_ids": torch.full((n,), -1), "next_id": torch.tensor(n)},
              "strategy": {"relocated": torch.zeros((), dtype=torch.long), "grown": torch.zeros((), dtype=torch.long)},
              "probe": {"per_gaussian": torch.arange(n).float()}}
    strat = MCMCStrategy(cap_max=50, min_opacity=0.3)
    return splats, opt, states, strat, TopologyOps(splats, {"gaussians": opt}, states,
                                                   {"strategy": strat, "probe": _Probe()})


@dataclass
class _Probe(Plugin):
    """A plugin with one declared per-Gaussian state key."""
    per_gaussian_state: ClassVar[tuple] = ("per_gaussian",)


def test_relocate_and_grow_bookkeeping():
    torch.manual_seed(0)
    splats, opt, states, strat, ops = _toy()
    dead0 = (torch.sigmoid(splats["opacities"].data) <= 0.3).nonzero().flatten()
    assert dead0.numel() > 0
    strat._relocate_and_grow(splats, states["strategy"], ops)
    n = ops.num
    assert n == min(50, math.floor(40 * 1.05)) == 42
    assert int(states["strategy"]["relocated"]) == dead0.numel() and int(states["strategy"]["grown"]) == 2
    assert (torch.sigmoid(splats["opacities"].data) >= 0.3 - 1e-6).all()  # no dead Gaussian left, copies clamped
    ids = states["core"]["ids"]
    assert ids.unique().numel() == n  # fresh ids for the relocated and the appended rows
    relocated = dead0
    assert (states["core"]["parent_ids"][relocated] >= 0).all()
    # the per-Gaussian plugin state followed the rows: a relocated row carries its source's value
    src_ids = states["core"]["parent_ids"][relocated]
    assert torch.equal(states["probe"]["per_gaussian"][relocated], src_ids.float())
    # Adam moments: zero for every copy and every source, untouched elsewhere
    p = splats["means"]
    st = opt.state[p]
    fresh = torch.zeros(n, dtype=torch.bool)
    fresh[relocated] = True
    fresh[40:] = True
    sources = set(src_ids.tolist()) | set(states["core"]["parent_ids"][40:].tolist())
    touched = fresh.clone()
    touched[list(sources)] = True
    assert (st["exp_avg"][touched] == 0).all()
    assert (st["exp_avg"][~touched] != 0).all()
    assert opt.param_groups[0]["params"][0] is splats["means"]


def test_cap_is_never_exceeded():
    torch.manual_seed(1)
    splats, opt, states, strat, ops = _toy(n=49)
    strat._relocate_and_grow(splats, states["strategy"], ops)
    assert ops.num == 50
    strat._relocate_and_grow(splats, states["strategy"], ops)
    assert ops.num == 50


def test_noise_moves_transparent_gaussians_only():
    torch.manual_seed(0)
    splats, opt, states, strat, ops = _toy()
    with torch.no_grad():
        splats["opacities"].data[:20] = 6.0  # opaque
        splats["opacities"].data[20:] = -8.0  # transparent
    before = splats["means"].data.clone()
    strat._inject_noise(splats, {"gaussians": opt})
    moved = (splats["means"].data - before).norm(dim=-1)
    assert moved[:20].max() < 1e-12 * max(1.0, float(moved[20:].max()))
    assert (moved[20:] > 0).all()


def _train(tmp_path, extra):
    from hydra.utils import instantiate

    from b3dgs.study.rounds import fit_round

    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        cfg = compose(config_name="train", overrides=[
            "model=mcmc", "data.max_side=32", "trainer.max_steps=80", "trainer.checkpoint_every=1000",
            "trainer.checkpoint_every_s=0", "trainer.enable_progress_bar=false", "logger=none", "strategy.refine_start=10",
            "strategy.refine_every=10", "strategy.refine_stop=70", "seed=0", "threads=1", "renderer=cpu", *extra])
    dm = instantiate(cfg.data)
    dm.setup("fit")
    return fit_round(cfg, dm.scene, tmp_path, 80)


def test_mcmc_trains_grows_to_the_cap_and_regularises(tmp_path):
    """The synthetic scene starts from 3874 points; 6 refinements of +5% reach the 4500 cap."""
    m = _train(tmp_path / "a", ["strategy.cap_max=4500"])
    assert m.num_gaussians == 4500
    st = m.states["strategy"]
    assert int(st["grown"]) == 4500 - 3874
    assert m.states["core"]["ids"].shape[0] == m.num_gaussians and m.states["core"]["ids"].unique().numel() == 4500
    reg = _train(tmp_path / "b", ["strategy.cap_max=4500", "strategy.opacity_reg=1.0"])
    o_plain = torch.sigmoid(m.splats["opacities"]).mean()
    o_reg = torch.sigmoid(reg.splats["opacities"]).mean()
    assert o_reg < o_plain  # the regulariser reached the loss (info["loss_terms"])

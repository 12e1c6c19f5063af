"""Densify and prune keep parameters, Adam moments and plugin state aligned."""
from dataclasses import dataclass

import pytest
import torch
from torch import nn

from b3dgs.ops import TopologyOps
from b3dgs.plugin import Plugin


@dataclass
class TagPlugin(Plugin):
    """Records every topology change it is told about."""

    def __post_init__(self):
        self.calls = []

    def on_topology(self, *, splats, optimizers, state, step, info):
        self.calls.append((info["op"], int(info["fresh"].sum())))


def make(n=10):
    torch.manual_seed(0)
    tag = torch.arange(n, dtype=torch.float32)
    splats = nn.ParameterDict({
        "means": nn.Parameter(torch.randn(n, 3) + tag[:, None] * 0),
        "scales": nn.Parameter(torch.full((n, 3), -1.0)),
        "quats": nn.Parameter(torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1)),
        "opacities": nn.Parameter(tag.clone()),  # opacity logit == original index: a tag
        "sh0": nn.Parameter(tag[:, None, None].repeat(1, 1, 3)),
        "shN": nn.Parameter(torch.zeros(n, 3, 3)),
    })
    opt = torch.optim.Adam([{"params": [p], "name": k} for k, p in splats.items()])
    loss = sum((p * (1 + torch.arange(p.shape[0]).view(-1, *[1] * (p.dim() - 1)))).sum() for p in splats.values())
    loss.backward()
    opt.step()
    plugin = TagPlugin()
    states = {
        "core": {"ids": torch.arange(n), "parent_ids": torch.full((n,), -1), "next_id": torch.tensor(n)},
        "tag": {"value": tag.clone(), "pair": tag[:, None].repeat(1, 2), "scalar": torch.tensor(3.0), "nested": {"v": tag.clone()}},
    }
    ops = TopologyOps(splats, {"gaussians": opt}, states, {"tag": plugin})
    return splats, opt, states, ops, plugin


def check_aligned(splats, opt, states, fresh_tag_ok=True):
    tag = torch.round(splats["sh0"].data[:, 0, 0])
    assert torch.equal(states["tag"]["value"], tag)
    assert torch.equal(states["tag"]["pair"][:, 0], tag)
    assert torch.equal(states["tag"]["nested"]["v"], tag)
    assert states["tag"]["scalar"].item() == 3.0
    p = splats["sh0"]
    st = opt.state[p]
    # non-fresh rows keep moments that depend on their original index: exp_avg = 0.1 * grad = 0.1 * (idx+1)
    nz = st["exp_avg"][:, 0, 0] != 0
    assert torch.allclose(st["exp_avg"][nz, 0, 0], 0.1 * (tag[nz] + 1))
    for group in opt.param_groups:
        assert group["params"][0] is splats[group["name"]]
    n = splats["means"].shape[0]
    for v in splats.values():
        assert v.shape[0] == n
    assert states["core"]["ids"].shape == (n,)
    assert len(set(states["core"]["ids"].tolist())) == n  # ids unique


def test_clone_split_prune_keep_alignment():
    splats, opt, states, ops, plugin = make(10)
    mask = torch.zeros(10, dtype=torch.bool)
    mask[[1, 4]] = True
    assert ops.clone(mask) == 2
    assert splats["means"].shape[0] == 12
    check_aligned(splats, opt, states)
    # clones: new ids, parents are the sources
    assert states["core"]["ids"][10:].tolist() == [10, 11]
    assert states["core"]["parent_ids"][10:].tolist() == [1, 4]
    # fresh rows have zero moments
    assert torch.all(opt.state[splats["sh0"]]["exp_avg"][10:] == 0)

    mask = torch.zeros(12, dtype=torch.bool)
    mask[[0, 11]] = True
    ops.split(mask)
    assert splats["means"].shape[0] == 14
    check_aligned(splats, opt, states)
    # the split parents (ids 0 and 11) are gone, 4 children have them as parents
    ids = states["core"]["ids"].tolist()
    assert 0 not in ids and 11 not in ids
    assert sorted(states["core"]["parent_ids"][-4:].tolist()) == [0, 0, 11, 11]
    # children are smaller by 1.6
    assert torch.allclose(splats["scales"].data[-1], torch.full((3,), -1.0 - torch.log(torch.tensor(1.6)).item()), atol=2e-3)

    prune = torch.round(splats["sh0"].data[:, 0, 0]) >= 5
    removed = ops.prune(prune, reason="test")
    check_aligned(splats, opt, states)
    assert ops.removed["test"] == removed
    assert plugin.calls == [("clone", 2), ("split", 4), ("prune", 0)]


def test_prune_all_keeps_one():
    splats, opt, states, ops, _ = make(5)
    ops.prune(torch.ones(5, dtype=torch.bool), reason="all")
    assert splats["means"].shape[0] == 1
    assert round(splats["opacities"].item()) == 4  # the most opaque survives
    check_aligned(splats, opt, states)


def test_prune_bad_mask():
    _, _, _, ops, _ = make(5)
    with pytest.raises(ValueError, match="mask must have shape"):
        ops.prune(torch.ones(4, dtype=torch.bool), reason="x")


def test_training_continues_after_ops():
    splats, opt, states, ops, _ = make(8)
    ops.clone(torch.ones(8, dtype=torch.bool))
    ops.prune(torch.arange(16) % 3 == 0, reason="x")
    loss = sum(p.square().sum() for p in splats.values())
    loss.backward()
    opt.step()  # the optimizer steps the new parameters
    for p in splats.values():
        assert p.grad is not None and torch.isfinite(p).all()


def test_reset_opacity():
    splats, opt, states, ops, _ = make(6)
    ops.reset_opacity(0.01)
    assert torch.all(torch.sigmoid(splats["opacities"].data) <= 0.01 + 1e-6)
    assert torch.all(opt.state[splats["opacities"]]["exp_avg"] == 0)

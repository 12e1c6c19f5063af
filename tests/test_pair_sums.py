"""The per-Gaussian pair sums (Σ_p w, Σ_p w²) are asked of the renderer only on steps where a block reads them
(:meth:`b3dgs.plugin.Plugin.reads_pair_sums`), and the default cadences keep the archived bits."""
import json

import pytest
import torch

from b3dgs.render.renderers import CPURenderer
from b3dgs_plugins.posterior.color import ColorBlock
from b3dgs_plugins.posterior.dp import DPBlock
from test_train import run_train

TINY = ["data.max_side=32", "+data.n_views=8", "trainer.enable_progress_bar=false", "logger=none",
        "trainer.max_steps=24", "trainer.eval_every=24", "strategy.refine_start=8", "strategy.refine_every=8",
        "strategy.refine_stop=20"]


@pytest.fixture
def asked(monkeypatch):
    """``return_weights`` of every training-step render (the core's renders with ``retain_means2d_grad``), in order."""
    calls: list[bool] = []
    render = CPURenderer.render

    def counting(self, params, camera, **kw):
        if kw.get("retain_means2d_grad"):
            calls.append(bool(kw.get("return_weights")))
        return render(self, params, camera, **kw)

    monkeypatch.setattr(CPURenderer, "render", counting)
    return calls


@pytest.mark.parametrize("model", ["standard", "niw"])
def test_models_without_pair_sum_readers_never_ask(tmp_path, asked, model):
    run_train(tmp_path, TINY + [f"model={model}"])
    assert len(asked) == 24 and not any(asked)


def test_a_block_that_reads_every_step_gets_the_sums_every_step(tmp_path, asked, monkeypatch):
    got = []
    post = DPBlock.step_post_backward

    def seen(self, *, info, **kw):
        got.append("weight_sum" in info["per_gaussian"] and "weight_sq_sum" in info["per_gaussian"])
        return post(self, info=info, **kw)

    monkeypatch.setattr(DPBlock, "step_post_backward", seen)
    run_train(tmp_path, TINY + ["model=standard", "posterior=[dp]", "posterior.dp.t_dp=8", "posterior.dp.cavi_every=8"])
    assert asked == [True] * 24 and got == [True] * 24


def test_asked_only_on_the_steps_a_block_declares(tmp_path, asked):
    # the colour block reads Σ w² from t_post on; DP, with a cadence of 5, on steps 0, 5, 10, ...
    run_train(tmp_path, TINY + ["model=standard", "posterior=[color]", "posterior.color.t_post=16"])
    assert asked == [s >= 16 for s in range(24)]
    asked.clear()
    run_train(tmp_path / "dp", TINY + ["model=standard", "posterior=[dp,color]", "posterior.color.t_post=16",
                                       "posterior.dp.pair_sums_every=5"])
    assert asked == [s % 5 == 0 or s >= 16 for s in range(24)]


def _digest(path) -> str:
    return json.loads((path / "metrics.json").read_text())["checkpoint"]["params_sha256"]


def test_colour_from_t_post_keeps_the_every_step_bits(tmp_path, monkeypatch):
    """The colour block's sums asked from t_post only give the parameters (and Σ w² state) of asking every step."""
    over = TINY + ["model=standard", "posterior=[color]", "posterior.color.t_post=12"]
    run_train(tmp_path / "from_t_post", over)
    monkeypatch.setattr(ColorBlock, "reads_pair_sums", lambda self, step, info: True)  # the core before the cadence
    run_train(tmp_path / "every", over)
    assert _digest(tmp_path / "from_t_post") == _digest(tmp_path / "every")
    a, b = (torch.load(tmp_path / d / "checkpoints" / "last.ckpt", weights_only=False)["b3dgs"]["states"]["color"]["wsq"]
            for d in ("from_t_post", "every"))
    assert torch.equal(a, b) and bool((a > 0).any())


def test_dpmm_default_cadence_is_every_step_and_keeps_its_bits(tmp_path, asked):
    over = TINY + ["model=dpmm", "posterior.dp.t_dp=8", "posterior.dp.cavi_every=8", "posterior.color.t_post=12",
                   "posterior.opacity.t_post=12", "posterior.noise.t_noise=8"]
    run_train(tmp_path / "default", over)
    assert asked == [True] * 24
    run_train(tmp_path / "explicit", over + ["posterior.dp.pair_sums_every=1", "posterior.color.pair_sums_every=1"])
    assert _digest(tmp_path / "default") == _digest(tmp_path / "explicit")
    run_train(tmp_path / "every4", over + ["posterior.dp.pair_sums_every=4", "posterior.color.pair_sums_every=4"])
    assert asked[48:] == [s % 4 == 0 for s in range(24)]


def test_strided_usage_ema_reads_every_kth_step_with_decay_ema_to_the_k():
    ws = torch.tensor([[2.0, 0.0, 1.0]])
    info = {"per_gaussian": {"weight_sum": ws}, "max_steps": 600, "num_train_views": 4}

    def usage(every: int, steps: int) -> torch.Tensor:
        blk = DPBlock(ema=0.9, pair_sums_every=every)
        st = {"usage": torch.zeros(3, dtype=torch.float64), "n_views": torch.tensor(4.0)}
        for s in range(steps):  # before t_dp: the usage EMA only
            blk.step_post_backward(splats=None, optimizers=None, state=st, step=s, info=info)
        return st["usage"]

    # every step: 1 - 0.9^4 of the stationary value 4 w; every 2nd step: reads at 0 and 2, 1 - (0.9^2)^2, the same
    target = (1 - 0.9 ** 4) * 4 * ws[0].double()
    assert torch.allclose(usage(1, 4), target) and torch.allclose(usage(2, 4), target)
    assert torch.allclose(usage(2, 3), target)  # step 3 is not read although the sums are there
    assert not torch.allclose(usage(2, 2), target)


@pytest.mark.parametrize("block", [DPBlock, ColorBlock])
@pytest.mark.parametrize("bad", [0, -2, 1.5])
def test_pair_sums_every_must_be_a_positive_integer(block, bad):
    from b3dgs.errors import B3dgsError

    with pytest.raises(B3dgsError, match="pair_sums_every"):
        block(pair_sums_every=bad).validate(max_steps=100)


def test_dp_cadence_bench_grid(tmp_path):
    dp_cadence = pytest.importorskip("bench.dp_cadence")
    assert dp_cadence.variants([4, 1]) == ["every1=", "every4=posterior.dp.pair_sums_every=4 "
                                                       "posterior.color.pair_sums_every=4"]
    with pytest.raises(SystemExit, match="--every"):
        dp_cadence.variants([0])
    # the table of an empty grid (trains nothing): bench/schedule.py's machinery under this name and title
    dp_cadence.main(["--table-only", "--scenes", "fox", "--seeds", "0", "--out", str(tmp_path / "o"),
                     "--archive", str(tmp_path / "a"), "--results-root", str(tmp_path)])
    out = json.loads((tmp_path / "dp_cadence.json").read_text())
    assert out["rows"] == [] and set(out["variants"]) == {"every1", "every4"}
    assert (tmp_path / "dp_cadence.md").read_text().startswith("# DPMM pair-sum cadences side by side")

"""bench/count_cost.py: the pass a count adds after training, timed on a trained run."""
import json

import pytest

from test_train import QUICK, run_train


def test_count_cost_times_each_pass_and_resumes(tmp_path, monkeypatch):
    import bench.count_cost as cc

    run = tmp_path / "toy" / "niw" / "s0"
    m = run_train(run, QUICK + ["model=niw", "trainer.max_steps=30", "model.sh_increase_every=10", "trainer.eval_every=30", "strategy.refine_start=10",
                                "strategy.refine_stop=25", "strategy.refine_every=10"])
    got = cc.measure(run, ["weight", "sh"], {})
    assert set(got) == {"weight", "sh"}
    for v in got.values():
        assert v["pass_s"] > 0 and v["views"] > 0
        assert v["share_pct"] == pytest.approx(100 * (v["block_s"] + v["pass_s"]) / (m["train_time_s"] + v["pass_s"]))
        side = 100 * (v["block_s"] / m["train_time_s"] + v["pass_s"] / (v["pass_s"] + m["steps"] * v["render_step_s"]))
        assert v["render_step_s"] > 0 and v["share_side_pct"] == pytest.approx(side)
    again = cc.measure(run, ["weight", "sh"], got)  # resumed: nothing timed again
    assert again == got
    md = cc.table({"runs": {"toy/niw/s0": got}, "load": "test"})
    assert "| toy/niw/s0 |" in md and "| sh |" in md
    monkeypatch.setattr(cc, "RESULTS", tmp_path)
    monkeypatch.setattr("sys.argv", ["count_cost", "--runs", str(tmp_path / "nothing_here")])
    with pytest.raises(SystemExit, match="no checkpoints/last.ckpt"):
        cc.main()
    assert not (tmp_path / "count_cost.json").exists()
    json.dumps(got)  # the results are plain JSON

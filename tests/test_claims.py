"""bench/claims.py: verdicts computed from per-scene results (holds, sign only, fails, parity, pending)."""
from __future__ import annotations

import json
from pathlib import Path

import pytest

claims = pytest.importorskip("bench.claims")


def _archive(root: Path, n_scenes: int) -> None:
    """Archived canonical runs: DPMM below standard everywhere, MCMC above, NIW equal; native variance
    rising with -PSNR."""
    for i in range(n_scenes):
        scene = f"scene{i}"
        base = 20.0 + i
        for method, psnr in (("standard", base), ("niw", base), ("dpmm", base - 0.5 - 0.1 * i), ("mcmc", base + 0.2)):
            for seed in (0, 1):
                d = root / "runs" / scene / method / f"s{seed}"
                d.mkdir(parents=True)
                (d / "metrics.json").write_text(json.dumps({"psnr": psnr, "seed": seed, "num_gaussians": 1000.0,
                                                            "render_fps": 10.0, "train_time_s": 100.0}))
                (d / "uq.json").write_text(json.dumps({
                    "proxy": {"cov95_err": 0.8, "ause_rmse": 0.02, "nll": 5.0},
                    "native": {"cov95_err": 0.05, "ause_rmse": 0.03, "nll": -1.0, "mean_var": 1.0 / psnr}}))


def _row(rows, cid):
    return next(r for r in rows if r["id"] == cid)


def test_verdicts_from_six_scenes(tmp_path):
    _archive(tmp_path, 6)
    rows, text = claims.build(tmp_path)
    assert _row(rows, "dpmm_psnr_cost")["verdict"] == "holds"  # 6/6 scenes, p = 2/64 < 0.05
    assert _row(rows, "dpmm_psnr_cost")["ours"] == pytest.approx(-0.75)
    assert _row(rows, "mcmc_psnr")["verdict"] == "fails"
    assert _row(rows, "parity_niw_vs_standard")["verdict"] == "parity by construction"
    assert _row(rows, "calibration_native_vs_proxy")["verdict"] == "holds"
    assert _row(rows, "native_ause_worse")["verdict"] == "holds"
    assert _row(rows, "dpmm_fewer_gaussians")["verdict"] == "parity by construction"
    sp = _row(rows, "spearman_niw")
    assert sp["ours"] == pytest.approx(1.0) and sp["verdict"] == "holds"
    # no active-view, uq.json or compression results here
    assert _row(rows, "active_native_vs_ensemble")["verdict"] == "pending"
    assert "**fails**" in text and "scene0" in text


def test_three_scenes_reach_sign_only(tmp_path):
    _archive(tmp_path, 3)
    rows, _ = claims.build(tmp_path)
    r = _row(rows, "dpmm_psnr_cost")
    assert r["verdict"] == "holds in sign only" and r["n_scenes"] == 3  # p floor 2/8 = 0.25
    assert "floor" in r["why"]


def test_unpaired_seeds_are_left_out(tmp_path):
    _archive(tmp_path, 6)
    d = tmp_path / "runs" / "scene0" / "standard" / "s2"  # a seed only standard has finished
    d.mkdir(parents=True)
    (d / "metrics.json").write_text(json.dumps({"psnr": 99.0, "seed": 2}))
    rows, _ = claims.build(tmp_path)
    assert _row(rows, "dpmm_psnr_cost")["per_scene"]["scene0"] == pytest.approx(-0.5)


def test_restricting_to_scenes_recomputes_the_verdicts(tmp_path):
    """--scenes: the same archive, two of its scenes: the p floor rises and 'holds' becomes 'holds in sign only'."""
    _archive(tmp_path, 6)
    rows, text = claims.build(tmp_path, only=["scene0", "scene3"])
    r = _row(rows, "dpmm_psnr_cost")
    assert r["n_scenes"] == 2 and r["verdict"] == "holds in sign only" and set(r["per_scene"]) == {"scene0", "scene3"}
    assert r["ours"] == pytest.approx(-0.65)
    assert _row(rows, "spearman_niw")["verdict"] == "pending"  # Spearman needs 3 scenes
    assert "scene1" not in text


def test_ensemble_rows_read_the_archive(tmp_path):
    """The per-scene deep ensemble comes from runs/<scene>/ensemble/uq.json when the archive has it."""
    _archive(tmp_path, 6)
    for i in range(6):
        d = tmp_path / "runs" / f"scene{i}" / "ensemble"
        d.mkdir()
        (d / "uq.json").write_text(json.dumps({"ensemble": {"cov95_err": 0.45, "ause_rmse": 0.02, "psnr": 21.0 + i}}))
    rows, _ = claims.build(tmp_path)
    r = _row(rows, "calibration_native_vs_ensemble")
    assert r["verdict"] == "holds" and r["ours"] == pytest.approx(0.40) and r["n_scenes"] == 6
    assert _row(rows, "ensemble_psnr")["ours"] == pytest.approx(1.0)


def test_change_table_and_escaped_cells(tmp_path):
    """What more scenes changed: a verdict that moves (sign only on 2 scenes -> holds on 6) is listed first, in bold;
    every table line has exactly its columns (a claim's |Cov@95 - 0.95| is escaped, not a cell border)."""
    import re

    _archive(tmp_path, 6)
    early, _ = claims.build(tmp_path, ["scene0", "scene1"])
    rows, text = claims.build(tmp_path)
    change = claims.change_md(early, rows)
    lines = [ln for ln in change.splitlines() if ln.startswith("| ") and "---" not in ln][1:]
    assert len(lines) == len(rows)
    dpmm = next(ln for ln in lines if ln.startswith("| DPMM - standard PSNR"))
    assert "holds in sign only" in dpmm and "**holds (-0.75 dB, p = 0.0312, 6 scenes)**" in dpmm
    assert lines.index(dpmm) < next(i for i, ln in enumerate(lines) if "Near-parity" in ln)  # changed rows first
    for table, columns in ((change, 3), (text, 9)):
        for ln in table.splitlines():
            if ln.startswith("|"):
                assert len(re.findall(r"(?<!\\)\|", ln)) == columns + 1, ln


def test_batch_acquisition_rows_read_the_active_view_pairs(tmp_path):
    """Issue 22's rows (batch-aware native against top-k native, the ensemble, farthest) come from active_view.json's
    paired per-scene differences, and are pending without them."""
    _archive(tmp_path, 3)
    rows, _ = claims.build(tmp_path)
    assert _row(rows, "batch_native_vs_farthest")["verdict"] == "pending"
    per = {"scene0": -0.2, "scene1": -0.1, "scene2": -0.3}
    (tmp_path / "active_view.json").write_text(json.dumps({"paired": {
        "native+greedy_conditioned-farthest": {"per_scene": per},
        "native+greedy_conditioned-native": {"per_scene": {k: -v for k, v in per.items()}}}}))
    rows, text = claims.build(tmp_path)
    far, topk = _row(rows, "batch_native_vs_farthest"), _row(rows, "batch_native_vs_topk")
    assert far["verdict"] == "fails" and far["ours"] == pytest.approx(-0.2) and far["n_scenes"] == 3
    assert topk["verdict"] == "holds in sign only" and topk["ours"] == pytest.approx(0.2)
    assert _row(rows, "batch_native_vs_ensemble")["verdict"] == "pending"
    assert "issue 22" in text


def test_active_rows_pool_both_ladders(tmp_path):
    """The 8 -> 16 scenes (active_view_8to16.json) are paired units beside the 16 -> 32 ones: five plus two scenes,
    every difference positive, reach p = 2/128 and 'holds'; the 16 -> 32 file alone would stop at p = 2/32."""
    _archive(tmp_path, 3)
    big = {f"big{i}": 0.3 + 0.01 * i for i in range(5)}
    small = {"small0": 0.2, "small1": 0.1}
    (tmp_path / "active_view.json").write_text(json.dumps({"paired": {"native-ensemble": {"per_scene": big}}}))
    rows, _ = claims.build(tmp_path)
    r = _row(rows, "active_native_vs_ensemble")
    assert r["n_scenes"] == 5 and r["verdict"] == "holds in sign only"
    (tmp_path / "active_view_8to16.json").write_text(json.dumps({"paired": {"native-ensemble": {"per_scene": small}}}))
    rows, _ = claims.build(tmp_path)
    r = _row(rows, "active_native_vs_ensemble")
    assert r["n_scenes"] == 7 and r["verdict"] == "holds"
    assert r["ours"] == pytest.approx(sum({**big, **small}.values()) / 7)


def test_active_rows_of_later_policies_read_the_extra_pairs(tmp_path):
    """A policy the campaign did not run (e.g. sh) is read from bench/active_view_extra.py's file (a list of
    {a, b, ladder, per_scene}), both ladders pooled; without that file its rows are pending."""
    _archive(tmp_path, 3)
    rows, _ = claims.build(tmp_path)
    assert _row(rows, "active_sh_vs_native")["verdict"] == "pending"
    paired = [{"a": "sh", "b": "native", "ladder": "16->32", "per_scene": {"big0": 0.4, "big1": -0.1}},
              {"a": "sh", "b": "native", "ladder": "8->16", "per_scene": {"small0": 0.2}},
              {"a": "sh", "b": "ensemble", "ladder": "16->32", "per_scene": {"big0": -9.0, "big1": -9.0}}]
    (tmp_path / "active_view_sh.json").write_text(json.dumps({"rows": [], "paired": paired}))
    rows, _ = claims.build(tmp_path)
    r = _row(rows, "active_sh_vs_native")
    assert r["n_scenes"] == 3 and r["ours"] == pytest.approx(0.5 / 3)
    assert _row(rows, "active_sh_vs_ensemble")["ours"] == pytest.approx(-9.0)


def test_active_rho_rows_read_the_paired_rho(tmp_path):
    """The ρ rows (score against the oracle error, against the support deficit) come from active_view_extra's
    paired_rho, one scene one unit; a 7/0 positive support ρ reaches 'holds'."""
    _archive(tmp_path, 3)
    per = {f"s{i}": 0.1 + 0.1 * i for i in range(7)}
    (tmp_path / "active_view_sh.json").write_text(json.dumps({"rows": [], "paired": [], "paired_rho": [
        {"rho": "rho_support", "a": "sh", "b": "native", "per_scene": per},
        {"rho": "rho", "a": "sh", "b": "native", "per_scene": {k: -v for k, v in per.items()}}]}))
    rows, _ = claims.build(tmp_path)
    assert _row(rows, "active_sh_rho_support_vs_native")["verdict"] == "holds"
    assert _row(rows, "active_sh_rho_vs_native")["verdict"] == "fails"
    assert _row(rows, "active_sh_rho_vs_ensemble")["verdict"] == "pending"


def test_per_seed_values_face_a_per_scene_ensemble_with_their_seed_mean():
    """diff(): a regime scored per seed against the deep ensemble (one value per scene) uses its mean over every
    seed, not only the seed the ensemble's row happens to carry."""
    a = {"s": {0: 0.9, 1: 0.7, 2: 0.8}, "t": {0: 0.5}}
    assert claims.diff(a, {"s": 0.6, "t": 0.5}) == pytest.approx({"s": 0.2, "t": 0.0})
    assert claims.diff({"s": 0.6}, a) == pytest.approx({"s": -0.2})
    assert claims.diff(a, {"s": {0: 0.5, 1: 0.5}}) == pytest.approx({"s": 0.3})  # per seed: paired seeds 0 1


def test_diverse_rows_of_a_later_policy_pair_with_the_campaigns_diverse_rows(tmp_path):
    """sh+diverse is read against ensemble+diverse (a key with a '+' on both sides); plain sh has no such row."""
    _archive(tmp_path, 3)
    paired = [{"a": "sh+diverse", "b": "ensemble+diverse", "ladder": "16->32", "per_scene": {"big0": 0.3, "big1": 0.1}}]
    (tmp_path / "active_view_sh.json").write_text(json.dumps({"rows": [], "paired": paired}))
    rows, _ = claims.build(tmp_path)
    assert _row(rows, "active_sh+diverse_vs_ensemble_diverse")["ours"] == pytest.approx(0.2)
    assert _row(rows, "active_sh+diverse_vs_native")["verdict"] == "pending"
    assert not [r for r in rows if r["id"] == "active_sh_vs_ensemble_diverse"]

"""bench/active_view.py: the budget ladder of a scene follows its train-view count."""
from __future__ import annotations

import sys

import pytest

active_view = pytest.importorskip("bench.active_view")


@pytest.mark.parametrize("n,ladder", [(17, "8to16"), (21, "8to16"), (39, "8to16"), (40, "16to32"), (86, "16to32")])
def test_ladder_of(n, ladder):
    assert active_view.ladder_of(n) == ladder
    init, acq = active_view.LADDERS[ladder]
    assert init + acq < n  # candidates leave a choice


def test_compression_archive_round_trip(tmp_path):
    """bench/compression.py: finished rows, bases and meta reach the archive; a fresh out dir gets them back, and a
    restore never overwrites a file already there (only_missing)."""
    compression = pytest.importorskip("bench.compression")
    from bench.common import archived_files, sync_results

    def sync(a, b, only_missing=False):
        return sync_results(a, b, compression.ARCHIVED, only_missing)

    out, arch, fresh = tmp_path / "out", tmp_path / "arch", tmp_path / "fresh"
    files = {"meta.json": "{}", "fox/s0/base.json": '{"b": 1}', "fox/s0/opacity_k55/result.json": '{"psnr": 1}',
             "fox/s0/scores/opacity.pt": "not archived", "fox/s0/opacity_k10/partial.tmp": "not archived"}
    for rel, text in files.items():
        (out / rel).parent.mkdir(parents=True, exist_ok=True)
        (out / rel).write_text(text)
    assert sync(out, arch) == 3
    assert sorted(str(p) for p in archived_files(arch, compression.ARCHIVED)) == [
        "fox/s0/base.json", "fox/s0/opacity_k55/result.json", "meta.json"]
    assert sync(out, arch) == 0  # unchanged files are not copied again
    (fresh / "fox" / "s0").mkdir(parents=True)
    (fresh / "fox" / "s0" / "base.json").write_text('{"b": 2}')
    assert sync(arch, fresh, only_missing=True) == 2
    assert (fresh / "fox" / "s0" / "base.json").read_text() == '{"b": 2}'
    assert (fresh / "fox" / "s0" / "opacity_k55" / "result.json").read_text() == '{"psnr": 1}'
    assert not list(arch.rglob(".*"))  # no temporary files left behind


def test_periodic_sync_keeps_rows_finished_during_the_block(tmp_path):
    """bench/common.PeriodicSync: a row finished while the block runs reaches the archive before the block ends."""
    import time

    from bench.common import PeriodicSync

    src, dst = tmp_path / "study", tmp_path / "arch"
    with PeriodicSync(src, dst, ("*/*_s*/result.json",), every_s=0.05):
        (src / "fox" / "native_s0").mkdir(parents=True)
        (src / "fox" / "native_s0" / "result.json").write_text('{"psnr": 20}')
        deadline = time.time() + 10
        while not (dst / "fox" / "native_s0" / "result.json").exists() and time.time() < deadline:
            time.sleep(0.05)
        assert (dst / "fox" / "native_s0" / "result.json").read_text() == '{"psnr": 20}'
        (src / "fox" / "uniform_s0").mkdir()
        (src / "fox" / "uniform_s0" / "result.json").write_text("{}")
    assert (dst / "fox" / "uniform_s0" / "result.json").exists()  # the final sync at the end of the block


def test_support_spearman_is_none_when_every_row_has_the_same_coverage(monkeypatch, tmp_path):
    """fern 8 -> 16: the test views' nearest training camera is an initial view for every row, so the support
    distance is constant, its rank correlation with PSNR undefined: None (never NaN, which the JSON writer refuses)."""
    import numpy as np

    from b3dgs.io import write_json

    centres = {"i0": np.zeros(3), "t0": np.array([0.1, 0, 0])}
    centres.update({f"c{k}": np.array([10.0 + k, 0, 0]) for k in range(8)})
    monkeypatch.setattr(active_view, "camera_geometry", lambda scene, args=None: (centres, 1.0))
    runs = [{"seed": 0, "psnr": 20.0 + 0.1 * k, "selected": [f"c{k}", f"c{(k + 1) % 8}"]} for k in range(6)]
    per_scene = {"fern": {"meta": {"initial_views": ["i0"], "test_views": ["t0"]}, "runs": runs, "seeds": [0]}}
    out = active_view.add_support(per_scene)
    assert out["fern"]["psnr_vs_support_spearman"] is None and out["fern"]["per_seed"] == []
    assert len({r["support_distance"] for r in runs}) == 1
    write_json(tmp_path / "support.json", out)  # no NaN left to refuse
    runs[0]["selected"] = ["t0", "c1"]  # one row now covers the test view: the correlation is defined again
    assert active_view.add_support(per_scene)["fern"]["psnr_vs_support_spearman"] is not None


def test_pooled_pairs_take_every_scene_of_both_ladders_as_one_unit():
    """Five 16 -> 32 scenes and two 8 -> 16 ones, all positive: pooled, the sign-flip p reaches 2/128 (each ladder
    alone stops at 2/32 and 2/4); a pair only one ladder has keeps its scenes; the markdown names both ladders."""
    big = {"paired": {"native-ensemble": {"per_scene": {f"b{i}": 0.1 * (i + 1) for i in range(5)}},
                      "native-proxy": {"per_scene": {"b0": -0.2}}}}
    small = {"paired": {"native-ensemble": {"per_scene": {"s0": 0.05, "s1": 0.2}}}}
    pooled = active_view.pooled_pairs([big, small])
    ne = pooled["native-ensemble"]
    assert ne["n_scenes"] == 7 and ne["scene_wins"] == 7
    assert ne["scene_sign_flip_p"] == pytest.approx(2 / 128) and ne["p_floor"] == pytest.approx(2 / 128)
    assert ne["delta_psnr"] == pytest.approx((0.1 + 0.2 + 0.3 + 0.4 + 0.5 + 0.05 + 0.2) / 7)
    assert pooled["native-proxy"]["n_scenes"] == 1 and pooled["native-proxy"]["scene_wins"] == 0
    text = active_view.pooled_markdown(pooled, {"b0": "16to32", "s0": "8to16"})
    assert "16to32 b0" in text and "8to16 s0" in text and "native − ensemble" in text


def test_each_scene_seed_is_one_job_and_walls_add_up(monkeypatch, tmp_path):
    """bench/active_view.py submits one job per scene-seed (so two seeds of one scene use both cores) and sums a
    scene-seed's wall time over the sessions that ran it."""
    import json

    calls = []
    monkeypatch.setattr(active_view, "run_scene", lambda sc, seeds, *a, **k: calls.append((sc, tuple(seeds)))
                        or {sd: 1.0 for sd in seeds})
    monkeypatch.setattr(active_view, "scene_ladders", lambda scenes: {})
    out = tmp_path / "study"
    out.mkdir()
    (out / "walls.json").write_text(json.dumps({"fox/s1": 5.0}))
    monkeypatch.setattr(sys, "argv", ["active_view.py", "--scenes", "fox", "ethiopian_head", "--seeds", "1", "2",
                                      "--jobs", "2", "--study-out", str(out), "--archive", str(tmp_path / "arch")])
    active_view.main()
    assert sorted(calls) == [("ethiopian_head", (1,)), ("ethiopian_head", (2,)), ("fox", (1,)), ("fox", (2,))]
    walls = json.loads((out / "walls.json").read_text())
    assert walls["fox/s1"] == 6.0 and walls["ethiopian_head/s2"] == 1.0


def test_extra_overrides_never_reach_the_committed_archive(tmp_path):
    """bench/active_view.py --extra (other policies, protocol) is another study: it is refused on the committed
    archive, whose meta.json and layout.json it would rewrite, and allowed on a study dir's own archive."""
    from bench.common import RESULTS

    with pytest.raises(SystemExit, match="would rewrite the committed archive"):
        active_view.refuse_committed(RESULTS / "active_view_runs", ["policies=[sh]"])
    active_view.refuse_committed(RESULTS / "active_view_runs", [])  # the campaign itself
    active_view.refuse_committed(tmp_path / "archive", ["policies=[sh]"])


def test_support_deficit_is_the_distance_to_the_nearest_initial_camera():
    """bench/active_view.support_deficit: each candidate's distance to the nearest initial camera centre; a score
    equal to it has ρ = 1 with it (the farthest policy's), a score ranking the other way ρ = -1."""
    import numpy as np

    from b3dgs.study.active_tables import oracle_rho

    centres = {"a": np.zeros(3), "b": np.array([10.0, 0, 0]), "c": np.array([1.0, 0, 0]),
               "d": np.array([4.0, 0, 0]), "e": np.array([0, 0, 3.0])}
    d = active_view.support_deficit(["a", "b"], ["c", "d", "e"], centres)
    assert d == pytest.approx({"c": 1.0, "d": 4.0, "e": 3.0})
    assert oracle_rho(d, d) == pytest.approx(1.0)
    assert oracle_rho({k: -v for k, v in d.items()}, d) == pytest.approx(-1.0)
    assert active_view.support_deficit([], ["c"], centres) == {}


def test_an_archive_inside_the_study_dir_is_not_copied_into_itself(tmp_path):
    """bench/common.sync_results: with the archive at <study-out>/archive, the archive's own files (dtu_scan24/...
    matches the row pattern */*_s*/*.json) are not synced into archive/archive/."""
    from bench.common import sync_results

    out = tmp_path / "study"
    (out / "dtu_scan24").mkdir(parents=True)
    (out / "dtu_scan24" / "meta.json").write_text("{}")
    (out / "dtu_scan24" / "sh_s0").mkdir()
    (out / "dtu_scan24" / "sh_s0" / "result.json").write_text('{"psnr": 1}')
    patterns = ("*/meta.json", "*/*_s*/*.json")
    assert sync_results(out, out / "archive", patterns) == 2
    assert sync_results(out, out / "archive", patterns) == 0
    assert not (out / "archive" / "archive").exists()
    assert sync_results(out / "archive", tmp_path / "fresh", patterns, only_missing=True) == 2


@pytest.mark.parametrize("model", ["standard", "niw", "dpmm"])
def test_bench_pins_the_archived_runs_posterior_blocks(model):
    """bench/common.model_overrides gives each model the posterior blocks of the committed canonical runs (their
    config.yaml), so a later change of conf/model/<name>.yaml's default blocks cannot reach the archived studies."""
    from omegaconf import OmegaConf

    from bench.common import ARCHIVED_POSTERIOR, RESULTS, compose, model_overrides

    archived = OmegaConf.load(RESULTS / "runs" / "fox" / model / "s0" / "config.yaml")
    blocks = list(archived.get("posterior") or {})
    assert blocks == ARCHIVED_POSTERIOR[model]
    over = model_overrides(model)
    assert over == [f"model={model}", f"posterior=[{','.join(blocks)}]"]
    assert list(compose("train", ["scene=fox", *over]).get("posterior") or {}) == blocks


def test_bench_active_view_pins_the_archived_study_protocol(monkeypatch, tmp_path):
    """The study bench/active_view.py starts (its pinned family_posterior included) has the protocol of the committed
    campaign folder: the pin records nothing there, so the archive's rows stay continuable."""
    import json

    from b3dgs.protocol import differing_keys
    from b3dgs.study.active import compose_config, family_config, study_protocol
    from bench.common import ARCHIVED_FAMILY_POSTERIOR, RESULTS

    monkeypatch.setenv("B3DGS_DATA", str(tmp_path))
    cfg = compose_config("study", ["scene=fox", "renderer=cpu", "seeds=[0]", f"out_dir={tmp_path}", "threads=1",
                                   "acquisition.score_max_side=64", ARCHIVED_FAMILY_POSTERIOR])
    cfg.trainer.default_root_dir = str(tmp_path)
    posteriors = {f: list(family_config(cfg, f, 0).get("posterior") or {}) for f in ("standard", "niw")}
    stored = json.loads((RESULTS / "active_view_runs" / "fox" / "protocol.json").read_text())["settings"]
    assert differing_keys(stored, json.loads(json.dumps(study_protocol(cfg, posteriors), default=str))) == []

"""bench/suggest.py's pieces without training: the sector's angular range (nearest camera direction), the hit rate
against chance, snapping suggestions to distinct held-out cameras, and the table from an archive."""
from __future__ import annotations

import json
import math
from types import SimpleNamespace

import numpy as np
import torch

from b3dgs.render_cli import _look_at
from b3dgs.types import Camera


def _cam(name, az, r=3.0):
    pos = np.array([r * math.cos(az), r * math.sin(az), 0.5])
    view = _look_at(pos, np.zeros(3), np.array([0.0, 0.0, 1.0]))
    return Camera(name, torch.tensor([[10.0, 0, 8], [0, 10.0, 8], [0, 0, 1]]), torch.from_numpy(view).float(), 16, 16)


def _scene():
    az = np.linspace(0, 2 * math.pi, 16, endpoint=False)
    cams = [_cam(f"v{i:02d}", a) for i, a in enumerate(az)]
    sector = [c for i, c in enumerate(cams) if i in (0, 1)]
    inter = [cams[8]]
    train = [c for c in cams if c not in sector and c not in inter]
    return SimpleNamespace(train=train, test=sector + inter,
                           test_groups={"sector": [c.name for c in sector], "interleaved": [c.name for c in inter]})


def _rec(azimuths, cand_azimuths):
    def d(a):
        return [math.cos(a), math.sin(a), 0.0]

    sug = []
    for i, a in enumerate(azimuths):
        vm = _cam("s", a, r=3.2).viewmat.double().numpy()
        sug.append({"rank": i + 1, "direction": d(a), "viewmat": vm.tolist()})
    return {"centre": [0.0, 0.0, 0.0], "suggestions": sug, "candidate_directions": {f"c{i}": d(a) for i, a in
                                                                                   enumerate(cand_azimuths)}}


def test_hit_rate_against_chance_and_snapping():
    from bench.suggest import hits, snap

    scene = _scene()
    step = 2 * math.pi / 16
    rec = _rec([0.1 * step, 1.1 * step, 5 * step], np.linspace(0, 2 * math.pi, 32, endpoint=False) + 0.01)
    h = hits(rec, scene)
    assert h["n"] == 3 and h["hit_rate"] == 2 / 3
    assert abs(h["chance"] - 4 / 32) < 1e-9  # 2 of 16 camera directions' Voronoi cells: 4 of 32 candidates
    # two suggestions nearest the same held-out camera take it and the next nearest
    rec = _rec([0.4 * step, 0.45 * step], [])
    assert snap(rec, scene, 2) == ["v00", "v01"]


def test_views_added_leave_half_the_held_out_views_to_score():
    """K: N where the held-out views are many; fewer (at least 1) so 4 policies' added views take at most half."""
    from bench.suggest import views_added

    assert views_added(8, 100, 4) == 8
    assert views_added(8, 16, 4) == 2 and views_added(8, 13, 4) == 1 and views_added(8, 6, 4) == 1


def test_table_pairs_over_scenes(tmp_path):
    from bench.suggest import table

    for k, sc in enumerate(["a", "b", "c"]):
        d = tmp_path / sc / "s0"
        d.mkdir(parents=True)
        (d / "hits.json").write_text(json.dumps({
            "info_gain": {"hit_rate": 0.8 + 0.05 * k, "chance": 0.1}, "distance": {"hit_rate": 0.5, "chance": 0.1},
            "cover": {"hit_rate": 0.4, "chance": 0.1}, "uniform": {"hit_rate": 0.1, "chance": 0.1}}))
        for pol, psnr in (("info_gain", 20.0 + k), ("uniform", 19.0 + k), ("distance", 19.5 + k), ("cover", 19.2 + k),
                          ("none", 18.0)):
            (d / f"outcome_{pol}.json").write_text(json.dumps({
                "sector": {"psnr": psnr, "lpips": 0.2}, "all": {"psnr": psnr + 1, "lpips": 0.1}, "views_added": 2,
                "eval_sector": ["x", "y"], "eval_all": ["x", "y", "z"]}))
    stale = tmp_path / "d" / "s0"  # a record from before the K rule (no views_added) is superseded, never counted
    stale.mkdir(parents=True)
    (stale / "outcome_info_gain.json").write_text(json.dumps({"sector": {"psnr": 99.0, "lpips": 0.0},
                                                              "all": {"psnr": 99.0, "lpips": 0.0}}))
    (tmp_path / "e" / "s0").mkdir(parents=True)
    (tmp_path / "e" / "s0" / "outcome_skipped.json").write_text("{}")
    running = tmp_path / "a" / "s1"  # a scene-seed whose other policies are still training: not counted yet
    running.mkdir(parents=True)
    (running / "outcome_info_gain.json").write_text(json.dumps({
        "sector": {"psnr": 99.0, "lpips": 0.0}, "all": {"psnr": 99.0, "lpips": 0.0}, "views_added": 2,
        "eval_sector": ["x"], "eval_all": ["x"]}))
    payload, text = table(tmp_path, ["a", "b", "c", "d", "e"], [0, 1])
    assert "d" not in payload["outcome"]["info_gain"] and payload["outcome_skipped"] == ["e s0"]
    assert payload["outcome"]["info_gain"]["a"][0] == 20.0  # seed 1's lone row left out
    assert "| a | 2 | 2 | 3 | 20.00 | 19.20 | 19.50 | 19.00 | 18.00 |" in text
    p = payload["paired"]
    assert abs(p["info_gain hit − chance"]["mean"] - 0.75) < 1e-9 and p["info_gain hit − chance"]["wins"] == 3
    assert abs(p["info_gain − distance (hit rate)"]["mean"] - 0.35) < 1e-9
    assert abs(p["info_gain − uniform (sector PSNR)"]["mean"] - 1.0) < 1e-9
    assert abs(p["info_gain − cover (sector PSNR)"]["mean"] - 0.8) < 1e-9
    assert "| info_gain − uniform | sector PSNR | 3 | +1.0000 | 3/0 |" in text


def test_a_base_retrained_with_other_parameters_is_refused_naming_both_machines(tmp_path):
    """A campaign resumed where its base run must be retrained (the work folder is gone, a new machine) may not mix
    that base with suggestions archived from the old one: other parameters are refused in one line that names the
    archived machine and this one; the same parameters, or no archive yet, pass."""
    import pytest

    from b3dgs.device import machine
    from b3dgs.errors import B3dgsError
    from bench.common import check_same_parameters

    arch = tmp_path / "base" / "metrics.json"
    check_same_parameters({"checkpoint": {"params_sha256": "aa"}}, arch, "fox s0 base")  # nothing archived yet
    arch.parent.mkdir(parents=True)
    arch.write_text(json.dumps({"checkpoint": {"params_sha256": "aa"},
                                "machine": {"cpu": "Old CPU", "cpu_capability": "AVX2"}}))
    check_same_parameters({"checkpoint": {"params_sha256": "aa"}}, arch, "fox s0 base")
    with pytest.raises(B3dgsError) as e:
        check_same_parameters({"checkpoint": {"params_sha256": "bb"}}, arch, "fox s0 base")
    msg = str(e.value)
    assert "\n" not in msg and "fox s0 base: retrained parameters bb differ from the archived run's aa" in msg
    assert "Old CPU (AVX2)" in msg and f"({machine()['cpu_capability']})" in msg and "--archive" in msg
    arch.write_text(json.dumps({"checkpoint": {"params_sha256": "aa"}}))  # archived before runs recorded machines
    with pytest.raises(B3dgsError, match="a machine not recorded"):
        check_same_parameters({"checkpoint": {"params_sha256": "bb"}}, arch, "fox s0 base")

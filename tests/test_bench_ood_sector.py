"""bench/ood_sector.py: the AUROC table from an archive (the held-out views' kinds and scores, uq.json per-view
variances), paired over scenes; resumable pieces are per scene."""
import json

import pytest

from b3dgs.io import write_json


def _scene(root, scene, sector, interleaved, regime_var):
    views = [{"name": f"v{i}", "kind": "sector", "distance": 1.0 + i, "info_gain_params": s, "info_gain_predictive": s,
              "cover": 0.5} for i, s in enumerate(sector)]
    views += [{"name": f"w{i}", "kind": "interleaved", "distance": 0.1 * i, "info_gain_params": s,
               "info_gain_predictive": -s, "cover": 0.5} for i, s in enumerate(interleaved)]
    write_json(root / scene / "views_s0.json", {"views": views, "score_max_side": 64})
    per_view = [{"name": v["name"], "mean_var": regime_var(v)} for v in views]
    write_json(root / scene / "niw" / "s0" / "uq.json", {"sh": {"per_view": per_view}})
    write_json(root / scene / "ensemble" / "uq.json",
               {"ensemble": {"per_view": [{"name": v["name"], "mean_var": 0.5} for v in views]}})


def test_table_aurocs_and_pairs(tmp_path):
    from bench.ood_sector import scene_aurocs, table

    # scene a: info gain separates perfectly; scene b: reversed; the sh regime follows the distance in both
    _scene(tmp_path, "a", [3.0, 4.0], [1.0, 2.0], lambda v: v["distance"])
    _scene(tmp_path, "b", [1.0, 2.0], [3.0, 4.0], lambda v: v["distance"])
    a = scene_aurocs(tmp_path, "a", 0)
    assert a["info_gain_params"] == 1.0 and a["distance"] == 1.0 and a["niw (sh)"] == 1.0
    assert a["cover"] == 0.5 and a["standard (ensemble)"] == 0.5  # ties: chance
    assert a["info_gain_predictive"] == 1.0  # sector positive, interleaved negated
    b = scene_aurocs(tmp_path, "b", 0)
    assert b["info_gain_params"] == 0.0 and "niw (proxy)" not in b  # a regime the file lacks is left out
    payload, text = table(tmp_path, ["a", "b"], [0])
    rows = payload["rows"]
    assert rows["info_gain_params"]["macro"] == pytest.approx(0.5)
    assert rows["niw (sh)"]["minus_standard (ensemble)"]["mean"] == pytest.approx(0.5)
    assert rows["niw (sh)"]["minus_standard (ensemble)"]["wins"] == 2
    assert "| niw (sh) | 2 | 1.000 |" in text and "| a | b |" in text
    assert scene_aurocs(tmp_path, "missing", 0) == {}
    json.dumps(payload)  # the JSON payload is serialisable

"""bench/active_view_extra.py: pairing later active-view rows with the committed campaign's."""
import pytest

from bench.active_view_extra import applies, cost, pair, pair_rho


def _row(scene, seed, policy, psnr, **against):
    r = {"scene": scene, "seed": seed, "ladder": "16->32", "policy": policy, "psnr": psnr, "rho": 0.5,
         "rho_support": 0.5}
    for b, v in against.items():
        r[f"psnr_{b}"], r[f"rho_{b}"], r[f"rho_support_{b}"] = v, 0.1, 0.2
    return r


def test_batch_rows_pair_only_with_batch_rows():
    """sh+diverse pairs with farthest and with ensemble+diverse; plain sh never with a diverse batch."""
    assert applies("sh+diverse", "farthest") and applies("sh+diverse", "ensemble+diverse")
    assert applies("sh", "ensemble") and not applies("sh", "ensemble+diverse")
    d = {"ensemble+diverse": 20.0, "farthest": 21.0}
    rows = [_row("a", 0, "sh", 22.0, **d), _row("a", 1, "sh", 23.0, **d), _row("b", 0, "sh", 20.0, **d),
            _row("a", 0, "sh+diverse", 22.5, **d), _row("b", 0, "sh+diverse", 19.0, **d)]
    against = ["farthest", "ensemble+diverse"]
    got = {(p["a"], p["b"]): p for p in pair(rows, ["sh", "sh+diverse"], against)}
    assert set(got) == {("sh", "farthest"), ("sh+diverse", "farthest"), ("sh+diverse", "ensemble+diverse")}
    assert got[("sh", "farthest")]["per_scene"] == pytest.approx({"a": 1.5, "b": -1.0})  # a: seed mean
    assert got[("sh+diverse", "ensemble+diverse")]["per_scene"] == pytest.approx({"a": 2.5, "b": -1.0})
    rho = {(p["rho"], p["a"], p["b"]) for p in pair_rho(rows, ["sh", "sh+diverse"], against)}
    # ρ is the score's, not the batch's: never against a batch row, which would repeat its top-k row's
    assert not [r for r in rho if "+" in r[2]] and ("rho_support", "sh+diverse", "farthest") in rho


def test_cost_reports_each_policys_scoring_seconds_beside_round_two():
    """The new rows' scoring seconds are theirs; a committed policy's come once per scene-seed from its own rows."""
    rows = []
    for scene, seed, t_new, t_old, r2 in (("a", 0, 2.0, 10.0, 100.0), ("a", 1, 4.0, 30.0, 300.0),
                                          ("b", 0, 6.0, 20.0, 200.0)):
        for policy, extra in (("ig", 0.0), ("ig+greedy", 1.0)):
            r = _row(scene, seed, policy, 20.0, fisher=19.0)
            r.update(scoring_time_s=t_new + extra, round2_time_s=r2, scoring_time_s_fisher=t_old)
            rows.append(r)
    rows.append({**_row("b", 1, "ig", 20.0), "scoring_time_s": None, "round2_time_s": None})  # not recorded
    got = {c["policy"]: c for c in cost(rows, ["ig", "ig+greedy"], ["fisher", "farthest"])}
    assert set(got) == {"ig", "ig+greedy", "fisher"}  # farthest: no committed seconds in any row
    assert got["ig"]["n"] == 3 and got["ig"]["median_s"] == 4.0 and (got["ig"]["min_s"], got["ig"]["max_s"]) == (2.0, 6.0)
    assert got["ig+greedy"]["median_s"] == 5.0 and got["ig"]["new"] and not got["fisher"]["new"]
    assert got["fisher"]["n"] == 3 and got["fisher"]["median_s"] == 20.0 and got["fisher"]["round2_median_s"] == 200.0


def test_lpips_pairs_with_lower_is_better():
    """LPIPS is paired like PSNR, but a lower LPIPS is the better one: a − b < 0 counts as a win."""
    rows = []
    for scene, a, b in (("a", 0.10, 0.12), ("b", 0.20, 0.25), ("c", 0.30, 0.29)):
        r = _row(scene, 0, "ig", 20.0, farthest=20.0)
        r.update(lpips=a, lpips_farthest=b)
        rows.append(r)
    (got,) = pair(rows, ["ig"], ["farthest"], key="lpips")
    assert got["per_scene"] == pytest.approx({"a": -0.02, "b": -0.05, "c": 0.01})
    assert (got["wins"], got["losses"]) == (2, 1) and got["mean"] == pytest.approx(-0.02)
    (psnr,) = pair(rows, ["ig"], ["farthest"])
    assert psnr["per_scene"] == {"a": 0.0, "b": 0.0, "c": 0.0}

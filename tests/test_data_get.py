"""``b3dgs-data``: scenes by name (issue 52 §2). This machine has no internet, so every download here comes from a
loopback ``http.server`` (127.0.0.1 only) in a thread, and the registry is pointed at it through
``$B3DGS_DATA_REGISTRY``: ``get fox`` runs the shipped registry's fox entry with only its host replaced.
"""
from __future__ import annotations

import hashlib
import io
import json
import os
import subprocess
import sys
import tarfile
import zipfile
from pathlib import Path

import pytest
import yaml
from PIL import Image

from b3dgs import datasets
from tests import loopback

ROOT = Path(__file__).resolve().parents[1]


# ---------------------------------------------------------------------------------------------- the loopback server
@pytest.fixture
def server():
    with loopback.serve() as srv:
        yield srv


@pytest.fixture
def env(tmp_path, monkeypatch):
    """The data root and the registry file in tmp_path; no waiting between retries."""
    root, registry = tmp_path / "root", tmp_path / "registry.yaml"
    monkeypatch.setenv("B3DGS_DATA", str(root))
    monkeypatch.setenv(datasets.REGISTRY_ENV, str(registry))
    monkeypatch.setattr(datasets, "RETRY_WAIT_S", 0.0)
    return root, registry


def _png(w=8, h=6) -> bytes:
    buf = io.BytesIO()
    Image.new("RGB", (w, h), (200, 40, 10)).save(buf, format="PNG")
    return buf.getvalue()


SCENE = {"transforms.json": b'{"frames": []}', "images/a.png": _png(), "images/b.png": _png()}


def _archive(kind: str, members: dict, links: dict = {}) -> bytes:
    """A zip or tar.gz of ``members`` (name -> bytes) and symbolic ``links`` (name -> target)."""
    buf = io.BytesIO()
    if kind == "zip":
        with zipfile.ZipFile(buf, "w") as z:
            for name, data in members.items():
                z.writestr(zipfile.ZipInfo(name), data)
            for name, target in links.items():
                info = zipfile.ZipInfo(name)
                info.external_attr = (0o120777 << 16)
                z.writestr(info, target)
    else:
        with tarfile.open(fileobj=buf, mode="w:gz") as t:
            for name, data in members.items():
                info = tarfile.TarInfo(name)
                info.size = len(data)
                t.addfile(info, io.BytesIO(data))
            for name, target in links.items():
                info = tarfile.TarInfo(name)
                info.type, info.linkname = tarfile.SYMTYPE, target
                t.addfile(info)
    return buf.getvalue()


def _entry(url: str, sha256=None, subdir="pack/mine", required=None) -> dict:
    return {"group": "test", "licence": "test only", "checked": "built by the test",
            "sources": [{"url": url, "sha256": sha256, "subdir": subdir}],
            "required": required or {"transforms.json": 1, "images/*.png": 2}}


def _registry(path: Path, entries: dict) -> None:
    path.write_text(yaml.safe_dump(entries, sort_keys=False))


def _leftovers(root: Path) -> list[str]:
    return sorted(p.relative_to(root).as_posix() for p in root.rglob("*")) if root.exists() else []


# ---------------------------------------------------------------------------------------------- get
@pytest.mark.parametrize("kind", ["zip", "tar.gz"])
def test_an_archive_is_fetched_checked_and_extracted_into_the_data_root(server, env, kind, capsys):
    root, registry = env
    data = _archive(kind, {f"pack/mine/{k}": v for k, v in SCENE.items()} | {"pack/other/x.txt": b"not ours"})
    server.files[f"/mine.{kind}"] = data
    _registry(registry, {"mine": _entry(f"{server.url}/mine.{kind}", hashlib.sha256(data).hexdigest())})
    assert datasets.main(["get", "mine"]) == 0
    assert f"mine: ready in {root / 'mine'}; train it: b3dgs-train data.path={root / 'mine'}\n" in capsys.readouterr().out
    assert sorted(p.relative_to(root / "mine").as_posix() for p in (root / "mine").rglob("*") if p.is_file()) == \
        sorted(SCENE)
    assert (root / "mine" / "images" / "a.png").read_bytes() == SCENE["images/a.png"]
    assert _leftovers(root) == sorted(["mine", *(f"mine/{k}" for k in SCENE), "mine/images"])  # no archive, no staging


def test_an_interrupted_download_resumes_with_a_range_request(server, env):
    root, registry = env
    data = _archive("zip", {f"pack/mine/{k}": v for k, v in SCENE.items()} | {"pack/mine/pad.bin": os.urandom(200_000)})
    server.files["/mine.zip"], server.cut = data, {"/mine.zip"}
    _registry(registry, {"mine": _entry(f"{server.url}/mine.zip", hashlib.sha256(data).hexdigest())})
    assert datasets.main(["get", "mine"]) == 0
    half = (len(data)) // 2
    assert server.log == [("/mine.zip", None), ("/mine.zip", f"bytes={half}-")]  # the second asks for the rest only
    assert (root / "mine" / "pad.bin").read_bytes() == zipfile.ZipFile(io.BytesIO(data)).read("pack/mine/pad.bin")


def test_a_part_file_left_by_an_earlier_run_is_resumed(server, env):
    root, registry = env
    data = _archive("tar.gz", {f"pack/mine/{k}": v for k, v in SCENE.items()})
    server.files["/mine.tar.gz"] = data
    (root / ".downloads").mkdir(parents=True)
    (root / ".downloads" / "mine.tar.gz.part").write_bytes(data[:100])
    _registry(registry, {"mine": _entry(f"{server.url}/mine.tar.gz", hashlib.sha256(data).hexdigest())})
    assert datasets.main(["get", "mine"]) == 0
    assert server.log == [("/mine.tar.gz", "bytes=100-")]
    assert datasets.is_present(datasets.load_registry()["mine"], root)


def test_a_signal_mid_download_keeps_the_part_file_and_the_rerun_resumes(server, env, monkeypatch, capsys):
    """SIGTERM (a cluster's, Docker's) while downloading: one line, exit code 143, the .part file kept; the same command
    then asks only for the rest."""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        pytest.skip("signal handlers live in the main thread, and this test runs in another")
    root, registry = env
    data = _archive("tar.gz", {f"pack/mine/{k}": v for k, v in SCENE.items()})
    server.files["/mine.tar.gz"] = data
    _registry(registry, {"mine": _entry(f"{server.url}/mine.tar.gz", hashlib.sha256(data).hexdigest())})
    real = datasets._fetch_once

    def cut(url, part, desc):
        part.write_bytes(data[:100])
        os.kill(os.getpid(), signal.SIGTERM)  # handled: raises b3dgs.signals.Interrupted here
        raise AssertionError("the signal did not stop the download")

    monkeypatch.setattr(datasets, "_fetch_once", cut)
    assert datasets.main(["get", "mine"]) == 143
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1] == "b3dgs-data: stopped by SIGTERM; run the same command again to resume the download"
    assert (root / ".downloads" / "mine.tar.gz.part").read_bytes() == data[:100]
    monkeypatch.setattr(datasets, "_fetch_once", real)
    assert datasets.main(["get", "mine"]) == 0
    assert server.log == [("/mine.tar.gz", "bytes=100-")]


def test_a_checksum_mismatch_is_refused_and_leaves_nothing_in_the_data_root(server, env, capsys):
    root, registry = env
    data = _archive("zip", {f"pack/mine/{k}": v for k, v in SCENE.items()})
    server.files["/mine.zip"] = data
    _registry(registry, {"mine": _entry(f"{server.url}/mine.zip", "0" * 64)})
    assert datasets.main(["get", "mine"]) == 2
    err = [ln for ln in capsys.readouterr().err.splitlines() if not ln.startswith("mine.zip")]  # less the bar
    assert len(err) == 1 and err[0].startswith("b3dgs-data: error: the download of ") and "(fix: " in err[0], err
    assert f"{server.url}/mine.zip" in err[0] and f"{root / '.downloads'}/ as mine.zip" in err[0]
    assert _leftovers(root) == []


@pytest.mark.parametrize("kind, members, links", [
    ("zip", {"pack/mine/../../evil.txt": b"x"}, {}),
    ("tar.gz", {"pack/mine/../../evil.txt": b"x"}, {}),
    ("tar.gz", {"/tmp/b3dgs-evil.txt": b"x"}, {}),
    ("zip", {}, {"pack/mine/images": "../../../../outside"}),
    ("tar.gz", {}, {"pack/mine/images": "/etc"}),
])
def test_an_archive_member_that_would_escape_the_folder_is_refused(server, env, tmp_path, kind, members, links,
                                                                  capsys):
    root, registry = env
    data = _archive(kind, {f"pack/mine/{k}": v for k, v in SCENE.items() if k != "images/b.png"} | members, links)
    server.files[f"/mine.{kind}"] = data
    _registry(registry, {"mine": _entry(f"{server.url}/mine.{kind}")})
    root.mkdir()
    before = sorted(p.name for p in tmp_path.iterdir())
    assert datasets.main(["get", "mine"]) == 2
    err = capsys.readouterr().err
    assert "outside the scene folder" in err and "(fix: " in err, err
    assert not (root / "mine").exists() and not list(root.glob(f".mine{datasets.STAGING_MARK}*"))
    assert sorted(p.name for p in tmp_path.iterdir()) == before and not Path("/tmp/b3dgs-evil.txt").exists()


def test_an_archive_without_the_required_files_is_refused(server, env, capsys):
    root, registry = env
    data = _archive("zip", {"pack/mine/transforms.json": b"{}"})
    server.files["/mine.zip"] = data
    _registry(registry, {"mine": _entry(f"{server.url}/mine.zip")})
    assert datasets.main(["get", "mine"]) == 2
    assert "lacks images/*.png (0 of 2)" in capsys.readouterr().err
    assert not (root / "mine").exists() and not list(root.glob(".mine*"))


def test_offline_one_line_names_the_url_and_the_folder_for_a_manual_download(env, capsys):
    root, registry = env
    url = "http://127.0.0.1:9/mine.zip"  # the discard port: nothing listens, the connection is refused
    _registry(registry, {"mine": _entry(url)})
    assert datasets.main(["get", "mine"]) == 2
    (line,) = [ln for ln in capsys.readouterr().err.splitlines() if ln.startswith("b3dgs-data")]
    assert line.startswith(f"b3dgs-data: error: cannot download {url}: ") and f"{root / '.downloads'}/ as mine.zip" in line
    assert not (root / "mine").exists()


def test_a_manual_download_placed_in_the_folder_is_used(server, env):
    root, registry = env
    data = _archive("zip", {f"mine/{k}": v for k, v in SCENE.items()})
    (root / ".downloads").mkdir(parents=True)
    (root / ".downloads" / "mine.zip").write_bytes(data)
    _registry(registry, {"mine": _entry("http://127.0.0.1:9/mine.zip", hashlib.sha256(data).hexdigest(), "mine")})
    assert datasets.main(["get", "mine"]) == 0 and datasets.is_present(datasets.load_registry()["mine"], root)


def test_an_already_present_scene_says_so_and_exits_0_without_a_request(server, env, capsys):
    root, registry = env
    for name, data in SCENE.items():
        (root / "mine" / name).parent.mkdir(parents=True, exist_ok=True)
        (root / "mine" / name).write_bytes(data)
    _registry(registry, {"mine": _entry(f"{server.url}/mine.zip")})
    assert datasets.main(["get", "mine"]) == 0
    assert capsys.readouterr().out.strip() == f"mine: already in {root / 'mine'}"
    assert server.log == []


def test_an_incomplete_folder_in_the_way_is_refused(env, capsys):
    root, registry = env
    (root / "mine").mkdir(parents=True)
    _registry(registry, {"mine": _entry("http://127.0.0.1:9/mine.zip")})
    assert datasets.main(["get", "mine"]) == 2
    assert f"{root / 'mine'} exists but lacks transforms.json (0 of 1), images/*.png (0 of 2) (fix: " in capsys.readouterr().err


def test_list_shows_the_scenes_and_which_are_present(env, capsys):
    root, registry = env
    (root / "here").mkdir(parents=True)
    (root / "here" / "transforms.json").write_text("{}")
    _registry(registry, {"here": _entry("http://127.0.0.1:9/a.zip", required={"transforms.json": 1}),
                         "away": _entry("http://127.0.0.1:9/b.zip")})
    assert datasets.main(["list"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0] == f"data root: {root} ($B3DGS_DATA)"
    rows = {ln.split()[0]: ln.split() for ln in lines[2:-1]}
    assert rows["here"][2] == "yes" and rows["away"][2] == "-" and list(rows) == ["here", "away"]


def test_an_unknown_name_is_one_line_with_a_suggestion(env, capsys):
    _registry(env[1], {"mine": _entry("http://127.0.0.1:9/a.zip")})
    assert datasets.main(["get", "mien"]) == 2
    assert "no scene or group named 'mien' in the registry; did you mean mine? (fix: `b3dgs-data list`" in \
        capsys.readouterr().err


# ---------------------------------------------------------------------------------------------- get fox
def _fox_fixture(server, tmp_path: Path) -> Path:
    """The shipped registry with fox's hosts replaced by the loopback server, which serves fox's files (67 small flat
    frames and a transforms.json at 4x the size) at the paths the registry names."""
    frames = loopback.frame_names()

    def body(name: str) -> bytes:
        if name.endswith(".jpg"):
            buf = io.BytesIO()
            Image.new("RGB", (40, 80), (90, 120, 30)).save(buf, format="JPEG")
            return buf.getvalue()
        if name.endswith("transforms.json"):
            return json.dumps({"fl_x": 40.0, "fl_y": 41.0, "cx": 20.0, "cy": 40.0, "w": 40.0, "h": 80.0, "frames": [
                {"file_path": n, "transform_matrix": [[1, 0, 0, 0.1 * i], [0, 1, 0, 0], [0, 0, 1, 3], [0, 0, 0, 1]]}
                for i, n in enumerate(frames)]}).encode()
        return b"licence text"

    return loopback.registry_on(server, tmp_path / "registry.yaml", body)


def test_get_fox_runs_against_the_loopback_fixture_because_this_machine_has_no_internet(server, tmp_path):
    """On this machine there is no internet, so `b3dgs-data get fox` (the console entry, in a subprocess, with the
    shipped registry's fox entry, only its host replaced) fetches from the loopback fixture; then scene=fox finds it
    and the transforms loader reads it, at a quarter of the size with the intrinsics scaled to match."""
    root = tmp_path / "root"
    env = {**os.environ, "B3DGS_DATA": str(root), datasets.REGISTRY_ENV: str(_fox_fixture(server, tmp_path)),
           "PYTHONPATH": f"{ROOT}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}
    cmd = [sys.executable, "-c", "import sys; sys.argv[0] = 'b3dgs-data'; from b3dgs.datasets import main; "
                                 "sys.exit(main())", "get", "fox"]
    res = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=300)
    assert res.returncode == 0, res.stderr[-2000:]
    assert f"fox: ready in {root / 'fox'}; train it: b3dgs-train scene=fox\n" in res.stdout
    assert len(server.log) == 69 and all(rng is None for _, rng in server.log)  # transforms, LICENSE, 67 frames
    meta = json.loads((root / "fox" / "transforms.json").read_text())
    assert (meta["fl_x"], meta["fl_y"], meta["cx"], meta["cy"], meta["w"], meta["h"]) == (10, 10.25, 5, 10, 10, 20)
    with Image.open(root / "fox" / "images" / "0115.jpg") as im:
        assert im.size == (10, 20)
    assert _leftovers(root) == sorted(["fox", "fox/images", "fox/transforms.json", "fox/LICENSE.txt",
                                       *(f"fox/images/{p.name}" for p in (root / "fox" / "images").iterdir())])
    again = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=300)
    assert again.returncode == 0 and again.stdout.strip() == f"fox: already in {root / 'fox'}"
    code = ("from hydra import compose, initialize_config_dir; from b3dgs import conf_dir; "
            "from b3dgs.data.transforms import load_transforms; from b3dgs.errors import *\n"
            "with initialize_config_dir(config_dir=conf_dir(), version_base='1.3'):\n"
            "    cfg = compose('train', overrides=['scene=fox'])\n"
            "print(cfg.data.path)")
    where = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=300)
    assert where.returncode == 0 and where.stdout.strip() == str(root / "fox"), where.stderr[-2000:]


# ---------------------------------------------------------------------------------------------- the registry
PAPER = ["bicycle", "bonsai", "counter", "flowers", "garden", "kitchen", "room", "stump", "treehill", "train", "truck",
         "drjohnson", "playroom"]


def test_the_registry_names_every_configured_scene_and_the_papers_thirteen():
    scenes = datasets.load_registry(datasets.REGISTRY_FILE)
    configured = {p.stem for p in (ROOT / "conf" / "scene").glob("*.yaml")} - {"synthetic"}
    assert set(PAPER) <= set(scenes) and configured == set(scenes), sorted(configured ^ set(scenes))  # scene=<name>
    for name in PAPER:  # what b3dgs-data get fetches, scene=<name> reads: its loader and folder
        text = (ROOT / "conf" / "scene" / f"{name}.yaml").read_text()
        assert "override /data: colmap" in text and f"path: ${{data_root}}/{name}\n" in text, name
    raw = yaml.safe_load(datasets.REGISTRY_FILE.read_text())
    for name, s in scenes.items():
        assert s.licence and s.required and s.sources and s.checked, name
        assert all("sha256" in src for src in raw[name]["sources"]), f"{name}: say sha256: null where none is published"
        assert all(src.sha256 is None or len(src.sha256) == 64 for src in s.sources), name
        assert all(src.files or datasets.is_archive(src) for src in s.sources), name
        assert all(next(iter(step)) in ("keep", "rename", "resize", "process") for step in s.layout), name
        assert "not fetched here" in s.checked.lower(), f"{name}: say how the entry was checked"
    assert {s.group for s in scenes.values() if s.name in PAPER} == {"mipnerf360", "tandt", "db"}


def test_the_data_root_falls_back_to_the_user_cache_on_a_fresh_clone(tmp_path, monkeypatch):
    import b3dgs

    monkeypatch.delenv("B3DGS_DATA", raising=False)
    monkeypatch.delenv("B3DGS_SHARED", raising=False)
    monkeypatch.setenv("B3DGS_CACHE", str(tmp_path / "cache"))
    monkeypatch.setattr(b3dgs, "conf_dir", lambda: str(tmp_path / "clone" / "conf"))
    assert b3dgs.data_root() == str(tmp_path / "cache" / "data")  # no ../shared/data beside the clone
    (tmp_path / "shared" / "data").mkdir(parents=True)
    assert b3dgs.data_root_and_origin() == (str(tmp_path / "shared" / "data"), "../shared/data beside the checkout")

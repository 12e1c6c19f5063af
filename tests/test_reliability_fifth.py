"""Fifth reliability pass (issue 55 §1, §2, §4): b3dgs-export, -render and -process write only what is theirs (a user's
file is refused, nothing goes into a run's checkpoints/, overwrite=true removes only what b3dgs listed, a model folder
is written whole or not at all), a photo is decoded whole before it is trusted, a file name that could be two files is
refused, and the fix texts name only what their command accepts."""
import ast
import json
import logging
import re
import shlex
import shutil
from pathlib import Path

import numpy as np
import pytest
from omegaconf import OmegaConf

from b3dgs.errors import B3dgsError
from tests.test_reliability_third import run_train, snapshot

ROOT = Path(__file__).resolve().parents[1]


def _export(**kw):
    from b3dgs.export import export

    return export(OmegaConf.create({"format": "ply", "checkpoint": None, "out": None, "overwrite": False, **kw}))


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    d = tmp_path_factory.mktemp("fifth") / "R"
    run_train(d, ["trainer.keep_checkpoints=true"])
    return d


# ------------------------------------------------------------------------------------- §1 writers: b3dgs-export
def test_export_refuses_a_users_file_and_replaces_it_only_with_overwrite(run, tmp_path):
    for fmt, name in (("ply", "mine.ply"), ("splat", "mine.splat")):
        user = tmp_path / name
        user.write_bytes(b"the user's own model")
        with pytest.raises(B3dgsError, match="exists and b3dgs did not write it") as e:
            _export(run=str(run), format=fmt, out=str(user))
        assert "overwrite=true" in e.value.fix and user.read_bytes() == b"the user's own model"
        _export(run=str(run), format=fmt, out=str(user), overwrite=True)
        assert user.read_bytes() != b"the user's own model"
    # in the run dir: a file its manifest does not list is the user's too; the run's own export is replaced
    (run / "export").mkdir(exist_ok=True)
    (run / "export" / "notes.splat").write_bytes(b"mine")
    with pytest.raises(B3dgsError, match="b3dgs did not write it"):
        _export(run=str(run), format="splat", out=str(run / "export" / "notes.splat"))
    assert (run / "export" / "notes.splat").read_bytes() == b"mine"
    _export(run=str(run))
    _export(run=str(run))  # its own export/point_cloud.ply: listed, replaced without asking
    with pytest.raises(B3dgsError, match="the run's own point_cloud.ply"):
        _export(run=str(run), out=str(run / "point_cloud.ply"), overwrite=True)


def test_export_writes_nothing_into_a_runs_checkpoints(run):
    before = snapshot(run / "checkpoints")
    for fmt, out in (("ply", run / "checkpoints" / "last.ckpt"), ("ply", run / "checkpoints" / "new.ply"),
                     ("3dgs", run / "checkpoints" / "m"), ("3dgs", run / "checkpoints")):
        for overwrite in (False, True):
            with pytest.raises(B3dgsError, match="checkpoints/ folder of the run"):
                _export(run=str(run), format=fmt, out=str(out), overwrite=overwrite)
    assert snapshot(run / "checkpoints") == before


def test_a_model_folder_is_written_whole_and_never_into_a_users(run, tmp_path):
    user = tmp_path / "model"
    (user / "point_cloud" / "iteration_30000").mkdir(parents=True)
    for f in ("cameras.json", "cfg_args", "point_cloud/iteration_30000/point_cloud.ply"):
        (user / f).write_text("the user's")
    before = snapshot(user)
    for overwrite in (False, True):
        with pytest.raises(B3dgsError, match="holds files b3dgs-export did not write") as e:
            _export(run=str(run), format="3dgs", out=str(user), overwrite=overwrite)
        assert "out=" in e.value.fix
    assert snapshot(user) == before and sorted(p.name for p in tmp_path.iterdir()) == ["model"]  # no staging left
    # its own folder is replaced whole: an earlier checkpoint's iteration does not stay beside the last one's
    ours = tmp_path / "ours"
    ckpts = sorted((run / "checkpoints").glob("step*.ckpt"))
    _export(run=str(run), format="3dgs", out=str(ours), checkpoint=str(ckpts[0]))
    w = _export(run=str(run), format="3dgs", out=str(ours))
    assert sorted(p.name for p in (ours / "point_cloud").iterdir()) == [f"iteration_{w['step']}"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["model", "ours"]
    # a user's file added to it makes it someone else's
    (ours / "notes.txt").write_text("mine")
    with pytest.raises(B3dgsError, match="notes.txt"):
        _export(run=str(run), format="3dgs", out=str(ours))
    # in the run dir: listed in the run's manifest, so that overwrite=true removes it with the run
    _export(run=str(run), format="3dgs")
    listed = json.loads((run / ".b3dgs-run.json").read_text())["files"]
    assert {"export/3dgs/cameras.json", "export/3dgs/cfg_args", "export/3dgs/.b3dgs-run.json"} <= set(listed)


def test_export_of_a_foreign_checkpoint_names_only_what_export_accepts(run, tmp_path):
    other = tmp_path / "O"
    run_train(other, ["seed=3"])
    with pytest.raises(B3dgsError, match="does not match this run") as e:
        _export(run=str(run), checkpoint=str(other / "checkpoints" / "last.ckpt"), out=str(tmp_path / "x.ply"))
    assert not re.search(r"\b(seed|model)=", e.value.fix) and "checkpoint=" in e.value.fix, e.value.fix


# ------------------------------------------------------------------------------------- §1 writers: b3dgs-render
def test_render_refuses_a_users_video_and_the_checkpoints_folder(run, tmp_path):
    from tests.test_manifest import render

    loose = tmp_path / "loose"
    loose.mkdir()
    (loose / "interpolate.mp4").write_bytes(b"the user's cut")
    with pytest.raises(B3dgsError, match="interpolate.mp4, which b3dgs did not write"):
        render(run, f"out={loose}", "path=interpolate", "frames=3")
    assert sorted(p.name for p in loose.iterdir()) == ["interpolate.mp4"]
    assert (loose / "interpolate.mp4").read_bytes() == b"the user's cut"
    render(run, f"out={loose}", "path=interpolate", "frames=3", "video=false")  # frames alone: nothing of the user's
    with pytest.raises(B3dgsError, match="interpolate.mp4, which b3dgs did not write"):
        render(run, f"out={loose}", "path=interpolate", "frames=3")
    assert (loose / "interpolate.mp4").read_bytes() == b"the user's cut"
    before = snapshot(run / "checkpoints")
    with pytest.raises(B3dgsError, match="checkpoints/ folder of the run"):
        render(run, f"out={run / 'checkpoints'}")
    assert snapshot(run / "checkpoints") == before
    # in the run dir, a frame its manifest does not list is someone else's
    out = run / "render" / "mine"
    out.mkdir(parents=True)
    (out / "frame_00000.png").write_bytes(b"edited by hand")
    with pytest.raises(B3dgsError, match="frame_00000.png, which b3dgs did not write"):
        render(run, f"out={out}")
    assert (out / "frame_00000.png").read_bytes() == b"edited by hand"


# ------------------------------------------------------------------------------------ §1 writers: b3dgs-process
def _jpegs(folder: Path, n: int = 3, side: int = 64) -> list[Path]:
    from PIL import Image

    folder.mkdir(parents=True, exist_ok=True)
    out = []
    for i in range(n):
        a = np.random.default_rng(i).integers(0, 255, (side, side + 16, 3), dtype=np.uint8)
        Image.fromarray(a).save(folder / f"p{i}.jpg", quality=95)
        out.append(folder / f"p{i}.jpg")
    return out


def test_process_overwrite_removes_only_what_it_listed(tmp_path):
    """overwrite=true: b3dgs-process's images, model and scene file go; a user's file in images/ and sparse/0/ stays
    (also for a state file from before it listed its files: the photos it names and pycolmap's model files)."""
    from b3dgs.process import STATE, WORK, _remove_ours

    for listed in (True, False):
        out = tmp_path / f"scene_{listed}"
        for f in ("images/a.jpg", "images/b.jpg", "sparse/0/cameras.bin", "sparse/0/images.bin",
                  "sparse/0/points3D.bin", "conf/scene/s.yaml", f"{WORK}/features.db", STATE):
            (out / f).parent.mkdir(parents=True, exist_ok=True)
            (out / f).write_bytes(b"ours")
        (out / "images" / "my_mask.png").write_bytes(b"mine")
        (out / "sparse" / "0" / "notes.txt").write_bytes(b"mine")
        state = {"photos": [["a.jpg", 1, 1], ["b.jpg", 1, 1]], "scene_file": "conf/scene/s.yaml"}
        if listed:
            state["files"] = ["images/a.jpg", "images/b.jpg", "sparse/0/cameras.bin", "sparse/0/images.bin",
                              "sparse/0/points3D.bin"]
        _remove_ours(out, state)
        left = sorted(p.relative_to(out).as_posix() for p in out.rglob("*") if p.is_file())
        assert left == ["images/my_mask.png", "sparse/0/notes.txt"], left


def test_process_moves_its_images_in_beside_a_users_and_refuses_to_replace_one(tmp_path):
    from b3dgs.process import _Run

    out = tmp_path / "scene"
    (out / "images").mkdir(parents=True)
    (out / "images" / "my_mask.png").write_bytes(b"mine")
    (out / "images" / "old.jpg").write_bytes(b"ours, from the last run")
    stage = tmp_path / "stage"
    stage.mkdir()
    for n in ("a.jpg", "images.bin"):
        (stage / n).write_bytes(b"new")
    run = _Run.__new__(_Run)
    run.out, run.state = out, {"files": ["images/old.jpg"]}
    run._into_place({"images/a.jpg": stage / "a.jpg", "sparse/0/images.bin": stage / "images.bin"})
    assert sorted(p.name for p in (out / "images").iterdir()) == ["a.jpg", "my_mask.png"]
    assert run.state["files"] == ["images/a.jpg", "sparse/0/images.bin"]
    (stage / "my_mask.png").write_bytes(b"new")
    with pytest.raises(B3dgsError, match="my_mask.png, which b3dgs-process did not write"):
        run._into_place({"images/my_mask.png": stage / "my_mask.png"})
    assert (out / "images" / "my_mask.png").read_bytes() == b"mine"


# ------------------------------------------------------------------------------------- §2 inputs read whole
def test_a_truncated_photo_is_refused_before_anything_is_written(tmp_path):
    from tests.test_process import _cfg

    from b3dgs.process import process

    photos = _jpegs(tmp_path / "photos")
    data = photos[1].read_bytes()
    photos[1].write_bytes(data[:int(len(data) * 0.45)])
    with pytest.raises(B3dgsError, match=r"cannot read the photo .*p1\.jpg whole: image file is truncated") as e:
        process(_cfg(images=str(tmp_path / "photos"), out=str(tmp_path / "out")))
    assert "\n" not in str(e.value) and not (tmp_path / "out").exists()
    (tmp_path / "photos" / "p1.jpg").write_bytes(b"\x89PNG\r\n\x1a\n" + b"\0" * 64)
    with pytest.raises(B3dgsError, match=r"p1\.jpg"):
        process(_cfg(images=str(tmp_path / "photos"), out=str(tmp_path / "out")))


def test_a_file_path_that_names_two_files_is_refused_with_both(tmp_path):
    from b3dgs.data.images import save_png
    from b3dgs.data.transforms import read_transforms

    (tmp_path / "images").mkdir()
    img = np.zeros((8, 8, 3))
    frames = []
    for i in range(2):
        save_png(tmp_path / "images" / f"{i}.png", img)
        frames.append({"file_path": f"images/{i}", "transform_matrix": np.eye(4).tolist()})
    (tmp_path / "transforms.json").write_text(json.dumps({"fl_x": 8.0, "w": 8, "h": 8, "frames": frames}))
    assert len(read_transforms(tmp_path)[0]) == 2
    shutil.copy(tmp_path / "images" / "1.png", tmp_path / "images" / "1.jpg")
    with pytest.raises(B3dgsError, match=r"'images/1' has no extension and two files have that name: 1\.png and "
                                         r"1\.jpg"):
        read_transforms(tmp_path)


# ------------------------------------------------------------------------------------- §4 fix texts
def test_the_fisheye_warning_says_the_images_were_undistorted(tmp_path, caplog):
    from tests.test_undistort import _write_transforms

    from b3dgs.data.transforms import load_transforms

    _write_transforms(tmp_path / "f", {}, {"camera_model": "OPENCV_FISHEYE", "k1": 0.05, "k2": -0.01, "p1": 0.001})
    with caplog.at_level(logging.WARNING, logger="b3dgs.data"):
        s = load_transforms(tmp_path / "f")
    said = [r.getMessage() for r in caplog.records if "p1" in r.getMessage()]
    assert len(said) == 1 and "not undistorted" not in said[0] and "IGNORED" not in said[0], said
    assert "frames undistorted with their OPENCV_FISHEYE lens" in said[0] and "p1=0.001" in said[0]
    assert s.extras["distortion"] == {} and float(s.cameras[0].K[0, 0]) < 80.0


@pytest.mark.parametrize("path", ["/data/my scans/garden", "/data/Bob's, scans [2]/garden", "/data/a\\b/c d"])
def test_the_printed_train_command_reaches_hydra_as_the_path(path):
    from hydra.core.override_parser.overrides_parser import OverridesParser

    from b3dgs.process import _searchpath_override, _shell_override

    parser = OverridesParser.create()
    (word,) = shlex.split(_shell_override("data.path", path))
    assert parser.parse_override(word).value() == path
    (word,) = shlex.split(shlex.quote(_searchpath_override(Path(path) / "conf")))
    assert parser.parse_override(word).value() == [f"file://{path}/conf"]


#: the CLI modules and their configs
CLIS = {"b3dgs/export.py": "export", "b3dgs/process.py": "process", "b3dgs/render_cli.py": "render",
        "b3dgs/eval.py": "eval", "b3dgs/train.py": "train", "b3dgs/viewer/app.py": "view",
        "b3dgs/report/app.py": "report"}
#: ``key=`` words of fix texts that are not options of the module's own command (another command's, named in the text)
OTHER_COMMANDS = {"b3dgs/eval.py": {"data.test_every", "data.test_split"}}  # "a run trained with data.test_every=8"
#: a key= word: after a space or a quote/bracket, a dotted name and "=" (not "==")
KEY = re.compile(r"(?:^|[\s(\"'`])\+?([a-z_][a-z0-9_]*(?:\.[a-z0-9_]+)*)=(?!=)")


def _fix_texts(path: Path) -> list[tuple[int, str]]:
    """The literal parts of each B3dgsError's fix (its second argument or ``fix=``), f-string placeholders dropped."""
    def text(node) -> str:
        if isinstance(node, ast.Constant) and isinstance(node.value, str):
            return node.value
        if isinstance(node, ast.JoinedStr):
            return "".join(text(v) if isinstance(v, ast.Constant) else "{}" for v in node.values)
        if isinstance(node, ast.BinOp):
            return text(node.left) + text(node.right)
        if isinstance(node, ast.IfExp):
            return text(node.body) + " | " + text(node.orelse)
        return ""

    out = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Call) and getattr(node.func, "id", None) == "B3dgsError":
            fix = node.args[1] if len(node.args) > 1 else next((k.value for k in node.keywords if k.arg == "fix"), None)
            if fix is not None:
                out.append((node.lineno, text(fix)))
    return out


def _is_key(key: str, config: str) -> bool:
    from b3dgs.confs import known_keys

    parts = key.split(".")
    if parts[0] == "hydra":
        return True
    return all(p in known_keys(".".join(parts[:i]), config) for i, p in enumerate(parts))


@pytest.mark.parametrize("module", sorted(CLIS))
def test_every_fix_text_names_only_options_of_its_command(module):
    """Each fix text of a CLI module names, as ``key=``, only keys its command's config has (a command quoted in
    backticks, `b3dgs-train ...`, is another command's and skipped)."""
    config = CLIS[module]
    bad = []
    for line, fix in _fix_texts(ROOT / module):
        own = re.sub(r"`[^`]*`", "", fix)  # `b3dgs-train ... hydra.run.dir=...`: another command's options
        for key in KEY.findall(own):
            if key not in OTHER_COMMANDS.get(module, set()) and not _is_key(key, config):
                bad.append(f"{module}:{line} {key}= in {fix!r}")
    assert not bad, bad

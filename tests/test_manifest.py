"""The run manifest lists files by name (issue 46 §1): overwrite=true and a second b3dgs-render remove exactly the
files b3dgs wrote, never a user's file beside them; a format-1 manifest (patterns) is read by the names its writers
give files. b3dgs-eval writes into no other run's uq.json (§6) and merges into no run that changed under it (§8)."""
import json
import shutil
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra

from b3dgs.errors import B3dgsError
from b3dgs.rundir import LOCK_NAME, MANIFEST_NAME
from b3dgs.train import CONF_DIR
from tests.test_reliability_third import run_train, snapshot


def files_of(d: Path) -> set[str]:
    """Every file of ``d`` (a symlinked folder as one entry, not followed), the manifest and lock aside."""
    from b3dgs.rundir import _iter_files

    return set(_iter_files(d)) - {MANIFEST_NAME, LOCK_NAME}


def manifest(d: Path) -> dict:
    return json.loads((d / MANIFEST_NAME).read_text())


def render(run: Path, *overrides: str) -> dict:
    from b3dgs.render_cli import render as render_run

    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        cfg = compose(config_name="render", overrides=[f"run={run}", "fps=4", *overrides])
    return render_run(cfg)


def _regimes(*names):
    from tests.test_reliability_third import _regimes as make

    return make(*names)


@pytest.fixture(scope="module")
def base_run(tmp_path_factory):
    """A finished tiny run with every writer on: TensorBoard, kept step checkpoints, renders."""
    d = tmp_path_factory.mktemp("manifest") / "D"
    run_train(d, ["data.n_views=16", "logger=tensorboard", "trainer.keep_checkpoints=true"])
    return d


@pytest.fixture
def run_copy(base_run, tmp_path):
    d = tmp_path / "D"
    shutil.copytree(base_run, d)
    return d


def test_the_manifest_lists_exactly_the_files_training_wrote(base_run):
    m = manifest(base_run)
    assert m["b3dgs_run"] == 2 and len(m["run_id"]) == 32 and not any("*" in f or "[" in f for f in m["files"])
    # every file of the run dir is listed by name (TensorBoard's event file, step checkpoints, renders included)
    assert files_of(base_run) == set(m["files"])
    assert {"checkpoints/step2.ckpt", "checkpoints/step4.ckpt", "tb/hparams.yaml", "renders/view_000.png"} <= set(
        m["files"])
    assert len([f for f in m["files"] if f.startswith("tb/events.out.tfevents.")]) == 1


def test_overwrite_keeps_a_users_video_beside_the_renders(run_copy):
    """§1: b3dgs-render run=D, then a user's D/render/test/my_cut.mp4, then overwrite=true: the clip stays."""
    d = run_copy
    w = render(d)
    out = d / "render" / "test"
    assert Path(w["video"]) == out / "test.mp4" and len(w["frames"]) == 2
    (out / "my_cut.mp4").write_bytes(b"the user's own cut")
    (d / "tb" / "events.out.tfevents.mine").write_bytes(b"mine")
    old = manifest(d)
    m = run_train(d, ["data.n_views=16", "logger=tensorboard", "overwrite=true", "seed=1"])
    assert m["seed"] == 1
    assert (out / "my_cut.mp4").read_bytes() == b"the user's own cut"
    assert (d / "tb" / "events.out.tfevents.mine").read_bytes() == b"mine"
    assert sorted(p.name for p in out.iterdir()) == ["my_cut.mp4"]  # our frames and video went, the clip stayed
    assert not (d / "checkpoints" / "step2.ckpt").exists()  # the old run's kept checkpoints went with it
    assert {"render/test/test.mp4", "render/test/frame_00000.png", "render/test/frame_00001.png"} <= set(old["files"])
    new = manifest(d)
    assert new["run_id"] != old["run_id"] and "render/test/test.mp4" not in new["files"]
    assert files_of(d) - set(new["files"]) == {"render/test/my_cut.mp4", "tb/events.out.tfevents.mine"}


def test_a_second_render_keeps_a_users_frame(run_copy, tmp_path):
    """§1: a second b3dgs-render run=D removes the frames of the first that it listed, and keeps a user's
    render/<path>/frame_final_edit.png; a shorter path leaves none of a longer one's frames."""
    d = run_copy
    out = d / "render" / "interpolate"
    render(d, "path=interpolate", "frames=5", "video=false")
    (out / "frame_final_edit.png").write_bytes(b"edited")
    (out / "frame_1.png").write_bytes(b"mine too")  # not a name b3dgs-render gives a frame
    render(d, "path=interpolate", "frames=3")
    assert sorted(p.name for p in out.iterdir()) == ["frame_00000.png", "frame_00001.png", "frame_00002.png",
                                                    "frame_1.png", "frame_final_edit.png", "interpolate.mp4"]
    listed = {f for f in manifest(d)["files"] if f.startswith("render/interpolate/")}
    want = [f"frame_0000{i}.png" for i in range(3)] + ["interpolate.mp4"]
    assert listed == {f"render/interpolate/{n}" for n in want}
    # outside a run dir: the files named as b3dgs-render names frames are replaced, nothing else
    loose = tmp_path / "loose"
    loose.mkdir()
    (loose / "frame_00007.png").write_bytes(b"an old frame")
    (loose / "frame_final_edit.png").write_bytes(b"edited")
    render(d, "path=interpolate", "frames=2", f"out={loose}", "video=false")
    assert sorted(p.name for p in loose.iterdir()) == [".b3dgs-render.json", "frame_00000.png", "frame_00001.png",
                                                       "frame_final_edit.png"]  # the record of what it wrote there


def test_a_format_1_manifest_is_read_by_the_names_b3dgs_gives_files(tmp_path):
    """Archived runs carry manifests of patterns: each wildcard matches only the names its writer gives files, so a
    user's clip, frame or checkpoint beside them stays; a folder reached through a symlink and `..` are never
    followed; the manifest is rewritten by name."""
    from b3dgs.rundir import remove_run_files, run_files

    d, outside = tmp_path / "run", tmp_path / "outside"
    ours = ["config.yaml", "metrics.json", "checkpoints/last.ckpt", "checkpoints/step300.ckpt",
            "tb/events.out.tfevents.1718000000.host.name.4242.0", "render/test/test.mp4", "render/test/frame_00000.png",
            "render/test/frame_00001.png", "uq.json", "uq/proxy_view_000.png", "renders/view_000.png"]
    theirs = ["render/test/my_cut.mp4", "render/test/frame_final_edit.png", "render/test/frame_1.png",
              "checkpoints/step_best.ckpt", "tb/events.out.tfevents.mine", "uq/notes.png", "renders/figure.png",
              "linked/x.png", "notes.txt"]
    for name in ours + theirs:
        if name.startswith("linked/"):
            continue
        (d / name).parent.mkdir(parents=True, exist_ok=True)
        (d / name).write_text("x")
    (outside / "x.png").parent.mkdir(parents=True)
    (outside / "x.png").write_text("outside")
    (d / "linked").symlink_to(outside, target_is_directory=True)
    (d / "metrics.json").write_text(json.dumps({"per_view": [{"name": "view_000.png"}]}))
    (d / "uq.json").write_text(json.dumps({"proxy": {"panels": ["uq/proxy_view_000.png"]}}))
    (d / MANIFEST_NAME).write_text(json.dumps({"b3dgs_run": 1, "created": "2025-01-01T00:00:00", "writes": [
        "config.yaml", "metrics.json", "checkpoints/last.ckpt", "checkpoints/step[0-9]*.ckpt",
        "tb/events.out.tfevents.*", "render/test/*.mp4", "render/test/frame_[0-9]*.png", "uq.json", "linked/*.png",
        "../outside/x.png", "*.txt"]}))
    assert run_files(d) == sorted(ours)
    remove_run_files(d)
    assert files_of(d) == set(theirs) - {"linked/x.png"} | {"linked"}
    assert (outside / "x.png").read_text() == "outside"
    m = manifest(d)
    assert m["b3dgs_run"] == 2 and m["files"] and not any("*" in f for f in m["files"])
    # a hand-edited format-2 manifest cannot reach outside the run dir either
    (d / MANIFEST_NAME).write_text(json.dumps({**m, "files": ["../outside/x.png", "linked/x.png", "/etc/hostname",
                                                              "notes.txt"]}))
    remove_run_files(d)
    assert (outside / "x.png").read_text() == "outside" and not (d / "notes.txt").exists()


def test_eval_out_another_run_is_refused(base_run, tmp_path):
    """§6: b3dgs-eval run=A out=B, B another run's dir: refused before any work, B's files unchanged; out= the run
    itself, a plain folder or a copy of the run (same parameter digest) are accepted."""
    from b3dgs.eval import evaluate_uq

    a, b = tmp_path / "A", tmp_path / "B"
    shutil.copytree(base_run, a)
    run_train(b, ["data.n_views=16", "seed=1"])
    before = snapshot(b)
    with pytest.raises(B3dgsError, match=rf"out={b} is the run dir of another run: its uq.json holds that run's "
                                         rf"results, not those of {a} \(fix: leave out= out"):
        evaluate_uq([str(a)], _regimes("constant"), max_views=1, panels=0, out_dir=b)
    assert snapshot(b) == before
    evaluate_uq([str(a)], _regimes("constant"), max_views=1, panels=0, out_dir=tmp_path / "plain")
    copy = tmp_path / "A_copy"
    shutil.copytree(base_run, copy)
    evaluate_uq([str(a)], _regimes("constant"), max_views=1, panels=1, out_dir=copy)
    assert json.loads((copy / "uq.json").read_text())["constant"]["runs"] == [str(a)]


def test_eval_refuses_to_merge_into_a_run_replaced_under_it(run_copy, tmp_path, monkeypatch):
    """§8: an eval whose run is replaced by overwrite=true seed=1 before it merges is refused in one line, and the
    new run's uq.json gets no stale entry; the same for a run scored into another folder."""
    from b3dgs.eval import evaluate_uq
    from b3dgs_plugins.uq.constant import ConstantUQ

    d = run_copy
    fit = ConstantUQ.fit

    def replaced_meanwhile(self, modules, scene):
        fit(self, modules, scene)
        run_train(d, ["data.n_views=16", "overwrite=true", "seed=1"])

    monkeypatch.setattr(ConstantUQ, "fit", replaced_meanwhile)
    with pytest.raises(B3dgsError, match=rf"{d} holds another run than when this b3dgs-eval started \(overwrite=true "
                                         rf"or a training replaced it meanwhile\): its results were not merged into "
                                         rf"{d / 'uq.json'} \(fix: run b3dgs-eval again"):
        evaluate_uq([str(d)], _regimes("constant"), max_views=1, panels=1)
    assert not (d / "uq.json").exists() and not list(d.glob(".uq-staging*")) and not (d / "uq").exists()
    assert json.loads((d / "metrics.json").read_text())["seed"] == 1

    # scored into a plain folder: the run's digest is compared (here the replacement is simulated)
    def digest_changed(self, modules, scene):
        fit(self, modules, scene)
        m = json.loads((d / "metrics.json").read_text())
        m["checkpoint"]["params_sha256"] = "0" * 64
        (d / "metrics.json").write_text(json.dumps(m))

    monkeypatch.setattr(ConstantUQ, "fit", digest_changed)
    out = tmp_path / "elsewhere"
    with pytest.raises(B3dgsError, match=rf"the run {d} changed while this b3dgs-eval ran .* \(fix: run b3dgs-eval "
                                         rf"run={d} again\)"):
        evaluate_uq([str(d)], _regimes("constant"), max_views=1, panels=0, out_dir=out)
    assert not (out / "uq.json").exists()


def test_render_paths_match_the_cli():
    """A format-1 manifest's ``*.mp4`` stands for the videos b3dgs-render could write then, all still its paths."""
    from b3dgs.render_cli import PATHS
    from b3dgs.upgrade import RENDER_PATHS

    assert RENDER_PATHS == ("test", "train", "interpolate") and set(RENDER_PATHS) <= set(PATHS)

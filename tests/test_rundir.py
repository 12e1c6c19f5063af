"""One process per run dir: the lock, unique default run dirs, refused runs that leave nothing behind,
concurrent trainings and a joblib multirun (tests/test_resume.py covers kills, signals and finished runs)."""
import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from b3dgs.errors import B3dgsError
from b3dgs.rundir import LOCK_NAME, remove_stale_tmp, run_dir_lock
from b3dgs.train import CONF_DIR
from tests.kill_hooks import kill_args

ROOT = Path(__file__).resolve().parents[1]

TINY = ["+data.n_views=8", "data.max_side=16", "trainer.max_steps=4", "trainer.eval_every=100",
        "trainer.checkpoint_every=2", "trainer.enable_progress_bar=false", "logger=none", "threads=1"]


def _train(args: list[str], env: dict | None = None, **kw):
    e = {**os.environ, **(env or {})}
    e["PYTHONPATH"] = os.pathsep.join(filter(None, [str(ROOT), e.get("PYTHONPATH")]))  # tests.kill_hooks
    return subprocess.Popen([sys.executable, "-m", "b3dgs.train", *TINY, *args], env=e, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, **kw)


def test_lock_refuses_a_second_holder_and_cleans_up(tmp_path):
    d = tmp_path / "run"
    with run_dir_lock(d):
        assert (d / LOCK_NAME).read_text().strip() == str(os.getpid())
        with pytest.raises(B3dgsError, match=rf"in use by another b3dgs-train \(pid {os.getpid()}\)"):
            with run_dir_lock(d):
                pass
    assert not d.exists()  # nothing was written: the dir goes too
    # a lock file left by a dead process (kill -9) holds no lock: it is taken over
    d.mkdir()
    (d / LOCK_NAME).write_text("999999999\n")
    (d / "keep").write_text("x")
    with run_dir_lock(d):
        assert (d / LOCK_NAME).read_text().strip() == str(os.getpid())
    assert sorted(p.name for p in d.iterdir()) == ["keep"]
    # a run dir that is a file
    with pytest.raises(B3dgsError, match="is a file"):
        with run_dir_lock(d / "keep" / "sub"):
            pass


def test_an_out_folder_takes_one_writer_of_a_command_at_a_time(tmp_path):
    """out= outside a run dir (b3dgs-render, b3dgs-suggest): a second job of the same command into the folder is
    refused in one line naming the holder, and leaves nothing; another command's lock does not block it."""
    from b3dgs.rundir import out_dir_lock
    from b3dgs.suggest import _claim

    out = tmp_path / "renders"
    with out_dir_lock(out, "b3dgs-render"):
        assert (out / ".b3dgs-render.lock").read_text().strip() == str(os.getpid())
        with pytest.raises(B3dgsError, match=rf"^out={out} is in use by another b3dgs-render \(pid {os.getpid()}\)"
                                             r" \(fix: wait for it to finish, or pass another out\)$"):
            with out_dir_lock(out, "b3dgs-render"):
                pass
        with _claim(out, tmp_path / "some_run", ["suggest.json"]):  # suggest's lock is its own
            (out / "suggest.json").write_text("{}")
            with pytest.raises(B3dgsError, match="in use by another b3dgs-suggest"):
                with _claim(out, tmp_path / "some_run", ["suggest.json"]):
                    pass
    assert sorted(p.name for p in out.iterdir()) == ["suggest.json"]  # the lock files go, the written file stays
    with pytest.raises(B3dgsError, match=r"^out=.* is a file \(or lies below one\) \(fix: pass out=PATH to a folder\)$"):
        with out_dir_lock(out / "suggest.json", "b3dgs-render"):
            pass
    fresh = tmp_path / "new"
    with out_dir_lock(fresh, "b3dgs-render"):
        pass
    assert not fresh.exists()  # a refused or empty first job leaves no folder


def test_another_process_holding_the_lock_is_named_and_its_death_frees_it(tmp_path):
    """b3dgs.locks across processes: the holder's pid in the refusal and in run_dir_busy; a killed holder
    (kill -9) leaves a lock file that holds nothing."""
    from b3dgs.rundir import run_dir_busy

    d = tmp_path / "run"
    code = ("import sys, time; from pathlib import Path; from b3dgs.rundir import run_dir_lock\n"
            f"with run_dir_lock(Path({str(d)!r})):\n"
            "    print('held', flush=True); time.sleep(60)\n")
    child = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    try:
        assert child.stdout.readline().strip() == "held"
        assert run_dir_busy(d) == str(child.pid)
        with pytest.raises(B3dgsError, match=rf"in use by another b3dgs-train \(pid {child.pid}\)"):
            with run_dir_lock(d):
                pass
    finally:
        child.send_signal(signal.SIGKILL)
        child.wait(timeout=30)
    assert (d / LOCK_NAME).exists() and run_dir_busy(d) is None
    with run_dir_lock(d):
        assert (d / LOCK_NAME).read_text().strip() == str(os.getpid())


def test_remove_stale_tmp(tmp_path):
    from b3dgs.io import atomic_path
    from b3dgs.rundir import record_written, write_manifest

    write_manifest(tmp_path)
    record_written(tmp_path, ["point_cloud.ply"])
    ours = []
    for name in ("point_cloud.ply", "checkpoints/last.ckpt", "renders/v0.png"):
        with pytest.raises(KeyboardInterrupt), atomic_path(tmp_path / name) as tmp:
            ours.append(tmp)
            shutil.copy(tmp, tmp.with_name("kept-" + tmp.name))  # what a kill -9 leaves (the finally never runs)
            raise KeyboardInterrupt
    for tmp in ours:
        tmp.with_name("kept-" + tmp.name).rename(tmp)
    older = [".point_cloud.ply.ab12cd34.tmp"]  # an older writer's temp of a listed file
    users = [".notes.tmp", "keep.tmp", ".report.md.ab12cd34.tmp", "renders/.my_cut.mp4.tmp"]  # not ours: stay
    for name in older + users:
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / name).write_text("x")
    gone = remove_stale_tmp(tmp_path)
    assert sorted(gone) == sorted(ours + [tmp_path / n for n in older])
    assert all((tmp_path / n).is_file() for n in users)


def test_default_run_dirs_are_unique_per_process():
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        cfg = compose(config_name="train", return_hydra_config=True)
    run_dir = OmegaConf.to_container(cfg.hydra.run, resolve=True)["dir"]
    assert f"_s0_{os.getpid()}-" in run_dir, run_dir
    assert cfg.hydra.output_subdir is None  # .hydra/ is written by b3dgs-train once the run is accepted


def test_concurrent_trainings_on_one_dir_exactly_one_runs(tmp_path):
    """The first training is stopped (SIGSTOP, by its own test hook) at step 1, holding the run dir; the
    second is refused in one line, and leaves nothing; the first then finishes."""
    d = tmp_path / "run"
    first = _train([f"hydra.run.dir={d}", *kill_args(step=1, sig="STOP")])
    _, status = os.waitpid(first.pid, os.WUNTRACED)
    assert os.WIFSTOPPED(status), status
    try:
        before = sorted(str(p.relative_to(d)) for p in d.rglob("*"))
        second = _train([f"hydra.run.dir={d}", "seed=1"])
        out, err = second.communicate(timeout=300)
        assert second.returncode == 2, err[-2000:]
        lines = [ln for ln in err.splitlines() if ln.strip()]
        assert lines == [f"b3dgs-train: error: the run dir {d} is in use by another b3dgs-train (pid {first.pid}) "
                         "(fix: wait for it to finish, or pass another hydra.run.dir)"], err[-2000:]
        assert sorted(str(p.relative_to(d)) for p in d.rglob("*")) == before
    finally:
        os.kill(first.pid, signal.SIGCONT)
    out, err = first.communicate(timeout=300)
    assert first.returncode == 0, err[-2000:]
    assert OmegaConf.load(d / "config.yaml").seed == 0 and (d / "metrics.json").exists()
    assert (d / ".hydra" / "overrides.yaml").exists() and (d / "train.log").exists() and not (d / LOCK_NAME).exists()


def test_refused_run_leaves_no_hydra_files_or_log(tmp_path):
    # an invalid value into a new dir: no dir at all
    d = tmp_path / "new"
    p = _train([f"hydra.run.dir={d}", "data.max_side=0"])
    _, err = p.communicate(timeout=300)
    assert p.returncode == 2 and "data.max_side=0" in err, err[-2000:]
    assert not d.exists()
    # a dir that holds someone else's files (no b3dgs run manifest): untouched
    d = tmp_path / "held"
    d.mkdir()
    (d / "config.yaml").write_text("seed: 0\n")
    p = _train([f"hydra.run.dir={d}"])
    _, err = p.communicate(timeout=300)
    assert p.returncode == 2 and "is not empty and holds no b3dgs run (config.yaml)" in err, err[-2000:]
    assert sorted(x.name for x in d.iterdir()) == ["config.yaml"]


def test_a_kill_right_after_the_log_appears_leaves_a_run_dir_resume_and_overwrite_take(tmp_path):
    """The run dir is claimed, its manifest written atomically, before anything else goes into it: ``kill -9`` right
    after ``train.log`` appears leaves a b3dgs run dir (manifest and log), which ``resume=auto`` and ``overwrite=true``
    both take over (before, the log came first and the folder was refused as someone else's)."""
    import shutil

    from b3dgs.rundir import MANIFEST_NAME

    d = tmp_path / "run"
    p = _train([f"hydra.run.dir={d}", *kill_args(point="log")])
    _, err = p.communicate(timeout=300)
    assert p.returncode == -signal.SIGKILL, err[-2000:]
    names = sorted(x.name for x in d.iterdir())
    assert "train.log" in names and MANIFEST_NAME in names and "config.yaml" not in names, names
    shutil.copytree(d, tmp_path / "run2")
    for run, flag in ((d, "resume=auto"), (tmp_path / "run2", "overwrite=true")):
        p = _train([f"hydra.run.dir={run}", flag])
        _, err = p.communicate(timeout=300)
        assert p.returncode == 0, (flag, err[-2000:])
        assert (run / "metrics.json").exists() and (run / "config.yaml").exists(), flag


@pytest.mark.slow
def test_joblib_multirun_over_a_non_seed_setting_loses_no_run(tmp_path):
    p = subprocess.run([sys.executable, "-m", "b3dgs.train", "-m", "hydra/launcher=joblib", "hydra.launcher.n_jobs=2",
                        "model.sh_degree=0,1", *TINY, f"hydra.sweep.dir={tmp_path}"], capture_output=True, text=True,
                       timeout=600)
    assert p.returncode == 0, p.stderr[-3000:]
    runs = sorted(tmp_path.glob("*/metrics.json"))
    assert len(runs) == 2, [str(x) for x in tmp_path.rglob("*")]
    assert sorted(OmegaConf.load(r.parent / "config.yaml").model.sh_degree for r in runs) == [0, 1]


def test_multirun_with_one_bad_value_runs_the_others(tmp_path):
    p = subprocess.run([sys.executable, "-m", "b3dgs.train", "-m", "seed=-1,1", *TINY, f"hydra.sweep.dir={tmp_path}"],
                       capture_output=True, text=True, timeout=600)
    assert p.returncode == 2, p.stderr[-3000:]
    assert "b3dgs-train: error: job 0: seed=-1 is invalid: it must be an integer in [0, 2^32) (fix: pass seed=0)" \
        in p.stderr.splitlines(), p.stderr[-3000:]
    assert [d.name for d in tmp_path.iterdir() if d.is_dir()] == ["1_synthetic_standard_s1"]  # job 0 left nothing
    assert (tmp_path / "1_synthetic_standard_s1" / "metrics.json").exists()


def test_a_killed_evals_staging_folder_is_removed_and_a_live_ones_kept(tmp_path):
    """b3dgs-eval stages panels in ``.uq-staging.<host>.<pid>.*``: a later eval removes the folder of a process that
    is gone, never a live one's or another host's; ``overwrite=true`` also removes the unnamed ones of older versions
    (issue 46 §9)."""
    import socket

    from b3dgs.rundir import remove_stale_staging, staging_prefix

    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    host = socket.gethostname()
    d = tmp_path / "run"
    p = _train([f"hydra.run.dir={d}"])
    _, err = p.communicate(timeout=300)
    assert p.returncode == 0, err[-2000:]
    names = {"dead": f".uq-staging.{host}.{dead.pid}.k1", "live": staging_prefix() + "k2",
             "other_host": f".uq-staging.elsewhere.{dead.pid}.k3", "legacy": ".uq-staging.q1w2e3r4"}
    for n in names.values():
        (d / n).mkdir(parents=True)
        (d / n / "panel.png").write_bytes(b"x")
    assert [p.name for p in remove_stale_staging(d)] == [names["dead"]]
    assert sorted(p.name for p in d.glob(".uq-staging.*")) == sorted(n for k, n in names.items() if k != "dead")
    # a training that overwrites the folder owns it: the legacy folder goes too, live and other hosts' stay
    p = _train([f"hydra.run.dir={d}", "overwrite=true"])
    _, err = p.communicate(timeout=300)
    assert p.returncode == 0, err[-2000:]
    assert not (d / names["legacy"]).exists()
    assert (d / names["live"]).is_dir() and (d / names["other_host"]).is_dir()

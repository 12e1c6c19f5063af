"""Every command stops on SIGTERM / SIGINT with one line and exit code 128 + the signal, having unwound its ``finally``
blocks (no temp file left, the run dir free for the next command), and the same command then runs to the end
(``b3dgs.signals``; training and b3dgs-process, which save or resume, have their own tests)."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
ENV = {**os.environ, "PYTHONPATH": f"{ROOT}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}
# the command, run with the named function replaced by one that signals its own process at its first call
SELF_SIGNAL = """
import os, signal, sys, importlib
mod, name, sig, prog = sys.argv[1:5]
m = importlib.import_module(mod)
real = getattr(m, name)
def hit(*a, **k):
    os.kill(os.getpid(), getattr(signal, "SIG" + sig))
    return real(*a, **k)
setattr(m, name, hit)
sys.argv = [prog, *sys.argv[5:]]
importlib.import_module({"b3dgs-suggest": "b3dgs.suggest", "b3dgs-eval": "b3dgs.eval"}[prog]).main()
"""


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    d = tmp_path_factory.mktemp("signals") / "run"
    res = subprocess.run([sys.executable, "-m", "b3dgs.train", "data.max_side=32", "+data.n_views=12",
                          "+data.n_points=400", "model.sh_degree=1", "model.sh_increase_every=5", "trainer.max_steps=20",
                          "trainer.eval_every=20", "logger=none", "trainer.enable_progress_bar=false",
                          f"hydra.run.dir={d}"], capture_output=True, text=True, timeout=600, cwd=ROOT, env=ENV)
    assert res.returncode == 0, res.stderr[-3000:]
    return d


@pytest.mark.parametrize("prog,hook,sig,args", [
    ("b3dgs-suggest", ("b3dgs.suggest", "_preview"), "TERM",
     ["n=2", "policy=farthest", "generate.azimuths=6", "generate.elevations=2", "preview_max_side=16"]),
    ("b3dgs-eval", ("b3dgs.uq.metrics", "evaluate_view"), "INT", ["uq=[proxy]", "uq.samples=2", "max_views=1"]),
])
def test_a_signal_mid_command_is_one_line_its_exit_code_and_a_clean_rerun(run, prog, hook, sig, args):
    argv = [f"run={run}", *args]
    res = subprocess.run([sys.executable, "-c", SELF_SIGNAL, *hook, sig, prog, *argv], capture_output=True, text=True,
                         timeout=600, cwd=run.parent, env=ENV)  # b3dgs-eval's job log goes below cwd, not the checkout
    ours = [ln for ln in res.stderr.splitlines() if ln.startswith(f"{prog}:")]
    assert res.returncode == {"TERM": 143, "INT": 130}[sig], res.stderr[-3000:]
    assert ours == [f"{prog}: stopped by SIG{sig}; run the same command again"], res.stderr[-3000:]
    assert "Traceback" not in res.stderr
    assert not [p for p in run.rglob("*.tmp")], "a temp file was left behind"
    again = subprocess.run([sys.executable, "-m", prog.replace("b3dgs-", "b3dgs."), *argv], capture_output=True,
                           text=True, timeout=600, cwd=run.parent, env=ENV)
    assert again.returncode == 0, again.stderr[-3000:]


def test_run_cli_ends_an_interrupted_command_with_its_own_advice(capsys):
    """The one line names what to do next: b3dgs-train's says resume=auto (a sweep stopped between its jobs)."""
    import signal

    from b3dgs.errors import run_cli
    from b3dgs.signals import Interrupted

    def stopped():
        raise Interrupted(signal.SIGTERM)

    with pytest.raises(SystemExit) as e:
        run_cli("b3dgs-x", stopped, argv=[], again="run it with resume=auto")
    assert e.value.code == 143
    assert capsys.readouterr().err == "b3dgs-x: stopped by SIGTERM; run it with resume=auto\n"
    src = (ROOT / "b3dgs" / "train.py").read_text()
    assert 'again="run the same command with resume=auto' in src


def test_b3dgs_lpips_stops_on_a_signal_with_one_line(monkeypatch, capsys):
    import signal
    import threading

    from b3dgs.metrics import lpips

    if threading.current_thread() is not threading.main_thread():
        pytest.skip("signal handlers live in the main thread, and this test runs in another")

    def build(*a):
        os.kill(os.getpid(), signal.SIGTERM)  # handled: raises b3dgs.signals.Interrupted here
        raise AssertionError("the signal did not stop it")

    monkeypatch.setattr(lpips, "build_weights", build)
    assert lpips.build_weights_cli([]) == 143
    assert capsys.readouterr().err == "b3dgs-lpips: stopped by SIGTERM; run the same command again\n"

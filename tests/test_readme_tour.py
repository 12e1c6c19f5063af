"""README.md's commands run as written, in order (issue 44 §6), on a fresh clone (issue 52): the tour block is parsed
from README.md (the README is the single source: a changed line there is a changed test), and every line runs in one
fresh folder after the ones before it, on the smoke protocol. What the test adds to a line is one explicit mapping,
``SMOKE`` below: overrides appended for speed (Hydra's later value wins), nothing else. Every README bash block is
accounted for:

* "A tour": every line runs, in order, in a temporary folder that holds only ``photos/``: ten photos the test renders
  (tests/test_process.py's noise-textured views of b3dgs.data.synthetic's world, which SfM registers), no poses. Nothing
  of ``../shared`` is used, as on a fresh clone: the data root (``$B3DGS_DATA``) is an empty temporary folder, and
  ``b3dgs-data get fox`` really downloads, extracts and lays out fox, from a loopback server because this machine has
  no internet (tests/loopback.py: the shipped registry's fox entry with only its host replaced, through
  ``$B3DGS_DATA_REGISTRY``, serving 67 frames rendered from the synthetic world with their true poses). ``b3dgs-view``
  serves until stopped: it is started, must answer HTTP at the URL it prints, and is then stopped (no browser is
  needed for that; tests/test_viewer.py drives one). No line needs a GPU (``renderer=auto`` picks the CPU).
* "Two commands": ``bash scripts/setup.sh`` is not run (it installs packages from the network; tests/test_install.py
  checks the wheel) and neither is ``python -m pytest`` (the suite this test is part of); the ``b3dgs-train`` after
  the set-up runs, first, with the same mapping.
* The campaign block (``python -m bench.studies ...``) runs from the repository root (``bench/`` is not installed) and
  takes days at its defaults, so it is not part of the tour; it runs here with ``CAMPAIGN_SMOKE`` appended (one
  synthetic scene, NIW only, 20 steps, its outputs and archive in a temporary folder, never bench/results/).
"""
import json
import os
import queue
import re
import shlex
import subprocess
import sys
import threading
import time
import tomllib
import urllib.request
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
ENV = {**{k: v for k, v in os.environ.items() if k != "HYDRA_FULL_ERROR"},
       "PYTHONPATH": f"{ROOT}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}
#: a fresh clone's environment has no data root of its own: the test sets $B3DGS_DATA (and the registry) itself
FRESH = {k: v for k, v in ENV.items() if k not in ("B3DGS_SHARED", "B3DGS_DATA", "B3DGS_DATA_REGISTRY")}
SCRIPTS = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["scripts"]  # b3dgs-x -> module:function

# ---------------------------------------------------------------------------------------------- the one mapping
# A README line -> the line the test runs: the line as written with these overrides appended, for speed only (fewer
# steps, pixels, samples, frames, policies, seeds of the active study, pruning rows). Keyed by the program (and the
# study for b3dgs-study); a program the README uses that is missing here fails test_every_readme_block_is_accounted_for.
TRAIN = ["trainer.max_steps=10", "trainer.eval_every=10", "trainer.checkpoint_every=10", "data.max_side=64",
         "model.init_num_random=2000",  # fox has no SfM points: 2000 random Gaussians instead of 20000
         "model.sh_increase_every=3"]  # SH degree 3 by step 9, as a full run has it: b3dgs-suggest's info_gain needs >= 1
SMOKE = {
    "b3dgs-data": [],  # downloads fox from the loopback server into the empty data root
    "b3dgs-process": [],  # the ten 160 px photos take seconds
    "b3dgs-train": TRAIN,
    "b3dgs-eval": ["uq.samples=4", "max_views=2"],
    "b3dgs-suggest": ["generate.azimuths=8", "generate.elevations=2", "targets.azimuths=6", "score_max_side=16",
                      "preview_max_side=32"],
    "b3dgs-view": ["port=0"],  # any free port; started, asked over HTTP, stopped
    "b3dgs-render": ["frames=4"],
    "b3dgs-export": [],
    "b3dgs-report": [],
    "b3dgs-study compress": ["strategies=[opacity,posterior_importance]", "keep=[0.5]", "finetune_steps=5",
                             "finetune_control=false",
                             "score_max_side=16", "progress_bar=false", "plots=false"],
    "b3dgs-study active": ["seeds=[0]", "policies=[uniform,native]", "family_baselines=[]", "oracle=false",
                           "plots=false", "trainer.max_steps=10", "data.max_side=64", "acquisition.score_max_side=16",
                           "model_overrides=['model.init_num_random=2000']",
                           "+policy_settings.native.regime.native.samples=4"],
}
CAMPAIGN_SMOKE = ["--scenes", "synthetic", "--seeds", "0", "--methods", "niw", "--max-steps", "20",
                  "--uq-samples", "4", "--extra", "data.max_side=32", "renderer=cpu",
                  "trainer.eval_every=20"]  # + --out/--report in tmp; one curve point, not one a step (no result changes)
NOT_RUN = {  # "Two commands" lines that are not run, and why
    "bash scripts/setup.sh": "installs packages from the network (tests/test_install.py checks the wheel)",
    "python -m pytest": "the suite this test belongs to",
    "python -m venv": "makes a virtual environment (the suite already runs in one it needs)",
    "source .venv/bin/activate": "activates that environment",
}
VIEW_TIMEOUT_S = 300


# ---------------------------------------------------------------------------------------------- README's blocks
def bash_blocks(text: str) -> dict[str, list[str]]:
    """The ```bash blocks of README.md by the heading above them (a second block under one heading: "<heading> 2"),
    each as its command lines (blank lines and whole-line comments dropped; ``&&`` splits a line)."""
    out, heading = {}, ""
    for m in re.finditer(r"^(#+ [^\n]*)$|^```bash\n(.*?)^```$", text, re.M | re.S):
        if m.group(1):
            heading = m.group(1).lstrip("#").strip()
            continue
        lines = [part.strip() for ln in m.group(2).splitlines() if ln.strip() and not ln.lstrip().startswith("#")
                 for part in ln.split(" && ")]
        key = heading if heading not in out else f"{heading} 2"
        out[key] = lines
    return out


BLOCKS = bash_blocks((ROOT / "README.md").read_text())


def program(argv: list[str]) -> str:
    return f"{argv[0]} {argv[1]}" if argv[0] == "b3dgs-study" else argv[0]


def smoke(line: str) -> list[str]:
    """The README line as argv (shell quoting and comments as bash reads them), with its SMOKE overrides."""
    argv = shlex.split(line, comments=True)
    return argv + SMOKE[program(argv)]


def python_argv(argv: list[str]) -> list[str]:
    """A b3dgs console script's argv as this interpreter runs it (the entry point pyproject.toml names), so that the
    checkout under test runs whatever is installed."""
    module, func = SCRIPTS[argv[0]].split(":")
    code = f"import sys; sys.argv[0] = {argv[0]!r}; from {module} import {func}; sys.exit({func}())"
    return [sys.executable, "-c", code, *argv[1:]]


def overrides(argv: list[str]) -> dict[str, str]:
    return dict(a.split("=", 1) for a in argv[1:] if "=" in a and not a.startswith("-"))


# ---------------------------------------------------------------------------------------------- what each line made
def check_made(argv: list[str], cwd: Path, stdout: str, env: dict) -> str:
    """What the line says it makes is there; returns a short note of it."""
    o, prog = overrides(argv), program(argv)
    if prog == "b3dgs-data":  # fetched into the empty data root, laid out as the registry says
        from b3dgs import datasets

        folder = Path(env["B3DGS_DATA"]) / argv[-1]
        assert f"{argv[-1]}: ready in {folder}; train it: b3dgs-train scene={argv[-1]}" in stdout.splitlines(), stdout
        assert datasets.missing(datasets.load_registry(env[datasets.REGISTRY_ENV])[argv[-1]], folder) == []
        return f"{folder}: {len(list((folder / 'images').iterdir()))} images"
    if prog == "b3dgs-process":
        out = cwd / o["out"]
        assert (out / "sparse" / "0" / "images.bin").is_file()
        assert (out / "conf" / "scene" / f"{out.name}.yaml").is_file()
        assert any(ln.startswith(f"train it: b3dgs-train scene={out.name} ") for ln in stdout.splitlines()), stdout
        return f"{out}: {len(list((out / 'images').iterdir()))} images"
    if prog == "b3dgs-train":
        if "-m" in argv:
            values = [v for k, v in o.items() if not k.startswith("hydra.") and "," in v and "[" not in v]
            jobs = int(np.prod([len(v.split(",")) for v in values]))
            runs = sorted((cwd / o["hydra.sweep.dir"]).glob("*/metrics.json"))
            assert len(runs) == jobs and (cwd / o["hydra.sweep.dir"] / "summary.md").is_file(), runs
            return f"{jobs} sweep runs"
        done = re.findall(r"Done: .* -> (\S+)$", stdout, re.M)
        run = cwd / o["hydra.run.dir"] if "hydra.run.dir" in o else Path(done[-1])
        assert json.loads((run / "metrics.json").read_text())["num_gaussians"] > 0, run
        return str(run.relative_to(cwd))
    if prog == "b3dgs-eval":
        uq = json.loads((cwd / o["run"] / "uq.json").read_text())
        assert set(o["uq"].strip("[]").split(",")) <= set(uq), sorted(uq)
        return f"uq.json: {sorted(uq)}"
    if prog == "b3dgs-suggest":
        rec = json.loads((cwd / o["run"] / "suggest" / "suggest.json").read_text())
        assert rec["policy"] == "info_gain" and rec["returned"] >= 1, rec["candidates"]
        assert not rec["information_map"].startswith("no information map"), rec["information_map"]
        assert all((cwd / o["run"] / "suggest" / s["preview"]).is_file() for s in rec["suggestions"])
        return f"{rec['returned']} suggestions"
    if prog == "b3dgs-render":
        mp4 = cwd / o["run"] / "render" / o["path"] / f"{o['path']}.mp4"
        assert mp4.stat().st_size > 1000, mp4
        return str(mp4)
    if prog == "b3dgs-export":
        out = cwd / o["run"] / "export" / {"splat": "scene.splat", "ply": "point_cloud.ply"}.get(o["format"], "3dgs")
        assert out.exists(), out
        return str(out)
    if prog == "b3dgs-report":
        md = (cwd / o["out"] / "report.md").read_text()
        assert "Canonical benchmark" in md and "Paired analysis" in md, md[:2000]
        return f"{o['out']}/report.md"
    if prog == "b3dgs-study compress":
        s = json.loads((cwd / o.get("out_dir", "outputs/compression") / "compression.json").read_text())
        assert s["pairs"], s
        return "compression.json"
    if prog == "b3dgs-study active":
        assert (cwd / o.get("out_dir", "outputs/study") / o["scene"] / "study.md").is_file()
        return "study.md"
    raise AssertionError(f"no check for {prog}")


def serve_and_stop(argv: list[str], cwd: Path, env: dict) -> str:
    """b3dgs-view: started, it must print its URL and answer it over HTTP; then it is stopped (SIGTERM)."""
    proc = subprocess.Popen(python_argv(argv), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=cwd,
                            env=env)
    lines: queue.Queue = queue.Queue()
    threading.Thread(target=lambda: [lines.put(ln) for ln in proc.stdout], daemon=True).start()
    seen, url, deadline = [], None, time.monotonic() + VIEW_TIMEOUT_S
    try:
        while url is None and time.monotonic() < deadline and proc.poll() is None:
            try:
                seen.append(lines.get(timeout=1))
            except queue.Empty:
                continue
            found = re.search(r" at (http://127\.0\.0\.1:\d+)\s", seen[-1])
            url = found.group(1) if found else None
        assert url is not None, "b3dgs-view printed no URL:\n" + "".join(seen[-30:])
        with urllib.request.urlopen(url + "/", timeout=60) as res:
            page = res.read().decode(errors="replace")
            assert res.status == 200 and "<html" in page.lower(), page[:500]
        return f"answered at {url}"
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=60)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


# ---------------------------------------------------------------------------------------------- the tests
def test_every_readme_block_is_accounted_for():
    """Every README bash block is the tour (run), "Two commands" (the set-up and the suite not run, b3dgs-train run)
    or the campaign (run in smoke form); every tour program has its SMOKE entry; the tour's b3dgs commands are
    installed entry points."""
    assert set(BLOCKS) == {"Two commands", "A tour", "A tour 2"}, sorted(BLOCKS)
    two = BLOCKS["Two commands"]
    assert "b3dgs-train" in two, two
    assert all(ln == "b3dgs-train" or any(ln.startswith(k) for k in NOT_RUN) for ln in two), two
    tour = BLOCKS["A tour"]
    assert len(tour) >= 10, tour
    for line in tour:
        argv = shlex.split(line, comments=True)
        assert argv[0] in SCRIPTS and program(argv) in SMOKE, line
        positional = argv[1:] if argv[0] == "b3dgs-data" else ("active", "compress")  # its argparse subcommands
        assert all(a.startswith("-m") or "=" in a for a in argv[1:] if a not in positional), line
    assert [shlex.split(ln, comments=True)[:3] for ln in BLOCKS["A tour 2"]] == [["python", "-m", "bench.studies"]]


@pytest.mark.slow
def test_a_fresh_clone_gets_fox_and_runs_the_tour_as_written_in_order(tmp_path):
    """Every line of the tour, in order, in one folder, with nothing of ../shared: an empty data root that
    ``b3dgs-data get fox`` fills from the loopback server (this machine has no internet) and photos the test makes;
    each line must exit 0 and leave what it says it makes."""
    from b3dgs import datasets
    from tests import loopback
    from tests.test_process import synthetic_photos

    cwd = tmp_path / "tour"
    synthetic_photos(cwd / "photos")
    lines = [ln for ln in BLOCKS["Two commands"] if ln == "b3dgs-train"] + BLOCKS["A tour"]
    assert ["b3dgs-data", "get", "fox"] in [shlex.split(ln, comments=True)[:3] for ln in lines], "no get fox"
    times = []
    with loopback.serve() as srv:
        env = {**FRESH, "B3DGS_DATA": str(tmp_path / "data"),
               datasets.REGISTRY_ENV: str(loopback.registry_on(srv, tmp_path / "registry.yaml",
                                                               loopback.synthetic_fox().__getitem__))}
        for line in lines:
            argv = smoke(line)
            t0 = time.perf_counter()
            if argv[0] == "b3dgs-view":
                note = serve_and_stop(argv, cwd, env)
            else:
                res = subprocess.run(python_argv(argv), capture_output=True, text=True, timeout=1800, cwd=cwd,
                                     env=env)
                assert res.returncode == 0, f"{line}\n-> {shlex.join(argv)}\n{res.stdout[-2000:]}\n{res.stderr[-3000:]}"
                note = check_made(argv, cwd, res.stdout + res.stderr, env)
            times.append((time.perf_counter() - t0, line, note))
        assert sum(1 for path, _ in srv.log if path.endswith(".jpg")) == len(loopback.frame_names())
    print("\n".join(f"{s:6.1f} s  {line}   [{note}]" for s, line, note in times))
    print(f"{sum(t[0] for t in times):.1f} s in all")


@pytest.mark.slow
def test_the_campaign_line_runs_in_smoke_form(tmp_path):
    """The README's campaign line, with CAMPAIGN_SMOKE and its outputs in tmp_path, from the repository root."""
    (line,) = BLOCKS["A tour 2"]
    out = tmp_path / "bench"
    argv = shlex.split(line, comments=True) + CAMPAIGN_SMOKE + ["--out", str(out), "--report", str(out / "report")]
    before = subprocess.run(["git", "status", "--porcelain", "--", "bench/results"], capture_output=True, text=True,
                            cwd=ROOT).stdout
    res = subprocess.run([sys.executable, *argv[1:]], capture_output=True, text=True, timeout=1800, cwd=ROOT, env=ENV)
    assert res.returncode == 0, res.stdout[-2000:] + res.stderr[-3000:]
    assert {"native", "proxy"} <= set(json.loads((out / "synthetic" / "niw" / "s0" / "uq.json").read_text()))
    assert "Canonical benchmark" in (out / "report" / "report.md").read_text()
    after = subprocess.run(["git", "status", "--porcelain", "--", "bench/results"], capture_output=True, text=True,
                           cwd=ROOT).stdout
    assert after == before  # nothing written into the committed results

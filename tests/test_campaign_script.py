"""scripts/campaign.sh: valid shell, and a wrong step is a one-line error naming the fix (no work folder made)."""
import os
import shutil
import subprocess
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "campaign.sh"


@pytest.mark.skipif(shutil.which("bash") is None, reason="needs bash")
def test_campaign_script_parses_and_rejects_unknown_step(tmp_path):
    assert subprocess.run(["bash", "-n", str(SCRIPT)]).returncode == 0
    env = dict(os.environ, CAMPAIGN=str(tmp_path / "camp"))
    r = subprocess.run(["bash", str(SCRIPT), "activ"], env=env, capture_output=True, text=True)
    assert r.returncode == 2
    assert "unknown step 'activ'" in r.stderr and "fix:" in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "camp").exists()


def test_campaign_script_is_parsed_whole_before_it_runs():
    """Bash reads a script as it executes: an edit (git pull) during an hours-long campaign would change the commands
    still to come. The body is one brace group ending in exit, which bash parses completely first."""
    lines = [ln for ln in SCRIPT.read_text().splitlines() if ln.strip()]
    body = lines[lines.index("{"):]
    assert body[-2:] == ["exit 0", "}"]


def test_checkout_steps_import_the_checkouts_code():
    """PYTHONPATH is exported as the frozen worktree's: a step that runs this checkout's scripts (tables, claims) must
    set it back, or it imports the pinned code (the campaign of 2026-11-26 failed at claims.py that way)."""
    text = SCRIPT.read_text()
    assert 'export PYTHONPATH="$CODE"' in text
    steps = [ln for ln in text.splitlines() if 'cd "$ROOT" &&' in ln and "python" in ln]
    assert len(steps) >= 3 and all('PYTHONPATH="$ROOT" python' in ln for ln in steps), steps

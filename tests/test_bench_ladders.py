"""bench/active_view.py: the budget ladder of a scene follows its train-view count (issue 21)."""
from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
active_view = pytest.importorskip("active_view")


@pytest.mark.parametrize("n,ladder", [(17, "8to16"), (21, "8to16"), (39, "8to16"), (40, "16to32"), (86, "16to32")])
def test_ladder_of(n, ladder):
    assert active_view.ladder_of(n) == ladder
    init, acq = active_view.LADDERS[ladder]
    assert init + acq < n  # candidates leave a choice


def test_compression_archive_round_trip(tmp_path):
    """bench/compression.py: finished rows, bases and meta reach the archive; a fresh out dir gets them back, and a
    restore never overwrites a file already there (only_missing)."""
    compression = pytest.importorskip("compression")
    out, arch, fresh = tmp_path / "out", tmp_path / "arch", tmp_path / "fresh"
    files = {"meta.json": "{}", "fox/s0/base.json": '{"b": 1}', "fox/s0/opacity_k55/result.json": '{"psnr": 1}',
             "fox/s0/scores/opacity.pt": "not archived", "fox/s0/opacity_k10/partial.tmp": "not archived"}
    for rel, text in files.items():
        (out / rel).parent.mkdir(parents=True, exist_ok=True)
        (out / rel).write_text(text)
    assert compression.sync(out, arch) == 3
    assert sorted(str(p) for p in compression.archived_files(arch)) == [
        "fox/s0/base.json", "fox/s0/opacity_k55/result.json", "meta.json"]
    assert compression.sync(out, arch) == 0  # unchanged files are not copied again
    (fresh / "fox" / "s0").mkdir(parents=True)
    (fresh / "fox" / "s0" / "base.json").write_text('{"b": 2}')
    assert compression.sync(arch, fresh, only_missing=True) == 2
    assert (fresh / "fox" / "s0" / "base.json").read_text() == '{"b": 2}'
    assert (fresh / "fox" / "s0" / "opacity_k55" / "result.json").read_text() == '{"psnr": 1}'
    assert not list(arch.rglob(".*"))  # no temporary files left behind

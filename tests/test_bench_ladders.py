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

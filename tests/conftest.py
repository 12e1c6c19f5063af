"""Shared test settings: where the read-only shared material lives (``../shared`` beside the repo)."""
import os
from pathlib import Path

import pytest

SHARED = Path(os.environ.get("B3DGS_SHARED", Path(__file__).resolve().parents[2] / "shared"))


@pytest.fixture
def gsplat_cpu():
    """gsplat's compiled backend replaced by the CPU emulation of ``tests/gsplat_cpu.py`` for one test, so
    ``renderer=gsplat renderer.device_name=cpu`` runs gsplat's own Python on the CPU; the real backend (if
    any) comes back afterwards. Skips only where gsplat is not installed (``pip install -e ".[test]"``)."""
    pytest.importorskip("gsplat", reason='gsplat is not installed (fix: pip install -e ".[test]")')
    from tests import gsplat_cpu as emulation

    previous = emulation.install()
    try:
        yield emulation
    finally:
        emulation.uninstall(previous)

"""Shared test settings: where the read-only shared material lives (``../shared`` beside the repo)."""
import os
from pathlib import Path

SHARED = Path(os.environ.get("B3DGS_SHARED", Path(__file__).resolve().parents[2] / "shared"))

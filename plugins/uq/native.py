"""Native posterior uncertainty: re-render posterior samples (paper Eq. 4)."""
from __future__ import annotations

from dataclasses import dataclass

from b3dgs.uq.native import NativeRegime


@dataclass
class NativeUQ(NativeRegime):
    """``uq=native`` (conf/uq/native.yaml): :class:`b3dgs.uq.native.NativeRegime`, var = u_p + σ̂²."""

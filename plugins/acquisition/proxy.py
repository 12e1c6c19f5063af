"""Proxy: mean position-jitter uncertainty (``plugins/uq/proxy.py``) of the phase-1 model."""
from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from b3dgs.acquisition import RegimePolicy


@dataclass
class ProxyPolicy(RegimePolicy):
    """Score = mean over pixels of the proxy u_p (S centre-jittered re-renders) of the ``regime``,
    :class:`b3dgs_plugins.uq.proxy.ProxyUQ` composed from conf/uq/proxy.yaml."""

    no_conditioning: ClassVar[str] = ("the jitter has one fixed scale for every Gaussian and no posterior: a view "
                                      "acquired without its image changes nothing the score depends on")

    family: str = "niw"

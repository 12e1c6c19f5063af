"""Scene loading: COLMAP, transforms.json, LLFF and the procedural synthetic scene.

``b3dgs.data.images`` is imported first so that PIL is loaded before anything could import
pycolmap (which only ``b3dgs-process`` imports, lazily; the COLMAP loader reads models with NumPy).
"""
from __future__ import annotations

from typing import Any

from b3dgs.data.images import load_image, save_png  # noqa: F401  (first: PIL before pycolmap)
from b3dgs.data.scene import SCENE_KINDS, compute_bounds, load_scene  # noqa: F401

__all__ = ["SCENE_KINDS", "SceneDataModule", "compute_bounds", "load_image", "load_scene", "save_png"]


def __getattr__(name: str) -> Any:  # lazy: importing lightning is slow
    if name == "SceneDataModule":
        from b3dgs.data.datamodule import SceneDataModule

        return SceneDataModule
    raise AttributeError(f"module 'b3dgs.data' has no attribute {name!r}")  # protocol: a module's __getattr__

"""Image reading and PNG writing, both through PIL.

Import-order hazard
-------------------
On this project's machines, importing ``pycolmap`` *before* PIL once made PIL's PNG encoder abort
the whole process (``free(): invalid pointer`` inside zlib's ``deflateEnd``: two zlib builds
clashing). This module imports ``PIL.Image``, ``PIL.PngImagePlugin`` and PIL's C core ``PIL._imaging``
at import time, and every b3dgs module that touches pycolmap imports this module first and only
imports ``pycolmap`` lazily, inside the function that needs it (see :func:`import_pycolmap`).
``tests/test_data.py::test_import_order_save_png`` writes and reads a PNG through PIL after either
import order (matplotlib, too, saves its PNGs through PIL in the same processes).

That ordering cannot help a user who imports pycolmap first: pycolmap 4.1.x and 4.2.x export their own
static zlib, and when ``libz.so.1`` is loaded after them (a fresh venv: nothing imported ``zlib`` before)
its internal calls bind to pycolmap's copy, so every deflate user aborts, Python's own
``zlib.compress`` included. pycolmap 4.0.x does not, so ``pyproject.toml`` pins ``pycolmap<4.1``.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Optional, Sequence

import numpy as np

# Import PIL (and its C core) eagerly, before anything can import pycolmap through b3dgs.
import PIL.PngImagePlugin  # noqa: F401,E402
from PIL import _imaging  # noqa: F401,E402
from PIL import Image, UnidentifiedImageError

from b3dgs.errors import B3dgsError
from b3dgs.io import atomic_path
from b3dgs.types import fit_size

IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".PNG", ".JPG", ".JPEG", ".bmp", ".tif", ".tiff", ".webp")
_MISSING_IMAGE_FIX = "restore the image, or correct the scene files that name it"
_UNREADABLE_FIX = "replace the file with a readable image (PNG or JPEG), or remove it and its camera from the scene"

__all__ = ["IMAGE_EXTENSIONS", "encode_png", "image_folders", "image_size", "import_pycolmap", "list_images",
           "load_image", "save_png"]

def image_folders(root: str | os.PathLike) -> list[str]:
    """The names of the folders directly inside ``root`` that hold image files, sorted (``images``, ``images_2``)."""
    root = Path(root)
    if not root.is_dir():
        return []
    return sorted(d.name for d in root.iterdir() if d.is_dir() and not d.name.startswith(".")
                  and any(f.suffix in IMAGE_EXTENSIONS for f in d.iterdir() if f.is_file()))


def import_pycolmap() -> Any:
    """Import and return ``pycolmap``; PIL (and its PNG plugin) is loaded first, by this module's imports."""
    try:
        import pycolmap
    except ImportError as e:  # pragma: no cover - pycolmap is a dependency (for b3dgs-process)
        raise B3dgsError("b3dgs-process (SfM) needs pycolmap, which is not installed",
                         'pip install "pycolmap<4.1"') from e
    return pycolmap


def list_images(folder: str | os.PathLike) -> list[Path]:
    """Image files directly inside ``folder``, sorted by name (hidden files skipped)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise B3dgsError(f"image folder {folder} does not exist", "pass the scene folder that holds it as data.path, "
                         "or name the image folder with data.images_dir")
    return sorted(
        p for p in folder.iterdir() if p.is_file() and not p.name.startswith(".") and p.suffix in IMAGE_EXTENSIONS
    )


def image_size(path: str | os.PathLike) -> tuple[int, int]:
    """(width, height) of an image file, reading only its header."""
    path = Path(path)
    if not path.is_file():
        raise B3dgsError(f"image file {path} does not exist", _MISSING_IMAGE_FIX)
    try:
        with Image.open(path) as im:
            return int(im.width), int(im.height)
    except (UnidentifiedImageError, OSError, ValueError) as e:
        raise B3dgsError(f"Cannot read image {path}: {e}", _UNREADABLE_FIX) from e


def _to_float_rgb(im: Image.Image, background: Sequence[float]) -> np.ndarray:
    """Decode a PIL image to float32 (H, W, 3) in [0, 1], compositing alpha over ``background``."""
    mode = im.mode
    if mode in ("I;16", "I;16B", "I;16L", "I", "F"):  # gray; 16-bit by the bit depth, never by the image's maximum
        a = np.asarray(im, dtype=np.float32) / (1.0 if mode == "F" else 65535.0)
        return np.repeat(np.clip(a, 0, 1)[..., None], 3, axis=2)
    if mode in ("RGBA", "LA", "PA", "RGBa", "La") or (mode == "P" and "transparency" in im.info):
        a = np.asarray(im.convert("RGBA"), dtype=np.float32) / 255.0
        rgb, alpha = a[..., :3], a[..., 3:4]
        bg = np.asarray(background, dtype=np.float32).reshape(1, 1, 3)
        return np.ascontiguousarray(rgb * alpha + bg * (1.0 - alpha), dtype=np.float32)
    if mode != "RGB":
        im = im.convert("RGB")
    return np.asarray(im, dtype=np.float32) / 255.0


def _resize_float(img: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Area (box-filter) resize of a float32 (H, W, 3) image to ``size`` = (w, h) with PIL."""
    chans = [
        np.asarray(Image.fromarray(np.ascontiguousarray(img[..., c])).resize(size, Image.Resampling.BOX))
        for c in range(img.shape[2])
    ]
    return np.clip(np.stack(chans, axis=-1), 0.0, 1.0).astype(np.float32)


def load_image(
    path: str | os.PathLike,
    max_side: Optional[int] = None,
    *,
    size: Optional[tuple[int, int]] = None,
    expected_size: Optional[tuple[int, int]] = None,
    background: Sequence[float] = (0.0, 0.0, 0.0),
) -> np.ndarray:
    """Decode an image once to float32 (H, W, 3) in [0, 1] at the target resolution: ``size`` (w, h), else downscaled
    (area filter, never up) so that the longest side is <= ``max_side``; transparent pixels (RGBA, LA, P+transparency)
    composited over ``background`` (RGB in [0, 1]). Raises :class:`B3dgsError` naming the file when it is missing or
    unreadable, or when its native (w, h) is not ``expected_size``."""
    path = Path(path)
    if not path.is_file():
        raise B3dgsError(f"image file {path} does not exist", _MISSING_IMAGE_FIX)
    try:
        with Image.open(path) as im:
            native = (int(im.width), int(im.height))
            if expected_size is not None and tuple(int(v) for v in expected_size) != native:
                raise B3dgsError(f"Image {path} is {native[0]}x{native[1]} but its camera says "
                                 f"{int(expected_size[0])}x{int(expected_size[1])} (w x h)",
                                 fix="restore the image at the size its camera was calibrated for, or recompute "
                                     "the poses on the images as they are (b3dgs-process)")
            im.load()
            out_size = tuple(size) if size is not None else fit_size(native[0], native[1], max_side)
            if out_size == native and im.mode == "RGB":
                return np.asarray(im, dtype=np.float32) / 255.0
            if out_size != native and im.mode == "RGB":
                # Area filter on 8-bit data, then convert (fast path for the common case).
                return np.asarray(im.resize(out_size, Image.Resampling.BOX), dtype=np.float32) / 255.0
            img = _to_float_rgb(im, background)
    except B3dgsError:  # a ValueError, not to be reported as an unreadable file
        raise
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError, Image.DecompressionBombError) as e:
        raise B3dgsError(f"Cannot read image {path}: {type(e).__name__}: {e}", _UNREADABLE_FIX) from e
    if out_size != native:
        img = _resize_float(img, out_size)
    return np.ascontiguousarray(img, dtype=np.float32)


# -------------------------------------------------------------------------------- PNG writing (PIL)


def _to_pil_array(array: Any) -> np.ndarray:
    """``array`` as what PIL writes: uint8 (H, W[, 3|4]) from floats in [0, 1] (clipped, rounded), bools or
    uint8, or uint16 (H, W) as a 16-bit gray image."""
    if hasattr(array, "detach"):  # torch.Tensor, without importing torch here
        array = array.detach().cpu().numpy()
    a = np.asarray(array)
    if a.ndim == 3 and a.shape[2] == 1:
        a = a[..., 0]
    if a.ndim not in (2, 3) or (a.ndim == 3 and a.shape[2] not in (3, 4)):
        raise B3dgsError(f"save_png expects (H, W), (H, W, 1), (H, W, 3) or (H, W, 4); got shape {a.shape}",
                         fix="pass an image array of shape (H, W), (H, W, 1), (H, W, 3) or (H, W, 4)")
    if a.shape[0] == 0 or a.shape[1] == 0:
        raise B3dgsError(f"save_png: empty image of shape {a.shape}",
                         fix="pass an image with at least one pixel (H, W >= 1)")
    if a.dtype == np.uint8 or (a.dtype == np.uint16 and a.ndim == 2):
        return np.ascontiguousarray(a)
    if a.dtype == np.bool_:
        return a.astype(np.uint8) * 255
    if np.issubdtype(a.dtype, np.integer):
        raise B3dgsError(f"save_png: integer images must be uint8 (or uint16 gray), got {a.dtype} of shape {a.shape}",
                         fix="pass floats in [0, 1], uint8, bool, or a uint16 gray (H, W) image; convert other "
                             "integers with .astype(np.uint8)")
    a = a.astype(np.float64)
    if not np.isfinite(a).all():
        raise B3dgsError("save_png: image contains NaN/Inf",
                         fix="pass finite pixel values; replace NaN with numpy.nan_to_num(image) first")
    return np.clip(np.round(a * 255.0), 0, 255).astype(np.uint8)


def encode_png(array: Any, compress_level: int = 6) -> bytes:
    """PNG bytes of an image (PIL's encoder): numpy array or torch tensor, (H, W) gray, (H, W, 3) RGB or
    (H, W, 4) RGBA; floats are taken as [0, 1] (clipped, rounded to 8 bit), uint8 as is, uint16 (H, W) as
    16-bit gray."""
    import io

    a = _to_pil_array(array)
    buf = io.BytesIO()
    Image.fromarray(a).save(buf, format="PNG", compress_level=int(compress_level))
    return buf.getvalue()


def save_png(path: str | os.PathLike, image: Any, compress_level: int = 6) -> Path:
    """Write ``image`` (numpy/torch, (H, W[, 1|3|4]), float in [0, 1] or uint8; uint16 (H, W) as 16-bit gray)
    as a PNG (:func:`encode_png`), atomically: the file is written to a temporary name in the same folder and
    renamed into place (:func:`b3dgs.io.atomic_path`), so a reader never sees a partial file."""
    data = encode_png(image, compress_level)
    path = Path(path)
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
    return path

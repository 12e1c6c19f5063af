"""LLFF scenes: ``poses_bounds.npy`` + ``images/``.

``poses_bounds.npy`` is (N, 17), one row per image file of ``images/`` in sorted name order: a row-major 3x5 matrix
``[R | t | hwf]`` then ``near, far``. ``R``'s columns are the camera's axes in world coordinates in LLFF's ``[down,
right, back]`` order (OpenCV's camera-to-world is ``[col1, col0, -col2]``), ``t`` the camera centre, ``hwf = (height,
width, focal)`` in pixels of the full-resolution images. Images that are a uniformly downscaled copy (e.g.
``images_4``) get the focal length scaled by the per-axis ratio; any other size mismatch raises. The principal point
is the image centre.

No NDC: the cameras are used as they are (perspective rasterisation in the normalised frame of
:func:`b3dgs.data.scene.preprocess`, as 3DGS does); ``near, far`` (which must satisfy 0 < near < far) only set LLFF's
focus depth, the centre of the random-initialisation box when the optical axes do not meet. There are no points: for
3DGS's initialisation load the scene's COLMAP model (``data=colmap``).
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from b3dgs.data.images import image_size, list_images
from b3dgs.data.scene import FrameSpec, RawScene, hint_smaller_copies, materialize, select_evenly
from b3dgs.errors import B3dgsError
from b3dgs.io import atomic_path
from b3dgs.types import Camera

__all__ = ["load_llff", "read_llff", "write_llff"]
_REGENERATE = "regenerate poses_bounds.npy (LLFF's imgs2poses) or load the scene's COLMAP model (data=colmap)"


def read_llff(path: str | os.PathLike, images_dir: str = "images") -> tuple[list[FrameSpec], np.ndarray]:
    """Parse ``poses_bounds.npy``: (frames sorted by image name, bounds (N, 2) near/far)."""
    root = Path(path)
    if not root.is_dir():
        raise B3dgsError(f"LLFF scene folder {root} does not exist", "pass data.path=PATH to an existing scene folder")
    pb_path = root / "poses_bounds.npy"
    if not pb_path.is_file():
        raise B3dgsError(f"{root} has no poses_bounds.npy, so it is not an LLFF scene",
                         "pass data.path=PATH to the folder that holds poses_bounds.npy (and images/)")
    try:
        pb = np.load(pb_path, allow_pickle=False)
    except (OSError, ValueError) as e:
        raise B3dgsError(f"Cannot read {pb_path}: {e}", _REGENERATE) from e
    if pb.ndim != 2 or pb.shape[1] != 17:
        raise B3dgsError(f"{pb_path} must be (N, 17), got {pb.shape}",
                         fix="regenerate poses_bounds.npy (LLFF's imgs2poses): each row holds a 3x5 pose+hwf matrix "
                             "and two depth bounds")
    pb = pb.astype(np.float64)
    if not np.isfinite(pb).all():
        bad = np.where(~np.isfinite(pb).all(axis=1))[0].tolist()
        raise B3dgsError(f"{pb_path}: non-finite values in rows {bad}", _REGENERATE)
    bad = np.where(~((pb[:, 15] > 0) & (pb[:, 16] > pb[:, 15])))[0].tolist()
    if bad:
        raise B3dgsError(f"{pb_path}: rows {bad[:5]} have near/far bounds that are not 0 < near < far", _REGENERATE)
    files = list_images(root / images_dir)
    if len(files) != len(pb):
        raise B3dgsError(f"{pb_path} has {len(pb)} poses but {root / images_dir} has {len(files)} images",
                         fix="keep exactly the images the poses were computed for in that folder (one per row, in "
                             "name order), pick another folder with data.images_dir, or regenerate poses_bounds.npy")
    frames = []
    for f, row in zip(files, pb):
        m = row[:15].reshape(3, 5)
        H, W, focal = m[:, 4]
        if not (H > 0 and W > 0 and focal > 0):
            raise B3dgsError(f"{pb_path}: invalid hwf {m[:, 4].tolist()} for {f.name}",
                             fix="regenerate poses_bounds.npy (LLFF's imgs2poses): height, width and focal must all "
                                 "be > 0")
        c2w = np.eye(4)
        c2w[:3] = np.stack([m[:, 1], m[:, 0], -m[:, 2], m[:, 3]], axis=1)  # right, down, forward = -back, centre
        try:
            viewmat = np.linalg.inv(c2w)
        except np.linalg.LinAlgError as e:
            raise B3dgsError(f"{pb_path}: singular pose for {f.name}", _REGENERATE) from e
        W0, H0 = int(round(W)), int(round(H))
        w, h = image_size(f)
        if (w, h) != (W0, H0):
            s = w / W0
            if abs(H0 * s - h) > 1.0 or s > 1.0:
                raise B3dgsError(f"Image {f} is {w}x{h} but poses_bounds.npy says {W0}x{H0} (w x h), which is not "
                                 "a uniform downscale", fix="point data.images_dir at the images the poses were "
                                 "computed for, or at copies downscaled by one factor in both axes (e.g. images_4)")
        sx, sy = w / W, h / H
        K = np.array([[focal * sx, 0.0, w / 2.0], [0.0, focal * sy, h / 2.0], [0.0, 0.0, 1.0]])
        frames.append(FrameSpec(f.name, f, K, viewmat, w, h))
    return frames, pb[:, 15:17].copy()


def load_llff(path: str | os.PathLike, max_side: Optional[int] = None, background: Sequence[float] = (0.0, 0.0, 0.0),
              max_images: Optional[int] = None, images_dir: str = "images") -> RawScene:
    """Load an LLFF scene: cameras (K at the loaded size, OpenCV w2c) and images; no points."""
    frames, bounds = read_llff(path, images_dir=images_dir)
    keep = select_evenly(len(frames), max_images)
    hint_smaller_copies(Path(path) / images_dir, [frames[i] for i in keep], max_side)
    cams = materialize([frames[i] for i in keep], max_side=max_side, background=background)
    near, far = np.median(bounds[keep], axis=0)
    # LLFF's own focus depth (as in its spiral-path code), used when the optical axes do not meet
    focus = 1.0 / (0.25 / near + 0.75 / far)
    return RawScene(
        name=Path(path).resolve().name, cameras=cams, extras={"bounds": bounds[keep], "focus_depth": focus}
    )


def write_llff(
    path: str | os.PathLike,
    cameras: Sequence[Camera],
    near_far: Sequence[float] | np.ndarray = (0.1, 100.0),
) -> Path:
    """Write ``poses_bounds.npy`` for ``cameras`` (square pixels, centred principal point assumed), one row per camera
    in their order (name the image files so that they sort the same way); ``near_far``: one pair or an (N, 2) array."""
    rows = []
    nf = np.broadcast_to(np.asarray(near_far, dtype=np.float64), (len(cameras), 2))
    for cam, b in zip(cameras, nf):
        c2w = np.linalg.inv(cam.viewmat.double().numpy())
        m = np.stack([c2w[:3, 1], c2w[:3, 0], -c2w[:3, 2], c2w[:3, 3],  # down, right, back, centre, hwf
                      np.array([cam.height, cam.width, float(cam.K[0, 0])], dtype=np.float64)], axis=1)
        rows.append(np.concatenate([m.reshape(-1), b]))
    out = Path(path) / "poses_bounds.npy"
    with atomic_path(out) as tmp:
        with open(tmp, "wb") as fh:
            np.save(fh, np.asarray(rows, dtype=np.float64))
    return out

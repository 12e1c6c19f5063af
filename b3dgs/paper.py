"""The paper's protocol constants that configs resolve (``experiment=paper``); no imports, so that ``import b3dgs``
(its config resolvers) can read them without an import cycle."""
from __future__ import annotations

from typing import Optional

#: the paper's image-folder policy (Appendix, "Dataset handling and hardware"): Mip-NeRF 360 outdoor scenes train on
#: ``images_4``, indoor ones on ``images_2``; every other scene (Tanks and Temples, Deep Blending, ...) on its native
#: ``images``. ``experiment=paper`` sets ``data.images_dir`` from it (:func:`paper_image_folder`).
PAPER_IMAGE_FOLDERS = {
    **dict.fromkeys(("bicycle", "flowers", "garden", "stump", "treehill"), "images_4"),  # Mip-NeRF 360 outdoor
    **dict.fromkeys(("bonsai", "counter", "kitchen", "room"), "images_2"),  # Mip-NeRF 360 indoor
}


def paper_image_folder(kind: str, name: str) -> Optional[str]:
    """The image folder the paper trains scene ``name`` on (:data:`PAPER_IMAGE_FOLDERS`) for a format with image
    folders (``colmap``, ``llff``); None (the format's own images, ``images/``) for every other scene or format."""
    return PAPER_IMAGE_FOLDERS.get(str(name)) if str(kind) in ("colmap", "llff") else None

"""Lightning DataModule over a :class:`~b3dgs.types.Scene`: one camera per step."""
from __future__ import annotations

from typing import Any, Optional, Sequence

import lightning as L
from torch.utils.data import DataLoader, Dataset

from b3dgs.data.scene import NEAR_PLANE, load_scene
from b3dgs.types import Camera, Scene

__all__ = ["CameraDataset", "SceneDataModule", "camera_collate"]


class CameraDataset(Dataset):
    """A list of cameras as a map-style dataset."""

    def __init__(self, cameras: Sequence[Camera]):
        self.cameras = list(cameras)

    def __len__(self) -> int:
        return len(self.cameras)

    def __getitem__(self, i: int) -> Camera:
        return self.cameras[i]


def camera_collate(batch: list[Camera]) -> Camera:
    """Batches hold exactly one camera; return the Camera itself."""
    if len(batch) != 1:
        raise ValueError(f"camera batches must have size 1, got {len(batch)}")
    return batch[0]


def _plain(x: Any) -> Any:
    """OmegaConf containers -> plain Python (without importing omegaconf eagerly)."""
    if x is None or isinstance(x, (str, int, float, bool)):
        return x
    try:
        from omegaconf import DictConfig, ListConfig, OmegaConf

        if isinstance(x, (DictConfig, ListConfig)):
            return OmegaConf.to_container(x, resolve=True)
    except ImportError:  # pragma: no cover
        pass
    return x


class SceneDataModule(L.LightningDataModule):
    """Loads a scene once in :meth:`setup` and serves cameras.

    * ``train_dataloader``: each train camera once per epoch, in a random order reshuffled every
      epoch (``shuffle=True`` draws from torch's global RNG, so ``lightning.seed_everything`` /
      ``torch.manual_seed`` makes the order reproducible); batch size 1, the batch *is* the Camera.
    * ``val_dataloader`` / ``test_dataloader``: the held-out cameras in sorted order.

    Arguments mirror :func:`b3dgs.data.load_scene` (``near_plane``: the renderer's, for the near-plane
    guard); ``name`` (optional) overrides the scene name;
    extra keyword arguments go to the format loader (e.g. ``n_views``, ``resolution``, ``seed``).
    A prebuilt ``scene`` may be passed instead (then nothing is loaded).
    """

    def __init__(
        self,
        kind: str = "synthetic",
        path: Optional[str] = None,
        max_side: Optional[int] = None,
        test_every: int = 8,
        train_indices: Optional[Sequence[int]] = None,
        normalize: bool = True,
        background: Sequence[float] = (0.0, 0.0, 0.0),
        max_images: Optional[int] = None,
        name: Optional[str] = None,
        scene: Optional[Scene] = None,
        near_plane: float = NEAR_PLANE,
        **kind_kwargs: Any,
    ):
        super().__init__()
        self.kind = str(kind)
        self.path = None if path is None else str(path)
        self.max_side = None if max_side is None else int(max_side)
        self.test_every = int(test_every)
        ti = _plain(train_indices)
        self.train_indices = None if ti is None else [int(i) for i in ti]
        self.normalize = bool(normalize)
        self.background = tuple(float(x) for x in _plain(background))
        self.max_images = None if max_images is None else int(max_images)
        self.name = name
        self.near_plane = float(near_plane)
        self.kind_kwargs = {k: _plain(v) for k, v in kind_kwargs.items()}
        self._scene: Optional[Scene] = scene

    @property
    def scene(self) -> Scene:
        if self._scene is None:
            self.setup()
        assert self._scene is not None
        return self._scene

    def setup(self, stage: Optional[str] = None) -> None:
        if self._scene is not None:
            return
        scene = load_scene(
            self.kind,
            self.path,
            max_side=self.max_side,
            test_every=self.test_every,
            train_indices=self.train_indices,
            normalize=self.normalize,
            background=self.background,
            max_images=self.max_images,
            near_plane=self.near_plane,
            **self.kind_kwargs,
        )
        if self.name:
            scene.name = str(self.name)
        self._scene = scene

    def _loader(self, cameras: Sequence[Camera], shuffle: bool) -> DataLoader:
        return DataLoader(
            CameraDataset(cameras),
            batch_size=1,
            shuffle=shuffle,
            num_workers=0,
            collate_fn=camera_collate,
        )

    def train_dataloader(self) -> DataLoader:
        return self._loader(self.scene.train, shuffle=True)

    def val_dataloader(self) -> DataLoader:
        return self._loader(self.scene.test, shuffle=False)

    def test_dataloader(self) -> DataLoader:
        return self._loader(self.scene.test, shuffle=False)

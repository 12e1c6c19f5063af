"""Lightning DataModule over a :class:`~b3dgs.types.Scene`: one camera per step."""
from __future__ import annotations

import os
from dataclasses import replace
from typing import Any, Iterator, Optional, Sequence

import lightning as L
import torch
from torch.utils.data import DataLoader, Sampler

from b3dgs.data.scene import SceneSettings, check_scene_settings, read_raw, read_scene
from b3dgs.errors import B3dgsError
from b3dgs.types import Camera, Scene

__all__ = ["ResumableDataLoader", "ResumableRandomSampler", "SceneDataModule", "camera_collate"]


def camera_collate(batch: list[Camera]) -> Camera:
    """Batches hold exactly one camera; return the Camera itself."""
    if len(batch) != 1:
        raise B3dgsError(f"camera batches must have size 1, got {len(batch)}",
                         fix="build the DataLoader with batch_size=1 (b3dgs trains on one camera per step), as "
                             "SceneDataModule does")
    return batch[0]


class ResumableRandomSampler(Sampler[int]):
    """Each index once per epoch in a random order, reshuffled every epoch, resumable mid-epoch.

    The order comes from the sampler's own ``torch.Generator`` (seeded from torch's global RNG when the sampler is made,
    so ``seed_everything`` makes it reproducible; never drawn from that RNG during training). :meth:`state_dict` holds
    the generator, the epoch's permutation and the position in it: the indices *consumed*, as a loader that fetches
    ahead (Lightning prefetches one batch) reports them with :meth:`mark_consumed` (``b3dgs.callbacks.ResumeState``
    does), else those yielded. An iterator started after :meth:`load_state_dict` yields the rest of that epoch, and
    the next one the next permutation, exactly as the uninterrupted sampler would."""

    def __init__(self, n: int, seed: Optional[int] = None):
        self.n = int(n)
        if seed is None:
            seed = int(torch.empty((), dtype=torch.int64).random_().item())
        self.generator = torch.Generator().manual_seed(int(seed))
        self.perm: Optional[list[int]] = None
        self.epoch = 0  # permutations drawn so far
        self._yielded = 0
        self._consumed: Optional[int] = None
        self.allow_resize = False  # a checkpoint of a smaller training set may be loaded (training rounds)

    def __len__(self) -> int:
        return self.n

    @property
    def position(self) -> int:
        """Indices of the current permutation consumed (or yielded, when nobody reports consumption)."""
        return self._yielded if self._consumed is None else self._consumed

    def mark_consumed(self, k: int) -> None:
        """``k`` indices of the current epoch's permutation have been used for training."""
        self._consumed = int(k)

    def __iter__(self) -> Iterator[int]:
        if self.perm is None or self.position >= self.n:
            self.perm = torch.randperm(self.n, generator=self.generator).tolist()
            self.epoch += 1
            self._yielded, self._consumed = 0, None
        perm, start = self.perm, self.position
        self._yielded = start
        for i in range(start, self.n):
            self._yielded = i + 1
            yield perm[i]

    def state_dict(self) -> dict[str, Any]:
        return {"n": self.n, "generator": self.generator.get_state(), "perm": self.perm, "epoch": self.epoch,
                "position": self.position}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        resized = int(state["n"]) != self.n  # allowed for a new training round with more views: a fresh epoch
        if resized and not self.allow_resize:
            raise B3dgsError(f"the checkpoint's view sampler has {state['n']} train views, this scene {self.n}",
                             "resume with the data settings of the checkpoint's run")
        self.generator.set_state(state["generator"])  # the generator's stream goes on in any case
        self.perm = None if resized or state["perm"] is None else [int(i) for i in state["perm"]]
        self.epoch = int(state["epoch"])
        self._yielded, self._consumed = 0 if resized else int(state["position"]), None


class ResumableDataLoader(DataLoader):
    """A DataLoader whose sampler's position goes into Lightning checkpoints (Lightning saves and restores
    the ``state_dict`` of any train loader that has one, before iterating it)."""

    def state_dict(self) -> dict[str, Any]:
        return {"sampler": self.sampler.state_dict()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.sampler.load_state_dict(state["sampler"])


class SceneDataModule(L.LightningDataModule):
    """Loads a scene once in :meth:`setup` and serves cameras, one per batch (the batch *is* the Camera): the train
    cameras each once per epoch in an order reshuffled every epoch (a :class:`ResumableRandomSampler`: reproducible
    under ``lightning.seed_everything``, its position saved in checkpoints, so a resumed run sees the same views), the
    held-out cameras in sorted order for validation and test.

    Arguments mirror :func:`b3dgs.data.load_scene` (``settings`` and flat ``data.*`` keys over it); ``name`` overrides
    the scene name; a prebuilt ``scene`` is served as it is (nothing loaded or checked); ``keep_raw`` (set before
    :meth:`setup`) keeps what was read, for :meth:`select_train`. The settings are checked when the data module is
    built (:meth:`validate`), before any scene is read."""

    def __init__(self, kind: str = "synthetic", path: Optional[str] = None, settings: Optional[SceneSettings] = None,
                 name: Optional[str] = None, scene: Optional[Scene] = None, **keys: Any):
        super().__init__()
        self.kind = str(kind)
        self.path = None if path is None else os.path.expanduser(str(path))  # data.path='~/scene' (quoted for Hydra)
        self.name = name
        self.settings, self.kind_kwargs = SceneSettings.split(keys, settings)
        self._scene: Optional[Scene] = scene
        self._format_loader = None  # the format loader, once validate has checked the settings
        self.train_sampler: Optional[ResumableRandomSampler] = None  # made by train_dataloader()
        self.allow_new_views = False  # a new training round: the sampler may resume from fewer train views
        self.keep_raw = False
        self._raw = None  # the scene as read (keep_raw)
        self.validate()

    def validate(self, **kwargs: Any) -> None:
        """Check the data settings, the scene folder and the format loader's own keywords
        (:func:`b3dgs.data.scene.check_scene_settings`); raise :class:`B3dgsError` naming the ``data.*`` key and the
        fix. Called when the data module is built; a prebuilt ``scene`` is not checked. ``kwargs``: nothing yet."""
        if self._scene is None:
            self._format_loader = check_scene_settings(self.kind, self.path, self.settings, self.kind_kwargs)

    @property
    def scene(self) -> Scene:
        if self._scene is None:
            self.setup()
        assert self._scene is not None
        return self._scene

    def setup(self, stage: Optional[str] = None) -> None:
        if self._scene is not None:
            return
        if self.keep_raw and self._raw is None:  # with the point tracks select_train(init_points_from_train_only) needs
            self._raw = read_raw(self._format_loader, self.path, self.settings, self.kind_kwargs, point_tracks=True)
        scene = read_scene(self._format_loader, self.kind, self.path, self.settings, self.kind_kwargs, raw=self._raw)
        if self.name:
            scene.name = str(self.name)
        self._scene = scene

    def select_train(self, train_indices: Sequence[int], init_points_from_train_only: bool = False) -> "SceneDataModule":
        """A data module over this one's views whose scene trains on ``train_indices`` of its training views only
        (the others become the scene's ``candidates``; ``init_points_from_train_only``: the initial points those
        views saw), made from what this one read (``keep_raw``) without reading the scene again."""
        self.setup()
        if self._raw is None:
            raise B3dgsError("select_train needs the views this data module read, and it did not keep them",
                             "set keep_raw = True before setup() (b3dgs.lifecycle.data_module(node, keep_raw=True))")
        settings = replace(self.settings, train_indices=[int(i) for i in train_indices],
                           init_points_from_train_only=bool(init_points_from_train_only))
        out = type(self)(self.kind, self.path, settings, name=self.name, **self.kind_kwargs)
        out._raw = self._raw
        out.setup()
        return out

    def train_dataloader(self) -> DataLoader:
        self.train_sampler = ResumableRandomSampler(len(self.scene.train))
        self.train_sampler.allow_resize = self.allow_new_views
        # every iter() of a DataLoader draws a worker base seed from its ``generator`` (the global RNG if
        # none): a private one keeps epoch starts off the global RNG, which a resumed run restores exactly
        return ResumableDataLoader(list(self.scene.train), batch_size=1, sampler=self.train_sampler,
                                   num_workers=0, collate_fn=camera_collate, generator=torch.Generator())

    def val_dataloader(self) -> DataLoader:  # a list of cameras is a map-style dataset
        return DataLoader(list(self.scene.test), batch_size=1, num_workers=0, collate_fn=camera_collate)

    def test_dataloader(self) -> DataLoader:
        return self.val_dataloader()

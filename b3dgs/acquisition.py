"""Acquisition policies (active view selection): the base class and the scoring context a policy gets.

A policy is a plugin like any other (``plugins/acquisition/<name>.py`` plus ``conf/acquisition/<name>.yaml``); the
study reads only what the class declares (:class:`AcquisitionPolicy`). Batch selection is a component of its own,
:class:`BatchSelector` (``conf/acquisition/batch/``), that reads the policy's declared methods, never its type;
docs/extending.md documents both protocols. A policy gets candidate cameras (``image=None``) and a
:class:`ScoringContext`, never the LightningModule, the data module or the candidates' images (the oracle aside).
"""
from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Callable, ClassVar, Optional, Sequence

import numpy as np
import torch
from torch import Tensor

from b3dgs.errors import B3dgsError, did_you_mean
from b3dgs.neighbours import nearest_distances, nearest_other_distances
from b3dgs.types import Camera, resize_image

__all__ = ["AcquisitionPolicy", "BatchSelector", "RegimePolicy", "ScoringContext", "Selection", "composed", "diverse_picks",
           "epistemic_scores", "top_k"]


@dataclass
class Selection:
    """A policy's answer: candidate positions in pick order, and a score per candidate (None: the policy
    ranks without scores, e.g. uniform spacing)."""

    indices: list[int]
    scores: Optional[list[float]] = None
    info: Optional[dict] = None  # what the batch selector did (mode, fallback, re-scores per pick, time)


def top_k(scores: Tensor, budget: int) -> list[int]:
    """The ``budget`` highest scores, ties broken by position (deterministic)."""
    s = scores.detach().double().cpu()
    order = sorted(range(len(s)), key=lambda i: (-float(s[i]), i))
    return order[: int(budget)]


@dataclass
class AcquisitionPolicy:
    """Base of the acquisition policies: score candidates, pick the top ``budget``."""

    family: str = "standard"  # the phase-1 model family it scores with and continues (a model= option)
    members: int = 1  # how many phase-1 models of that family (seeds s, s+1, ...) it scores with
    uses_ground_truth: ClassVar[bool] = False  # True only for the analysis-only oracle
    selects_batch: ClassVar[bool] = False  # True: ``select`` builds the batch itself (only batch=topk applies)
    #: why ``condition`` cannot update this policy's score (recorded when greedy_conditioned falls back to diverse)
    no_conditioning: ClassVar[str] = "the policy declares no condition() (its score has no posterior to update)"

    def validate(self, **kwargs) -> None:
        from b3dgs.confs import option_names

        families = option_names("model")  # any model= option, b3dgs's or a package's
        if self.family not in families:
            raise B3dgsError(f"acquisition family={self.family!r} is not a model option"
                             f"{did_you_mean(self.family, families)}",
                             f"pass family=<a model= option: {'|'.join(families)}>")
        if int(self.members) < 1:
            raise B3dgsError(f"{type(self).__name__}.members={self.members} must be >= 1", "pass members=1 (or 3 for ensemble)")

    def score(self, ctx: "ScoringContext", candidates: Sequence[Camera]) -> Tensor:
        """(K,) scores, higher = acquire first."""
        raise NotImplementedError  # protocol: an abstract method (subclasses implement it)

    def select(self, ctx: "ScoringContext", candidates: Sequence[Camera], budget: int) -> Selection:
        scores = self.score(ctx, candidates)
        return Selection(top_k(scores, budget), [float(v) for v in scores.detach().double().cpu()])

    # ---------------------------------------------------------------- what batch selectors use
    def score_at(self, ctx: "ScoringContext", candidates: Sequence[Camera], positions: Sequence[int]) -> Tensor:
        """Scores of ``candidates[i]`` for ``i`` in ``positions``, as ``score(ctx, candidates)`` gives them (a
        policy whose score draws per-candidate random numbers keys them by position). Default: score the
        subset, exact for scores that depend on the candidate alone."""
        return self.score(ctx, [candidates[i] for i in positions])

    def condition(self, ctx: "ScoringContext", camera: Camera) -> bool:
        """Score from now on as if ``camera`` had been acquired, without its image (greedy_conditioned calls it
        after each pick). Returns whether the score changed. Default: False, nothing changes, and
        greedy_conditioned selects as ``diverse`` would, recording ``no_conditioning`` as the reason."""
        return False

    def conditioned_ratio(self, ctx: "ScoringContext", candidates: Sequence[Camera],
                          positions: Sequence[int]) -> Optional[Tensor]:
        """A cheap estimate (no sampling) of how much the conditioning so far has changed each candidate's
        score: conditioned / unconditioned, per position. greedy_conditioned re-scores exactly the candidates
        this ranks first. Default None: the last exact scores serve as upper bounds (lazy greedy)."""
        return None

    def reset_conditioning(self, ctx: "ScoringContext") -> None:
        """Undo every :meth:`condition` (the selector calls it when its batch is done)."""


def composed(policy: AcquisitionPolicy, field: str, group: str):
    """``policy.<field>``, unwrapped when a keyed ``conf/<group>`` file composed into it gave a one-entry mapping."""
    r = getattr(policy, field)
    if isinstance(r, Mapping):
        if len(r) != 1:
            raise B3dgsError(f"{type(policy).__name__}: {field} holds {len(r)} entries ({', '.join(map(str, r))}), "
                             "expected one", f"compose it with defaults: [/{group}@{field}: <name>]")
        r = next(iter(r.values()))
    return r


@dataclass
class RegimePolicy(AcquisitionPolicy):
    """A score policy that is a UQ regime plus a reduction: a candidate's score is the mean over its pixels of the
    regime's epistemic variance (:func:`epistemic_scores`). ``regime`` is the regime of ``conf/uq/<name>.yaml``,
    composed by Hydra (``defaults: [/uq@regime: <name>]``; settings by name: ``regime: {<name>: {samples: 16}}``),
    so a policy and ``uq=[<name>]`` are one configuration. A keyed conf/uq file gives a one-entry mapping, which
    :meth:`uq` unwraps."""

    regime: Any = None

    def validate(self, **kwargs) -> None:
        super().validate(**kwargs)
        self.uq()

    def uq(self):
        """The UQ regime this policy scores with (one instance for the policy's life: its fit is cached per
        scoring context)."""
        r = composed(self, "regime", "uq")
        if not (callable(getattr(r, "fit", None)) and callable(getattr(r, "predict", None))):
            raise B3dgsError(f"{type(self).__name__}: regime is {type(r).__name__}, not a UQ regime",
                             "compose it with defaults: [/uq@regime: <name>] (a conf/uq option)")
        self.regime = r
        return r

    def score(self, ctx: "ScoringContext", candidates: Sequence[Camera]) -> Tensor:
        return self.score_at(ctx, candidates, range(len(candidates)))

    def score_at(self, ctx: "ScoringContext", candidates: Sequence[Camera], positions: Sequence[int]) -> Tensor:
        with torch.no_grad():
            return epistemic_scores(ctx, self.uq(), candidates, positions)


@dataclass
class BatchSelector:
    """Base of the batch options (``conf/acquisition/batch/<name>.yaml``): turn a policy into ``budget``
    picks through the policy's declared methods only. ``own_batch_ok``: whether it also applies to a policy
    that builds its batch itself (``selects_batch``); only ``topk`` (the policy's own select) does."""

    own_batch_ok: ClassVar[bool] = False

    def validate(self, **kwargs) -> None:
        """Refuse bad settings (one line, :class:`B3dgsError`)."""

    def applies_to(self, policy: AcquisitionPolicy) -> bool:
        return self.own_batch_ok or not policy.selects_batch

    def select(self, policy: AcquisitionPolicy, ctx: "ScoringContext", candidates: Sequence[Camera],
               budget: int) -> Selection:
        raise NotImplementedError  # protocol: an abstract method (subclasses implement it)


def _pool_spacing(points: np.ndarray) -> float:
    """Median distance from each point to its nearest other point (0 when fewer than two)."""
    if len(points) < 2:
        return 0.0
    return float(np.median(nearest_other_distances(points)[:, 0]))


def diverse_picks(scores: Sequence[float], cand: np.ndarray, train: np.ndarray, budget: int,
                  radius: float) -> tuple[list[int], float]:
    """Greedy with diminishing returns (``batch=diverse``): pick the candidate maximising
    s_i · (1 − exp(−d_i² / (2 (radius·h)²))), where d_i is its centre's distance to the nearest training or
    already picked camera centre and h the median nearest-neighbour spacing of the pool (training +
    candidate centres); then update d and repeat. Scores are shifted to be >= 0 when some are negative; ties
    go to the first candidate. radius → 0 gives top-k (but never an exact copy, d = 0, of a chosen camera);
    a large radius weighs s·d². Returns (picks, h)."""
    s = np.asarray(scores, dtype=np.float64)
    if len(s) and s.min() < 0:
        s = s - s.min()
    pool = np.concatenate([train.reshape(-1, 3), cand.reshape(-1, 3)])
    h = _pool_spacing(pool)
    scale2 = 2.0 * (float(radius) * h) ** 2

    def value(d):
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            return s * np.where(np.isinf(d), 1.0, -np.expm1(-np.square(d) / scale2) if scale2 > 0 else (d > 0) * 1.0)

    return greedy_spread(cand, train, budget, value)[0], h


def check_radius(radius, option: str) -> None:
    """Refuse a ``batch=<option>`` radius that is not a finite number > 0 (diverse and its fallback)."""
    if isinstance(radius, bool) or not isinstance(radius, (int, float)) or not (0 < float(radius) < math.inf):
        raise B3dgsError(f"acquisition batch {option}: radius={radius!r} must be a finite number > 0",
                         f"pass +acquisition.batch_settings.{option}.radius=1.0 (in units of the pool's median camera spacing)")


def greedy_spread(cand: np.ndarray, train: np.ndarray, budget: int,
                  value: Callable[[np.ndarray], np.ndarray]) -> tuple[list[int], np.ndarray]:
    """Greedy picks among the camera centres ``cand``: each time the (first) maximum of ``value(d)``, where d is each
    candidate's distance to the nearest training (``train``) or already picked centre (inf with neither); picked
    candidates are never picked again. Returns (picks, d before any pick)."""
    d0 = d = nearest_distances(cand, train)
    picks: list[int] = []
    for _ in range(min(int(budget), len(cand))):
        v = np.asarray(value(d), dtype=np.float64).copy()
        v[picks] = -np.inf
        i = int(np.argmax(v))  # the first of equal values: deterministic
        picks.append(i)
        d = np.minimum(d, np.linalg.norm(cand - cand[i], axis=-1))
    return picks, d0


# ---------------------------------------------------------------------------------------------- context
class ScoringContext:
    """What a policy may use to score candidates (see the module docstring).

    ``models``: the phase-1 module(s) of the policy's family (member 0 continues); they stay private.
    ``train``: the current training cameras with their images; ``score_max_side``: candidates and
    training views are scored at this resolution (None: full); ``ground_truth``: a function name ->
    image, given only to a policy that declares ``uses_ground_truth`` (the oracle).
    """

    def __init__(self, models: Sequence[Any], train: Sequence[Camera], score_max_side: Optional[int] = None,
                 extent: float = 1.0, seed: int = 0, ground_truth: Optional[Callable[[str], Tensor]] = None):
        self._models = list(models)
        self._gt = ground_truth
        self.score_max_side = score_max_side
        self.extent = float(extent)
        self.seed = int(seed)
        self.train = [c.fit(score_max_side or None) for c in train]
        self._regimes: dict[Any, Any] = {}  # fitted regimes and posterior block states

    # ---------------------------------------------------------------- cameras and renders
    @property
    def num_members(self) -> int:
        return len(self._models)

    @property
    def device(self) -> torch.device:
        return self._models[0].splats["means"].device

    def camera(self, camera: Camera) -> Camera:
        """``camera`` at the scoring resolution (never with an image)."""
        return camera.with_image(None).fit(self.score_max_side or None)

    def generator(self, salt: int = 0) -> torch.Generator:
        return torch.Generator(device="cpu").manual_seed(self.seed * 1000003 + salt)

    def sh_degree(self, member: int = 0) -> int:
        """The SH degree the phase-1 model renders with (its active degree)."""
        return int(self._models[member].active_sh_degree())

    def params(self, member: int = 0, requires_grad: bool = False) -> dict[str, Tensor]:
        """Copies of the point-estimate parameters (leaf tensors, own dtype and device)."""
        return {k: v.detach().clone().requires_grad_(requires_grad) for k, v in self._models[member].params().items()}

    def render(self, camera: Camera, member: int = 0, params: Optional[dict] = None, grad: bool = False,
               return_weights: bool = False):
        """Render ``camera`` at the scoring resolution (``params``: another parameter set, e.g. from
        :meth:`params` with gradients; ``grad``: keep the autograd graph; ``return_weights``: also the
        per-Gaussian compositing sums Σ_p w_kp and Σ_p w_kp²)."""
        m = self._models[member]
        with torch.set_grad_enabled(grad):
            return m.render_camera(self.camera(camera), params=params, return_weights=return_weights)

    # ---------------------------------------------------------------- uncertainty regimes
    def fit_posterior(self, block, member: int = 0) -> dict:
        """The state of posterior ``block`` (e.g. one a policy composes from ``conf/posterior``) on the phase-1 model,
        from one view pass over the training views at the scoring resolution (cached per block object)."""
        key = ("posterior", id(block), member)
        if key not in self._regimes:
            m = self._models[member]
            state = block.initialize_state(splats=m.splats, scene=None, info={})
            m.prepare_posterior(self.train, blocks=[("policy", block, state)])
            self._regimes[key] = state
        return self._regimes[key]

    def fit_regime(self, regime, member: int = 0):
        """``regime`` (a :class:`b3dgs.uq.regime.UQRegime`) fitted on the phase-1 model and the training
        views at the scoring resolution (cached per regime object)."""
        from types import SimpleNamespace

        key = id(regime)
        if key not in self._regimes:
            scene = SimpleNamespace(train=self.train, test=[], extent=self.extent, candidates=[])
            regime.fit([self._models[member]], scene)
            self._regimes[key] = regime
        return self._regimes[key]

    def predict(self, regime, camera: Camera, salt: int = 0):
        """The fitted ``regime``'s prediction for ``camera`` at the scoring resolution."""
        return self.fit_regime(regime).predict(self.camera(camera), generator=self.generator(salt))

    # ---------------------------------------------------------------- ground truth (oracle only)
    def ground_truth(self, camera: Camera) -> Tensor:
        if self._gt is None:
            raise B3dgsError(f"a policy asked for the ground truth of candidate {camera.name!r}",
                             "only a policy that declares uses_ground_truth (the analysis-only oracle) gets it")
        small = self.camera(camera)
        return resize_image(self._gt(camera.name).to(self.device), small.width, small.height)


def epistemic_scores(ctx: ScoringContext, regime, candidates: Sequence[Camera], positions: Sequence[int]) -> Tensor:
    """Mean epistemic u_p of ``regime`` for ``candidates[i]``, ``i`` in ``positions``; candidate i's draws use
    the generator salted with i, so a subset scores exactly as the full list does (native, proxy)."""
    return torch.stack([ctx.predict(regime, candidates[i], salt=i).epistemic.double().mean() for i in positions]).cpu()


def camera_centres(cameras: Sequence[Camera]) -> np.ndarray:
    return np.stack([c.center.double().cpu().numpy() for c in cameras]) if cameras else np.zeros((0, 3))

"""``b3dgs-study active``: fixed-budget active view selection (paper section 3.2, Table 2).

Protocol per scene and seed s: ``initial_views`` training views evenly spaced over the sorted training list
(the same for every policy); phase 1 trains each model family the policies start from (standard, niw) for
``max_steps // phase1_divisor`` steps, once, shared by every policy (the ensemble's extra members are the
family's phase-1 models of seeds s+1, s+2, shared with those seeds' rows); each policy scores the candidate
pool (cameras only) and picks ``acquire`` views; its run continues the phase-1 model (member s) on the grown
training set to ``trainer.max_steps`` (same Gaussians, Adam moments and schedules) and is evaluated on the
test views.

Everything is resumable: phase-1 models and finished rows (``result.json``) are never retrained, a row's
selection is saved before its second round (``selection.json``), and an interrupted round resumes from its
``checkpoints/last.ckpt``. Outputs per scene: ``study.json``, ``study.md`` and ``plots/``
(:mod:`b3dgs.study.active_tables`).
"""
from __future__ import annotations

import copy
import dataclasses
import functools
import json
import logging
import math
import sys
import time
from pathlib import Path
from typing import Any, Optional

import numpy as np
from omegaconf import DictConfig, ListConfig, OmegaConf, open_dict

from b3dgs.confs import compose_config, option_names
from b3dgs.data.scene import select_evenly, take_candidate_store
from b3dgs.errors import B3dgsError, did_you_mean
from b3dgs.io import write_json
from b3dgs.lifecycle import Run, data_module
from b3dgs.protocol import RUN_IGNORED, check_stored_protocol, check_stored_scene, run_protocol, scene_digest
from b3dgs.study.cli import main as cli_main, study_app
from b3dgs.study.rounds import load_round, training_signature
from b3dgs.upgrade import FAMILY_POSTERIOR_UNRECORDED, omit_study_defaults, protocol_from_meta

log = logging.getLogger(__name__)

#: a study row's records (:meth:`b3dgs.lifecycle.Run.record`): the done marker, the picks saved before round 2, and
#: the done marker of a phase-1 model
ROW_DONE, ROW_SELECTION, PHASE1_DONE = "result.json", "selection.json", "phase1.json"


# ---------------------------------------------------------------------------------------------- config
def family_posterior_override(cfg: DictConfig, family: str) -> list[str]:
    """``[posterior=[...]]`` when the study pins ``family_posterior.<family>``, else ``[]`` (the model's own blocks,
    conf/model/<family>.yaml); an unknown block or a non-list is a one-line error."""
    pins = cfg.get("family_posterior") or {}
    if not isinstance(pins, (dict, DictConfig)):
        raise B3dgsError(f"family_posterior must map a family to its posterior blocks, got {pins!r}",
                         "pass e.g. family_posterior={niw:[niw]}")
    blocks = pins.get(family)
    if blocks is None:
        return []
    if not isinstance(blocks, (list, tuple, ListConfig)) or not all(isinstance(b, str) for b in blocks):
        raise B3dgsError(f"family_posterior.{family} must be a list of posterior block names, got {blocks!r}",
                         f"pass e.g. family_posterior.{family}=[niw]")
    unknown = [b for b in blocks if b not in option_names("posterior")]
    if unknown:
        raise B3dgsError(f"family_posterior.{family}: unknown posterior block {unknown[0]!r}",
                         f"use blocks of conf/posterior/: {', '.join(option_names('posterior'))}")
    return [f"posterior=[{','.join(blocks)}]"]


def family_config(cfg: DictConfig, family: str, seed: int) -> DictConfig:
    """A ``b3dgs-train``-shaped config: the study's data, renderer, strategy, trainer (and ``schedule`` when the study
    sets one, ``+schedule=dash``) with ``model=family`` (its posterior blocks pinned by ``family_posterior``)."""
    fam = compose_config("train", [f"model={family}", *family_posterior_override(cfg, family),
                                   *[str(o) for o in (cfg.get("model_overrides") or [])]])
    out = OmegaConf.create({"data": cfg.data, "renderer": cfg.renderer, "strategy": cfg.strategy,
                            "trainer": cfg.trainer, "model": fam.model, "posterior": fam.get("posterior") or {},
                            "seed": int(seed), "threads": cfg.get("threads"),
                            "callbacks": cfg.get("callbacks") or {}})
    if cfg.get("schedule") is not None:  # +schedule=dash: every round follows that training schedule
        out.schedule = cfg.schedule
    if "data_root" in cfg:  # a named scene's data.path is ${data_root}/<name>: the node must resolve here too
        out.data_root = cfg.data_root
    return out


def option_node(config_name: str, group: str, name: str, settings: Optional[DictConfig], fix: str) -> DictConfig:
    """``conf/<group>/<name>.yaml`` (or a package's) composed under ``config_name``'s app, with
    ``settings[name]`` merged in; an unknown option is a one-line error with ``fix``."""
    try:
        node = compose_config(config_name, [f"+{group}@option={name}"]).option
    except Exception as e:  # noqa: BLE001 - unknown option: one line with the fix
        raise B3dgsError(f"unknown {group} option {name!r} ({type(e).__name__})", fix) from None
    with open_dict(node):
        if settings is not None and settings.get(name) is not None:
            node.merge_with(settings.get(name))
    return node


def load_policy(name: str, settings: Optional[DictConfig] = None):
    """(label, policy) for ``name`` or ``name@family`` from ``conf/acquisition/<name>.yaml`` (or a package's)."""
    from hydra.utils import instantiate

    base, _, family = str(name).partition("@")
    node = option_node("study", "acquisition", base, settings,
                       f"pass policies=[...] of conf/acquisition/<name>.yaml ({', '.join(option_names('acquisition'))})"
                       " or a package's")
    if family:
        with open_dict(node):
            node.family = family
    try:
        policy = instantiate(node, _convert_="all")
    except Exception as e:  # noqa: BLE001 - a setting the policy does not have: one line naming where it lives
        import re

        bad = re.search(r"unexpected keyword argument '(\w+)'", str(e))
        if bad is None:
            raise
        regime = node.get("regime")
        where = (f" (the policy scores with a UQ regime: pass policy_settings.{base}.regime.{next(iter(regime))}."
                 f"{bad.group(1)}=...)") if isinstance(regime, DictConfig) and len(regime) == 1 else ""
        raise B3dgsError(f"acquisition {base}: no setting {bad.group(1)!r}{where}",
                         f"pass only the fields of conf/acquisition/{base}.yaml") from None
    policy.validate()
    label = base if not family else f"{base}@{family}"
    return label, policy


#: the batch option a row label without ``+batch`` uses (its label stays the policy's: rows from before
#: batch options existed keep their folders)
DEFAULT_BATCH = "topk"


def load_batch(name: str, settings: Optional[DictConfig] = None):
    """The batch selector ``conf/acquisition/batch/<name>.yaml`` with ``settings[name]`` merged in."""
    from hydra.utils import instantiate

    node = option_node("study", "acquisition/batch", str(name), settings,
                       f"pass acquisition.batch={'|'.join(option_names('acquisition/batch'))} "
                       "(conf/acquisition/batch/<name>.yaml)")
    try:
        batch = instantiate(node, _convert_="all")
    except Exception as e:  # noqa: BLE001 - a misspelt setting: one line naming it
        raise B3dgsError(f"acquisition batch {name}: bad settings ({' '.join(str(e.__cause__ or e).split())[:200]})",
                         f"pass only the fields of conf/acquisition/batch/{name}.yaml") from None
    batch.validate()
    return batch


@dataclasses.dataclass(frozen=True)
class StudyRow:
    """One row of the study, a config node: ``{policy: native, family: niw, batch: diverse, blocks: [niw, sh]}``.

    ``policy``: conf/acquisition/<name>.yaml (or a package's); ``family``: the model family its rounds train (default:
    the policy's own); ``batch``: conf/acquisition/batch/<name>.yaml (default: a row per ``acquisition.batch``);
    ``blocks``: the family's posterior blocks (as ``family_posterior.<family>``; rows of one family agree).
    ``policies=[native@niw+diverse]`` is the shorthand of the same node (:meth:`parse`)."""

    policy: str
    family: Optional[str] = None
    batch: Optional[str] = None
    blocks: Optional[tuple] = None

    @classmethod
    def parse(cls, entry: Any) -> "StudyRow":
        """A ``policies`` entry: a node with the fields above, or its shorthand ``policy[@family][+batch]`` (either
        order of the two suffixes); anything else is a one-line error."""
        example = "policies=[native,{policy:native,family:niw,batch:diverse}] (shorthand: native@niw+diverse)"
        if isinstance(entry, (dict, DictConfig)):
            node = OmegaConf.to_container(entry, resolve=True) if isinstance(entry, DictConfig) else dict(entry)
            fields = [f.name for f in dataclasses.fields(cls)]
            unknown = [k for k in node if k not in fields]
            if unknown:
                raise B3dgsError(f"a study row has no field {unknown[0]!r}{did_you_mean(unknown[0], fields)}",
                                 f"a row holds {', '.join(fields)}, e.g. {example}")
            if not isinstance(node.get("policy"), str) or not node["policy"]:
                raise B3dgsError(f"a study row needs its policy, got {node!r}", f"pass e.g. {example}")
            for k in ("family", "batch"):
                if node.get(k) is not None and not isinstance(node[k], str):
                    raise B3dgsError(f"study row {node['policy']}: {k} must be a name, got {node[k]!r}",
                                     f"pass e.g. {example}")
            blocks = node.get("blocks")
            if blocks is not None:
                if not isinstance(blocks, (list, tuple)) or not all(isinstance(b, str) for b in blocks):
                    raise B3dgsError(f"study row {node['policy']}: blocks must be a list of posterior block names, "
                                     f"got {blocks!r}", "pass e.g. {policy:sh,family:niw,blocks:[niw,sh]}")
                node["blocks"] = tuple(blocks)
            return cls(**node)
        if not isinstance(entry, str) or not entry:
            raise B3dgsError(f"a study row must be a policy name or a node, got {entry!r}", f"pass e.g. {example}")
        base, _, fam = str(entry).partition("@")
        batch = None
        if "+" in fam:
            fam, _, batch = fam.partition("+")
        if "+" in base:
            base, _, batch = base.partition("+")
        return cls(policy=base, family=fam or None, batch=batch)

    @property
    def policy_name(self) -> str:
        """``policy`` or ``policy@family`` (what :func:`load_policy` takes)."""
        return self.policy if self.family is None else f"{self.policy}@{self.family}"


def study_rows(cfg: DictConfig) -> list[StudyRow]:
    """The study's rows (``policies``: nodes or their shorthand), their ``blocks`` checked by :func:`row_pins`."""
    row_pins(cfg)
    return [StudyRow.parse(e) for e in (cfg.get("policies") or [])]


def row_pins(cfg: DictConfig) -> dict:
    """``family_posterior`` with the rows' ``blocks`` added, each row's checked against the other rows of its family
    and against ``family_posterior``."""
    pins = {k: list(v) for k, v in (cfg.get("family_posterior") or {}).items()}
    for r in [StudyRow.parse(e) for e in (cfg.get("policies") or [])]:
        if r.blocks is None:
            continue
        fam = r.family or load_policy(r.policy)[1].family
        have = pins.get(fam)
        if have is not None and tuple(have) != r.blocks:
            raise B3dgsError(f"study row {r.policy}: blocks {list(r.blocks)} differ from {list(have)}, which "
                             f"another row or family_posterior.{fam} gives family {fam}",
                             "rows of one family train one phase-1 model: give them the same blocks")
        pins[fam] = list(r.blocks)
    return pins


def batch_names(cfg: DictConfig) -> list[str]:
    """``acquisition.batch``: one name or a list (every score-based policy gets a row per name)."""
    v = cfg.get("acquisition", {}).get("batch", DEFAULT_BATCH)
    names = [v] if isinstance(v, str) else list(v or [])
    if not names or not all(isinstance(n, str) and n for n in names):
        raise B3dgsError(f"acquisition.batch={v!r} is invalid", "pass acquisition.batch=topk or a list, e.g. "
                         "acquisition.batch=[topk,greedy_conditioned,diverse]")
    return list(dict.fromkeys(names))


def study_pairs(cfg: DictConfig) -> list[list[str]]:
    """``pairs``: the paired rows asked for besides the rule's (:func:`b3dgs.study.active_tables.pairs_for`)."""
    pairs = [p if isinstance(p, str) else list(p) for p in cfg.get("pairs") or []]
    for p in pairs:
        if not (isinstance(p, list) and len(p) == 2 and all(isinstance(x, str) for x in p)):
            raise B3dgsError(f"pairs: {p!r} is not a pair of policies", "pass e.g. 'pairs=[[native,proxy]]'")
    return pairs


# ---------------------------------------------------------------------------------------------- views
def pca_angles(cameras) -> np.ndarray:
    """Angle of every camera centre in the plane of the first two principal components (deterministic sign)."""
    xy = pca_xy(cameras)
    return np.arctan2(xy[:, 1], xy[:, 0])


def pca_xy(cameras) -> np.ndarray:
    """(n, 2) camera centres in the plane of their first two principal components (a top view)."""
    from b3dgs.acquisition import camera_centres

    c = camera_centres(cameras)
    c = c - c.mean(0)
    _, _, vt = np.linalg.svd(c, full_matrices=False)
    basis = vt[:2]
    for i in range(2):  # sign convention: the largest |coefficient| positive
        if basis[i][np.argmax(np.abs(basis[i]))] < 0:
            basis[i] = -basis[i]
    return c @ basis.T


def initial_views(cfg: DictConfig, train) -> tuple[list[int], list[str]]:
    """(indices into the sorted train list of the initial views, names of the views in the hole)."""
    for key in ("initial_views", "acquire"):
        v = cfg.get(key)
        if isinstance(v, bool) or not isinstance(v, int) or v < 1:
            raise B3dgsError(f"{key}={v} is invalid: it must be an integer >= 1",
                             f"pass {key}=16 (views {'to start from' if key == 'initial_views' else 'added after phase 1'})")
    n = len(train)
    k = int(cfg.initial_views)
    if k + int(cfg.acquire) > n:
        raise B3dgsError(f"the scene has {n} training views, fewer than initial_views + acquire = {k + int(cfg.acquire)}",
                         "pass a smaller initial_views / acquire, or a scene with more views")
    init = select_evenly(n, k)
    hole: list[str] = []
    if cfg.variant == "support_hole":
        order = np.argsort(pca_angles(train), kind="stable")
        width = max(1, int(math.ceil(float(cfg.hole_fraction) * n)))
        hole_idx = set(order[:width].tolist())
        hole = sorted(train[i].name for i in hole_idx)
        init = [i for i in init if i not in hole_idx]
    elif cfg.variant != "standard":
        raise B3dgsError(f"variant={cfg.variant} is unknown", "pass variant=standard or variant=support_hole")
    return init, hole


# ---------------------------------------------------------------------------------------------- study
#: study keys that decide which rows exist or where they go, not what a row holds
STUDY_IGNORED = ("policies", "pairs", "family_baselines", "share_training", "oracle", "seeds", "seed", "out_dir", "plots",
                 "acquisition.batch",  # batch settings (acquisition.batch_settings) do change rows
                 "family_posterior")  # recorded as the families' resolved blocks instead (study_protocol)


def merged_policies(meta_path: Path, policies: list, key: str = "policies") -> list:
    """The policies (or another list, ``key``) a scene folder's ``meta.json`` lists after this invocation: the earlier
    ones first, then this invocation's new ones. A study extended by a subset of its policies (or by new ones) keeps
    its rows listed."""
    earlier = (json.loads(meta_path.read_text()).get(key) or []) if meta_path.exists() else []
    return [*earlier, *[p for p in policies if p not in earlier]]


def study_protocol(cfg: DictConfig, family_posteriors: Optional[dict] = None) -> dict:
    """The flattened study settings that change its rows and caches (``out_dir/<scene>/protocol.json``), with
    ``family_posterior.<family>``: the posterior blocks of each family's model as composed (``family_posteriors``:
    the families of :data:`b3dgs.upgrade.FAMILY_POSTERIOR_UNRECORDED` and the pinned ones), where they differ from that
    table (:func:`b3dgs.upgrade.omit_study_defaults`)."""
    out = run_protocol(OmegaConf.to_container(cfg, resolve=True), ignore=RUN_IGNORED + STUDY_IGNORED)
    return omit_study_defaults(out, family_posteriors)


def legacy_protocol(out: Path) -> Optional[dict]:
    """What a scene folder written before ``protocol.json`` says of its settings (``meta.json``:
    :func:`b3dgs.upgrade.protocol_from_meta`), else None."""
    try:
        meta = json.loads((out / "meta.json").read_text())
    except (OSError, ValueError):
        return None
    return protocol_from_meta(meta)


class ActiveStudy:
    """One scene: phase-1 models, rows (policy × seed), results; see the module docstring."""

    def __init__(self, cfg: DictConfig):
        pins = row_pins(cfg)  # rows' blocks are their families' pins (one phase-1 model per family)
        if pins != {k: list(v) for k, v in (cfg.get("family_posterior") or {}).items()}:
            cfg = cfg.copy()
            with open_dict(cfg):
                cfg.family_posterior = pins
        self.cfg = cfg
        self.total = int(cfg.trainer.max_steps)
        self.phase1 = self.total // int(cfg.phase1_divisor)
        if not 0 < self.phase1 < self.total:
            raise B3dgsError(f"phase 1 would be {self.phase1} of {self.total} steps",
                             "pass trainer.max_steps >= 2 and phase1_divisor >= 2")
        full = data_module(cfg.data, keep_raw=True)  # the scene is read once: the pool, then its initial views
        self.pool_train = full.scene.train
        digest_of_pool = scene_digest(full.scene)  # before the candidates' images move to their store
        self.init_idx, self.hole = initial_views(cfg, self.pool_train)
        self.scene = full.select_train(self.init_idx, bool(cfg.init_points_from_train_only)).scene
        # the candidates' images: read by this driver only (acquisition, oracle, contact sheet)
        self.store = take_candidate_store(self.scene)
        self.out = Path(str(cfg.out_dir)) / self.scene.name
        self._family_cfgs: dict[str, DictConfig] = {}
        self.labels_policies = self._policies()
        for fam in sorted({p.family for _, p in self.labels_policies}):
            self.family_cfg(fam, 0)  # composed now, at start
        # the blocks of the core families and of the pinned ones (not of the families in use: protocol.json must not
        # depend on the policies run; another family's folders from before family_posterior stay valid)
        families = sorted(set(FAMILY_POSTERIOR_UNRECORDED) | set(cfg.get("family_posterior") or {}))
        posteriors = {fam: list(self.family_cfg(fam, 0).get("posterior") or {}) for fam in families}
        self.protocol = check_stored_protocol(
            self.out, study_protocol(cfg, posteriors), legacy=legacy_protocol(self.out),
            fix="pass another out_dir, or the settings of the rows there (their protocol.json) to continue them "
                "(a family's posterior blocks: family_posterior={niw:[...]})")
        self.scene_digest = check_stored_scene(
            self.out, digest_of_pool, fix=f"pass another out_dir (or remove {self.out} to start this scene over)")

    def family_cfg(self, family: str, seed: int) -> DictConfig:
        """:func:`family_config`, composed and validated (as ``b3dgs-train``'s) once per family when first needed: a
        study never re-reads conf/ mid-run, so editing a config file while it runs cannot hand its rows a config the
        loaded code lacks."""
        if family not in self._family_cfgs:
            from b3dgs.validation import validate_config

            cfg = family_config(self.cfg, family, 0)
            self._family_cfgs[family] = cfg, validate_config(cfg, app="train")
        out = self._family_cfgs[family][0].copy()
        out.seed = int(seed)
        return out

    def family_plugins(self, family: str) -> dict:
        """Copies of the plugins :meth:`family_cfg` validated, for one model (a round validates nothing again)."""
        self.family_cfg(family, 0)
        return copy.deepcopy(self._family_cfgs[family][1])

    def _policies(self) -> list[tuple[str, Any]]:
        """(row label, policy) of every row; ``self.batches[label]`` is the row's batch selector. A policy in
        ``policies`` without ``+batch`` gets a row per ``acquisition.batch`` option that applies to it (a policy
        that builds its batch itself gets its own selection, the topk row); ``name+batch`` asks for that row."""
        bset = self.cfg.get("acquisition", {}).get("batch_settings")
        selectors = {b: load_batch(b, bset) for b in batch_names(self.cfg)}
        rows = []  # (policy label, policy, batch name)
        for row in study_rows(self.cfg):
            pname, batch = row.policy_name, row.batch
            label, p = load_policy(pname, self.cfg.get("policy_settings"))
            if batch is None:  # one policy object per row: a policy caches its fitted regime
                mine = [b for b, sel in selectors.items() if sel.applies_to(p)] or [DEFAULT_BATCH]
                rows += [(label, load_policy(pname, self.cfg.get("policy_settings"))[1], b) for b in mine]
                continue
            if batch not in selectors:
                selectors[batch] = load_batch(batch, bset)
            if not selectors[batch].applies_to(p):
                raise B3dgsError(f"policy {pname} builds its batch itself, so batch {batch} does not apply to it",
                                 f"pass {pname} (its own selection) or a score-based policy with +{batch}")
            rows.append((label, p, batch))
        families = list(dict.fromkeys(p.family for _, p, _ in rows))
        have = {(type(p), p.family, b) for _, p, b in rows}
        for base in self.cfg.get("family_baselines") or []:
            for fam in families:
                label, p = load_policy(f"{base}@{fam}", self.cfg.get("policy_settings"))
                if (type(p), fam, DEFAULT_BATCH) not in have:
                    rows.append((label, p, DEFAULT_BATCH))
                    have.add((type(p), fam, DEFAULT_BATCH))
        # a label names the family when the policy's default family differs, e.g. uniform@niw
        out = []
        self.batches = {}
        default_family = functools.cache(lambda base: load_policy(base)[1].family)  # each base built once to read it
        for label, p, b in rows:
            base = label.partition("@")[0]
            lab = base if p.family == default_family(base) else f"{base}@{p.family}"
            lab = lab if b == DEFAULT_BATCH else f"{lab}+{b}"  # top-k rows keep the label rows always had
            if lab not in self.batches:
                out.append((lab, p))
                self.batches[lab] = selectors.get(b) or load_batch(b, bset)
        return out

    # ------------------------------------------------------------------ phase 1
    def phase1_dir(self, family: str, seed: int) -> Path:
        return self.out / "phase1" / f"{family}_s{seed}"

    def phase1_model(self, family: str, seed: int) -> str:
        """The phase-1 checkpoint of ``family`` and ``seed`` (trained once; an interrupted one resumes; one whose
        record was restored from an archive without its checkpoint is trained again, bit for bit the same)."""
        run = Run(run_dir=self.phase1_dir(family, seed))
        ckpt = run.run_dir / "checkpoints" / "last.ckpt"
        if (run.run_dir / PHASE1_DONE).exists() and ckpt.exists():
            return str(ckpt)
        from b3dgs.study.rounds import fit_round

        with run.exclusive():  # seeds run as parallel jobs share phase-1 models (the ensemble's members)
            if (run.run_dir / PHASE1_DONE).exists() and ckpt.exists():  # another job trained it while this one waited
                return str(ckpt)
            t0 = time.perf_counter()
            log.info("phase 1: %s seed %d, %d steps on %d views", family, seed, self.phase1, len(self.scene.train))
            fit_round(self.family_cfg(family, seed), self.scene, run.run_dir, self.phase1,
                      ckpt_path=str(ckpt) if ckpt.exists() else None, plugins=self.family_plugins(family))
            run.record(PHASE1_DONE, {"family": family, "seed": seed, "steps": self.phase1,
                                     "train_time_s": time.perf_counter() - t0,
                                     "train_views": [c.name for c in self.scene.train],
                                     "scene_digest": self.scene_digest})
            return str(ckpt)

    def scoring_models(self, family: str, seed: int, members: int):
        return [load_round(self.family_cfg(family, seed + i), self.scene, self.phase1_model(family, seed + i),
                           self.family_plugins(family)) for i in range(members)]

    def oracle_errors(self, family: str, seed: int) -> dict[str, float]:
        """The phase-1 model's current render error on every candidate (analysis only, cached)."""
        path = self.phase1_dir(family, seed) / "oracle.json"
        if path.exists():
            return json.loads(path.read_text())
        _, oracle = load_policy("oracle", self.cfg.get("policy_settings"))
        ctx = self.context(self.scoring_models(family, seed, 1), oracle, seed)
        scores = oracle.score(ctx, self.scene.candidates)
        out = {c.name: float(s) for c, s in zip(self.scene.candidates, scores)}
        write_json(path, out)
        return out

    def context(self, models, policy, seed: int, score_max_side: Any = "config"):
        """The policy's :class:`ScoringContext` (``score_max_side``: the study's ``acquisition.score_max_side``
        unless given; None scores at full size)."""
        from b3dgs.acquisition import ScoringContext

        side = self.cfg.acquisition.get("score_max_side") if score_max_side == "config" else score_max_side
        return ScoringContext(models, self.scene.train, side, self.scene.extent, seed,
                              ground_truth=self.store.image if policy.uses_ground_truth else None)

    # ------------------------------------------------------------------ rows
    def run_row(self, label: str, policy, seed: int) -> dict:
        from b3dgs.study.rounds import fit_round  # looked up per call (tests wrap it)

        row = Run(run_dir=self.out / f"{label}_s{seed}")  # a row is a run; result.json its done marker
        d, res = row.run_dir, row.recorded(ROW_DONE)
        if res is not None:  # a finished row is never retrained
            return res
        cands = self.scene.candidates
        sel = row.recorded(ROW_SELECTION)
        if sel is None:
            models = self.scoring_models(policy.family, seed, int(policy.members))
            ctx = self.context(models, policy, seed)
            t0 = time.perf_counter()
            s = self.batches[label].select(policy, ctx, cands, int(self.cfg.acquire))
            dt = time.perf_counter() - t0
            scores = None if s.scores is None else {c.name: float(v) for c, v in zip(cands, s.scores)}
            top = None if scores is None else sorted(scores.items(), key=lambda kv: (-kv[1], kv[0]))[:10]
            sel = {"policy": label, "seed": seed, "family": policy.family, "selected": [cands[i].name for i in s.indices],
                   "scores": scores, "top10": top, "scoring_time_s": dt, "members": int(policy.members),
                   "uses_ground_truth": bool(policy.uses_ground_truth), "batch": StudyRow.parse(label).batch or DEFAULT_BATCH,
                   "batch_info": s.info}
            row.record(ROW_SELECTION, sel)
            del models, ctx
        twin = self.training_twin(label, policy.family, seed, sel["selected"])
        hole_hits = sum(1 for n in sel["selected"] if n in set(self.hole)) if self.hole else None
        if twin is not None:  # the same training run exists: share it, never retrain it
            res = {**sel, **{k: twin[k] for k in ("psnr", "ssim", "lpips", "train_time_s", "round2_time_s",
                                                  "num_gaussians", "steps")},
                   "training_shared_with": twin["policy"], "hole_hits": hole_hits}
            return row.record(ROW_DONE, res)
        by_name = {c.name: c for c in cands}
        acquired = [self.store.acquire(by_name[n]) for n in sel["selected"]]
        scene2 = dataclasses.replace(self.scene, train=list(self.scene.train) + acquired,
                                     candidates=[c for c in cands if c.name not in set(sel["selected"])])
        own = d / "checkpoints" / "last.ckpt"
        cfg_f, plugins = self.family_cfg(policy.family, seed), self.family_plugins(policy.family)
        t0 = time.perf_counter()
        if own.exists():  # an interrupted second round
            module = fit_round(cfg_f, scene2, d, self.total, ckpt_path=str(own), plugins=plugins)
        else:
            module = fit_round(cfg_f, scene2, d, self.total, ckpt_path=self.phase1_model(policy.family, seed),
                               new_round=True, plugins=plugins)
        t_round2 = time.perf_counter() - t0
        t_phase1 = float(Run(run_dir=self.phase1_dir(policy.family, seed)).recorded(PHASE1_DONE)["train_time_s"])
        ev = self.evaluate(module)
        res = {**sel, "psnr": ev.get("psnr"), "ssim": ev.get("ssim"), "lpips": ev.get("lpips"),
               "train_time_s": t_phase1 + t_round2, "round2_time_s": t_round2,
               "num_gaussians": module.num_gaussians, "steps": int(module.global_step), "hole_hits": hole_hits,
               "scene_digest": self.scene_digest}
        return row.record(ROW_DONE, res)

    def training_twin(self, label: str, family: str, seed: int, selected: list[str]) -> Optional[dict]:
        """A finished, separately trained row of this seed whose second round is the same run: the same
        training signature and the same acquired views in the same order (e.g. ``uniform@niw`` and
        ``uniform``, since NIW only observes training). None when ``share_training`` is off."""
        if not self.cfg.get("share_training", True):
            return None
        mine = training_signature(self.family_cfg(family, seed))
        for other, pol in self.labels_policies:
            res = None if other == label else Run(run_dir=self.out / f"{other}_s{seed}").recorded(ROW_DONE)
            if res is None:
                continue
            if res.get("training_shared_with") is None and res["selected"] == list(selected) \
                    and training_signature(self.family_cfg(pol.family, seed)) == mine:
                return res
        return None

    def evaluate(self, module) -> dict:
        from b3dgs.metrics.views import evaluate_views
        from b3dgs.metrics.lpips import get_lpips

        lp, _ = get_lpips()
        module.eval()
        return evaluate_views(module, self.scene.test, lpips_model=lp)

    # ------------------------------------------------------------------ all
    def run(self) -> dict:
        meta = {"scene": self.scene.name, "variant": str(self.cfg.variant), "initial_views": [c.name for c in self.scene.train],
                "candidates": [c.name for c in self.scene.candidates], "hole": self.hole,
                "test_views": [c.name for c in self.scene.test], "phase1_steps": self.phase1, "total_steps": self.total,
                "acquire": int(self.cfg.acquire), "score_max_side": self.cfg.acquisition.get("score_max_side"),
                "point_filter": self.store.point_filter,
                "policies": merged_policies(self.out / "meta.json", [l for l, _ in self.labels_policies]),
                "pool_train_views": [c.name for c in self.pool_train]}
        meta["pairs"] = merged_policies(self.out / "meta.json", study_pairs(self.cfg), "pairs")
        write_json(self.out / "meta.json", meta)
        xy = pca_xy(self.pool_train)
        write_json(self.out / "layout.json", {"xy": {c.name: [float(a), float(b)] for c, (a, b) in zip(self.pool_train, xy)},
                                              "initial": meta["initial_views"], "hole": self.hole})
        for seed in [int(s) for s in self.cfg.seeds]:
            for label, policy in self.labels_policies:
                res = self.run_row(label, policy, seed)
                log.info("%s s%d: PSNR %.3f, picked %s", label, seed, res["psnr"] or float("nan"), res["selected"])
            if self.cfg.get("oracle", True):
                for fam in sorted({p.family for _, p in self.labels_policies}):
                    self.oracle_errors(fam, seed)
        from b3dgs.study.active_tables import write_report

        return write_report(self.out, plots=bool(self.cfg.get("plots", True)), store=self.store)


def hydra_main() -> None:
    """Run the study from the command line (``b3dgs-study active ...``)."""
    study_app("study", ActiveStudy)()


def main() -> None:
    """``b3dgs-study active ...`` (see :mod:`b3dgs.study.cli`)."""
    if sys.argv[1:2] != ["active"]:
        sys.argv.insert(1, "active")
    cli_main()


if __name__ == "__main__":
    main()

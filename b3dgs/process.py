"""``b3dgs-process``: a folder of photos to a COLMAP scene that ``b3dgs-train`` trains (``conf/process.yaml``).

    b3dgs-process images=photos/ out=data/mine                     # then the printed `b3dgs-train scene=mine ...`
    b3dgs-process images=photos/ out=data/mine matcher=sequential max_side=1000

Four stages with pycolmap on the CPU, each with a bar and its time: ``extract`` (SIFT), ``match`` (``matcher=auto``:
exhaustive up to 200 photos, else COLMAP's sequential matcher in name order; no vocabulary tree, which needs a download),
``map`` (incremental; the largest model kept, retried at an initial triangulation angle of 8° then 4° instead of 16°
while fewer than ``min_registered`` photos register) and ``undistort`` (PINHOLE, long side at most ``max_side``, the
cameras and 2D points scaled by the same per-axis ratio). ``video=clip.mp4 fps=2`` decodes frames first
(:func:`extract_frames`). The same photos and ``seed`` give the same scene (:func:`_renumber`; RANSAC seeded).

The result is the COLMAP layout ``data=colmap`` loads (``out/images/``, ``out/sparse/0/``) plus
``out/conf/scene/<name>.yaml``. Resumable: each stage writes a ``.partial`` path under ``out/.b3dgs-process/``, renames
it when done and records itself in ``out/.b3dgs-process.json`` with its options and the photo listing's fingerprint; a
rerun skips recorded stages with the same options and reruns a changed one and those after it. A changed photo folder
or a foreign ``out=`` is refused; ``overwrite=true`` removes only the files the state file lists. docs/user-guide.md
has the user's view (progress, refusals, timings).
"""
from __future__ import annotations

import hashlib
import json
import math
import os
import re
import shlex
import shutil
import sys
import threading
import time
from contextlib import closing, contextmanager, suppress
from pathlib import Path
from typing import Any, Callable, Iterator, Optional

import hydra
from omegaconf import DictConfig

from b3dgs import conf_dir, data_root
from b3dgs.errors import B3dgsError, cli_main, did_you_mean, known_errors
from b3dgs.io import atomic_path, write_json
from b3dgs.rundir import remove_listed
from b3dgs.signals import PENDING, Interrupted, interrupt_handlers

__all__ = ["EXHAUSTIVE_UP_TO", "STAGES", "extract_frames", "list_photos", "main", "process"]

STATE = ".b3dgs-process.json"   # the record of finished stages, in out/
WORK = ".b3dgs-process"         # the stages' own files (databases, the raw model), in out/
LOCK = ".b3dgs-process.lock"
FRAMES = "frames"                # video=: the frames, in out/.b3dgs-process/
STAGES = ("extract", "match", "map", "undistort")
PHOTO_SUFFIXES = (".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff")
MATCHERS = ("auto", "exhaustive", "sequential")
EXHAUSTIVE_UP_TO = 200          # matcher=auto: exhaustive up to this many photos, sequential beyond
SEQUENTIAL_OVERLAP = 10         # COLMAP's default, quadratic: each photo with those 1, 2, 4, ..., 512 after it
MIN_PHOTOS = 3
MAP_RETRIES = (8.0, 4.0)        # init_min_tri_angle (degrees) of the mapping tries after COLMAP's 16°
FORMAT = 1                      # of the state file
CONF_DIR = conf_dir()
NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")


# ----------------------------------------------------------------------------------------------- the photos


def list_photos(folder: Path) -> list[Path]:
    """The photos directly inside ``folder`` (:data:`PHOTO_SUFFIXES`, any case; hidden files skipped), by name.
    Raises :class:`B3dgsError` for a missing or unreadable folder, unreadable photos and fewer than 3 photos."""
    fix = "pass images= the folder whose files are the photos"
    if not folder.exists():
        raise B3dgsError(f"images={folder}: no such folder", fix)
    if not folder.is_dir():
        raise B3dgsError(f"images={folder} is a file, not a folder", fix)
    try:
        entries = sorted(folder.iterdir())
    except OSError as e:
        raise B3dgsError(f"cannot read the folder images={folder}: {e.strerror or e}",
                         "make it readable (chmod u+rx), or pass another folder") from e
    photos = [p for p in entries if not p.name.startswith(".") and p.suffix.lower() in PHOTO_SUFFIXES and p.is_file()]
    if not photos:
        subs = [p.name for p in entries if p.is_dir() and not p.name.startswith(".")]
        hint = f"; it has the subfolders {', '.join(subs[:3])}{', ...' if len(subs) > 3 else ''}" if subs else ""
        raise B3dgsError(f"images={folder} holds no photos ({' '.join(PHOTO_SUFFIXES)}){hint}",
                         f"{fix} (subfolders are not read)")
    unreadable = [p.name for p in photos if not os.access(p, os.R_OK)]
    if unreadable:
        raise B3dgsError(f"{len(unreadable)} photos in images={folder} cannot be read ({', '.join(unreadable[:3])})",
                         "make them readable (chmod u+r), or move them out of the folder")
    if len(photos) < MIN_PHOTOS:
        raise B3dgsError(f"images={folder} holds {len(photos)} photo{'s' if len(photos) != 1 else ''}; structure "
                         f"from motion needs at least {MIN_PHOTOS} views of the scene",
                         "add photos taken from different positions, each part of the scene in 3 or more of them "
                         "(20-200 is typical)")
    return photos


def _sizes(photos: list[Path]) -> list[tuple[int, int]]:
    """(width, height) of every photo, each decoded whole first (a JPEG at 1/8 scale, which still reads all of its
    data): a truncated or corrupt photo is refused in one line naming it, before anything is written (SfM would
    register it and the undistortion copy its missing part as a flat fill)."""
    from PIL import Image

    out = []
    for p in photos:
        try:
            with Image.open(p) as im:
                size = int(im.width), int(im.height)
                im.draft("RGB", (max(1, size[0] // 8), max(1, size[1] // 8)))  # JPEG only; others decode in full
                im.load()
        except Exception as e:  # noqa: BLE001 - PIL raises OSError, SyntaxError, ValueError, zlib errors...
            why = " ".join(str(e).replace(f"'{p}'", "it").replace(str(p), "it").split()) or type(e).__name__
            raise B3dgsError(f"cannot read the photo {p} whole: {why}",
                             "remove it from images= or replace it with a complete copy") from None
        out.append(size)
    return out


# ----------------------------------------------------------------------------------------------- progress


def _say(text: str) -> None:
    print(text, flush=True)


def _bar(desc: str, total: int, unit: str):
    from b3dgs.progress import progress

    return progress(total=total, desc=f"  {desc}", unit=unit, file=sys.stdout)


def _advance(bar, n: int) -> None:
    n = min(int(n), int(bar.total)) if bar.total else int(n)
    if n > bar.n:
        bar.update(n - bar.n)


def _stop_if_signalled() -> None:
    """Raise :class:`b3dgs.signals.Interrupted` for a SIGINT / SIGTERM recorded since :func:`process` began. The
    handlers only record (``deferred``): an exception raised wherever the signal lands could be swallowed by a
    library's ``except Exception`` (tqdm's monitor thread start is one), so it is raised here, at known points."""
    if PENDING.signum is not None:
        raise Interrupted(PENDING.signum)


def _call(fn: Callable[[], Any], poll: Optional[Callable[[], None]] = None, period: float = 0.5) -> Any:
    """``fn()`` (one pycolmap call) in a worker thread, while this thread calls ``poll()`` every ``period`` seconds and
    acts on SIGINT / SIGTERM within ``period``: a signal handler runs only in the main thread and only between Python
    calls, so a stage run in the main thread would ignore Ctrl-C until it returned."""
    box: dict[str, Any] = {}

    def target() -> None:
        try:
            box["value"] = fn()
        except BaseException as e:  # noqa: BLE001 - re-raised in the calling thread
            box["error"] = e

    t = threading.Thread(target=target, name="b3dgs-process-colmap", daemon=True)
    t.start()
    while t.is_alive():
        t.join(period)
        _stop_if_signalled()
        if poll is not None:
            poll()
    if "error" in box:
        raise box["error"]
    return box.get("value")


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path)
    elif path.exists() or path.is_symlink():
        path.unlink()
    for suffix in ("-wal", "-shm", "-journal"):
        Path(f"{path}{suffix}").unlink(missing_ok=True)


@contextmanager
def _colmap_log(verbose: bool) -> Iterator[Any]:
    """pycolmap with its log off (its errors too: b3dgs-process reports what failed in its own line; everything with
    ``verbose``); the old level restored."""
    from b3dgs.data.images import import_pycolmap

    pycolmap = import_pycolmap()
    old = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = 0 if verbose else 3
    try:
        yield pycolmap
    finally:
        pycolmap.logging.minloglevel = old


# ----------------------------------------------------------------------------------------------- the stages


def _renumber(pycolmap, src: Path, dst: Path, names: list[str]) -> None:
    """Copy the feature database ``src`` into ``dst`` with its ids in name order: photo ``names[i]`` gets image and
    frame id ``i + 1``, its camera and rig ids numbered by first use in that order. COLMAP's extractor numbers photos
    as its threads finish them, and every later stage depends on the ids (a pair's matches are stored from the smaller
    id to the larger, which changes RANSAC's samples; the mapper breaks ties by id): with these ids, the same photos
    give the same scene whatever the thread count or timing."""
    _remove(dst)
    with closing(pycolmap.Database.open(str(src))) as old, closing(pycolmap.Database.open(str(dst))) as new:
        images = {im.name: im for im in old.read_all_images()}
        cameras = {c.camera_id: c for c in old.read_all_cameras()}
        priors = {}
        for prior in old.read_all_pose_priors():
            priors.setdefault(int(prior.corr_data_id.id), []).append(prior)
        cam_ids: dict[int, int] = {}
        for i, name in enumerate((n for n in names if n in images), start=1):
            im = images[name]
            if im.camera_id not in cam_ids:
                cam = cameras[im.camera_id]
                cam_ids[im.camera_id] = cam.camera_id = len(cam_ids) + 1
                new.write_camera(cam, use_camera_id=True)
                rig = pycolmap.Rig()
                rig.rig_id = cam.camera_id
                rig.add_ref_sensor(pycolmap.sensor_t(pycolmap.SensorType.CAMERA, cam.camera_id))
                new.write_rig(rig, use_rig_id=True)
            cam_id = cam_ids[im.camera_id]
            keypoints, descriptors = old.read_keypoints(im.image_id), old.read_descriptors(im.image_id)
            frame = pycolmap.Frame()
            frame.frame_id, frame.rig_id = i, cam_id
            frame.add_data_id(pycolmap.data_t(pycolmap.sensor_t(pycolmap.SensorType.CAMERA, cam_id), i))
            new.write_frame(frame, use_frame_id=True)
            for prior in priors.get(int(im.image_id), []):
                prior.corr_data_id = pycolmap.data_t(pycolmap.sensor_t(pycolmap.SensorType.CAMERA, cam_id), i)
                new.write_pose_prior(prior)
            im.image_id, im.camera_id, im.frame_id = i, cam_id, i
            new.write_image(im, use_image_id=True)
            new.write_keypoints(i, keypoints)
            new.write_descriptors(i, descriptors)


class _Run:
    """One ``b3dgs-process`` invocation: its inputs, options and the paths of its stages."""

    def __init__(self, cfg: DictConfig, photos: list[Path], sizes: list[tuple[int, int]], images: Path, out: Path,
                 single: bool, matcher: str, state: dict):
        self.cfg, self.photos, self.sizes, self.images, self.out = cfg, photos, sizes, images, out
        self.state = state
        self.work = out / WORK
        self.single, self.matcher = single, matcher
        self.threads = -1 if cfg.get("threads") is None else int(cfg.threads)
        self.names = [p.name for p in photos]

    # the options each stage ran with; each includes the ones before it, so a change reruns every later stage
    def keys(self) -> dict[str, dict]:
        c = self.cfg
        extract = {"camera_model": str(c.camera_model), "single_camera": self.single,
                   "sift_max_side": int(c.sift_max_side)}
        match = {**extract, "matcher": self.matcher, "seed": int(c.seed)}
        return {"extract": extract, "match": match, "map": dict(match),
                "undistort": {**match, "max_side": int(c.max_side)}}

    def outputs(self, stage: str) -> list[Path]:
        return {"extract": [self.work / "features.db"], "match": [self.work / "matches.db"],
                "map": [self.work / "model" / "images.bin"],
                "undistort": [self.out / "images", self.out / "sparse" / "0" / "images.bin"]}[stage]

    def _chunk(self, n: int, least: int) -> int:
        """Items per pycolmap call: at least ``least`` (and 4 per thread), at most 50 calls in all. Each call ends
        with a database the next one reads, so the bar counts real work, and no second SQLite ever reads the
        database while pycolmap writes it (two SQLite libraries in one process break each other's file locks:
        polling it that way crashed pycolmap with SIGBUS)."""
        threads = (os.cpu_count() or 1) if self.threads < 0 else self.threads
        return max(least, 4 * threads, math.ceil(n / 50))

    def extract(self, pycolmap) -> dict:
        part = self.work / "features.db.partial"
        _remove(part)
        opts = pycolmap.FeatureExtractionOptions()
        opts.max_image_size = int(self.cfg.sift_max_side)
        opts.num_threads = self.threads
        mode = pycolmap.CameraMode.SINGLE if self.single else pycolmap.CameraMode.PER_IMAGE
        bar = _bar("extract", len(self.names), " photos")
        step, camera = self._chunk(len(self.names), 8), -1
        for start in range(0, len(self.names), step):
            names = self.names[start:start + step]
            reader = pycolmap.ImageReaderOptions()
            reader.camera_model = str(self.cfg.camera_model)
            reader.existing_camera_id = camera  # one shared camera: the first call's, for the later calls too
            _call(lambda: pycolmap.extract_features(part, self.images, image_names=names, camera_mode=mode,
                                                    reader_options=reader, extraction_options=opts,
                                                    device=pycolmap.Device.cpu))
            if self.single and camera < 0 and part.is_file():
                with closing(pycolmap.Database.open(str(part))) as db:
                    camera = min((c.camera_id for c in db.read_all_cameras()), default=-1)
            bar.update(len(names))
        bar.close()
        if not part.is_file():
            raise B3dgsError(f"pycolmap extracted no features from the photos in {self.images}",
                             "check that the photos open in an image viewer; verbose=true shows COLMAP's log")
        with closing(pycolmap.Database.open(str(part))) as db:
            rows = {im.name: int(db.num_keypoints_for_image(im.image_id)) for im in db.read_all_images()}
        _renumber(pycolmap, part, self.work / "features.db.sorted", self.names)
        os.replace(self.work / "features.db.sorted", self.work / "features.db")
        _remove(part)
        empty = [n for n in self.names if not rows.get(n)]
        return {"keypoints": sum(rows.values()), "photos_without_features": empty,
                "note": f"{sum(rows.values()):,} keypoints"
                        + (f"; {len(empty)} photos without features ({', '.join(empty[:3])})" if empty else "")}

    @staticmethod
    def _sequential(pycolmap):
        """COLMAP's sequential pairing with its defaults (quadratic overlap of 10), without loop detection."""
        pairing = pycolmap.SequentialPairingOptions()
        pairing.overlap = SEQUENTIAL_OVERLAP
        pairing.quadratic_overlap = True
        pairing.loop_detection = False
        return pairing

    def _pairs(self, pycolmap, db_path: Path) -> list[tuple[str, str]]:
        """The pairs to match, by name: every pair in blocks of 50 photos (as COLMAP's exhaustive matcher visits
        them, so each call loads the features of at most 100 photos), or those of COLMAP's sequential generator."""
        if self.matcher == "exhaustive":
            n, b = len(self.names), 50
            return [(self.names[i], self.names[j]) for s1 in range(0, n, b) for s2 in range(s1, n, b)
                    for i in range(s1, min(s1 + b, n)) for j in range(max(s2, i + 1), min(s2 + b, n))]
        with closing(pycolmap.Database.open(str(db_path))) as db:
            names = {im.image_id: im.name for im in db.read_all_images()}
            gen = pycolmap.SequentialPairGenerator(self._sequential(pycolmap), db)
            return [(names[a], names[b]) for a, b in gen.all_pairs()]

    def match(self, pycolmap) -> dict:
        part, listing = self.work / "matches.db.partial", self.work / "pairs.partial.txt"
        _remove(part)
        shutil.copyfile(self.work / "features.db", part)
        opts = pycolmap.FeatureMatchingOptions()
        opts.num_threads = self.threads
        verify = pycolmap.TwoViewGeometryOptions()
        verify.ransac.random_seed = int(self.cfg.seed)  # else each pair's RANSAC is seeded at random
        pairs = self._pairs(pycolmap, part)
        bar = _bar(f"match ({self.matcher})", len(pairs), " pairs")
        if any(c.isspace() for x in self.names for c in x):
            # COLMAP's pair list is "name1 name2" per line: names with white space take its own matcher in one call
            run = pycolmap.match_exhaustive if self.matcher == "exhaustive" else pycolmap.match_sequential
            kw = {} if self.matcher == "exhaustive" else {"pairing_options": self._sequential(pycolmap)}
            _call(lambda: run(part, matching_options=opts, verification_options=verify, device=pycolmap.Device.cpu,
                              **kw))
            bar.update(len(pairs))
        else:
            step = self._chunk(len(pairs), 400)
            for start in range(0, len(pairs), step):
                chunk = pairs[start:start + step]
                listing.write_text("".join(f"{a} {b}\n" for a, b in chunk))
                pairing = pycolmap.ImportedPairingOptions()
                pairing.match_list_path = str(listing)
                _call(lambda: pycolmap.match_image_pairs(part, matching_options=opts, pairing_options=pairing,
                                                         verification_options=verify, device=pycolmap.Device.cpu))
                bar.update(len(chunk))
        bar.close()
        _remove(listing)
        with closing(pycolmap.Database.open(str(part))) as db:
            ids = {im.image_id: im.name for im in db.read_all_images()}
            pair_ids, inliers = db.read_two_view_geometry_num_inliers()
            matched = {ids.get(int(i)) for p, k in zip(pair_ids, inliers) if k > 0
                       for i in pycolmap.pair_id_to_image_pair(p)}
            verified = sum(1 for k in inliers if k > 0)
        os.replace(part, self.work / "matches.db")
        return {"pairs": len(pairs), "verified_pairs": verified,
                "photos_without_matches": [n for n in self.names if n not in matched],
                "note": f"{verified:,} of {len(pairs):,} pairs with verified matches"}

    def need(self) -> int:
        """The fewest registered photos a model must have (``min_registered`` of them, and at least 3)."""
        return max(MIN_PHOTOS, math.ceil(float(self.cfg.min_registered) * len(self.names) - 1e-9))

    def may_retry(self, rec: dict) -> bool:
        """Whether a recorded mapping registered fewer than :meth:`need` without making every try (it ran under a
        lower ``min_registered``): then it is run again."""
        return int(rec.get("registered", 0)) < self.need() and len(rec.get("tries", [])) <= len(MAP_RETRIES)

    def _map_once(self, pycolmap, part: Path, tri: Optional[float], desc: str) -> tuple[int, Any, int]:
        """One incremental mapping into ``part``: (registered photos of its largest model, that model, models)."""
        _remove(part)
        part.mkdir(parents=True)
        opts = pycolmap.IncrementalPipelineOptions()
        opts.random_seed = int(self.cfg.seed)
        opts.min_model_size = MIN_PHOTOS
        # one thread: the mapper's bundle adjustment and triangulation sum in thread order, and under load two runs
        # of the same photos differed by 0.26 in pose (the full suite beside other jobs); extraction and matching
        # keep every thread (their results no longer depend on the order threads finish in)
        opts.num_threads = 1
        if tri is not None:
            opts.mapper.init_min_tri_angle = tri
        bar = _bar(desc, len(self.names), " photos")
        started = [0, 0]  # models started (2 photos each), photos added after their first pair

        def step(k: int) -> None:
            started[k] += 1
            _advance(bar, 2 * started[0] + started[1])

        recs = _call(lambda: pycolmap.incremental_mapping(self.work / "matches.db", self.images, part, options=opts,
                                                          initial_image_pair_callback=lambda: step(0),
                                                          next_image_callback=lambda: step(1)))
        bar.close()
        if not recs:
            return 0, None, 0
        best = max(recs.items(), key=lambda kv: (kv[1].num_reg_images(), -kv[0]))[1]
        return int(best.num_reg_images()), best, len(recs)

    def map(self, pycolmap) -> dict:
        """Incremental mapping with COLMAP's options; when its largest model registers fewer than :meth:`need`,
        again with a smaller ``init_min_tri_angle`` (:data:`MAP_RETRIES`), keeping the largest model of all tries."""
        part, model_part, model = self.work / "mapping.partial", self.work / "model.partial", self.work / "model"
        _remove(model_part)
        n, best, tries, models = len(self.names), (0, None, 0), [], 0
        for k, tri in enumerate((None, *MAP_RETRIES)):
            if k:
                _say(f"  map: {best[0]} of {n} photos registered, fewer than {self.need()}; again with "
                     f"init_min_tri_angle={tri:g}° (COLMAP's 16° fails on small baselines, e.g. forward-facing photos)")
            desc = "map" if tri is None else f"map (init_min_tri_angle={tri:g})"
            got = self._map_once(pycolmap, part, tri, desc)
            tries.append({"init_min_tri_angle": tri, "registered": got[0], "models": got[2]})
            if got[1] is not None and got[0] > best[0]:
                best = got
                _remove(model_part)
                model_part.mkdir(parents=True)
                got[1].write(model_part)
            if best[0] >= self.need():
                break
        _remove(part)
        _remove(model)
        reg_n, rec, models = best
        if rec is None:
            return {"registered": 0, "models": 0, "points": 0, "unregistered": self.names, "tries": tries,
                    "note": "no model: no pair of photos could start one"}
        os.replace(model_part, model)
        reg = {im.name for im in rec.images.values() if im.has_pose}
        missing = [x for x in self.names if x not in reg]
        error = float(rec.compute_mean_reprojection_error())
        error = error if math.isfinite(error) else None  # JSON has no NaN
        shown = "n/a" if error is None else f"{error:.2f} px"
        return {"registered": len(reg), "models": models, "points": int(rec.num_points3D()),
                "reprojection_error_px": error, "unregistered": missing, "tries": tries,
                "note": f"{len(reg)} of {n} photos registered, {rec.num_points3D():,} points, mean reprojection "
                        f"{shown}" + (f", {models} models (the largest kept)" if models > 1 else "")
                        + (f", after {len(tries)} tries" if len(tries) > 1 else "")}

    def _into_place(self, new: dict[str, Path]) -> None:
        """Move the files ``new`` (name in ``out`` -> staged file) into ``out``, replacing only what b3dgs-process
        wrote there (:func:`_owned`): a user's file in ``images/`` or ``sparse/0/`` stays, and one that a new file
        would replace is refused. The names are recorded before they are moved; the earlier ones not written again
        go. A kill in between leaves the stage unrecorded, and the rerun does it again."""
        owned = _owned(self.out, self.state)
        clash = [f for f in new if (self.out / f).exists() and f not in owned]
        if clash:
            raise B3dgsError(f"out={self.out} holds {', '.join(clash[:3])}, which b3dgs-process did not write and "
                             "would replace", f"move {'them' if len(clash) > 1 else 'it'} out of {self.out}, or "
                             "pass out= a new folder")
        remove_listed(self.out, [f for f in owned if f not in new])
        self.state["files"] = sorted(set(owned) | set(new))
        write_json(self.out / STATE, self.state)
        for f, src in new.items():
            (self.out / f).parent.mkdir(parents=True, exist_ok=True)
            os.replace(src, self.out / f)
        self.state["files"] = sorted(new)
        write_json(self.out / STATE, self.state)

    def undistort(self, pycolmap) -> dict:
        from PIL import Image

        from b3dgs.types import fit_size

        stage = self.work / "undistort.partial"
        _remove(stage)
        model = pycolmap.Reconstruction(str(self.work / "model"))
        n = sum(1 for im in model.images.values() if im.has_pose)
        bar = _bar("undistort", n, " photos")
        _call(lambda: pycolmap.undistort_images(stage, self.work / "model", self.images, num_threads=self.threads),
              lambda: _advance(bar, len(list((stage / "images").iterdir())) if (stage / "images").is_dir() else 0))
        bar.close()
        rec = pycolmap.Reconstruction(str(stage / "sparse"))
        max_side = int(self.cfg.max_side)
        scales = {}
        for cam in rec.cameras.values():
            w, h = int(cam.width), int(cam.height)
            w2, h2 = fit_size(w, h, max_side)
            scales[cam.camera_id] = (w2 / w, h2 / h, w2, h2, (w2, h2) != (w, h))
            if (w2, h2) != (w, h):
                cam.rescale(w2, h2)
        images = [im for im in rec.images.values() if im.has_pose]
        bar = _bar(f"resize (long side <= {max_side} px)", len(images), " photos")
        for im in images:
            _stop_if_signalled()
            sx, sy, w2, h2, resize = scales[im.camera_id]
            if resize:
                path = stage / "images" / im.name
                with Image.open(path) as src:
                    fmt = src.format
                    small = src.resize((w2, h2), Image.LANCZOS)
                small.save(path, format=fmt, **({"quality": 95} if fmt == "JPEG" else {}))
                for p in im.points2D:
                    p.xy = [p.xy[0] * sx, p.xy[1] * sy]
            bar.update(1)
        bar.close()
        (stage / "model").mkdir()
        rec.write(str(stage / "model"))
        sizes = sorted({(v[2], v[3]) for v in scales.values()})
        self._into_place({**{f"images/{n}": stage / "images" / n for n in sorted(os.listdir(stage / "images"))},
                          **{f"sparse/0/{n}": stage / "model" / n for n in sorted(os.listdir(stage / "model"))}})
        _remove(stage)
        size = " / ".join(f"{w}x{h}" for w, h in sizes[:3]) + (" / ..." if len(sizes) > 3 else "")
        return {"images": len(images), "sizes": [list(s) for s in sizes], "size": size,
                "note": f"{len(images)} PINHOLE images of {size} px"}


# ----------------------------------------------------------------------------------------------- state and checks


def _read_state(out: Path) -> Optional[dict]:
    path = out / STATE
    if not path.is_file():
        return None
    try:
        state, why = json.loads(path.read_text()), "not a b3dgs-process record"
    except (OSError, ValueError) as e:
        state, why = None, e
    if isinstance(state, dict) and state.get("format") == FORMAT and isinstance(state.get("stages"), dict):
        return state
    raise B3dgsError(f"{path} is damaged ({why})",
                     f"delete {out} (or that file and {out / WORK}) and run again, or pass out= a new folder")


def _check_out(out: Path, images: Path, state: Optional[dict], key: str = "images") -> None:
    if out.exists() and not out.is_dir():
        raise B3dgsError(f"out={out} is a file", "pass out= a new or empty folder")
    if images.resolve().is_relative_to(out.resolve()):
        raise B3dgsError(f"{key}={images} is inside out={out}, where the undistorted images are written",
                         f"pass out= a folder outside the photos' folder, e.g. out={out.parent / (out.name + '_scene')}")
    if state is None and out.is_dir():
        other = sorted(p.name for p in out.iterdir() if p.name != LOCK)
        if other:
            raise B3dgsError(f"out={out} holds what b3dgs-process did not write "
                             f"({', '.join(other[:3])}{f' and {len(other) - 3} more' if len(other) > 3 else ''})",
                             "pass out= a new or empty folder")


def _left_out(state: dict, names: list[str]) -> dict[str, str]:
    """Every photo the scene does not hold, by name, with why (the first that applies, in stage order)."""
    reasons = [(set(state["stages"][stage].get(key, [])), why) for stage, key, why in (
        ("extract", "photos_without_features", "no SIFT features found"),
        ("match", "photos_without_matches", "no verified matches with any other photo"),
        ("map", "unregistered", "not registered by the mapper"))]
    whys = {n: next((why for left, why in reasons if n in left), None) for n in names}
    return {n: why for n, why in whys.items() if why is not None}


def _not_photos(folder: Path) -> list[str]:
    """The files in ``folder`` that :func:`list_photos` does not read (another suffix; hidden files not named)."""
    try:
        return sorted(p.name for p in folder.iterdir() if p.is_file() and not p.name.startswith(".")
                      and p.suffix.lower() not in PHOTO_SUFFIXES)
    except OSError:
        return []


def _diff(old: list, new: list) -> str:
    a, b = {r[0]: r[1:] for r in old}, {r[0]: r[1:] for r in new}
    added, removed = len(set(b) - set(a)), len(set(a) - set(b))
    changed = sum(1 for k in set(a) & set(b) if a[k] != b[k])
    return f"{added} added, {removed} removed, {changed} changed"


#: what pycolmap writes into a model folder (``sparse/0/``): a state file from before b3dgs-process listed its files
#: owns these there, and the photos it lists in ``images/``
MODEL_FILES = ("cameras.bin", "images.bin", "points3D.bin", "rigs.bin", "frames.bin")


def _owned(out: Path, state: dict) -> list[str]:
    """The files b3dgs-process wrote into ``out``'s ``images/`` and ``sparse/0/``, as its state file lists them (one
    written before it listed them: the photos it names and pycolmap's model files)."""
    files = state.get("files")
    if isinstance(files, list) and all(isinstance(f, str) for f in files):
        return list(files)
    names = [r[0] for r in state.get("photos", []) if isinstance(r, list) and r and isinstance(r[0], str)]
    return [f"images/{n}" for n in names] + [f"sparse/0/{n}" for n in MODEL_FILES]


def _remove_ours(out: Path, state: dict) -> None:
    """``overwrite=true``: what b3dgs-process wrote into ``out``, by name (:func:`_owned`, its work folder, the scene
    file and the state file), and the folders that this leaves empty; a user's file beside them stays."""
    scene_file = state.get("scene_file")
    remove_listed(out, [*_owned(out, state), *([scene_file] if isinstance(scene_file, str) else [])])
    _remove(out / WORK)
    _remove(out / STATE)


def _check_options(cfg: DictConfig, pycolmap) -> None:
    matcher = str(cfg.matcher)
    if matcher not in MATCHERS:
        raise B3dgsError(f"matcher={matcher} is not a matcher{did_you_mean(matcher, MATCHERS)}",
                         f"pass matcher={'|'.join(MATCHERS)}")
    models = [m for m in pycolmap.CameraModelId.__members__ if m != "INVALID"]
    if str(cfg.camera_model) not in models:
        raise B3dgsError(f"camera_model={cfg.camera_model} is not a COLMAP camera model"
                         f"{did_you_mean(str(cfg.camera_model), models)}", f"pass one of {', '.join(models)}")


def _scene_name(cfg: DictConfig, out: Path) -> str:
    given = cfg.get("name")
    name = str(given) if given is not None else re.sub(r"[^A-Za-z0-9_.-]", "_", out.name).lstrip("_.-") or "scene"
    if not NAME_RE.match(name):
        raise B3dgsError(f"name={name} is not a scene name", "pass name= letters, digits, _ . - (a letter or digit first)")
    if cfg.get("scene_file", True) and (Path(CONF_DIR) / "scene" / f"{name}.yaml").is_file():
        raise B3dgsError(f"name={name} is a scene b3dgs already has (conf/scene/{name}.yaml); scene={name} would load "
                         "that one", "pass name= another name")
    return name


def _hydra_value(value: str) -> str:
    """``value`` as Hydra's override grammar reads it back unchanged: quoted (``'...'``, its quotes and backslashes
    escaped) unless it holds only characters the grammar takes bare."""
    if all(c.isascii() and (c.isalnum() or c in "_./:-+~@") for c in value):
        return value
    escaped = re.sub(r"(\\+)(?='|$)", lambda m: 2 * m.group(1), value)  # Hydra un-escapes only these backslashes
    return "'" + escaped.replace("'", "\\'") + "'"


def _searchpath_override(conf: Path) -> str:
    return f"hydra.searchpath=[{_hydra_value(f'file://{conf}')}]"


def _shell_override(key: str, value: str) -> str:
    """``key=value`` as a shell word that reaches Hydra as ``value`` (spaces, quotes, commas in a path)."""
    return shlex.quote(f"{key}={_hydra_value(value)}")


def _scene_yaml(name: str, out: Path, images: Path, summary: str, command: str) -> str:
    root = Path(data_root()).absolute()
    path = f"${{data_root}}/{out.name}" if out.parent.resolve() == root.resolve() else str(out.resolve())
    return (f"# @package _global_\n"
            f"# {name}: written by b3dgs-process from {images} ({summary}).\n"
            f"# Train it: {command}\n"
            f"# or copy this file into conf/scene/ (or a package's conf/scene/) and drop the hydra.searchpath.\n"
            f"defaults:\n"
            f"  - override /data: colmap\n"
            f"data:\n"
            f"  path: {json.dumps(path)}\n")


def _registration_check(stats: dict, n: int, run: _Run) -> None:
    cfg = run.cfg
    reg, need = int(stats.get("registered", 0)), run.need()
    if reg >= need:
        return
    tries = ["photos with more overlap (each part of the scene in 3+ photos, neighbours sharing most of the view)"]
    if run.matcher == "sequential":
        tries.append("matcher=exhaustive (sequential matching pairs photos by name order only)")
    big = max(max(s) for s in run.sizes)
    if big > int(cfg.sift_max_side):
        tries.append(f"sift_max_side={big} (the photos are up to {big} px; SIFT sees {cfg.sift_max_side})")
    elif big < 1000:
        tries.append(f"larger photos (these are at most {big} px)")
    if str(cfg.camera_model) in ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL"):
        tries.append("camera_model=OPENCV for a wide-angle lens")
    if reg >= MIN_PHOTOS:
        tries.append(f"or min_registered={math.floor(100 * reg / n) / 100:g} to keep the {reg} registered")
    models, attempts = int(stats.get("models", 0)), len(stats.get("tries", []))
    where = f" (the largest of {models} models)" if models > 1 else ""
    where += f" after {attempts} mapping tries" if attempts > 1 else ""
    raise B3dgsError(f"only {reg} of {n} photos registered{where}; b3dgs-process needs {need} "
                     f"(min_registered={cfg.min_registered:g})", "try " + "; ".join(tries))


# ----------------------------------------------------------------------------------------------- the command


def process(cfg: DictConfig) -> dict:
    """Run (or resume) the stages for ``cfg`` (``conf/process.yaml``); returns a summary (``out``, ``name``,
    ``command``, per stage ``{"skipped", "seconds", ...}``)."""
    from b3dgs.data.images import import_pycolmap
    from b3dgs.validation import validate_config

    validate_config(cfg, app="process")
    import_pycolmap()  # first: importing pycolmap installs glog's handler (a stack trace) for SIGTERM
    with interrupt_handlers() as pending:  # SIGINT / SIGTERM: b3dgs.signals.Interrupted, also while a stage runs
        pending.deferred = True  # recorded, and raised by _stop_if_signalled
        return _process(cfg)


def _process(cfg: DictConfig) -> dict:
    from b3dgs.locks import LockHeld, process_lock

    out = Path(os.path.abspath(Path(str(cfg.out)).expanduser()))
    video = _video_arg(cfg)
    if video is None:
        images = Path(os.path.abspath(Path(str(cfg.images)).expanduser()))  # absolute, without ".."
        photos = list_photos(images)
        sizes = _sizes(photos)  # reads every header: an unreadable photo is refused before anything is written
    else:
        images, photos, sizes = out / WORK / FRAMES, [], []  # the frames, extracted once the lock is held
    with _colmap_log(bool(cfg.get("verbose", False))) as pycolmap:
        _check_options(cfg, pycolmap)
        name = _scene_name(cfg, out)
        state = _read_state(out)
        _check_out(out, video or images, state, "images" if video is None else "video")
        out.mkdir(parents=True, exist_ok=True)
        try:
            with process_lock(out / LOCK, wait=False, remove=True):
                if state is not None and bool(cfg.get("overwrite", False)):
                    _remove_ours(out, state)
                    state = None
                if video is not None:
                    photos = _frames(cfg, video, images, out, state)
                    sizes = _sizes(photos)
                return _process_locked(cfg, photos, sizes, images, out, name, state, pycolmap, video)
        except LockHeld as e:
            raise B3dgsError(f"out={out} is in use by another b3dgs-process (pid {e.pid})",
                             "wait for it to finish, or pass out= another folder") from None


def _video_arg(cfg: DictConfig) -> Optional[Path]:
    """``video=`` as an absolute path (None without it), checked: one of images= and video=, a file."""
    given_images, given_video = cfg.get("images") is not None, cfg.get("video") is not None
    if given_images and given_video:
        raise B3dgsError(f"both images={cfg.images} and video={cfg.video} given",
                         "pass images= (a folder of photos) or video= (a clip whose frames are the photos), not both")
    if not given_images and not given_video:
        raise B3dgsError("no photos given", "pass images= a folder of photos, or video= a clip (with fps=)")
    if not given_video:
        return None
    video = Path(os.path.abspath(Path(str(cfg.video)).expanduser()))
    if not video.is_file():
        raise B3dgsError(f"video={video}: {'a folder, not a file' if video.is_dir() else 'no such file'}",
                         "pass video= a video file (e.g. clip.mp4), or images= a folder of photos")
    return video


def _video_key(video: Path, fps: float) -> dict:
    st = video.stat()
    return {"path": str(video), "size": int(st.st_size), "mtime_ns": int(st.st_mtime_ns), "fps": float(fps)}


def _frames(cfg: DictConfig, video: Path, folder: Path, out: Path, state: Optional[dict]) -> list[Path]:
    """``video=``'s frames at ``fps=`` in ``folder`` (extracted once: a rerun with the same video and fps finds them),
    as :func:`list_photos` lists them. A different video (or fps) than ``out`` was processed from is refused."""
    key = _video_key(video, float(cfg.fps))
    if state is not None:
        if state.get("video") != key:
            old = state.get("video") or {}
            was = f"video={old.get('path')} fps={old.get('fps'):g}" if old else f"images={state.get('images')}"
            raise B3dgsError(f"out={out} was processed from {was}, not this video={video} fps={cfg.fps:g} (or the "
                             "video changed since)", "pass overwrite=true to process it afresh, or out= a new folder")
        if folder.is_dir():
            return list_photos(folder)
    part = folder.with_name(folder.name + ".partial")
    _remove(part)
    _remove(folder)
    t0 = time.perf_counter()
    _say(f"[0/{len(STAGES)}] frames: {video.name} at fps={cfg.fps:g}")
    n = _call(lambda: extract_frames(video, part, float(cfg.fps)))
    os.replace(part, folder)
    _say(f"[0/{len(STAGES)}] frames: {n} frames in {time.perf_counter() - t0:.1f} s")
    if state is not None:
        state["video"] = key
    return list_photos(folder)


def extract_frames(video: Path, folder: Path, fps: float, quality: int = 2) -> int:
    """Decode ``video`` whole with imageio-ffmpeg's ffmpeg and write one frame per 1/``fps`` seconds into ``folder`` as
    ``frame_00001.jpg``, ... (ffmpeg's JPEG ``-q:v quality``, 2 the best but one); returns how many. A video ffmpeg
    cannot open or that fails to decode anywhere (``-xerror``: a truncated clip stops ffmpeg with an error instead of
    ending early) raises :class:`B3dgsError` with ffmpeg's last line; so do fewer than 3 frames. The frames already
    written stay for the caller to remove. Each frame gets the video's modification time, so frames extracted again
    list the same (the state file's fingerprint)."""
    import subprocess

    import imageio_ffmpeg

    folder.mkdir(parents=True, exist_ok=True)
    fix = "re-encode or re-download the video (it should play to its end), or pass images= a folder of photos"
    try:
        gen = imageio_ffmpeg.read_frames(str(video))
        total = round(float(next(gen).get("duration") or 0) * fps) or None
        gen.close()
    except (OSError, RuntimeError, StopIteration, KeyError, ValueError):
        total = None  # the decoding below names the problem
    cmd = [imageio_ffmpeg.get_ffmpeg_exe(), "-nostdin", "-v", "error", "-xerror", "-err_detect", "explode",
           "-i", str(video), "-vf", f"fps={fps:g}", "-q:v", str(int(quality)), str(folder / "frame_%05d.jpg")]
    bar = _bar("frames", total or 0, " frames")
    proc = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    err: list[bytes] = []
    reader = threading.Thread(target=lambda: err.append(proc.stderr.read()), daemon=True)
    reader.start()
    try:
        while proc.poll() is None:
            time.sleep(0.2)
            _stop_if_signalled()
            _advance(bar, len(os.listdir(folder)))
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    reader.join()
    frames = sorted(folder.glob("frame_*.jpg"))
    _advance(bar, len(frames))
    bar.close()
    if proc.returncode != 0:
        lines = [re.sub(r"^\[[^\]]*\]\s*", "", ln.strip()) for ln in b"".join(err).decode(errors="replace").splitlines()]
        lines = [ln for ln in lines if ln]
        why = " ".join((lines[0] if lines else f"ffmpeg exit code {proc.returncode}").split()).replace(str(video), "it")
        raise B3dgsError(f"cannot decode video={video} whole ({len(frames)} frames read): {why[:200]}", fix)
    mtime = video.stat().st_mtime_ns
    for f in frames:
        os.utime(f, ns=(mtime, mtime))
    if len(frames) < MIN_PHOTOS:
        raise B3dgsError(f"video={video} gave {len(frames)} frame{'s' if len(frames) != 1 else ''} at fps={fps:g}; "
                         f"structure from motion needs at least {MIN_PHOTOS}", "pass a larger fps=, or a longer video")
    return len(frames)


def _process_locked(cfg, photos, sizes, images, out, name, state, pycolmap, video=None) -> dict:
    t_start = time.perf_counter()
    listing = [[p.name, int((st := p.stat()).st_size), int(st.st_mtime_ns)] for p in photos]
    fp = hashlib.sha256("".join(f"{n}\t{s}\t{m}\n" for n, s, m in listing).encode()).hexdigest()
    if state is not None and state.get("fingerprint") != fp:
        raise B3dgsError(f"images={images} changed since {out} was processed from it "
                         f"({_diff(state.get('photos', []), listing)})",
                         "pass overwrite=true to process it afresh, or out= a new folder")
    single = bool(cfg.single_camera) if cfg.get("single_camera") is not None else len(set(sizes)) == 1
    matcher = str(cfg.matcher)
    if matcher == "auto":
        matcher = "exhaustive" if len(photos) <= EXHAUSTIVE_UP_TO else "sequential"
    if state is None:
        state = {"format": FORMAT, "images": str(images), "fingerprint": fp, "photos": listing, "stages": {},
                 "files": []}
        if video is not None:
            state["video"] = _video_key(video, float(cfg.fps))
    run = _Run(cfg, photos, sizes, images, out, single, matcher, state)
    state["images"] = str(images)
    run.work.mkdir(parents=True, exist_ok=True)
    write_json(out / STATE, state)
    keys = run.keys()
    cams = "one camera" if single else "one camera per photo"
    source = f"{images}" if video is None else f"{images} (frames of {video} at fps={cfg.fps:g})"
    _say(f"b3dgs-process: {len(photos)} photos in {source} -> {out} ({matcher} matching, {cfg.camera_model}, {cams})")
    report: dict[str, Any] = {}
    for i, stage in enumerate(STAGES):
        _stop_if_signalled()
        tag = f"[{i + 1}/{len(STAGES)}] {stage}"
        rec, why = state["stages"].get(stage), ""
        if rec is not None and rec.get("key") != keys[stage]:
            changed = [f"{k} {rec['key'].get(k)} -> {v}" for k, v in keys[stage].items() if rec["key"].get(k) != v]
            why = f" (options changed: {', '.join(changed)})"
        elif rec is not None and stage == "map" and run.may_retry(rec):
            why = f" (it registered {rec.get('registered', 0)}, fewer than {run.need()}, with tries left)"
        elif rec is not None and not all(p.exists() for p in run.outputs(stage)):
            why = " (its output is gone)"
        if rec is not None and not why:
            _say(f"{tag}: done earlier ({rec['seconds']:.1f} s; {rec.get('note', '')}), skipped")
            report[stage] = {**rec, "skipped": True}
        else:
            for later in STAGES[i:]:  # this stage and every later one are redone
                state["stages"].pop(later, None)
            write_json(out / STATE, state)
            _say(f"{tag}{why}")
            t0 = time.perf_counter()
            try:
                _stop_if_signalled()
                stats = getattr(run, stage)(pycolmap)
            except Interrupted as e:
                e.stage = stage
                raise
            seconds = time.perf_counter() - t0
            state["stages"][stage] = {"key": keys[stage], "seconds": round(seconds, 3), **stats}
            write_json(out / STATE, state)
            _say(f"{tag}: {stats['note']} in {seconds:.1f} s")
            report[stage] = {**state["stages"][stage], "skipped": False}
        if stage == "map":
            _registration_check(state["stages"]["map"], len(photos), run)
    # the scene file: written every run (the name may have changed); scene_file=false: none (b3dgs-data get, whose
    # scenes have their own in conf/scene/), and the one an earlier run wrote goes
    m, u = state["stages"]["map"], state["stages"]["undistort"]
    summary = f"{m['registered']} of {len(photos)} photos registered; PINHOLE, {u['size']} px (max_side={cfg.max_side})"
    with_file = bool(cfg.get("scene_file", True))
    plain = f"b3dgs-train data=colmap {_shell_override('data.path', str(out))}"
    command = f"b3dgs-train scene={name} {shlex.quote(_searchpath_override(out / 'conf'))}" if with_file else plain
    scene_file = f"conf/scene/{name}.yaml" if with_file else None
    old = state.get("scene_file")
    if old and old != scene_file:
        _remove(out / old)
        for folder in ((out / old).parent, out / "conf"):  # the folders it leaves empty
            with suppress(OSError):
                folder.rmdir()
    target = out / scene_file if scene_file else None
    if target is not None:
        text = _scene_yaml(name, out, images if video is None else video, summary, command)
        if not target.is_file() or target.read_text() != text:
            with atomic_path(target) as tmp:
                tmp.write_text(text)
    state["scene_file"], state["name"] = scene_file, name
    write_json(out / STATE, state)
    total = time.perf_counter() - t_start
    _say(f"b3dgs-process: {summary}; " + ", ".join(f"{s} {state['stages'][s]['seconds']:.1f} s" for s in STAGES)
         + f" (this run {total:.1f} s)")
    left_out = _left_out(state, [p.name for p in photos])
    for why in dict.fromkeys(left_out.values()):
        names = [n for n, w in left_out.items() if w == why]
        _say(f"left out ({why}): {len(names)} photo{'s' if len(names) > 1 else ''}: {', '.join(names)}")
    skipped = _not_photos(images) if video is None else []
    if skipped:
        _say(f"not read (not a photo: {' '.join(PHOTO_SUFFIXES)}): {', '.join(skipped)}")
    _say(f"scene: {out}/images, {out}/sparse/0" + (f", {target}" if target is not None else ""))
    _say(f"train it: {command}")
    if target is not None:
        _say(f"      or: {plain}")
    return {"out": str(out), "name": name, "command": command, "scene_file": None if target is None else str(target),
            "stages": report, "registered": int(m["registered"]), "photos": len(photos), "seconds": total,
            "left_out": left_out, "not_photos": skipped}


@hydra.main(version_base="1.3", config_path=CONF_DIR, config_name="process")
def hydra_main(cfg: DictConfig) -> None:
    with known_errors("b3dgs-process", cfg):
        try:
            process(cfg)
        except Interrupted as e:
            during = f" during the {e.stage} stage" if getattr(e, "stage", None) else ""
            sys.stdout.flush()
            sys.stderr.write(f"b3dgs-process: {e}{during}; run the same command again to resume (finished stages "
                             f"are kept)\n")
            sys.stderr.flush()
            os._exit(e.exit_code)  # at once: the stage's pycolmap call may still run in its thread


main = cli_main("b3dgs-process", hydra_main, "process")


if __name__ == "__main__":
    main()

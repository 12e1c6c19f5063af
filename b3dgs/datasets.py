"""Scenes by name, as nerfstudio's ``ns-download-data``: ``b3dgs-data list`` and ``b3dgs-data get NAME``.

The registry, ``b3dgs/datasets.yaml`` (``$B3DGS_DATA_REGISTRY`` replaces it), gives each scene its public source,
licence, checksum where one is published, layout steps and the files the finished folder must hold. ``get``
downloads into ``<data_root>/.downloads`` (a ``.part`` file resumed with an HTTP Range request), checks the sum,
extracts into a staging folder beside the scene (refusing members that would land outside it), runs the layout
steps, checks the required files and renames the staging folder onto ``<data_root>/<name>``: a scene folder is
complete or absent. ``data_root`` is :func:`b3dgs.data_root` (see :data:`EXAMPLES`), the folder ``scene=NAME`` reads.
"""
from __future__ import annotations

import argparse
import fnmatch
import hashlib
import http.client
import os
import shutil
import stat
import subprocess
import sys
import tarfile
import tempfile
import time
import urllib.error
import urllib.parse
import urllib.request
import zipfile
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath
from typing import Any, Callable, Iterator, Optional

from b3dgs.errors import EXIT_CODE, B3dgsError, did_you_mean, format_error
from b3dgs.io import atomic_path, write_json

PROG = "b3dgs-data"
REGISTRY_ENV = "B3DGS_DATA_REGISTRY"
REGISTRY_FILE = Path(__file__).with_name("datasets.yaml")
DOWNLOADS = ".downloads"  # <data_root>/.downloads: archives and their .part files
STAGING_MARK = ".b3dgs-staging-"  # <data_root>/.<name>.b3dgs-staging-<random>: a scene being laid out
ATTEMPTS = 3  # tries per download; each one resumes where the last stopped
RETRY_WAIT_S = 1.0
TIMEOUT_S = 60.0
CHUNK = 1 << 20
ARCHIVES = (".zip", ".tar", ".tar.gz", ".tgz", ".tar.bz2", ".tar.xz")
_BAD_ARCHIVE = "the archive is not the one the registry names; delete it and download it again"


@dataclass(frozen=True)
class Source:
    """One download: an archive (its ``subdir`` becomes the scene) or, with ``files``, a base URL and the files
    fetched from it (``"path"`` or ``"path -> dest"``)."""

    url: str
    sha256: Optional[str] = None
    subdir: str = ""
    filename: str = ""
    files: tuple[str, ...] = ()

    @property
    def name(self) -> str:
        """The downloaded archive's file name."""
        return self.filename or PurePosixPath(urllib.parse.urlparse(self.url).path).name


@dataclass(frozen=True)
class Scene:
    """A registry entry (``b3dgs/datasets.yaml`` documents each field)."""

    name: str
    group: str
    licence: str
    sources: tuple[Source, ...]
    required: dict = field(default_factory=dict)
    layout: tuple[dict, ...] = ()
    checked: str = ""
    note: str = ""


def registry_path() -> Path:
    """``$B3DGS_DATA_REGISTRY`` if set, else the registry shipped with b3dgs."""
    return Path(os.environ.get(REGISTRY_ENV) or REGISTRY_FILE)


def load_registry(path: Optional[os.PathLike] = None) -> dict[str, Scene]:
    """The registry's scenes by name."""
    import yaml

    path = Path(path) if path is not None else registry_path()
    try:
        raw = yaml.safe_load(path.read_text()) or {}
    except (OSError, yaml.YAMLError) as e:
        raise B3dgsError(f"cannot read the scene registry {path}: {' '.join(str(e).split())}",
                         f"point ${REGISTRY_ENV} at a readable YAML file, or unset it") from None
    scenes = {}
    for name, d in raw.items():
        sources = tuple(Source(url=s["url"], sha256=s.get("sha256"), subdir=str(s.get("subdir") or ""),
                               filename=str(s.get("filename") or ""), files=tuple(s.get("files") or ()))
                        for s in d.get("sources", ()))
        scenes[str(name)] = Scene(str(name), str(d.get("group", "")), str(d.get("licence", "")), sources,
                                  dict(d.get("required") or {}), tuple(d.get("layout") or ()),
                                  str(d.get("checked", "")), str(d.get("note", "")))
    return scenes


# ---------------------------------------------------------------------------------------------- what is there
def missing(scene: Scene, folder: Path) -> list[str]:
    """The required globs ``folder`` does not satisfy, as ``"<glob> (n of N)"``; empty when the scene is complete."""
    out = []
    for pattern, count in scene.required.items():
        n = sum(1 for p in folder.glob(pattern) if p.is_file()) if folder.is_dir() else 0
        if (count is None and n == 0) or (count is not None and n != int(count)):
            out.append(f"{pattern} ({n} of {'1+' if count is None else count})")
    return out


def is_present(scene: Scene, root: Path) -> bool:
    return (root / scene.name).is_dir() and not missing(scene, root / scene.name)


def resolve(names: list[str], scenes: dict[str, Scene]) -> list[Scene]:
    """Scenes by name or group (``mipnerf360``, ``shared``, ...), in registry order, each once."""
    out: list[Scene] = []
    groups = {s.group for s in scenes.values()}
    for name in names:
        if name in scenes:
            picked = [scenes[name]]
        elif name in groups:
            picked = [s for s in scenes.values() if s.group == name]
        else:
            raise B3dgsError(f"no scene or group named {name!r} in the registry{did_you_mean(name, [*scenes, *groups])}",
                             f"`{PROG} list` shows the named scenes")
        out += [s for s in picked if s not in out]
    return out


# ---------------------------------------------------------------------------------------------- download
def _say(text: str) -> None:
    print(text, flush=True)


def _manual(url: str, dest: Path, name: str) -> str:
    return f"download {url} by hand into {dest.parent}/ as {dest.name}, then run `{PROG} get {name}` again"


def sha256_of(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(CHUNK), b""):
            h.update(block)
    return h.hexdigest()


def _fetch_once(url: str, part: Path, bar_desc: str) -> None:
    """One HTTP request appending to ``part`` from its current size (Range); raises on a short or failed response."""
    from b3dgs.progress import progress

    have = part.stat().st_size if part.exists() else 0
    req = urllib.request.Request(url, headers={"User-Agent": f"{PROG} (b3dgs)"})
    if have:
        req.add_header("Range", f"bytes={have}-")
    try:
        res = urllib.request.urlopen(req, timeout=TIMEOUT_S)
    except urllib.error.HTTPError as e:
        if e.code == 416 and have:  # the range starts at the end: what we have is the whole file
            return
        raise
    with res:
        if have and res.status != 206:  # the server ignores Range: start again
            have = 0
        length = res.headers.get("Content-Length")
        total = have + int(length) if length is not None else None
        with open(part, "ab" if have else "wb") as f, progress(total=total, initial=have, unit="B", unit_scale=True,
                                                               unit_divisor=1024, desc=bar_desc) as bar:
            for block in iter(lambda: res.read(CHUNK), b""):
                f.write(block)
                bar.update(len(block))
    if total is not None and part.stat().st_size < total:
        raise http.client.IncompleteRead(b"", total - part.stat().st_size)  # the connection was cut: resume


def download(url: str, dest: Path, sha256: Optional[str], scene: str, attempts: int = ATTEMPTS) -> Path:
    """``url`` saved as ``dest`` (kept and reused when already there), through ``dest.part``, resumed on a cut
    connection, its sha256 checked when known. A failure or a bad sum is one line naming the URL and where to put a
    manual download."""
    if not dest.is_file():
        part = dest.with_name(dest.name + ".part")
        dest.parent.mkdir(parents=True, exist_ok=True)
        for attempt in range(attempts):
            try:
                _fetch_once(url, part, dest.name)
                break
            except (OSError, http.client.HTTPException, ValueError) as e:  # URLError, a cut or refused connection
                error = e
            if attempt + 1 < attempts:
                time.sleep(RETRY_WAIT_S)
        else:  # every attempt failed
            reason = getattr(error, "reason", None) or error
            raise B3dgsError(f"cannot download {url}: {' '.join(str(reason).split())}",
                             f"check the connection and rerun (the download resumes), or {_manual(url, dest, scene)}")
        os.replace(part, dest)
    if sha256:
        got = sha256_of(dest)
        if got != sha256.lower():
            dest.unlink()
            raise B3dgsError(f"the download of {url} has sha256 {got}, not the registry's {sha256} (removed)",
                             f"rerun to download it again, or {_manual(url, dest, scene)}")
    return dest


# ---------------------------------------------------------------------------------------------- safe extraction
def _member_path(name: str, archive: Path) -> PurePosixPath:
    """A member's path, refused when it is absolute or climbs out with ``..``."""
    p = PurePosixPath(name.replace("\\", "/"))
    if p.is_absolute() or name.startswith(("/", "\\")) or ".." in p.parts or (p.parts and ":" in p.parts[0]):
        raise B3dgsError(f"the archive {archive.name} holds {name!r}, which would be written outside the scene folder",
                         _BAD_ARCHIVE)
    return p


def _link_escapes(member: PurePosixPath, target: str) -> bool:
    t = PurePosixPath(target.replace("\\", "/"))
    if t.is_absolute():
        return True
    depth = 0
    for part in (*member.parent.parts, *t.parts):
        depth = depth - 1 if part == ".." else depth + (part not in ("", "."))
        if depth < 0:
            return True
    return False


class _Member:
    """An archive member as extraction needs it: path, kind (file, dir, link), link target, an opener."""

    def __init__(self, path: PurePosixPath, kind: str, target: str, opener: Callable[[], Any]):
        self.path, self.kind, self.target, self.open = path, kind, target, opener


@contextmanager
def _members(archive: Path) -> Iterator[list[_Member]]:
    """The members of a zip or tar archive, readable while the context is open."""
    if archive.name.endswith(".zip"):
        with zipfile.ZipFile(archive) as z:
            out = []
            for info in z.infolist():
                p = _member_path(info.filename, archive)
                if stat.S_ISLNK(info.external_attr >> 16):
                    out.append(_Member(p, "link", z.read(info).decode(), lambda: None))
                else:
                    out.append(_Member(p, "dir" if info.is_dir() else "file", "", lambda i=info: z.open(i)))
            yield out
        return
    with tarfile.open(archive) as t:
        out = []
        for info in t:
            p = _member_path(info.name, archive)
            if info.issym() or info.islnk():  # a hard link names an archive path: made relative to the member
                target = info.linkname if info.issym() else str(PurePosixPath(*[".."] * (len(p.parts) - 1),
                                                                               info.linkname))
                out.append(_Member(p, "link", target, lambda: None))
            elif info.isdir():
                out.append(_Member(p, "dir", "", lambda: None))
            elif info.isfile():
                out.append(_Member(p, "file", "", lambda i=info: t.extractfile(i)))
            # devices and fifos are not scene data: skipped
        yield out


def _subdir_prefix(paths: list[PurePosixPath], subdir: str) -> PurePosixPath:
    """Where ``subdir`` is in the archive: at its top, or under one wrapping folder (GitHub's ``repo-<commit>/``)."""
    want = PurePosixPath(subdir)
    tops = sorted({p.parts[0] for p in paths if len(p.parts) > 1})
    for prefix in (want, *(PurePosixPath(t) / want for t in tops)):
        if any(p.parts[:len(prefix.parts)] == prefix.parts and len(p.parts) > len(prefix.parts) for p in paths):
            return prefix
    raise B3dgsError(f"the archive holds no folder {subdir}", _BAD_ARCHIVE)


def extract(archive: Path, subdir: str, dest: Path) -> None:
    """``subdir`` of a zip or tar archive into ``dest``. Every member is checked first: an absolute path, a ``..``
    or a link pointing out of the folder refuses the whole archive before anything is written."""
    with _members(archive) as members:
        for m in members:
            if m.kind == "link" and _link_escapes(m.path, m.target):
                raise B3dgsError(f"the archive {archive.name} holds the link {m.path} -> {m.target}, which points "
                                 "outside the scene folder", _BAD_ARCHIVE)
        prefix = _subdir_prefix([m.path for m in members], subdir)
        root = dest.resolve()
        for m in members:
            if m.path.parts[:len(prefix.parts)] != prefix.parts or len(m.path.parts) == len(prefix.parts):
                continue
            rel = PurePosixPath(*m.path.parts[len(prefix.parts):])
            out = dest.joinpath(*rel.parts)
            if root not in (out.parent.resolve(), *out.parent.resolve().parents):  # through a link extracted before
                raise B3dgsError(f"the archive {archive.name} writes {m.path} through a link out of the scene folder",
                                 _BAD_ARCHIVE)
            if m.kind == "dir":
                out.mkdir(parents=True, exist_ok=True)
            elif m.kind == "link":
                out.parent.mkdir(parents=True, exist_ok=True)
                if _link_escapes(rel, m.target):
                    raise B3dgsError(f"the link {m.path} -> {m.target} points outside the scene folder", _BAD_ARCHIVE)
                out.symlink_to(m.target)
            else:
                out.parent.mkdir(parents=True, exist_ok=True)
                with m.open() as src, open(out, "wb") as f:
                    shutil.copyfileobj(src, f, CHUNK)


def is_archive(source: Source) -> bool:
    return not source.files and source.name.lower().endswith(ARCHIVES)


# ---------------------------------------------------------------------------------------------- layout steps
def _keep(folder: Path, patterns: list[str]) -> None:
    for p in sorted(folder.rglob("*"), reverse=True):
        rel = p.relative_to(folder).as_posix()
        if p.is_dir() and not p.is_symlink():
            if not any(p.iterdir()):
                p.rmdir()
        elif not any(fnmatch.fnmatch(rel, pat) for pat in patterns):
            p.unlink()


def _resize(folder: Path, step: dict) -> None:
    """Images of ``step['folder']`` resized in place (Lanczos) by ``factor`` or to ``size``; a ``transforms``
    file's intrinsics (fl_x, fl_y, cx, cy, w, h) scaled to match."""
    import json

    from PIL import Image

    scale = None
    for p in sorted((folder / step["folder"]).iterdir()):
        if p.suffix.lower() not in (".jpg", ".jpeg", ".png"):
            continue
        with Image.open(p) as im:
            w, h = im.size
            size = (round(w / step["factor"]), round(h / step["factor"])) if "factor" in step else tuple(step["size"])
            small = im.resize(size, Image.LANCZOS)
        with atomic_path(p) as tmp:
            small.save(tmp, format=Image.registered_extensions()[p.suffix.lower()],
                       **({"quality": 95} if p.suffix.lower() in (".jpg", ".jpeg") else {}))
        scale = (size[0] / w, size[1] / h)
    if step.get("transforms") and scale is not None:
        path = folder / step["transforms"]
        meta = json.loads(path.read_text())
        for key, s in (("fl_x", scale[0]), ("cx", scale[0]), ("w", scale[0]), ("fl_y", scale[1]), ("cy", scale[1]),
                       ("h", scale[1])):
            if key in meta:
                meta[key] = float(meta[key]) * s
        write_json(path, meta)


def _process(folder: Path, step: dict, name: str) -> Path:
    """b3dgs-process (SfM) on the photos of ``step['images']`` matching ``step['pattern']``; returns its scene."""
    photos = folder.parent / f"{folder.name}-photos"
    photos.mkdir()
    src = folder / step.get("images", ".")
    for p in sorted(src.iterdir()):
        if p.is_file() and fnmatch.fnmatch(p.name, step.get("pattern", "*")):
            os.replace(p, photos / p.name)
    out = folder.parent / f"{folder.name}-sfm"
    # scene_file=false: the registry's scenes have their own conf/scene/<name>.yaml (b3dgs-process would refuse the
    # name), and its scene file would name this staging folder
    cmd = [sys.executable, "-m", "b3dgs.process", f"images={photos}", f"out={out}", f"name={name}",
           f"max_side={int(step.get('max_side', 1600))}", "scene_file=false"]
    _say(f"{name}: structure from motion: {' '.join(cmd[1:])}")
    res = subprocess.run(cmd, stdout=subprocess.PIPE, text=True)  # progress bars and errors: on stderr, as they come
    for line in res.stdout.splitlines():  # its summary, without the lines naming the staging folder
        if not line.startswith(("scene: ", "train it: ")):
            _say(line)
    if res.returncode != 0:
        raise B3dgsError(f"b3dgs-process could not make a COLMAP model of {name}'s photos (its error is above)",
                         f"rerun `{PROG} get {name}`; the download is kept")
    shutil.rmtree(photos)
    shutil.rmtree(folder)
    # the scene is images/ and sparse/0/: b3dgs-process's work files (SfM's databases and raw model, larger than the
    # scene) and its state go
    for p in out.iterdir():
        if p.name in ("images", "sparse"):
            continue
        if p.is_dir() and not p.is_symlink():
            shutil.rmtree(p)
        else:
            p.unlink()
    return out


def apply_layout(folder: Path, scene: Scene) -> Path:
    """The scene's layout steps on ``folder``; returns the folder that holds the result."""
    for step in scene.layout:
        (kind, arg), = step.items()
        if kind == "keep":
            _keep(folder, list(arg))
        elif kind == "rename":
            for old, new in arg.items():
                os.replace(folder / old, folder / new)
        elif kind == "resize":
            _resize(folder, dict(arg))
        elif kind == "process":
            folder = _process(folder, dict(arg), scene.name)
        else:
            raise B3dgsError(f"the registry's scene {scene.name} has an unknown layout step {kind!r}",
                             "use keep, rename, resize or process (b3dgs/datasets.yaml documents them)")
    return folder


# ---------------------------------------------------------------------------------------------- get
def get(scene: Scene, root: Path, scenes: Optional[dict[str, Scene]] = None) -> str:
    """Fetch and lay out ``scene`` in ``root`` (see the module docstring); returns what it did, as one line."""
    target = root / scene.name
    if target.exists():
        lack = missing(scene, target)
        if not lack:
            return f"{scene.name}: already in {target}"
        raise B3dgsError(f"{target} exists but lacks {', '.join(lack)}",
                         f"move it away (or complete it by hand), then run `{PROG} get {scene.name}` again")
    root.mkdir(parents=True, exist_ok=True)
    downloads = root / DOWNLOADS
    staging = Path(tempfile.mkdtemp(prefix=f".{scene.name}{STAGING_MARK}", dir=root))
    folder = staging / "scene"
    folder.mkdir()
    try:
        archives = []
        for source in scene.sources:
            for entry in source.files:  # a base URL and files from it
                src, _, dst = (part.strip() for part in str(entry).partition("->"))
                dst = dst or src
                got = download(source.url + src, downloads / scene.name / dst, None, scene.name)
                (folder / dst).parent.mkdir(parents=True, exist_ok=True)
                shutil.copyfile(got, folder / dst)
            if is_archive(source):
                archive = download(source.url, downloads / source.name, source.sha256, scene.name)
                _say(f"{scene.name}: extracting {source.subdir or 'everything'} from {archive.name}")
                extract(archive, source.subdir, folder)
                archives.append(source)
            elif not source.files:
                got = download(source.url, downloads / scene.name / source.name, source.sha256, scene.name)
                shutil.copyfile(got, folder / source.name)
        folder = apply_layout(folder, scene)
        lack = missing(scene, folder)
        if lack:
            raise B3dgsError(f"the download of {scene.name} lacks {', '.join(lack)} after its layout steps",
                             "the source changed since the registry was written; report it, or place the scene by "
                             f"hand in {target}")
        os.replace(folder, target)
        kept = []  # the scene is in place: its downloads go, but an archive other missing scenes hold
        shutil.rmtree(downloads / scene.name, ignore_errors=True)
        for source in archives:
            others = [s.name for s in (scenes or {}).values() if s.name != scene.name
                      and any(o.url == source.url for o in s.sources) and not is_present(s, root)]
            if others:
                kept.append(f"{source.name} kept for {', '.join(others)}")
            else:
                (downloads / source.name).unlink(missing_ok=True)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
        for p in (downloads / scene.name, downloads):
            if p.is_dir() and not any(p.iterdir()):
                p.rmdir()
    kept_note = f" ({'; '.join(kept)})" if kept else ""
    return f"{scene.name}: ready in {target}{kept_note}; {train_command(scene.name, root)}"


def train_command(name: str, root: Path) -> str:
    """How to train a fetched scene: ``scene=<name>`` where a ``scene/<name>.yaml`` (b3dgs's or a package's) reads it
    from this data root, else ``data.path=``."""
    from b3dgs import data_root
    from b3dgs.confs import option_names

    if name in option_names("scene") and \
            Path(data_root()).expanduser().resolve() == Path(root).expanduser().resolve():
        return f"train it: b3dgs-train scene={name}"
    return f"train it: b3dgs-train data.path={root / name}"


# ---------------------------------------------------------------------------------------------- CLI
EXAMPLES = f"""examples:
  {PROG} list                 # the named scenes, which are present, where the data root is
  {PROG} get fox              # fetch fox into the data root; then: b3dgs-train scene=fox
  B3DGS_DATA=/big/disk {PROG} get mipnerf360   # the nine Mip-NeRF 360 scenes (17 GB) on another disk

The data root: $B3DGS_DATA; else $B3DGS_SHARED/data; else ../shared/data beside the checkout when it exists; else
$B3DGS_CACHE/data or ~/.cache/b3dgs/data. scene=NAME reads <data_root>/NAME. A scene already there is left as it is.
Sources, licences and how each entry was checked: {REGISTRY_FILE.name} beside b3dgs/datasets.py ($B3DGS_DATA_REGISTRY
replaces it)."""


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog=PROG, formatter_class=argparse.RawDescriptionHelpFormatter, epilog=EXAMPLES,
                                 description="Scenes by name: list the registry's scenes, or fetch one from its "
                                             "original public source into the data root (resumable, checked, "
                                             "extracted atomically).")
    sub = ap.add_subparsers(dest="command", required=True, metavar="{list,get}")
    sub.add_parser("list", help="the named scenes and which are present under the data root")
    g = sub.add_parser("get", help="fetch scenes (or groups: shared, mipnerf360, tandt, db) into the data root",
                       formatter_class=argparse.RawDescriptionHelpFormatter, epilog=EXAMPLES)
    g.add_argument("names", nargs="+", metavar="NAME")
    return ap


def list_lines(scenes: dict[str, Scene], root: Path, origin: str) -> list[str]:
    lines = [f"data root: {root} ({origin})", f"{'scene':<16} {'group':<11} {'present':<8} source"]
    for s in scenes.values():
        host = urllib.parse.urlparse(s.sources[0].url).netloc if s.sources else "-"
        lines.append(f"{s.name:<16} {s.group:<11} {'yes' if is_present(s, root) else '-':<8} {host}")
    lines.append(f"fetch one: {PROG} get NAME; licences and sources: {registry_path()}")
    return lines


def main(argv: Optional[list[str]] = None) -> int:
    """Console entry point ``b3dgs-data``: one-line errors, exit code 2 (:mod:`b3dgs.errors`)."""
    from b3dgs import data_root_and_origin

    args = _parser().parse_args(argv)
    root_s, origin = data_root_and_origin()
    root = Path(root_s).expanduser()
    from b3dgs.signals import Interrupted, interrupt_handlers

    try:
        with interrupt_handlers():  # SIGINT / SIGTERM unwind: the partial download is kept for the next run
            scenes = load_registry()
            if args.command == "list":
                _say("\n".join(list_lines(scenes, root, origin)))
                return 0
            for scene in resolve(args.names, scenes):
                _say(get(scene, root, scenes))
            return 0
    except Interrupted as e:
        return e.report(PROG, "run the same command again to resume the download")
    except Exception as e:  # noqa: BLE001 - known errors as one line; anything else is a bug with its traceback
        msg = format_error(e)
        if msg is None:
            raise
        sys.stderr.write(f"{PROG}: error: {msg}\n")
        return EXIT_CODE


if __name__ == "__main__":
    sys.exit(main())

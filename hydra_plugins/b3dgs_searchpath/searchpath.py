"""Hydra search-path plugin: config options contributed by installed packages.

A package adds options to b3dgs's config groups by shipping ``its_pkg/conf/<group>/<name>.yaml`` and
declaring one entry point::

    [project.entry-points."b3dgs.conf"]
    its_pkg = "its_pkg.conf"

Each entry point's value is appended to the search path as ``pkg://<value>``. The plugin acts only
when the primary config is b3dgs's own (Hydra runs every installed search-path plugin for every app).

b3dgs's conf dir and those packages' are read through the config sources below: a ``_target_`` node in their files
holds only its deviations from the target's dataclass defaults, and the source fills in the other fields from the
class (:func:`b3dgs.confs.with_field_defaults`), so a default has one home, the dataclass field.
"""
from __future__ import annotations

from importlib.metadata import entry_points
from importlib.util import find_spec
from pathlib import Path

from hydra._internal.core_plugins.file_config_source import FileConfigSource
from hydra._internal.core_plugins.importlib_resources_config_source import ImportlibResourcesConfigSource
from hydra.core.config_search_path import ConfigSearchPath
from hydra.plugins.config_source import ConfigResult
from hydra.plugins.search_path_plugin import SearchPathPlugin

ENTRY_POINT_GROUP = "b3dgs.conf"


def _b3dgs_conf() -> str:
    """b3dgs's conf dir as ``b3dgs.conf_dir()`` finds it, without importing b3dgs into every Hydra app."""
    spec = find_spec("b3dgs")
    if spec is None or not spec.origin:
        return ""
    here = Path(spec.origin).resolve().parent
    return (here / "conf" if (here / "conf" / "train.yaml").is_file() else here.parent / "conf").as_posix()


def _is_b3dgs_app(search_path: ConfigSearchPath) -> bool:
    own = _b3dgs_conf()
    for element in search_path.get_path():
        path = str(element.path).replace("file://", "")
        if element.provider == "main" and Path(path).resolve().as_posix() == own:
            return True
    return False


class _FieldDefaults:
    """A config source whose ``_target_`` nodes get their target's dataclass defaults where the file sets none."""

    def load_config(self, config_path: str) -> ConfigResult:
        from b3dgs.confs import with_field_defaults  # only when a b3dgs app composes

        result = super().load_config(config_path)  # type: ignore[misc]
        result.config = with_field_defaults(result.config)
        return result


class B3dgsFileConfigSource(_FieldDefaults, FileConfigSource):
    """b3dgs's conf dir (``b3dgs-file://``)."""

    @staticmethod
    def scheme() -> str:
        return "b3dgs-file"


class B3dgsPkgConfigSource(_FieldDefaults, ImportlibResourcesConfigSource):
    """An installed package's conf (``b3dgs-pkg://``, a ``b3dgs.conf`` entry point)."""

    @staticmethod
    def scheme() -> str:
        return "b3dgs-pkg"


class B3dgsSearchPathPlugin(SearchPathPlugin):
    def manipulate_search_path(self, search_path: ConfigSearchPath) -> None:
        if not _is_b3dgs_app(search_path):
            return
        for element in search_path.get_path():  # b3dgs's own conf dir, read with the dataclass defaults filled in
            path = str(element.path)
            if element.provider == "main" and (path.startswith("file://") or "://" not in path):
                element.path = "b3dgs-file://" + path.removeprefix("file://")
        for ep in sorted(entry_points(group=ENTRY_POINT_GROUP), key=lambda e: e.name):
            search_path.append(provider=f"b3dgs-ext-{ep.name}", path=f"b3dgs-pkg://{ep.value}")

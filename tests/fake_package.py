"""Install a throw-away package that adds config options through the ``b3dgs.conf`` entry point."""
import importlib
import textwrap
from pathlib import Path


def install_conf_package(tmp_path: Path, monkeypatch, name: str, group: str, module: str, source: str,
                         options: dict[str, str]) -> None:
    """``name`` with ``name/<module>.py`` (``source``) and ``name/conf/<group>/<option>.yaml`` for each of
    ``options``, plus the dist-info declaring ``[b3dgs.conf] name = name.conf``; importable from ``tmp_path``."""
    pkg = tmp_path / name
    (pkg / "conf" / group).mkdir(parents=True)
    for d in (pkg, pkg / "conf", pkg / "conf" / group):
        (d / "__init__.py").write_text("")
    (pkg / f"{module}.py").write_text(textwrap.dedent(source))
    for option, yaml in options.items():
        (pkg / "conf" / group / f"{option}.yaml").write_text(yaml)
    dist = tmp_path / f"{name}-0.1.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {name.replace('_', '-')}\nVersion: 0.1\n")
    (dist / "entry_points.txt").write_text(f"[b3dgs.conf]\n{name} = {name}.conf\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    importlib.invalidate_caches()

"""Where b3dgs's own files are (a leaf module: it imports nothing of b3dgs, so any module may import it)."""


def conf_dir() -> str:
    """b3dgs's config directory: ``b3dgs/conf`` inside an installed wheel (``pyproject.toml`` maps the
    repository's ``conf/`` there), else ``conf/`` beside the package in a source checkout or an editable
    install."""
    from pathlib import Path

    here = Path(__file__).resolve().parent  # b3dgs/
    return str(here / "conf" if (here / "conf" / "train.yaml").is_file() else here.parent / "conf")

"""b3dgs: Bayesian 3D Gaussian Splatting on the CPU (PyTorch Lightning + Hydra)."""
# PIL's PNG/zlib bindings must be loaded before pycolmap's (a zlib clash seen with pycolmap 4.2.1).
import PIL.Image  # noqa: F401
import PIL.PngImagePlugin  # noqa: F401

__version__ = "0.1.0"

from b3dgs.paths import conf_dir  # noqa: E402 - b3dgs.conf_dir, the one everything imports


def data_root_and_origin() -> tuple[str, str]:
    """The folder of the named scenes and where that choice came from: ``$B3DGS_DATA``; else ``$B3DGS_SHARED/data``;
    else ``../shared/data`` beside a source checkout when that folder exists (where the benchmark scenes live); else
    the user cache, ``$B3DGS_CACHE/data`` or ``~/.cache/b3dgs/data`` (where ``b3dgs-data get`` puts scenes on a
    fresh clone)."""
    import os
    from pathlib import Path

    if os.environ.get("B3DGS_DATA"):
        return os.environ["B3DGS_DATA"], "$B3DGS_DATA"
    if os.environ.get("B3DGS_SHARED"):
        return str(Path(os.environ["B3DGS_SHARED"]) / "data"), "$B3DGS_SHARED/data"
    beside = Path(conf_dir()).resolve().parent.parent / "shared" / "data"
    if beside.is_dir():
        return str(beside), "../shared/data beside the checkout"
    cache = os.environ.get("B3DGS_CACHE")
    base = Path(cache).expanduser() if cache else Path.home() / ".cache" / "b3dgs"
    return str(base / "data"), "the user cache ($B3DGS_CACHE/data, else ~/.cache/b3dgs/data)"


def data_root() -> str:
    """The folder of the named scenes (``conf/scene/<name>.yaml``: ``<data_root>/<name>``): see
    :func:`data_root_and_origin`."""
    return data_root_and_origin()[0]


def _register_resolvers() -> None:
    from pathlib import Path

    from omegaconf import OmegaConf

    def scene_name(p) -> str:  # a scene's folder name; data.path=.../lego/transforms_train.json: lego
        path = Path(str(p)) if p else None
        return "scene" if path is None else path.parent.name if path.suffix.lower() == ".json" else path.name

    if not OmegaConf.has_resolver("b3dgs.basename"):
        OmegaConf.register_new_resolver("b3dgs.basename", scene_name)
    if not OmegaConf.has_resolver("b3dgs.div"):
        # integer division, for schedules that scale with trainer.max_steps (t_dp = max_steps / 6)
        OmegaConf.register_new_resolver("b3dgs.div", lambda a, b: int(a) // int(b))
    if not OmegaConf.has_resolver("b3dgs.paper_images"):
        # the paper's image folder of a scene (experiment=paper): images_4 / images_2 for Mip-NeRF 360, else null
        def paper_images(kind, name):
            from b3dgs.paper import paper_image_folder

            return paper_image_folder(kind, name)

        OmegaConf.register_new_resolver("b3dgs.paper_images", paper_images)
    if not OmegaConf.has_resolver("b3dgs.data_root"):
        OmegaConf.register_new_resolver("b3dgs.data_root", data_root)
    if not OmegaConf.has_resolver("b3dgs.help"):
        # every command's --help (hydra.help.template in conf/<app>.yaml): b3dgs.confs.help_text
        def help_text(*args, _parent_=None):
            from b3dgs.confs import help_text

            return help_text(*args, _parent_=_parent_)

        OmegaConf.register_new_resolver("b3dgs.help", help_text)
    if not OmegaConf.has_resolver("b3dgs.uid"):
        # default run dirs unique per process (conf/hydra/default.yaml): "<pid>-<4 random hex digits>", cached, so
        # resolved once per config in the launching process (joblib workers get the parent's value)
        import os

        OmegaConf.register_new_resolver("b3dgs.uid", lambda: f"{os.getpid()}-{os.urandom(2).hex()}", use_cache=True)


_register_resolvers()

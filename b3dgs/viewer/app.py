"""``b3dgs-view run=DIR [port=8080] [mode=...]``: serve the viewer of a finished run (``conf/view.yaml``).

Known problems (a missing, unfinished or other-version run dir, viser not installed, a mode the run cannot
show) print one line ``b3dgs-view: error: ... (fix: ...)`` and exit with code 2.
"""
from __future__ import annotations

import logging
import sys
import time
from pathlib import Path

import hydra
from omegaconf import DictConfig

from b3dgs.errors import B3dgsError
from b3dgs.train import CONF_DIR

log = logging.getLogger(__name__)

__all__ = ["main", "serve"]

SETTINGS = ("host", "port", "max_side", "min_side", "target_ms", "still_ms", "samples", "jitter", "sigma_max", "mode",
            "frusta")


def settings_from_cfg(cfg: DictConfig):
    from b3dgs.viewer.modes import MODES
    from b3dgs.viewer.server import ViewerSettings

    kw = {k: cfg.get(k) for k in SETTINGS if cfg.get(k) is not None}
    if str(kw.get("mode", "rgb")) not in MODES:
        raise B3dgsError(f"unknown viewer mode {kw['mode']!r}", f"pass mode= one of {', '.join(MODES)}")
    for key, least in (("port", 0), ("min_side", 8), ("samples", 2)):
        if key in kw and (not isinstance(kw[key], int) or isinstance(kw[key], bool) or kw[key] < least):
            raise B3dgsError(f"{key}={kw[key]} is not a valid {key}", f"pass {key}= an integer >= {least}")
    if "max_side" in kw and (not isinstance(kw["max_side"], int) or kw["max_side"] < 8):
        raise B3dgsError(f"max_side={kw['max_side']} is too small", "pass max_side= an integer >= 8, or null")
    for key in ("target_ms", "still_ms", "jitter", "sigma_max"):
        if key in kw and not (isinstance(kw[key], (int, float)) and kw[key] > 0):
            raise B3dgsError(f"{key}={kw[key]} must be a positive number", f"pass {key}= a number > 0")
    if "count_scale" in cfg:  # null is a value here (the model's own posterior), not "unset"
        c = cfg.get("count_scale")
        if c is not None and not (isinstance(c, (int, float)) and not isinstance(c, bool) and 0 < c < float("inf")):
            raise B3dgsError(f"count_scale={c} is not a valid count scale", "pass count_scale= a number > 0, or null")
        kw["count_scale"] = None if c is None else float(c)
    return ViewerSettings(**kw)


def serve(cfg: DictConfig):
    """Open the run, start the viewer; returns the started :class:`~b3dgs.viewer.server.ViewerApp`."""
    import torch

    try:
        import viser  # noqa: F401
    except ImportError:
        raise B3dgsError("the viewer needs viser, which is not installed", 'pip install -e ".[viewer]"') from None
    from b3dgs.viewer.run import open_run
    from b3dgs.viewer.server import ViewerApp

    settings = settings_from_cfg(cfg)
    if cfg.get("threads"):
        torch.set_num_threads(int(cfg.threads))
    renderer = None
    if cfg.get("renderer"):
        from b3dgs.render.renderers import make_renderer

        renderer = make_renderer(str(cfg.renderer))
        renderer.check_available()
    run = open_run(Path(str(cfg.run)), acquired=cfg.get("acquired"), renderer=renderer)
    app = ViewerApp(run, settings).start()
    extra = f", {len(run.acquired)} acquired views" if run.acquired else ""
    print(f"b3dgs-view: {run.path} (model={run.metrics.get('method')}, {run.module.num_gaussians} Gaussians, renderer "
          f"{run.module.renderer.name}{extra}) at {app.url()}  (modes: {', '.join(app.modes.available())}; Ctrl-C stops)",
          flush=True)
    return app


@hydra.main(version_base="1.3", config_path=CONF_DIR, config_name="view")
def hydra_main(cfg: DictConfig) -> None:
    from b3dgs.errors import known_errors, quiet_known_noise

    with known_errors("b3dgs-view", cfg):
        quiet_known_noise()
        logging.getLogger("websockets").setLevel(logging.WARNING)
        app = serve(cfg)
        limit = cfg.get("duration_s")
        t0 = time.time()
        try:
            while limit is None or time.time() - t0 < float(limit):
                time.sleep(0.2)
        except KeyboardInterrupt:
            pass
        finally:
            app.stop()


def main() -> None:
    """``b3dgs-view``: one-line errors with exit code 2 (see :mod:`b3dgs.errors`)."""
    from b3dgs.errors import run_cli

    run_cli("b3dgs-view", hydra_main)


if __name__ == "__main__":
    main()
    sys.exit(0)

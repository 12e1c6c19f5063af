"""``b3dgs-view run=DIR [port=8080] [mode=...]``: serve the viewer of a finished run (``conf/view.yaml``).

Known problems (a missing, unfinished or other-version run dir, viser not installed, a mode the run cannot
show, a port outside 0-65535, a host that is not an address of this machine) print one line
``b3dgs-view: error: ... (fix: ...)`` and exit with code 2, before anything is served. ``--help`` lists the
modes and every option (from ``conf/view.yaml``). Ctrl-C stops the viewer (exit code 0); SIGTERM stops it with one
line, ``b3dgs-view: stopped by SIGTERM``, and exit code 143.
"""
from __future__ import annotations

import logging
import signal
import sys
import time
from pathlib import Path

import hydra
from omegaconf import DictConfig, OmegaConf

from b3dgs.errors import B3dgsError, known_errors, quiet_known_noise, run_cli
from b3dgs import conf_dir
from b3dgs.viewer.server import ViewerApp, ViewerSettings

CONF_DIR = conf_dir()

log = logging.getLogger(__name__)

__all__ = ["main", "serve"]

SETTINGS = ("host", "port", "max_side", "min_side", "target_ms", "still_ms", "samples", "jitter", "sigma_max", "mode",
            "frusta", "photos", "start")
STARTS = ("orbit", "camera")


def settings_from_cfg(cfg: DictConfig):
    from b3dgs.validation import validate_config
    from b3dgs.viewer.modes import MODES

    port = cfg.get("port", 0)
    if not isinstance(port, int) or isinstance(port, bool) or not 0 <= port <= 65535:
        raise B3dgsError(f"port={port} is not a TCP port (0-65535)", "pass port=8080, or port=0 for any free port")
    validate_config(cfg, app="view")
    kw = {k: cfg.get(k) for k in SETTINGS if cfg.get(k) is not None}
    if str(kw.get("mode", "rgb")) not in MODES:
        raise B3dgsError(f"unknown viewer mode {kw['mode']!r}", f"pass mode= one of {', '.join(MODES)}")
    if str(kw.get("start", "orbit")) not in STARTS:
        raise B3dgsError(f"start={kw['start']} is not a start view", f"pass start= one of {', '.join(STARTS)}")
    for key in ("max_side", "count_scale"):  # null is a value here (no cap; the model's own posterior), not "unset"
        if key in cfg:
            kw[key] = cfg.get(key)
    return ViewerSettings(**kw)


def check_host(host: str, timeout: float = 3.0) -> None:
    """Refuse (one line) a ``host`` that does not resolve, within ``timeout`` seconds, to an address of this machine
    (the server could not bind to it)."""
    import socket
    from concurrent.futures import ThreadPoolExecutor, TimeoutError as Late

    fix = "pass host=127.0.0.1 (this machine only) or host=0.0.0.0 (every interface of this machine)"
    pool = ThreadPoolExecutor(max_workers=1)
    try:
        infos = pool.submit(socket.getaddrinfo, host, 0, 0, socket.SOCK_STREAM).result(timeout=timeout)
    except Late:
        raise B3dgsError(f"host={host} did not resolve within {timeout:g} s", fix) from None
    except (socket.gaierror, UnicodeError) as e:
        raise B3dgsError(f"host={host} is not a known host name or address ({e})", fix) from None
    finally:
        pool.shutdown(wait=False)
    why = None
    for family, kind, proto, _, addr in infos:
        with socket.socket(family, kind, proto) as sock:
            try:
                sock.bind((addr[0], 0, *addr[2:]))
                return
            except OSError as e:
                why = e.strerror or str(e)
    raise B3dgsError(f"cannot serve on host={host}: {why} (it is not an address of this machine)", fix)


def serve(cfg: DictConfig, settings=None):
    """Open the run, start the viewer; returns the started :class:`~b3dgs.viewer.server.ViewerApp`."""
    if settings is None:
        settings = settings_from_cfg(cfg)
        check_host(str(settings.host))
    import torch

    try:
        import viser  # noqa: F401
    except ImportError:
        raise B3dgsError("the viewer needs viser, which is not installed", 'pip install -e ".[viewer]"') from None
    from b3dgs.viewer.run import open_run

    if cfg.get("threads"):
        torch.set_num_threads(int(cfg.threads))
    renderer = None
    if cfg.get("renderer"):
        from b3dgs.render.renderers import make_renderer

        renderer = make_renderer(str(cfg.renderer))
        renderer.check_available()
    run = open_run(Path(str(cfg.run)), acquired=cfg.get("acquired"), renderer=renderer,
                   data_path=OmegaConf.select(cfg, "data.path"))
    app = ViewerApp(run, settings).start()
    extra = f", {len(run.acquired)} acquired views" if run.acquired else ""
    print(f"b3dgs-view: {run.path} (model={run.metrics.get('method')}, {run.module.num_gaussians} Gaussians, renderer "
          f"{run.module.renderer.name}{extra}) at {app.url()}  (modes: {', '.join(app.modes.available())}; Ctrl-C stops)",
          flush=True)
    return app


@hydra.main(version_base="1.3", config_path=CONF_DIR, config_name="view")
def hydra_main(cfg: DictConfig) -> None:
    with known_errors("b3dgs-view", cfg):
        settings = settings_from_cfg(cfg)  # a bad value or an address it cannot serve on: refused within a second or two
        check_host(str(settings.host))
        quiet_known_noise()
        logging.getLogger("websockets").setLevel(logging.WARNING)
        from b3dgs.signals import Interrupted, interrupt_handlers

        with interrupt_handlers() as pending:
            pending.deferred = True  # SIGINT / SIGTERM are recorded, and end the loop below (also while loading)
            app = serve(cfg, settings)
            limit = cfg.get("duration_s")
            t0 = time.time()
            try:
                while pending.signum is None and (limit is None or time.time() - t0 < float(limit)):
                    time.sleep(0.2)
            finally:
                app.stop()
            if pending.signum not in (None, signal.SIGINT):  # Ctrl-C is the way to stop it: exit code 0
                sys.exit(Interrupted(pending.signum).report("b3dgs-view"))


def help_text() -> str:
    """``b3dgs-view --help``: its purpose and examples (``hydra.help.header`` of ``conf/view.yaml``), usage, the modes (:data:`b3dgs.viewer.modes.MODES`) and the options with their defaults
    and comments (``conf/view.yaml``)."""
    import re

    from b3dgs.confs import load_primary
    from b3dgs.viewer.modes import MODES

    header = str(load_primary("view")["hydra"]["help"]["header"]).rstrip()  # the purpose and three examples
    lines = [header, "", "usage: b3dgs-view run=DIR [key=value ...]", "",
             "Modes (mode=NAME at start, or the panel's Mode menu; a run offers those its model supports):"]
    lines += [f"  {m.key:<14}{m.label}: {m.what}" for m in MODES.values()]
    lines += ["", "Options (key=value; defaults from conf/view.yaml):"]
    text = (Path(CONF_DIR) / "view.yaml").read_text()
    for ln in text[text.index("\nrun:") + 1:text.index("\nb3dgs:")].splitlines():
        opt = re.match(r"^(\w+):\s*(.*?)\s*(?:#\s?(.*))?$", ln)
        more = re.match(r"^\s+#\s?(.*)$", ln)
        if opt:
            lines.append(f"  {opt.group(1) + '=' + opt.group(2):<22}{opt.group(3) or ''}")
        elif more:
            lines.append(f"  {'':<22}{more.group(1)}")
    return "\n".join(lines)


def main() -> None:
    """``b3dgs-view``: one-line errors with exit code 2 (see :mod:`b3dgs.errors`); ``--help`` lists modes and options."""
    if any(a in ("--help", "-h") for a in sys.argv[1:]):
        print(help_text())
        return
    run_cli("b3dgs-view", hydra_main, config="view")


if __name__ == "__main__":
    main()
    sys.exit(0)

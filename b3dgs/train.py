"""``b3dgs-train``: the Hydra app that trains one model and writes its run dir.

``train(cfg)`` does the work and returns the metrics dict; ``main()`` is the console entry point: known
errors print ``b3dgs-train: error: <problem> (fix: <what to do>)`` and exit with code 2 (full traceback
with ``HYDRA_FULL_ERROR=1`` or ``b3dgs.debug=true``).
"""
from __future__ import annotations

import sys
from typing import Optional

import hydra
from omegaconf import DictConfig

from b3dgs import conf_dir
from b3dgs.labels import register_resolver

CONF_DIR = conf_dir()
register_resolver()  # ${b3dgs.method:} in run dir names (conf/hydra/default.yaml)


def train(cfg: DictConfig) -> dict:
    """Train one model into its run dir; returns the metrics dict.

    Run dir contract: the lock first; once every check has passed the manifest, the job log, ``.hydra/`` and
    ``config.yaml`` (:func:`b3dgs.rundir.claim_run_dir`); ``checkpoints/last.ckpt`` every ``trainer.checkpoint_every``
    steps and ``trainer.checkpoint_every_s`` seconds and at the end; the renders, ``point_cloud.ply``, the curve, and
    ``metrics.json`` last, the "done" marker. A finished run is never rewritten. ``resume=auto`` continues bit for bit
    as the uninterrupted run would, and is refused for another model, posterior, strategy, scene, ``trainer.max_steps``
    or seed. SIGINT / SIGTERM save a checkpoint and raise :class:`b3dgs.signals.Interrupted`.
    """
    from b3dgs.lifecycle import Run

    return Run(cfg, app="train").train()


@hydra.main(version_base="1.3", config_path=CONF_DIR, config_name="train")
def hydra_main(cfg: DictConfig) -> Optional[float]:
    from b3dgs.errors import known_errors
    from b3dgs.signals import Interrupted

    with known_errors("b3dgs-train", cfg, quiet=True):
        try:
            metrics = train(cfg)
        except Interrupted as e:
            at = "before training started" if e.step is None else f"at step {e.step}"
            sys.stderr.write(f"b3dgs-train: {e} {at}; resume with resume=auto\n")
            sys.stderr.flush()
            sys.exit(e.exit_code)
    return metrics.get("psnr")


def main() -> None:
    """``b3dgs-train``: one-line errors with exit code 2 (see :mod:`b3dgs.errors`)."""
    from b3dgs.errors import run_cli

    from b3dgs.data.scene import infer_data_override

    run_cli("b3dgs-train", hydra_main, config="train", prepare_argv=infer_data_override,
            again="run the same command with resume=auto (a sweep's finished runs are kept)")


if __name__ == "__main__":
    # through the importable module, so that the joblib launcher can pickle the task (not __main__'s copy)
    from b3dgs.train import main as _main

    _main()

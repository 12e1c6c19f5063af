"""``b3dgs-study <study> [hydra overrides]``: the first argument names the study."""
from __future__ import annotations

import sys

from b3dgs import conf_dir

CONF_DIR = conf_dir()

STUDIES = {  # name: (module, what it is, its config)
    "active": ("b3dgs.study.active", "fixed-budget active view selection 16 -> 32 (conf/study.yaml)", "study"),
    "compress": ("b3dgs.study.compression", "compression ladder on matched checkpoints, with PUP (conf/compress.yaml)",
                 "compress"),
}


def study_app(config_name: str, study_cls):
    """The Hydra app of a study: ``study_cls(cfg).run()`` with ``threads`` applied and one-line errors; its last line
    names the study's folder (``study.out``) and the tables written there."""
    import hydra
    import torch

    @hydra.main(version_base="1.3", config_path=CONF_DIR, config_name=config_name)
    def app(cfg) -> None:
        from b3dgs.errors import known_errors, quiet_known_noise

        with known_errors("b3dgs-study", cfg):
            quiet_known_noise()
            if cfg.get("threads"):
                torch.set_num_threads(int(cfg.threads))
            study = study_cls(cfg)
            study.run()
            tables = sorted(p.name for p in study.out.glob("*.md"))
            print(f"b3dgs-study: wrote {study.out}" + (f" ({', '.join(tables)})" if tables else ""),
                  flush=True)

    return app


def main() -> None:
    import importlib

    from b3dgs.errors import run_cli

    if len(sys.argv) < 2 or sys.argv[1] not in STUDIES:
        lines = "\n".join(f"  b3dgs-study {k} ...   {doc}" for k, (_, doc, _) in STUDIES.items())
        got = f" (got {sys.argv[1]!r})" if len(sys.argv) >= 2 else ""
        print(f"usage: b3dgs-study <study> [hydra overrides]{got}\n{lines}", file=sys.stderr)
        raise SystemExit(2)
    module, _, config = STUDIES[sys.argv.pop(1)]
    run_cli("b3dgs-study", importlib.import_module(module).hydra_main, config=config)


if __name__ == "__main__":
    main()

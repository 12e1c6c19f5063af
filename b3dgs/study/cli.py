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
        from b3dgs.errors import known_errors

        with known_errors("b3dgs-study", cfg, quiet=True):
            if cfg.get("threads"):
                torch.set_num_threads(int(cfg.threads))
            study = study_cls(cfg)
            study.run()
            tables = sorted(p.name for p in study.out.glob("*.md"))
            print(f"b3dgs-study: wrote {study.out}" + (f" ({', '.join(tables)})" if tables else ""),
                  flush=True)

    return app


def usage(got: str = "") -> str:
    """``b3dgs-study --help``: the purpose, the studies, and an example of each (the first of its config's
    ``hydra.help.header``) and how to get a study's own help."""
    from b3dgs.confs import load_primary

    lines = ["b3dgs-study: the paper's studies, each its own Hydra app: active view selection, compression.",
             f"usage: b3dgs-study <study> [hydra overrides]{got}"]
    lines += [f"  {k:<9} {doc}" for k, (_, doc, _) in STUDIES.items()]
    lines.append("Examples:")
    for _, _, config in STUDIES.values():
        header = str(((load_primary(config).get("hydra") or {}).get("help") or {}).get("header", ""))
        lines += [ln for ln in header.splitlines() if ln.startswith("  b3dgs-study ")][:1]
    lines.append("  b3dgs-study active --help                            # a study's examples, config groups and config")
    return "\n".join(lines)


def main() -> None:
    import importlib

    from b3dgs.errors import run_cli

    if len(sys.argv) < 2 or sys.argv[1] not in STUDIES:
        asked = len(sys.argv) >= 2 and sys.argv[1] in ("-h", "--help")
        got = f" (got {sys.argv[1]!r})" if len(sys.argv) >= 2 and not asked else ""
        print(usage(got), file=sys.stdout if asked else sys.stderr)
        raise SystemExit(0 if asked else 2)  # protocol: exit after the usage line, as argparse does
    module, _, config = STUDIES[sys.argv.pop(1)]
    from b3dgs.data.scene import infer_data_override

    run_cli("b3dgs-study", importlib.import_module(module).hydra_main, config=config,
            prepare_argv=infer_data_override if config == "study" else None)  # active: data.path alone reads its format


if __name__ == "__main__":
    main()

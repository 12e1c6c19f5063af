"""``b3dgs-report``: the canonical benchmark table, paired scene-level statistics, error against run time
and the paper's bounded studies (OOD support deficit, sparse views, constrained initialisation), read
from finished run dirs. See :mod:`b3dgs.report.app` (entry point) and :mod:`b3dgs.report.collect`."""
from b3dgs.report.collect import ReportError, Run, load_runs

__all__ = ["ReportError", "Run", "load_runs", "build_report"]


def build_report(cfg):
    """Write report.md / report.html / report.json for ``cfg`` (see conf/report.yaml)."""
    from b3dgs.report.app import build_report as _build

    return _build(cfg)

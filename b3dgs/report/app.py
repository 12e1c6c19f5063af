"""``b3dgs-report``: read finished run dirs and write report.md, report.html (self-contained) and
report.json with the PNG figures beside them. ``build_report(cfg)`` does the work; ``main()`` is the
Hydra entry point (``conf/report.yaml``)."""
from __future__ import annotations

import logging
import re
import sys
from contextlib import suppress
from pathlib import Path
from typing import Optional

import hydra
from omegaconf import DictConfig, ListConfig, OmegaConf

from b3dgs.errors import B3dgsError, cli_main
from b3dgs.io import atomic_path, to_jsonable, write_json
from b3dgs.report import analysis as A
from b3dgs.report import plots
from b3dgs.report.collect import ReportError, Run, group, load_runs, machine_kinds, method_order
from b3dgs.report.document import Figure, Heading, Para, Table, fmt, to_html, to_markdown
from b3dgs.train import CONF_DIR

log = logging.getLogger(__name__)

__all__ = ["build_report", "main"]

SPECS = {"psnr": ".3f", "ssim": ".4f", "lpips": ".4f", "ause_rmse": ".4f", "ece": ".4f", "cov95": ".3f",
         "num_gaussians": ",.0f", "render_fps": ".1f", "train_time_s": ".1f", "block_time_pct": ".2f",
         "cov95_err": ".3f", "nll": ".3f", "spearman": ".3f", "time_s": ".1f"}


def _as_list(v) -> list:
    if v is None:
        return []
    if isinstance(v, (list, tuple, ListConfig)):
        return [str(x) for x in v]
    return [str(v)]


def _p(v: Optional[float]) -> str:
    return fmt(v, ".3g")


# ------------------------------------------------------------------------------------------------ tables
def table_columns(cols, regimes=None, default: Optional[str] = None) -> list[tuple[str, str, str]]:
    """(row key, header, number format) per column: a uq.json column once per regime of ``regimes``, the regime
    named in its header where there are several or it is not ``default`` (cfg.uq_regime)."""
    out = []
    for k, label, src in cols:
        for g in (regimes or [None]) if src == A.UQ else [None]:
            named = g is not None and (len(regimes) > 1 or g != default)
            out.append((A.uq_key(k, g, regimes) if g else k, f"{label} ({g})" if named else label, SPECS.get(k, ".4g")))
    return out


def macro_table(rows: dict[str, dict], caption: str, cols=None, regimes=None, default: Optional[str] = None) -> Table:
    """Macro rows (:func:`b3dgs.report.analysis.macro_row`) as a table; ``regimes``: those the rows were built with."""
    cols = cols or [c for c in A.COLUMNS]
    keys = table_columns(cols, regimes, default)
    header = ["Method"] + [label for _, label, _ in keys] + ["scenes", "runs"]
    body = []
    for m, r in rows.items():
        body.append([m] + [fmt(r.get(k), spec) + ("*" if k in r.get("partial", {}) else "") for k, _, spec in keys]
                    + [str(r["n_scenes"]), str(r["n_runs"])])
    note = "Macro means over scenes of per-scene seed means (the paper's Table 1 aggregation)."
    if any(k == "block_time_pct" for k, _, _ in cols):
        note += (" Blocks % of time: the posterior blocks' share of each run's training time, timed inside the run "
                 "(wall times across runs trained at different machine loads are not comparable; this share is).")
    if any(r.get("partial") for r in rows.values()):
        note += " * = logged on fewer scenes than the method ran (mean over those scenes only)."
    return Table(header, body, caption, note)


def paired_table(results: list[dict], caption: str) -> Table:
    header = ["Metric", "Mean Δ", "CI", "CI method", "Scene wins / losses", "p (2-sided)", "p floor 2/2ⁿ",
              "p (1-sided)", "scenes (pairs)"]
    rows = []
    for r in (r for r in results if r["n"]):  # metrics neither method logged are left out
        ci = r["ci"]
        ci_s = "—" if ci["low"] is None else f"[{ci['low']:+.4g}, {ci['high']:+.4g}]"
        how = (ci["method"] or "none") + (f" ({ci['reason']})" if ci.get("reason") else "")
        wl = f"{r['wins']} / {r['losses']}" + (f" ({r['ties']} tied)" if r["ties"] else "")
        rows.append([r["metric"], fmt(r["mean"], ".4g", signed=True), ci_s, how, wl, _p(r["p_two_sided"]),
                     _p(r["p_floor"]), _p(r["p_one_sided"]), f"{r['n']} ({r['n_pairs']})"])
    note = ("Cluster bootstrap over scenes (scipy.stats.bootstrap on per-scene mean differences); exact sign-flip "
            "permutation p over scene means (scipy.stats.permutation_test, permutation_type='samples', "
            "n_resamples=inf). With n scenes no two-sided p can fall below 2/2ⁿ: a p at that floor is the "
            "strongest result n scenes can give, not evidence of a large effect. Wins count the favourable "
            "direction (lower is better for LPIPS).")
    return Table(header, rows, caption, note)


def per_scene_table(ps: dict, methods: list[str], caption: str) -> Table:
    rows = []
    for scene, by_m in ps.items():
        rows.append([scene] + [("—" if m not in by_m or by_m[m]["mean"] is None else
                                f"{by_m[m]['mean']:.3f}" + (f" ± {by_m[m]['sem']:.3f}" if by_m[m]["sem"] else "")
                                + f" (n={by_m[m]['n']})") for m in methods])
    return Table(["Scene"] + methods, rows, caption, "Seed mean ± SEM over seeds (n seeds).")


DEFAULT_PAIR = ("dpmm", "standard")  # pair=null: the paper's comparison, where both ran


def choose_pair(pair, methods) -> tuple[Optional[tuple[str, str]], Optional[str]]:
    """The paired analysis' (first, second) method and a line saying why (None where it is the one asked for).

    ``pair`` given: it, where both methods ran. ``pair`` null: dpmm − standard where both ran, else the two methods
    present (the later in the paper's order first: niw − standard), else none, naming the pairs to ask for."""
    ms = method_order(methods)
    if pair:
        a, b = [str(x) for x in pair]
        if {a, b} <= set(ms):
            return (a, b), None
        return None, f"No paired analysis: pair={[a, b]} needs both methods; found {ms} (choose two with pair=[A,B])."
    if set(DEFAULT_PAIR) <= set(ms):
        return DEFAULT_PAIR, None
    if len(ms) == 2:
        return (ms[1], ms[0]), (f"Paired analysis of the two methods present, {ms[1]} − {ms[0]} (the default "
                                f"{DEFAULT_PAIR[0]} − {DEFAULT_PAIR[1]} needs both; pair=[A,B] chooses another).")
    if len(ms) < 2:
        return None, f"No paired analysis: one method ran ({', '.join(ms)}); pair=[A,B] compares two."
    options = [f"pair=[{b},{a}]" for i, a in enumerate(ms) for b in ms[i + 1:]]
    return None, (f"No paired analysis: {len(ms)} methods ran ({', '.join(ms)}) and the default "
                  f"{DEFAULT_PAIR[0]} − {DEFAULT_PAIR[1]} needs both; choose a pair: {', '.join(options)}.")


# ------------------------------------------------------------------------------------------------ sections
class Builder:
    def __init__(self, cfg: DictConfig, out: Path):
        self.cfg, self.out = cfg, out
        self.blocks: list = []
        self.figures: list[str] = []
        self.boot = dict(OmegaConf.to_container(cfg.bootstrap, resolve=True))
        self.tag = ""  # figure file-name suffix of the current group_by group ("" without group_by)
        self.uq_regime = None if cfg.get("uq_regime") is None else str(cfg.uq_regime)

    def png(self, name: str) -> Path:
        """The path of figure ``name`` of the current group."""
        return self.out / f"{name}{self.tag}.png"

    def figure(self, path: Path, caption: str) -> None:
        self.blocks.append(Figure(path, caption))
        self.figures.append(path.name)

    def pairs(self, runs: list[Run], pair: tuple[str, str], metrics, regime_of=None) -> list[dict]:
        a, b = pair
        return [A.paired(runs, a, b, m, (regime_of or {}).get(m), **self.boot) for m in metrics]

    def canonical(self, runs: list[Run], suffix: str = "") -> dict:
        """The canonical benchmark of ``runs``; ``suffix``: the group_by values in the headings (" [k=v]")."""
        cfg, B = self.cfg, self.blocks
        methods = method_order(r.method for r in runs)
        regimes = A.uq_regimes(runs, self.uq_regime)
        table = A.canonical_table(runs, regimes)
        src = (f"from the '{regimes[0]}' uq.json regime" if len(regimes) == 1 else
               f"per uq.json regime: {', '.join(regimes)}" if regimes else "from uq.json, which these runs lack")
        B += [Heading("Canonical benchmark" + suffix),
              macro_table(table, f"Canonical table (AUSE, ECE, Cov@95 {src})", regimes=regimes, default=self.uq_regime)]
        ps = A.per_scene(runs, "psnr")
        B.append(per_scene_table(ps, methods, "Per-scene PSNR (dB)"))
        out: dict = {"table": table, "per_scene_psnr": ps}
        uq = A.uq_table(runs)
        if uq:
            labels = {"psnr": "PSNR ↑", "ause_rmse": "AUSE ↓", "ece": "ECE ↓", "cov95": "Cov@95",
                      "cov95_err": "|Cov@95 − 0.95| ↓", "nll": "NLL", "spearman": "Spearman ρ ↑",
                      "time_s": "UQ time (s)", "train_time_s": "train time (s)"}
            B.append(Table(["Method (regime)"] + [labels[k] for k in A.UQ_COLUMNS] + ["scenes", "runs"],
                           [[k] + [fmt(r[c], SPECS.get(c, ".4g")) for c in A.UQ_COLUMNS]
                            + [str(r["n_scenes"]), str(r["n_runs"])] for k, r in uq.items()],
                           "Uncertainty regimes (the paper's Table 3 shape)",
                           "Every uq.json regime of the canonical runs, macro means over scenes of per-scene seed means. "
                           "PSNR is the regime's predictive mean (the ensemble's is its members' average render). NLL is "
                           "comparable only within one regime. The ensemble's train time is the sum over its members."))
            out["uq_table"] = uq
        pair, why = choose_pair(cfg.get("pair"), methods)
        if pair:
            a, b = pair
            res = self.pairs(runs, pair, [str(m) for m in cfg.paired_metrics])
            B += [Heading(f"Paired analysis: {a} − {b}", 3), *([Para(why)] if why else []),
                  paired_table(res, f"{a} − {b}, scene-level")]
            self.figure(plots.plot_paired(res, self.png("paired")),
                        f"Per-scene Δ ({a} − {b}): bars per scene, the mean (line) and its bootstrap CI (band).")
            out["paired"] = res
        else:
            B.append(Para(why))
        B.append(Heading("Error against run time", 3))
        cv = A.curves(runs, "psnr")
        out["curves"] = {"psnr": cv}
        if cv:
            self.figure(plots.plot_curves(cv, self.png("curves_psnr")),
                        "Test PSNR against training seconds (evaluation excluded), seed mean ± 1 SEM, one panel per scene.")
        cl = A.curves(runs, "lpips")
        if cl:
            out["curves"]["lpips"] = cl
            self.figure(plots.plot_curves(cl, self.png("curves_lpips"), "test LPIPS"),
                        "Test LPIPS against training seconds, seed mean ± 1 SEM.")
        else:
            B.append(Para("LPIPS is not logged in curve.json (the curve callback records PSNR and #Gaussians), "
                          "so only the final LPIPS appears, in the tables."))
        pa = A.pareto(runs)
        out["pareto"] = pa
        self.figure(plots.plot_pareto(pa, self.png("pareto")),
                    "Final PSNR against train time, #Gaussians and render FPS (per-scene seed means; the last row "
                    "is the macro mean). Ringed points joined by a dashed line form the Pareto frontier.")
        fr = [float(f) for f in cfg.time_fractions]
        tt = A.time_to_target(runs, fr)
        out["time_to_target"] = tt
        keys = [f"t{round(f * 100):d}" for f in fr]
        B.append(Table(["Method"] + [f"time to {k[1:]}% of gain (s)" for k in keys] + ["final train time (s)"],
                       [[m] + [fmt(r[k], ".1f") for k in keys] + [fmt(r["train_time_s"], ".1f")] for m, r in tt.items()],
                       "Time to target",
                       "Per run: first training time at which test PSNR reaches the fraction of its final gain over the "
                       "first logged point (linear interpolation between logged points); seed means, macro mean."))
        return out

    def ood(self, runs: list[Run], suffix: str = "") -> Optional[dict]:
        from b3dgs.report.ood import ood_study

        o = self.cfg.ood
        regimes = _as_list(o.get("regimes")) or None
        if not any(r.uq for r in runs):
            self.blocks += [Heading("OOD support deficit" + suffix),
                            Para("No uq.json in these runs: run b3dgs-eval run=RUN uq=[proxy,native] (or "
                                 "python -m bench.studies --uq) to add the per-view uncertainties.")]
            return None
        res = ood_study(runs, float(o.quantile), str(o.score), regimes)
        q = float(o.quantile)
        rows = [[k, fmt(v["auroc"], ".3f"), fmt(v["auprc"], ".3f"), fmt(v["prevalence"], ".2f"),
                 fmt(v["gap"], ".3g", signed=True), str(v["n_scenes"]), str(v["n_runs"])] for k, v in res["rows"].items()]
        self.blocks += [Heading("OOD support deficit" + suffix), Table(
            ["Detector (method (regime))", "AUROC", "AUPRC", "OOD share", "OOD − ID gap", "scenes", "runs"], rows,
            f"Support-deficit OOD: ID = best-supported {q:.3g} quantile of test views, OOD = worst {q:.3g}",
            f"Support score = distance to the nearest training camera centre / scene extent. Detector: per-view "
            f"'{o.score}' from uq.json. Per run AUROC/AUPRC (scikit-learn; AUPRC's chance level is the OOD share), "
            "seed means per scene, macro mean over scenes. Geometric support only, not semantic novelty.")]
        if res["skipped"]:
            self.blocks.append(Para("Skipped: " + "; ".join(res["skipped"])))
        if res["views"]:
            self.figure(plots.plot_ood(res["views"], self.png("ood")),
                        "Per-view uncertainty against support score; green ID, red OOD, grey ignored middle band.")
        return res

    def sparse(self, runs: list[Run], canonical: list[Run], suffix: str = "") -> dict:
        """Sparse-view confirmation and compactness tables; the 'all' budget comes from canonical runs."""
        levels = sorted({r.level for r in runs if r.level != "all"}, key=int)
        by_level = {lv: [r for r in runs if r.level == lv] for lv in levels}
        all_runs = [r for r in runs if r.level == "all"] or canonical
        if all_runs:
            by_level["all"] = all_runs
        methods = method_order(r.method for rs in by_level.values() for r in rs)
        pair, why = choose_pair(self.cfg.get("pair"), methods)
        a, b = pair or ("", "")
        regimes = A.uq_regimes([r for rs in by_level.values() for r in rs], self.uq_regime)
        table: dict = {}
        q_rows, c_rows = [], []
        for lv, rs in by_level.items():
            table[lv] = {m: A.macro_row(v, regimes) for (m,), v in group(rs, "method").items()}
            get = lambda m, k: table[lv].get(m, {}).get(k)  # noqa: E731
            q_rows.append([str(lv)] + [fmt(get(m, "psnr"), ".3f") for m in methods]
                          + [fmt(get(m, "lpips"), ".4f") for m in methods])
            if pair:
                pp = A.paired(rs, a, b, "psnr", **self.boot)
                pl = A.paired(rs, a, b, "lpips", **self.boot)
                table[lv]["_paired"] = {"psnr": pp, "lpips": pl}
                q_rows[-1] += [fmt(pp["mean"], ".3f", signed=True), f"{pp['wins']} / {pp['n']}",
                               f"{pl['wins']} / {pl['n']}", _p(pp["p_two_sided"])]
            c_rows.append([str(lv)] + [fmt(get(m, "num_gaussians"), ",.0f") for m in methods]
                          + [fmt(get(m, "render_fps"), ".1f") for m in methods]
                          + [fmt(get(m, "train_time_s"), ".1f") for m in methods])
        paired_cols = [f"ΔPSNR ({a}−{b})", f"{a} PSNR wins", f"{a} LPIPS wins", "p (2-sided)"] if pair else []
        self.blocks += [
            Heading("Sparse views" + suffix), *([Para(why)] if why else []),
            Table(["Budget"] + [f"{m} PSNR" for m in methods] + [f"{m} LPIPS" for m in methods] + paired_cols, q_rows,
                  "Sparse-view confirmation (macro means over scenes of seed means)",
                  "Budget = train views, spread evenly over the sorted train list; 'all' = the canonical runs."
                  + (" Wins are scene means over seeds out of the scenes with both methods." if pair else "")),
            Table(["Budget"] + [f"{m} Gauss." for m in methods] + [f"{m} FPS" for m in methods]
                  + [f"{m} time (s)" for m in methods], c_rows, "Sparse-view compactness, throughput and run time")]
        plot_tab = {lv: {m: v for m, v in t.items() if not m.startswith("_")} for lv, t in table.items()}
        self.figure(plots.plot_levels(plot_tab, self.png("sparse"), "train views"),
                    "Sparse views: macro PSNR and train time against the train-view budget.")
        return table

    def level_study(self, name: str, runs: list[Run], caption: str) -> dict:
        """A study with one variable (init cap or a user's ``study.level``): macro table and paired rows per level
        (a study without levels: one table, captioned with the study alone)."""
        out: dict = {}
        self.blocks.append(Heading(caption))
        pair, why = choose_pair(self.cfg.get("pair"), [r.method for r in runs])
        if why:
            self.blocks.append(Para(why))
        regimes = A.uq_regimes(runs, self.uq_regime)
        cols = [c for c in A.COLUMNS if c[0] in ("psnr", "ssim", "lpips", "cov95", "num_gaussians", "train_time_s")]
        for (lv,), rs in group(runs, "level").items():
            label = f"{name} = {lv}" if lv is not None else caption
            rows = {m: A.macro_row(v, regimes) for (m,), v in
                    sorted(group(rs, "method").items(), key=lambda kv: method_order(r.method for r in rs).index(kv[0][0]))}
            self.blocks.append(macro_table(rows, label, cols, regimes, self.uq_regime))
            out[str(lv)] = {"table": rows}
            if pair:
                res = self.pairs(rs, pair, ["psnr", "lpips", "cov95"], {"cov95": regimes[0] if regimes else None})
                self.blocks.append(paired_table(res, f"{label}: paired {pair[0]} − {pair[1]}"))
                out[str(lv)]["paired"] = res
        return out


def _group_tag(split: str) -> tuple[str, str]:
    """(figure file-name suffix, heading suffix) of a group_by group ("", "" without group_by)."""
    return (f"_{re.sub(r'[^A-Za-z0-9_.=-]+', '_', split)}", f" [{split}]") if split else ("", "")


def build_report(cfg: DictConfig) -> dict[str, Path]:
    """Write the report for ``cfg`` (conf/report.yaml); returns the written paths."""
    from b3dgs.validation import validate_config

    validate_config(cfg, app="report")
    patterns = _as_list(cfg.get("runs"))
    if not patterns:
        raise ReportError("runs= is empty",
                          fix="pass a glob of finished run dirs, e.g. b3dgs-report runs='outputs/train/*'")
    if cfg.get("pair") is not None and len(_as_list(cfg.pair)) != 2:
        raise ReportError(f"pair={_as_list(cfg.pair)} names {len(_as_list(cfg.pair))} methods; the paired analysis "
                          "takes two", "pass pair=[A,B] (first − second), e.g. pair=[niw,standard], or pair=null")
    out = Path(str(cfg.out))
    out.mkdir(parents=True, exist_ok=True)
    group_by = _as_list(cfg.get("group_by"))
    runs, unfinished = load_runs(patterns, str(cfg.get("on_duplicate", "error")), group_by)
    bld = Builder(cfg, out)
    studies = {k[0]: v for k, v in group(runs, "study").items()}
    # the canonical (non-study) runs: one group, or one per value of the group_by keys
    canonical = {s: rs for s, rs in studies.items() if rs[0].base_study == "canonical"}
    canonical_of = {rs[0].split: rs for rs in canonical.values()}
    protocols = sorted({f"{r.study}: {r.config.get('trainer', {}).get('max_steps')} steps, "
                        f"max_side {r.config.get('data', {}).get('max_side')}" for r in runs})
    bld.blocks.append(Para(
        f"{len(runs)} finished run{'s' * (len(runs) != 1)} from "
        + (f"runs={patterns}" if len(patterns) <= 6 else f"{len(patterns)} run-dir patterns (each run's path is in report.json)")
        + (f" ({len(unfinished)} unfinished run dirs without metrics.json skipped)" if unfinished else "")
        + f"; scenes {sorted({r.scene for r in runs})}, methods {method_order(r.method for r in runs)}, seeds "
        f"{sorted({r.seed for r in runs})}; protocols: {'; '.join(protocols)}. Grouped by each run's own config "
        "(data.name, model.name, seed; study from data.train_indices / model.init_max_points)"
        + (f", each study split by group_by={group_by} into a section per value." if group_by else ".")))
    shared = [r for r in runs if r.metrics.get("training_shared_with")]
    if shared:
        bld.blocks.append(Para(
            f"{len(shared)} run(s) are the same training run as another and share its metrics "
            f"(`training_shared_with` in metrics.json; methods {method_order({r.method for r in shared})}): their "
            "posterior blocks only observe training (changes_training = False, tested bit for bit), so their "
            "differences to that run are zero by construction, not measured evidence."))
    data: dict = {"runs": [{"path": str(r.path), "study": r.study, "level": r.level, "scene": r.scene,
                            "method": r.method, "seed": r.seed, "uq_regimes": sorted(r.uq),
                            "training_shared_with": r.metrics.get("training_shared_with")} for r in runs],
                  "unfinished": [str(u) for u in unfinished], "config": OmegaConf.to_container(cfg, resolve=True)}
    kinds = machine_kinds(runs)
    if len(kinds) > 1:
        bld.blocks.append(Para(
            f"The runs trained on {len(kinds)} kinds of machine ("
            + "; ".join(f"{k}: {n} run{'s' * (n != 1)}" for k, n in kinds.items())
            + "): time and FPS differences between runs of different kinds measure the machines as much as the "
            "methods, and training reproduces its bits on one kind only (a seed-sized difference elsewhere)."))
        data["machine_kinds"] = kinds
    for study, rs in canonical.items():
        split = rs[0].split
        bld.tag, suffix = _group_tag(split)
        res = bld.canonical(rs, suffix)
        ood = bld.ood(rs, suffix) if cfg.ood.enabled else None
        if split:  # report.json: canonical_groups[split] = {canonical, ood}
            data.setdefault("canonical_groups", {})[split] = {"canonical": res, "ood": ood}
        else:
            data["canonical"] = res
            if cfg.ood.enabled:
                data["ood"] = ood
    if not canonical:
        bld.blocks.append(Para("No canonical runs (every run belongs to a study)."))
    data["studies"] = {}
    for study, rs in studies.items():
        base, split = rs[0].base_study, rs[0].split
        bld.tag, suffix = _group_tag(split)
        if base == "canonical":
            continue
        if base == "sparse":
            data["studies"][study] = bld.sparse(rs, canonical_of.get(split, []), suffix)
        elif base == "initcap":
            data["studies"][study] = bld.level_study("init cap", rs, "Constrained initialisation" + suffix)
        else:
            data["studies"][study] = bld.level_study(f"{base} level", rs, f"Study: {study}")
    data["figures"] = bld.figures
    title = str(cfg.get("title", "b3dgs report"))
    paths = {"md": out / "report.md", "html": out / "report.html", "json": out / "report.json"}
    with atomic_path(paths["md"]) as tmp:
        tmp.write_text(to_markdown(title, bld.blocks) + "\n")
    with atomic_path(paths["html"]) as tmp:
        tmp.write_text(to_html(title, bld.blocks))
    write_json(paths["json"], to_jsonable(data))
    log.info("Report of %d run%s -> %s", len(runs), "s" * (len(runs) != 1), out)
    return paths


@hydra.main(version_base="1.3", config_path=CONF_DIR, config_name="report")
def _hydra_main(cfg: DictConfig) -> None:
    from b3dgs.rundir import arm_run_log

    out = Path(str(cfg.out))
    existed = out.is_dir() and any(out.iterdir())
    try:
        paths = build_report(cfg)
    except B3dgsError as e:  # a ReportError, or a bad value (b3dgs.validation)
        if not existed:  # Hydra made the folder for the job log; a refused report leaves nothing
            with suppress(OSError):
                out.rmdir()
        print(f"b3dgs-report: error: {e}", file=sys.stderr)
        sys.exit(2)
    arm_run_log()  # the job log (conf/report.yaml: held in memory until the report is written)
    print(f"b3dgs-report: wrote {paths['md']}, {paths['html']}, {paths['json']}")


main = cli_main("b3dgs-report", _hydra_main, "report")  # composition errors as one line, exit code 2


if __name__ == "__main__":
    main()

"""Older on-disk formats (b3dgs/upgrade.py): one test per format of :data:`b3dgs.upgrade.UPGRADES`, each reading a
file of that format (built here, or an archived one of bench/results) and checking that it reads as the current
format does; and no module but b3dgs/upgrade.py defines a conversion of its own."""
import ast
import json
import shutil
from pathlib import Path

import pytest
import yaml
from omegaconf import OmegaConf

from b3dgs import upgrade

ROOT = Path(__file__).resolve().parents[1]
#: an archived run of the seven-scene campaign: ``_target_: plugins.*``, trainer ``log_every``/``progress_bar``, no
#: ``schedule``, no ``trainer.precision``/``deterministic`` or ``data.test_split``, uq.json entries without ``panels``
ARCHIVED = ROOT / "bench" / "results" / "runs" / "fox" / "niw" / "s0"


def _archived_cfg() -> dict:
    return yaml.safe_load((ARCHIVED / "config.yaml").read_text())


def test_config_targets_before_the_install_rename(tmp_path):
    """An archived config.yaml names ``plugins.*``; the readers see ``b3dgs_plugins.*``, as a current run writes."""
    from b3dgs.uq.store import _read_config

    raw = _archived_cfg()
    assert raw["posterior"]["niw"]["_target_"] == "plugins.posterior.niw.NIWBlock"  # the old format, still archived
    shutil.copy(ARCHIVED / "config.yaml", tmp_path / "config.yaml")
    cfg = _read_config(tmp_path)
    assert cfg["posterior"]["niw"]["_target_"] == "b3dgs_plugins.posterior.niw.NIWBlock"
    assert cfg["strategy"]["_target_"] == "b3dgs_plugins.strategy.default.AdaptiveDensityControl"
    assert cfg["data"]["_target_"] == raw["data"]["_target_"]  # b3dgs.* paths unchanged
    current = {**raw, "posterior": {"niw": {**raw["posterior"]["niw"], "_target_": "b3dgs_plugins.posterior.niw.NIWBlock"}},
               "strategy": {**raw["strategy"], "_target_": "b3dgs_plugins.strategy.default.AdaptiveDensityControl"}}
    assert cfg == current


def test_config_renderer_backend_before_renderer_plugins():
    """``renderer: {backend: torch}`` (and no node: auto) builds the renderer the current ``renderer=torch`` does."""
    from b3dgs.confs import load_option
    from b3dgs.lifecycle import build_renderer

    assert upgrade.renderer_option({"backend": "torch"}) == "torch"
    assert upgrade.renderer_option(None) == "auto" and upgrade.renderer_option({}) == "auto"
    current = OmegaConf.create(load_option("renderer", "torch"))
    assert upgrade.renderer_option(current) is None
    old, new = build_renderer(OmegaConf.create({"backend": "torch"})), build_renderer(current)
    assert type(old) is type(new) and old.name == new.name == "torch" and old.device == new.device


def test_config_trainer_keys_before_the_lightning_target():
    """The archived trainer node (``log_every``, ``progress_bar``) builds the Trainer its current keys build."""
    from b3dgs.lifecycle import build_trainer
    from b3dgs.render.renderers import make_renderer

    old = _archived_cfg()["trainer"]
    assert {"log_every", "progress_bar"} <= set(old) and "_target_" not in old
    assert upgrade.trainer_arg("log_every") == "log_every_n_steps" and upgrade.trainer_arg("max_steps") == "max_steps"
    new = {upgrade.trainer_arg(k): v for k, v in old.items()}
    renderer = make_renderer("torch")
    fixed = {"default_root_dir": None, "max_steps": 3}
    a = build_trainer(OmegaConf.create(old), renderer, [], **fixed)
    b = build_trainer(OmegaConf.create(new), renderer, [], **fixed)
    assert a.log_every_n_steps == b.log_every_n_steps == 50
    assert a.progress_bar_callback is None and b.progress_bar_callback is None  # progress_bar: false kept


def test_config_and_identity_without_a_schedule():
    """No ``schedule`` (before schedules) is the constant schedule, in a config and in a checkpoint identity."""
    from b3dgs.checkpoint import identity_mismatch
    from b3dgs.schedule import ConstantSchedule, make_schedule

    assert "schedule" not in _archived_cfg()
    assert type(make_schedule(_archived_cfg().get("schedule"))) is ConstantSchedule
    assert upgrade.schedule_node(None) == upgrade.CONSTANT_SCHEDULE
    upgrade.schedule_node(None)["x"] = 1  # a copy: the constant stays as it is
    assert upgrade.CONSTANT_SCHEDULE == {"_target_": "b3dgs.schedule.ConstantSchedule"}
    saved = {"model": "niw", "posterior": {}, "hparams": {"max_steps": 10, "seed": 0}}
    assert identity_mismatch(saved, {**saved, "schedule": dict(upgrade.CONSTANT_SCHEDULE)}) is None
    dash = {**saved, "schedule": {"_target_": "b3dgs.schedule.DashSchedule"}}
    assert identity_mismatch(saved, dash) is not None


def test_config_without_the_later_run_settings():
    """A run written before ``trainer.precision`` etc. were settings has the protocol of one that sets the values
    those runs used; another value is a different protocol."""
    from b3dgs.protocol import run_protocol

    old = _archived_cfg()
    assert "precision" not in old["trainer"] and "test_split" not in old["data"]
    new = json.loads(json.dumps(old))
    for key, value in upgrade.RUN_DEFAULTS.items():  # each setting the run's config has the node of
        *path, name = key.split(".")
        node = new
        for part in path:
            node = node.get(part) if isinstance(node, dict) else None
        if isinstance(node, dict):
            node[name] = value
    assert run_protocol(old) == run_protocol(new)
    new["data"]["test_split"] = "sector"
    assert run_protocol(old) != run_protocol(new)


def test_study_protocol_before_batch_options_and_family_posterior():
    """Empty batch settings and the unrecorded families' blocks are left out; a pinned or changed family is kept."""
    settings = {"acquire": 4, "acquisition.batch_settings": {}}
    assert upgrade.omit_study_defaults(dict(settings), dict(upgrade.FAMILY_POSTERIOR_UNRECORDED)) == {"acquire": 4}
    out = upgrade.omit_study_defaults(dict(settings), {"niw": ["niw", "sh"], "standard": []})
    assert out == {"acquire": 4, "family_posterior.niw": ["niw", "sh"]}
    assert upgrade.omit_study_defaults({"acquisition.batch_settings": {"diverse": {"r": 1}}}) == {
        "acquisition.batch_settings": {"diverse": {"r": 1}}}


def test_study_folder_with_meta_json_only(tmp_path):
    """A scene folder written before protocol.json: its meta.json's settings are checked, then protocol.json is
    written; other settings are refused."""
    from b3dgs.errors import B3dgsError
    from b3dgs.protocol import check_stored_protocol
    from b3dgs.study.active import legacy_protocol

    meta = {"acquire": 4, "total_steps": 600, "variant": "standard", "initial_views": [0, 3, 5],
            "score_max_side": 64}
    assert upgrade.protocol_from_meta(meta) == {"acquire": 4, "trainer.max_steps": 600, "variant": "standard",
                                                "acquisition.score_max_side": 64, "initial_views": 3}
    (tmp_path / "meta.json").write_text(json.dumps(meta))
    settings = {"acquire": 4, "trainer.max_steps": 600, "variant": "standard", "acquisition.score_max_side": 64,
                "initial_views": 3, "seed_list": [0]}
    with pytest.raises(B3dgsError, match="trainer.max_steps"):
        check_stored_protocol(tmp_path, {**settings, "trainer.max_steps": 900}, "fix", legacy_protocol(tmp_path))
    assert not (tmp_path / "protocol.json").exists()
    check_stored_protocol(tmp_path, settings, "fix", legacy_protocol(tmp_path))
    assert json.loads((tmp_path / "protocol.json").read_text())["settings"] == settings
    assert legacy_protocol(tmp_path / "nothing") is None


def test_metrics_without_posterior_pass_s():
    """The report's block share of a run from before the pass was timed counts the pass as 0 s."""
    from b3dgs.report.collect import Run

    old = {"train_time_s": 200.0, "block_time_s": {"niw": 2.0}}
    assert upgrade.posterior_pass_s(old) == 0.0
    assert Run(Path("x"), {}, old).value("block_time_pct") == Run(Path("x"), {}, {**old, "posterior_pass_s": 0}).value(
        "block_time_pct") == pytest.approx(1.0)


def test_uq_json_entries_without_panels(tmp_path):
    """An archived uq.json lists no panels: each regime's are ``uq/<regime>_<view>.png`` of its ``_meta`` views,
    as a current entry lists them."""
    uq = json.loads((ARCHIVED / "uq.json").read_text())
    assert "panels" not in uq["native"] and uq["_meta"]["views"]
    views = [Path(v).stem for v in uq["_meta"]["views"]]
    assert upgrade.uq_panels("native", uq["native"], uq["_meta"]) == [f"uq/native_{v}.png" for v in views]
    assert upgrade.uq_panels("native", {"panels": ["uq/a.png"]}, uq["_meta"]) == ["uq/a.png"]


def _v1_dir(tmp_path: Path, manifest: bool) -> tuple[Path, list[str], list[str]]:
    """A run dir of b3dgs's files and a user's, with a format-1 manifest or none (a run from before manifests)."""
    from b3dgs.rundir import MANIFEST_NAME

    d = tmp_path / "run"
    ours = [".hydra/config.yaml", "checkpoints/last.ckpt", "checkpoints/step300.ckpt", "config.yaml", "metrics.json",
            "renders/view_000.png", "tb/events.out.tfevents.1718000000.host.4242.0", "uq.json",
            "uq/native_view_000.png", "uq/proxy_view_000.png"]
    theirs = ["checkpoints/step_best.ckpt", "notes.txt", "renders/figure.png", "uq/native_mine.png"]
    for name in ours + theirs:
        (d / name).parent.mkdir(parents=True, exist_ok=True)
        (d / name).write_text("x")
    (d / "config.yaml").write_text(yaml.safe_dump({"data": {}, "model": {}, "seed": 0}))
    (d / "metrics.json").write_text(json.dumps({"per_view": [{"name": "view_000.png"}], "checkpoint": {}}))
    (d / "uq.json").write_text(json.dumps({"_meta": {"views": ["view_000.png"]}, "native": {},
                                           "proxy": {"panels": ["uq/proxy_view_000.png"]}}))
    if manifest:
        (d / MANIFEST_NAME).write_text(json.dumps({"b3dgs_run": 1, "created": "2025-01-01T00:00:00", "writes": [
            "config.yaml", ".hydra/config.yaml", "metrics.json", "checkpoints/last.ckpt", "checkpoints/step[0-9]*.ckpt",
            "tb/events.out.tfevents.*", "uq.json"]}))
    return d, ours, theirs


def test_manifest_format_1_patterns(tmp_path):
    """A format-1 manifest (``writes`` patterns) lists the files its patterns name by our writers' names, plus the
    renders and uq panels; the first write turns it into format 2 with the same files."""
    from b3dgs.rundir import MANIFEST_NAME, record_written, run_files

    d, ours, _ = _v1_dir(tmp_path, manifest=True)
    assert run_files(d) == sorted(ours)
    record_written(d, ["extra.json"])
    m = json.loads((d / MANIFEST_NAME).read_text())
    assert m["b3dgs_run"] == 2 and "writes" not in m and sorted(m["files"]) == sorted([*ours, "extra.json"])
    assert m["run_id"] == "created 2025-01-01T00:00:00"  # the run keeps its identity (manifest_run_id)


def test_manifest_format_1_run_id(tmp_path):
    """A format-1 manifest had no ``run_id``: its run's identity is its creation time, kept when it is rewritten."""
    from b3dgs.rundir import manifest_token, run_dir_stamp

    assert upgrade.manifest_run_id({"b3dgs_run": 2, "run_id": "abc"}) == "abc"
    assert upgrade.manifest_run_id({"b3dgs_run": 1, "created": "2025"}) == "created 2025"
    d, _, _ = _v1_dir(tmp_path, manifest=True)
    assert manifest_token(json.loads((d / ".b3dgs-run.json").read_text())) == "created 2025-01-01T00:00:00"
    assert run_dir_stamp(d)["run_id"] == "created 2025-01-01T00:00:00"


def test_run_dir_without_a_manifest(tmp_path):
    """A run dir from before manifests is a ``legacy`` run whose files are those a format-1 manifest would list."""
    from b3dgs.rundir import run_dir_kind, run_files

    d, ours, theirs = _v1_dir(tmp_path, manifest=False)
    assert run_dir_kind(d) == "legacy" and run_files(d) == sorted(ours)
    assert upgrade.premanifest_files(theirs) == []


def test_temp_files_before_the_marker(tmp_path):
    """A temp file an older writer left (``.<name>.<random>.tmp``) of a file the manifest lists is removed like a
    current one; a user's ``.*.tmp`` stays."""
    from b3dgs.rundir import record_written, remove_stale_tmp

    assert upgrade.old_temp_target(".metrics.json.k2j4_x9a.tmp") == "metrics.json"
    assert upgrade.old_temp_target(".notes.tmp") is None and upgrade.old_temp_target(".a.b3dgs-ABCDefgh.tmp") is None
    d, _, _ = _v1_dir(tmp_path, manifest=False)
    record_written(d, ["metrics.json", "uq.json"])
    old, now, mine = d / ".metrics.json.k2j4_x9a.tmp", d / ".uq.json.b3dgs-Ab3dEf_h.tmp", d / ".notes.json.k2j4_x9a.tmp"
    for p in (old, now, mine):
        p.write_text("x")
    assert sorted(remove_stale_tmp(d)) == sorted([old, now]) and mine.exists()


#: each format of :data:`b3dgs.upgrade.UPGRADES` -> its test above
TESTS = {
    "config/checkpoint _target_ plugins.* (before c2b61e1)": test_config_targets_before_the_install_rename,
    "config renderer {backend: ...} (before 00f6cdc)": test_config_renderer_backend_before_renderer_plugins,
    "config trainer progress_bar/log_every (before ab57b0a)": test_config_trainer_keys_before_the_lightning_target,
    "config/checkpoint without schedule (before 16ebca2)": test_config_and_identity_without_a_schedule,
    "config without precision/deterministic/test split keys (before ab57b0a)": test_config_without_the_later_run_settings,
    "study protocol.json without batch_settings/family_posterior (before 5daa7cb/b529740)":
        test_study_protocol_before_batch_options_and_family_posterior,
    "study folder with meta.json only (before 9ef1d55)": test_study_folder_with_meta_json_only,
    "metrics.json without posterior_pass_s (before bb449df)": test_metrics_without_posterior_pass_s,
    "uq.json entry without panels (before 7a1e6d8)": test_uq_json_entries_without_panels,
    ".b3dgs-run.json format 1: writes patterns (before aff6d34)": test_manifest_format_1_patterns,
    ".b3dgs-run.json format 1: no run_id (before aff6d34)": test_manifest_format_1_run_id,
    "run dir without a manifest": test_run_dir_without_a_manifest,
    "atomic temp file .<name>.<random>.tmp (before 0467be2)": test_temp_files_before_the_marker,
}


def test_every_format_has_a_test_and_a_docstring():
    assert set(TESTS) == set(upgrade.UPGRADES)
    for name, fn in upgrade.UPGRADES.items():
        assert fn.__module__ == "b3dgs.upgrade" and fn.__doc__ and len(fn.__doc__.split()) >= 8, name
    assert upgrade._V1_TRAIN_FILES == __import__("b3dgs.rundir").rundir.TRAIN_FILES  # frozen as it was


#: names that hold a conversion of an older format: b3dgs/upgrade.py's, and those the readers carried before it
CONVERSION_NAMES = {*upgrade.__all__, "_OLD_TRAINER_KEYS", "_V1_NAMES", "_V1_TRAIN_FILES", "_v1_matches", "_v1_files",
                    "_old_panels", "_uq_outputs", "_TEMP_BEFORE"} - {"UPGRADES"}


def _definitions(path: Path) -> set[str]:
    """Names a module defines: functions and classes (at any depth) and module or class attributes (a function's
    local variables and imports are not definitions)."""
    tree = ast.parse(path.read_text(), str(path))
    out = set()
    scopes = [tree.body]
    for node in ast.walk(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            out.add(node.name)
        if isinstance(node, ast.ClassDef):
            scopes.append(node.body)
    for body in scopes:
        for node in body:
            if isinstance(node, (ast.Assign, ast.AnnAssign)):
                for t in (node.targets if isinstance(node, ast.Assign) else [node.target]):
                    out |= {n.id for n in ast.walk(t) if isinstance(n, ast.Name)}
    return out


def test_no_other_module_defines_an_upgrade():
    """Conversions of older formats live in b3dgs/upgrade.py only: no other module of b3dgs/, plugins/ or bench/
    defines one of its names, or renames ``plugins.`` class paths itself."""
    files = [p for pkg in ("b3dgs", "plugins") for p in (ROOT / pkg).rglob("*.py")] + list((ROOT / "bench").glob("*.py"))
    assert len(files) > 50 and ROOT / "b3dgs" / "upgrade.py" in files
    offenders = {}
    for p in files:
        if p.name == "upgrade.py" and p.parent.name == "b3dgs":
            continue
        text = p.read_text()
        bad = sorted(_definitions(p) & CONVERSION_NAMES)
        if '"b3dgs_plugins."' in text or "'b3dgs_plugins.'" in text:
            bad.append("a plugins. -> b3dgs_plugins. rename")
        if bad:
            offenders[str(p.relative_to(ROOT))] = bad
    assert not offenders, offenders


def test_the_check_finds_a_conversion(tmp_path):
    """The definitions check sees a module-level table and a function."""
    p = tmp_path / "m.py"
    p.write_text("_OLD_TRAINER_KEYS = {'log_every': 'log_every_n_steps'}\ndef upgrade_targets(n):\n"
                 "    posterior_pass_s = 0\n    return n\n")
    assert _definitions(p) & CONVERSION_NAMES == {"_OLD_TRAINER_KEYS", "upgrade_targets"}  # not a local variable

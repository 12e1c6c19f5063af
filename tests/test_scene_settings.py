"""The scene settings are one dataclass (issue 53 §5): SceneSettings holds every common ``data.*`` setting and its
default once; load_scene, the data module and preprocess take it instead of threading the keywords one by one, and the
flat ``data.*`` keys a config writes stay as they are."""
from __future__ import annotations

import dataclasses
import inspect
from pathlib import Path

import pytest
from omegaconf import OmegaConf

from b3dgs import conf_dir
from b3dgs.data.datamodule import SceneDataModule
from b3dgs.data.scene import SceneSettings, load_scene, preprocess
from b3dgs.errors import B3dgsError

FIELDS = {f.name for f in dataclasses.fields(SceneSettings)}


def test_no_signature_threads_a_setting():
    """The defaults live in the dataclass only: no signature repeats a field."""
    for f in (load_scene, preprocess, SceneDataModule.__init__):
        params = set(inspect.signature(f).parameters)
        assert "settings" in params and not params & FIELDS, f.__qualname__


def test_flat_keys_and_a_settings_object_are_one():
    dm = SceneDataModule(kind="synthetic", max_side=16, test_every=4, background=[0, 0, 0], n_views=8, resolution=16)
    assert dm.settings == SceneSettings(max_side=16, test_every=4, background=[0, 0, 0])
    assert dm.kind_kwargs == {"n_views": 8, "resolution": 16}
    a = load_scene("synthetic", None, max_side=16, test_every=4, n_views=8, resolution=16)
    b = load_scene("synthetic", None, SceneSettings(max_side=32, test_every=4), max_side=16, n_views=8, resolution=16)
    assert [c.name for c in a.test] == [c.name for c in b.test] == [c.name for c in dm.scene.test]
    assert a.train[0].image.shape == b.train[0].image.shape == (16, 16, 3)  # the flat key over the object's


@pytest.mark.parametrize("build", [
    lambda: SceneDataModule(kind="synthetic", max_sid=16, n_views=4, resolution=8),
    lambda: load_scene("synthetic", None, test_evry=4, n_views=4, resolution=8),
])
def test_a_wrong_key_is_named_with_the_valid_ones(build):
    """Before: a TypeError from inside the format loader when the scene was read."""
    with pytest.raises(B3dgsError) as e:
        build()
    msg = str(e.value)
    assert "\n" not in msg and "is not a setting of data=synthetic; did you mean" in msg
    assert all(k in msg for k in ("test_every", "max_side", "n_views", "resolution"))


def test_every_data_config_lists_the_settings():
    """The keys users override (data.max_side=256, data.test_split=sector, ...) are in every data option as composed
    (the files hold only their deviations; the config sources fill in the fields, b3dgs.confs.field_defaults), and
    the config check knows each field of the dataclass with its type."""
    from b3dgs.confs import field_defaults, with_field_defaults
    from b3dgs.schema import _fields

    assert set(field_defaults("b3dgs.data.datamodule.SceneDataModule")) == FIELDS - {"init_points_from_train_only"}
    for f in sorted(Path(conf_dir(), "data").glob("*.yaml")):
        node = OmegaConf.to_container(with_field_defaults(OmegaConf.load(f)), resolve=False)
        if "_target_" in node:
            assert FIELDS - {"init_points_from_train_only"} <= set(node), f.name
    fields, _ = _fields(SceneDataModule)
    assert FIELDS <= set(fields) and "settings" not in fields
    assert fields["test_every"] == (int, 8) and fields["max_side"][1] is None

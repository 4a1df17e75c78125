"""A map's runtime takes one typed, frozen `RuntimeSettings`, built from `Settings` in one place
(service/maps/runtime/settings.py, docs/design/service.md §8): no setting is passed one by one, and none
has a default of its own that could drift from `Settings`'."""

from __future__ import annotations

import dataclasses
import inspect

import pytest

from service.maps.runtime import MapRuntime
from service.maps.runtime.settings import RuntimeSettings
from service.settings import Settings
from tests.service.maps.maps_fixtures import registry


def test_the_runtime_settings_are_settings_fields_under_their_names(tmp_path):
    s = Settings(data_dir=tmp_path, max_streams=3, snapshot_every=7, visits=11, verify_neighbours=4,
                 stream_keep_seconds=2.5, idempotency_keys=13, loop_closures=17)
    got = RuntimeSettings.of(s)
    for f in dataclasses.fields(RuntimeSettings):
        assert f.name in Settings.model_fields  # the same name, hence Settings' default and check
        assert f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING
        assert getattr(got, f.name) == getattr(s, f.name)
    with pytest.raises(dataclasses.FrozenInstanceError):
        got.max_streams = 4  # type: ignore[misc]


def test_the_runtime_takes_one_settings_object():
    params = inspect.signature(MapRuntime.__init__).parameters
    assert list(params) == ["self", "record", "catalog", "feature_dim", "settings", "budget"]


def test_a_registry_builds_its_runtimes_with_its_settings(tmp_path):
    with registry(tmp_path, max_streams=5, snapshot_keep=2, idempotency_cache=9) as reg:
        rt = reg.get("default")
        assert isinstance(rt, MapRuntime)
        assert rt.settings == RuntimeSettings.of(reg.settings)
        assert rt.memory().streams.max == 5 and rt.keys.size == 9

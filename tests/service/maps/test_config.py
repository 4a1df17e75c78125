"""One typed map configuration (service/maps/config.py): the only home of a map's options, defaults and
checks; the create request, the map resource, failed maps and stored maps derive from it."""

from __future__ import annotations

import pytest
from pydantic import ValidationError

from models.frontend import backbones
from models.memory import registry as memories
from service.maps.config import DEFAULT_REVISIT_THRESHOLD, SHOWN_PARAMS, MapConfig, MapOptions, resolve
from service.maps.errors import InvalidConfiguration
from service.schemas import CreateMap, MapParams


def new(**options) -> MapConfig:
    return resolve(MapOptions(**options), default_preset="cortexloc-grid", default_backbone="alexnet")


def test_a_resolved_configuration_is_stored_and_read_back_unchanged():
    config = new(seed=5, memory="none", localiser={"beam": 64}, thumbnails=True)
    again = MapConfig.parse(config.stored())
    assert again == config and again.stored() == config.stored()
    assert (config.seed, config.tm["seed"], config.slsbh["seed"]) == (5, 5, 5)


def test_a_map_made_before_an_option_existed_runs_with_its_default():
    stored = new().stored()
    for name in ("backbone", "memory", "revisit_threshold", "localiser", "projection", "thumbnails"):
        del stored[name]
    old = MapConfig.parse(stored)
    got = (old.backbone, old.memory, old.revisit_threshold, old.localiser, old.projection, old.thumbnails)
    assert got == ("alexnet", "tm", DEFAULT_REVISIT_THRESHOLD, {}, "dense", False)


def test_frozen_except_the_revisit_threshold():
    config = new()
    with pytest.raises(ValidationError):
        config.memory = "none"
    with pytest.raises(ValidationError):
        config.tm = {}
    changed = config.with_revisit_threshold(0.5)
    assert changed.revisit_threshold == 0.5 and config.revisit_threshold == DEFAULT_REVISIT_THRESHOLD
    with pytest.raises(InvalidConfiguration) as info:
        config.with_revisit_threshold(1.5)
    assert info.value.errors[0]["name"] == "revisit_threshold"
    assert config.revisit_threshold == DEFAULT_REVISIT_THRESHOLD


@pytest.mark.parametrize(("change", "name"), [
    ({"memory": "lstm"}, "memory"), ({"backbone": "vgg"}, "backbone"), ({"revisit_threshold": -0.1},
                                                                        "revisit_threshold"),
    ({"localiser": {"beam": 0}}, "localiser.beam"), ({"slsbh": {"k": 3}}, "slsbh.k"),
    ({"projection": "diagonal"}, "projection"), ({"surprise": 1}, "surprise"),
])
def test_stored_values_pass_the_same_checks_as_a_new_map(change, name):
    """A stored (or imported) configuration this version rejects is refused by name, as a request is."""
    with pytest.raises(InvalidConfiguration) as info:
        MapConfig.parse({**new().stored(), **change})
    assert name in {e["name"] for e in info.value.errors}


def test_a_failed_map_shows_what_can_be_read_of_its_stored_values():
    stored = {**new().stored(), "memory": 7, "tm": "garbage", "localiser": {"beam": 0}}
    shown = MapConfig.salvage(stored)
    assert shown.memory == "tm" and shown.tm == {} and shown.seed == stored["seed"]
    assert shown.localiser == {"beam": 0}  # as stored: a failed map shows it, it does not run it
    assert MapConfig.salvage("not a dict").backbone == "alexnet"


def test_the_request_and_the_resource_derive_from_the_configuration():
    assert set(CreateMap.model_fields) == set(MapOptions.model_fields) | {"map_id"}
    assert tuple(MapParams.model_fields) == SHOWN_PARAMS
    assert set(SHOWN_PARAMS) <= set(MapConfig.model_fields)
    for name in backbones.names():  # the registries name the choices, listed nowhere else
        assert name in MapOptions.model_fields["backbone"].description
    for name in memories.names():
        assert name in MapOptions.model_fields["memory"].description


def test_every_bad_option_of_a_request_is_named_at_once():
    with pytest.raises(InvalidConfiguration) as info:
        new(tm={"cellsPerColumn": 0}, slsbh={"s": 2}, localiser={"beam": 0})
    assert {e["name"] for e in info.value.errors} == {"tm.cellsPerColumn", "slsbh.s", "localiser.beam"}
    with pytest.raises(InvalidConfiguration) as info:
        new(preset="no-such-preset")
    assert info.value.errors[0]["name"] == "preset"

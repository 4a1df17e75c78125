"""A map's configuration: one typed model, the only home of a map's options, their defaults and their
checks (docs/design/service.md §1.1).

`MapOptions` is what a client chooses (the create request is it plus a `map_id`); `resolve` merges the
request's overrides over the preset and freezes the result as a `MapConfig`, every value checked before
anything is converted or allocated. A `MapConfig` is what is stored (the catalog row, `map.sqlite`'s meta,
a snapshot's manifest: `stored()`), what a stored map is read back as (`MapConfig.parse`, the same checks,
so a map created by the API, the `default` map made at startup and an imported snapshot pass one gate),
and what the map resource shows (`shown()`). It is frozen except `revisit_threshold` and
`verify_revisit`, which `PATCH` changes (`with_changes`: every check again). A field's default is also
what a map made before the option existed runs with (`backbone: alexnet`, `memory: tm`, `projection:
dense`, ...).
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Literal

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    PrivateAttr,
    TypeAdapter,
    ValidationError,
    field_validator,
    model_validator,
)

from models import geometry, presets
from models.frontend import backbones, images, slsbh
from models.localisation import LocaliserOptions, SequenceLocaliser, default_conf
from models.memory import registry as memories
from models.memory.temporal_memory import validate
from models.pipeline import MapModel
from service.maps.errors import InvalidConfiguration

__all__ = ["DEFAULT_RESIZE", "DEFAULT_REVISIT_THRESHOLD", "SHOWN_PARAMS", "MapConfig", "MapOptions",
           "Sections", "map_model", "resolve"]

#: A new map's `revisit_threshold` (docs/design/service.md §1.2): the confidence at which an answer is
#: called a revisit. docs/results.md §10.1: chosen on the Nordland `tune` half only, per route (two laps
#: across seasons, the same lap twice with pixel noise, a short lap, a stop, an excursion; learning
#: streams and the localise mode; places never stored, one half of `tune` learned and the other driven)
#: for the default map at map seeds 1 (the evaluations') and 42 (a new map's): the lowest confidence
#: with no false revisit in lap 1 or on never-stored places and precision >= 0.99 on every route is
#: 0.905 (`seasons`' lap 2 at seed 42), rounded up; re-chosen whenever the localiser's confidences
#: change (last: §10.9, 0.92 -> 0.91). Changeable per map with PATCH; a map keeps its own.
DEFAULT_REVISIT_THRESHOLD = 0.91

#: A new map's `resize` (crop | squash: how a frame of any shape becomes the backbone's 224 x 224 input,
#: docs/design/science.md §6). docs/results.md §9.6: through the service's path on Nordland, on 2:1
#: frames and on 4:3 frames cut from the same footage, squash gave more right places and more revisits
#: than crop on both shapes, in every seed. Maps made before the option keep `crop` (the field's default).
DEFAULT_RESIZE = "squash"

#: The options the map resource shows under `params` (the others are its top-level fields).
SHOWN_PARAMS = ("tm", "slsbh", "seed", "memory", "projection", "localiser", "resize", "keyframes")

#: Options a map once had and no longer has: a stored value is ignored (`exclude_recent`: the own-trail
#: rule of docs/design/science.md §11.6 replaced it).
RETIRED = ("exclude_recent",)


def _body(name: str, message: str) -> dict[str, str]:
    return {"location": "body", "name": name, "message": message}


class _OptionsError(ValueError):
    """The checks between options failed: `errors` in the shape of InvalidConfiguration's."""

    def __init__(self, errors: list[dict[str, str]]) -> None:
        super().__init__("; ".join(e["message"] for e in errors))
        self.errors = errors


def _invalid(e: ValidationError) -> InvalidConfiguration:
    """A failed validation as the one domain error, each offending option named."""
    errors: list[dict[str, str]] = []
    for err in e.errors(include_url=False):
        cause = (err.get("ctx") or {}).get("error")
        if isinstance(cause, _OptionsError):
            errors.extend(cause.errors)
        else:
            errors.append(_body(".".join(str(p) for p in err["loc"]), f"{err['msg']} (got "
                                f"{repr(err.get('input'))[:40]})"))
    return _problem(errors)


def _problem(errors: list[dict[str, str]]) -> InvalidConfiguration:
    return InvalidConfiguration("; ".join(f"{x['name']}: {x['message']}" for x in errors), errors)


def _section_errors(e: presets.ParamsError) -> list[dict[str, str]]:
    return [_body(f"{e.section}.{name}", message) for name, message in e.errors]


#: Each section's typed form (`models.presets`, `models.localisation`): names, defaults; its `of`
#: checks types and ranges.
_SECTIONS: dict[str, Any] = {"tm": presets.TmOptions, "slsbh": presets.SlsbhOptions,
                             "localiser": LocaliserOptions}


@dataclass(frozen=True, slots=True)
class Sections:
    """A map's option sections, typed: what the map's models read (never the stored dicts). Made once,
    where a configuration is checked (`MapConfig`: a new map, a map opened from its store, a snapshot's
    manifest); a stored map's missing options take the sections' defaults."""

    tm: presets.TmOptions
    slsbh: presets.SlsbhOptions
    localiser: LocaliserOptions
    keyframes: geometry.KeyframeOptions | None


def _salvaged(section: Any, values: Any) -> Any:
    """A section of stored values this version rejects: as far as they are valid, else the defaults
    (None for absent keyframes)."""
    if values is None and section is geometry.KeyframeOptions:
        return None
    try:
        return section.of(values)
    except (ValueError, TypeError):  # ParamsError and pydantic's ValidationError are ValueErrors
        return section()


def _check_sections(**sections: dict[str, Any]) -> tuple[list[dict[str, str]], dict[str, Any]]:
    """Every offending option of the given sections; the valid sections, typed (their defaults filled
    in)."""
    errors: list[dict[str, str]] = []
    valid: dict[str, Any] = {}
    for section, values in sections.items():
        try:
            valid[section] = _SECTIONS[section].of(values)
        except presets.ParamsError as e:
            errors.extend(_section_errors(e))
    return errors, valid


class MapOptions(BaseModel):
    """What a client chooses for a new map; every field optional. `tm`, `slsbh` and `localiser` are
    overrides merged over the preset, checked option by option by `resolve`."""

    # strict: `"seed": true` is not a seed nor `"thumbnails": "yes"` a choice, as inside the sections
    model_config = ConfigDict(extra="forbid", strict=True)
    preset: str | None = Field(default=None, description="a preset (`cortexloc presets`; default: the "
                               "service's CORTEXLOC_DEFAULT_PRESET)")
    seed: int | None = Field(default=None, description="the TM's seed (and the projection's); >= 0")
    tm: dict[str, Any] | None = Field(default=None, description="Temporal Memory overrides, NuPIC names")
    slsbh: dict[str, Any] | None = Field(default=None, description="sLSBH overrides: k, s, seed, adapt_tau")
    backbone: str | None = Field(default=None, description=f"{' | '.join(backbones.names())} (default: "
                                 "the service's, resolved at startup); frozen with the map")
    memory: str = Field(default="tm", description=f"{' | '.join(memories.names())} (`none`: the sLSBH "
                        "code is the winner-cell SDR, the Temporal Memory left out)")
    revisit_threshold: float | None = Field(default=None, description="confidence at which "
                                            "`place.revisit` is true, in [0, 1]; changeable with PATCH")
    localiser: dict[str, Any] | None = Field(default=None, description="sequence localiser options "
                                             "(docs/design/science.md §11.3)")
    thumbnails: bool = Field(default=False, description="keep a small JPEG of each learned frame")
    resize: str | None = Field(default=None, description=f"{' | '.join(images.MODES)}: how a frame becomes "
                               "the backbone's square input (crop: the middle, as the paper; squash: the "
                               f"whole frame; default: {DEFAULT_RESIZE}); frozen with the map")
    keyframes: dict[str, Any] | None = Field(default=None, description="keep each learned frame's local "
                                             "features for verifying revisits: {\"features\": orb | sift | "
                                             "akaze, \"max\": N} (docs/design/science.md §12); frozen")
    verify_revisit: bool = Field(default=False, description="`place.revisit` needs a verified keyframe "
                                 "(needs keyframes); changeable with PATCH")

    def digest(self) -> str:
        """SHA-256 of the options as asked (the members sent, as sent): a creation's retry sends the same
        body, so it has the same digest whatever defaults apply by then (docs/design/service.md §1.1)."""
        asked = json.dumps(self.model_dump(mode="json", exclude_unset=True), sort_keys=True,
                           separators=(",", ":"))
        return hashlib.sha256(asked.encode()).hexdigest()


class MapConfig(BaseModel):
    """A map's resolved configuration, frozen with the map except `revisit_threshold`."""

    model_config = ConfigDict(extra="forbid", validate_assignment=True)
    preset: str | None = Field(default=None, frozen=True)
    tm: dict[str, Any] = Field(frozen=True, description="Temporal Memory parameters, NuPIC names")
    slsbh: dict[str, Any] = Field(frozen=True, description="sLSBH: k, s, seed, adapt_tau")
    seed: int = Field(frozen=True)
    backbone: str = Field(default=backbones.PAPER, frozen=True)
    memory: str = Field(default="tm", frozen=True)
    revisit_threshold: float = Field(default=DEFAULT_REVISIT_THRESHOLD, ge=0.0, le=1.0)
    localiser: dict[str, Any] = Field(default_factory=dict, frozen=True,
                                      description="localiser options over its defaults")
    projection: Literal["dense", "sparse"] = Field(
        default="dense", frozen=True,
        description="dense | sparse (the very sparse projection, where dense would break the map's size "
                    "budget)")
    projection_sha256: str = Field(default="", frozen=True)
    encoder_id: str = Field(default="", frozen=True)
    thumbnails: bool = Field(default=False, frozen=True)
    warnings: list[str] = Field(default_factory=list, frozen=True)
    resize: str = Field(default="crop", frozen=True,
                        description="crop | squash: how the map's frames become the backbone's square "
                                    "input (crop: the middle of a wide frame; squash: all of it, distorted)")
    keyframes: dict[str, Any] | None = Field(
        default=None, frozen=True,
        description="{features, max}: the local features kept per learned frame (docs/design/science.md "
                    "§12.1); null: none kept")
    verify_revisit: bool = Field(default=False, description="a revisit needs a verified keyframe "
                                 "(docs/design/science.md §12.2); changeable with PATCH")
    made_by: str = Field(default="", frozen=True,
                         description="a keyed creation's Idempotency-Key and options as asked, each by its "
                                     "SHA-256 (`<key>:<options>`), so that its retry is told from another "
                                     "client's creation (docs/design/service.md §1.1); empty: made "
                                     "without a key")
    _sections: Sections = PrivateAttr()

    @property
    def sections(self) -> Sections:
        """The option sections, typed (set by the checks; a `salvage`d configuration's: what was valid of
        each section, else its defaults)."""
        return self._sections

    def streams_bytes(self, max_streams: int) -> int:
        """What `max_streams` streams hold in this map: each one's localiser state and condition
        (`SequenceLocaliser.stream_bytes` over the TM's columns, the code's width)."""
        width = int(self.sections.tm.columnDimensions)
        return int(max_streams) * SequenceLocaliser(self.sections.localiser).stream_bytes(width)

    @field_validator("keyframes")
    @classmethod
    def _keyframes(cls, value: dict[str, Any] | None) -> dict[str, Any] | None:
        """`models.geometry.KeyframeParams`: names, types, ranges, an extractor this OpenCV build has;
        stored with its defaults filled in."""
        if value is None:
            return None
        try:
            return geometry.KeyframeParams.model_validate(value).model_dump()
        except ValidationError as e:
            raise _OptionsError([_body("keyframes." + ".".join(map(str, err["loc"])), err["msg"])
                                 for err in e.errors(include_url=False)]) from None

    @field_validator("revisit_threshold")
    @classmethod
    def _no_negative_zero(cls, value: float) -> float:
        """-0.0 is stored as 0.0: it passes the range check, and a reader that prints or divides by it
        sees a sign it never meant."""
        return value + 0.0

    @model_validator(mode="before")
    @classmethod
    def _drop_retired(cls, values: Any) -> Any:
        return {k: v for k, v in values.items() if k not in RETIRED} if isinstance(values, dict) else values

    @model_validator(mode="after")
    def _check(self) -> MapConfig:
        """Each section by its model (`models.presets.TmParams`, `SlsbhParams`,
        `models.localisation.LocaliserParams`: names, types, ranges), then the rules between options."""
        errors, valid = _check_sections(tm=self.tm, slsbh=self.slsbh, localiser=self.localiser)
        if not errors:
            try:
                validate(valid["tm"])  # NuPIC's rules between TM parameters (its warnings are `resolve`'s)
            except presets.ParamsError as e:
                errors.extend(_section_errors(e))
        if errors:
            raise _OptionsError(errors)
        k, columns = valid["slsbh"].k, valid["tm"].columnDimensions
        try:
            slsbh.n_ones(k, valid["slsbh"].s)
        except ValueError as e:
            errors.append(_body("slsbh.s", str(e)))
        if k * 2 != columns:
            errors.append(_body("slsbh.k", f"2k must equal columnDimensions ({columns})"))
        if self.backbone not in backbones.names():
            errors.append(_body("backbone", f"unknown backbone {self.backbone!r}; known: "
                                f"{', '.join(backbones.names())}"))
        if self.memory not in memories.names():
            errors.append(_body("memory", f"memory must be one of {', '.join(memories.names())}"))
        if self.resize not in images.MODES:
            errors.append(_body("resize", f"resize must be one of {', '.join(images.MODES)}"))
        if self.verify_revisit and self.keyframes is None:  # it could never be met: no revisit at all
            errors.append(_body("verify_revisit", "verify_revisit needs keyframes: create the map with "
                                "the keyframes option"))
        if errors:
            raise _OptionsError(errors)
        kf = None if self.keyframes is None else geometry.KeyframeOptions.of(self.keyframes)
        self._sections = Sections(valid["tm"], valid["slsbh"], valid["localiser"], kf)
        return self

    @classmethod
    def parse(cls, values: Mapping[str, Any]) -> MapConfig:
        """A configuration from stored or resolved values. Raises InvalidConfiguration naming each
        offending option."""
        try:
            return cls.model_validate(dict(values))
        except ValidationError as e:
            raise _invalid(e) from None

    @classmethod
    def salvage(cls, stored: Any) -> MapConfig:
        """What can be shown of stored values this version rejects (a map that cannot be opened): each
        field that is valid alone as it is, else its default (empty sections, seed 0). Unchecked."""
        values = stored if isinstance(stored, dict) else {}
        kept: dict[str, Any] = {}
        for name, field in cls.model_fields.items():
            if name in values:
                try:
                    kept[name] = TypeAdapter(field.annotation).validate_python(values[name])
                    continue
                except ValidationError:
                    pass
            kept[name] = ({"tm": {}, "slsbh": {}, "seed": 0}[name] if field.is_required()
                          else field.get_default(call_default_factory=True))
        config = cls.model_construct(**kept)
        config._sections = Sections(*(_salvaged(_SECTIONS[name], kept[name]) for name in ("tm", "slsbh",
                                                                                         "localiser")),
                                    _salvaged(geometry.KeyframeOptions, kept["keyframes"]))
        return config

    def with_revisit_threshold(self, value: float) -> MapConfig:
        """A copy with another `revisit_threshold`. Raises InvalidConfiguration outside [0, 1]."""
        return self.with_changes(revisit_threshold=value)

    def with_changes(self, **changes: Any) -> MapConfig:
        """A copy with the options PATCH changes (`revisit_threshold`, `verify_revisit`), all checked
        before any is applied. Raises InvalidConfiguration (a threshold outside [0, 1], verify_revisit
        on a map without keyframes)."""
        try:
            return MapConfig.model_validate({**self.model_dump(), **changes})
        except ValidationError as e:
            raise _invalid(e) from None

    def stored(self) -> dict[str, Any]:
        """The values as stored (catalog row, map.sqlite meta, manifest): JSON types."""
        return self.model_dump(mode="json")

    def shown(self) -> dict[str, Any]:
        """The map resource's `params` (SHOWN_PARAMS); the localiser's options merged over its defaults."""
        out = {name: getattr(self, name) for name in SHOWN_PARAMS}
        out["localiser"] = {**default_conf, **self.localiser}
        return out


def resolve(options: MapOptions, *, default_preset: str, default_backbone: str) -> MapConfig:
    """A new map's configuration: the preset (the request's, else `default_preset`) <- the request's
    overrides, checked before anything is converted or allocated. `projection`, `projection_sha256` and
    `encoder_id` are left for the registry to fill in.

    Raises:
        InvalidConfiguration: `errors` names each offending option (`tm.<name>`, `slsbh.<name>`,
            `localiser.<name>`, `backbone`, `memory`, `revisit_threshold`), or the unknown preset.
    """
    preset = options.preset or default_preset
    seed = {} if options.seed is None else {"seed": options.seed}
    s_conf: dict[str, Any] = {}
    try:
        s_conf = {**presets.slsbh_params(preset), **(options.slsbh or {})}
        tm = presets.tm_params(preset, {**(options.tm or {}), **seed})
        tm_options = presets.TmOptions.of(tm)
        warnings = validate(tm_options)
    except presets.ParamsError as e:  # reported with the other sections' errors, all at once
        others, _ = _check_sections(slsbh=s_conf, localiser=dict(options.localiser or {}))
        raise _problem(_section_errors(e) + others) from None
    except (KeyError, ValueError) as e:  # no such preset, or one without a TM
        msg = str(e).strip("'\"")
        raise InvalidConfiguration(msg, [_body("preset", msg)]) from e
    # the projection's seed: the TM's where neither the request nor the preset gives one (the preset's
    # section always names it, `presets.slsbh_params`)
    s_conf = {name: tm_options.seed if name == "seed" and value is None else value
              for name, value in s_conf.items()}
    values: dict[str, Any] = {
        "preset": preset, "tm": tm, "slsbh": s_conf, "seed": tm_options.seed,
        "backbone": options.backbone or default_backbone, "memory": options.memory,
        "localiser": dict(options.localiser or {}), "thumbnails": options.thumbnails, "warnings": warnings,
        "resize": DEFAULT_RESIZE if options.resize is None else options.resize,
        "keyframes": options.keyframes, "verify_revisit": options.verify_revisit}
    if options.revisit_threshold is not None:
        values["revisit_threshold"] = options.revisit_threshold
    return MapConfig.parse(values)


def map_model(config: MapConfig, *, max_observations: int) -> MapModel:
    """A fresh pipeline model (models.pipeline) of a map with this configuration."""
    sections = config.sections
    return MapModel.new(sections.tm, sections.localiser, max_observations=max_observations,
                        memory=config.memory, s=float(sections.slsbh.s), adapt_tau=sections.slsbh.adapt_tau)

"""A map's parameters, resolved once and frozen (docs/design/service.md §1.1).

One validation path: the preset, then the request's overrides merged over it, each section checked by
its pydantic model (`models.presets.TmParams`, `models.presets.SlsbhParams`,
`models.localisation.LocaliserParams`: names, types, ranges), then the rules between sections.
`CreateMap` (service/schemas.py) only shapes the request; every value is
judged here, so a map created by the API and one created at startup (`default`) pass the same checks.
"""

from __future__ import annotations

from typing import Any

from pydantic import ValidationError

from models import geometry, presets
from models.frontend import backbones, images, slsbh
from models.localisation import LocaliserParams
from models.memory.temporal_memory import validate
from models.pipeline import MapModel
from service.maps.errors import InvalidConfiguration

__all__ = ["DEFAULT_RESIZE", "DEFAULT_REVISIT_THRESHOLD", "MEMORY_KINDS", "check_keyframes",
           "check_revisit_threshold", "check_verify_revisit", "map_model", "map_option", "resolve_params"]

#: A new map's `revisit_threshold` (docs/design/service.md §1.2): the confidence at which an answer is
#: called a revisit. docs/results.md §10: chosen on the Nordland `tune` half only, per route (two laps
#: across seasons, the same lap twice with pixel noise, a short lap, a stop, an excursion; learning
#: streams and the localise mode, with and without the Temporal Memory): the lowest confidence with no
#: false revisit in lap 1 and precision >= 0.99 on every route is 0.915 (the map without the memory on
#: the stop, excursion and two-season routes; 0.86 with it), rounded up; changeable per map with PATCH.
DEFAULT_REVISIT_THRESHOLD = 0.92

#: A new map's `resize` (crop | squash: how a frame of any shape becomes the backbone's 224 x 224 input,
#: docs/design/science.md §6). docs/results.md §9.6: through the service's path on Nordland, on 2:1
#: frames and on 4:3 frames cut from the same footage, squash gave more right places and more revisits
#: than crop on both shapes, in every seed. Maps made before the option keep `crop` (_LEGACY).
DEFAULT_RESIZE = "squash"

#: `memory`: `tm` (the Temporal Memory's winner cells) or `none` (the sLSBH code itself: the ablation).
MEMORY_KINDS = ("tm", "none")

# What maps made before an option existed run with (their params lack the key).
_LEGACY = {"backbone": "alexnet", "memory": "tm", "revisit_threshold": DEFAULT_REVISIT_THRESHOLD,
           "localiser": {}, "projection": "dense", "resize": "crop", "keyframes": None,
           "verify_revisit": False}


def map_option(params: dict[str, Any], name: str) -> Any:
    """A map's option, or what a map made before it existed runs with (`alexnet`, `tm`, ...)."""
    return params.get(name, _LEGACY[name])


def map_model(params: dict[str, Any], *, max_observations: int) -> MapModel:
    """A fresh pipeline model (models.pipeline) of a map with these frozen parameters."""
    return MapModel.new(params["tm"], map_option(params, "localiser"), max_observations=max_observations,
                        memory=map_option(params, "memory"), s=float(params["slsbh"]["s"]),
                        adapt_tau=int(params["slsbh"].get("adapt_tau", 0)))  # maps made before it: none


def check_revisit_threshold(value: float) -> float:
    """The threshold as stored: raises InvalidConfiguration unless 0 <= value <= 1; -0.0 is stored as 0.0
    (it passes the range check, and a reader that prints or divides by it sees a sign it never meant)."""
    if not 0.0 <= float(value) <= 1.0:
        msg = f"revisit_threshold must be in [0, 1], got {value}"
        raise InvalidConfiguration(msg, [_body("revisit_threshold", msg)])
    return float(value) + 0.0  # -0.0 + 0.0 == +0.0


def check_keyframes(value: dict[str, Any] | None) -> dict[str, Any] | None:
    """The `keyframes` option as stored ({"features", "max"}, docs/design/science.md §12.1), None = off;
    raises InvalidConfiguration naming `keyframes.<field>` for a bad value or an extractor this OpenCV
    build lacks (`models.geometry.KeyframeParams`)."""
    if value is None:
        return None
    try:
        kf = geometry.KeyframeParams.model_validate(value)
    except ValidationError as e:
        errors = [_body("keyframes." + ".".join(map(str, err["loc"])), err["msg"]) for err in e.errors()]
        raise InvalidConfiguration("; ".join(f"{x['name']}: {x['message']}" for x in errors), errors) from e
    return kf.model_dump()


def check_verify_revisit(value: bool, keyframes: dict[str, Any] | None) -> bool:
    """`verify_revisit` as stored: true (a revisit needs a verified keyframe) only on a map that keeps
    keyframes, else InvalidConfiguration (it could never be met: no revisit at all)."""
    if value and keyframes is None:
        msg = "verify_revisit needs keyframes: create the map with the keyframes option"
        raise InvalidConfiguration(msg, [_body("verify_revisit", msg)])
    return bool(value)


def _body(name: str, message: str) -> dict[str, str]:
    return {"location": "body", "name": name, "message": message}


def resolve_params(preset: str, *, seed: int | None = None, tm: dict[str, Any] | None = None,
                   slsbh_conf: dict[str, Any] | None = None,
                   backbone: str = "alexnet", memory: str = "tm",
                   revisit_threshold: float = DEFAULT_REVISIT_THRESHOLD,
                   localiser: dict[str, Any] | None = None, resize: str = DEFAULT_RESIZE,
                   keyframes: dict[str, Any] | None = None, verify_revisit: bool = False) -> dict[str, Any]:
    """Freeze a map's parameters: preset <- overrides, every value checked before anything is
    converted or allocated.

    Args:
        preset: a preset name with a `tm` section.
        seed: overrides `tm.seed` (and so the projection's seed unless `slsbh.seed` is given).
        tm, slsbh_conf: the request's overrides, as sent.
        backbone: a registered backbone (`models.frontend.backbones`), frozen into the map.
        memory: `tm` | `none` (MEMORY_KINDS). revisit_threshold: in [0, 1] (changeable later).
        localiser: options over `models.localisation.default_conf` (docs/design/science.md §11.3).
        resize: crop | squash (`models.frontend.images.MODES`), frozen into the map.
        keyframes: {"features": orb | sift | akaze, "max": N} (`check_keyframes`), frozen; None = off.
        verify_revisit: a revisit needs a verified keyframe (changeable later; needs keyframes).

    Returns:
        {"preset", "tm", "slsbh", "seed", "backbone", "memory", "revisit_threshold",
        "localiser", "resize", "keyframes", "verify_revisit", "warnings"}.

    Raises:
        InvalidConfiguration: `errors` names each offending parameter (`tm.<name>`, `slsbh.<name>`,
            `localiser.<name>`, `backbone`, `memory`, `resize`), or the unknown preset.
    """
    keyframes = check_keyframes(keyframes)
    verify_revisit = check_verify_revisit(verify_revisit, keyframes)
    errors: list[dict[str, str]] = []

    def collect(e: presets.ParamsError) -> None:
        errors.extend(_body(f"{e.section}.{name}", message) for name, message in e.errors)

    warnings: list[str] = []
    tm_params: dict[str, Any] = {}
    try:
        tm_params = presets.tm_params(preset, {**(tm or {}), **({} if seed is None else {"seed": seed})})
        warnings = validate(tm_params)
    except presets.ParamsError as e:
        collect(e)
    except (KeyError, ValueError) as e:  # no such preset, or one without a TM
        msg = str(e).strip("'\"")
        raise InvalidConfiguration(msg, [_body("preset", msg)]) from e
    s_conf = {**presets.slsbh_params(preset), **(slsbh_conf or {})}
    for model, section, values in ((presets.SlsbhParams, "slsbh", s_conf),
                                   (LocaliserParams, "localiser", localiser or {})):
        try:
            presets.check_section(model, section, values)
        except presets.ParamsError as e:
            collect(e)
    if errors:
        raise InvalidConfiguration("; ".join(f"{e['name']}: {e['message']}" for e in errors), errors)
    if s_conf["seed"] is None:
        s_conf["seed"] = tm_params["seed"]
    try:
        slsbh.n_ones(s_conf["k"], s_conf["s"])
    except ValueError as e:
        errors.append(_body("slsbh.s", str(e)))
    if s_conf["k"] * 2 != tm_params["columnDimensions"]:
        errors.append(_body("slsbh.k", f"2k must equal columnDimensions ({tm_params['columnDimensions']})"))
    if backbone not in backbones.names():
        known = ", ".join(backbones.names())
        errors.append(_body("backbone", f"unknown backbone {backbone!r}; known: {known}"))
    if memory not in MEMORY_KINDS:
        errors.append(_body("memory", f"memory must be one of {', '.join(MEMORY_KINDS)}"))
    if resize not in images.MODES:
        errors.append(_body("resize", f"resize must be one of {', '.join(images.MODES)}"))
    if errors:
        raise InvalidConfiguration("; ".join(e["message"] for e in errors), errors)
    return {"preset": preset, "tm": tm_params, "slsbh": s_conf, "seed": tm_params["seed"],
            "backbone": backbone, "memory": memory,
            "revisit_threshold": check_revisit_threshold(revisit_threshold),
            "localiser": dict(localiser or {}), "resize": resize, "keyframes": keyframes,
            "verify_revisit": verify_revisit, "warnings": warnings}

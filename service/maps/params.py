"""A map's parameters, resolved once and frozen (docs/design/service.md §1.1).

One validation path: the preset, then the request's overrides merged over it, each section checked by
its pydantic model (`models.presets.TmParams`, `models.presets.SlsbhParams`: names, types, ranges), then
the rules between sections. `CreateMap` (service/schemas.py) only shapes the request; every value is
judged here, so a map created by the API and one created at startup (`default`) pass the same checks.
"""

from __future__ import annotations

from typing import Any

from models import presets
from models.frontend import slsbh
from models.memory.temporal_memory import validate
from service.maps.errors import InvalidConfiguration

__all__ = ["resolve_params"]


def _body(name: str, message: str) -> dict[str, str]:
    return {"location": "body", "name": name, "message": message}


def resolve_params(preset: str, *, seed: int | None = None, tm: dict[str, Any] | None = None,
                   slsbh_conf: dict[str, Any] | None = None, exclude_recent: int = 0) -> dict[str, Any]:
    """Freeze a map's parameters: preset <- overrides, every value checked before anything is
    converted or allocated.

    Args:
        preset: a preset name with a `tm` section.
        seed: overrides `tm.seed` (and so the projection's seed unless `slsbh.seed` is given).
        tm, slsbh_conf: the request's overrides, as sent.
        exclude_recent: frozen into the map.

    Returns:
        {"preset", "tm", "slsbh", "seed", "exclude_recent", "warnings"}.

    Raises:
        InvalidConfiguration: `errors` names each offending parameter (`tm.<name>`, `slsbh.<name>`),
            or the unknown preset.
    """
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
    try:
        presets.check_section(presets.SlsbhParams, "slsbh", s_conf)
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
    if errors:
        raise InvalidConfiguration("; ".join(e["message"] for e in errors), errors)
    return {"preset": preset, "tm": tm_params, "slsbh": s_conf, "seed": tm_params["seed"],
            "exclude_recent": int(exclude_recent), "warnings": warnings}

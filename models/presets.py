"""Named presets as data (docs/design/science.md §3.7, §4) and the merge of a caller's overrides.

A preset is a plain dict: a one-line description plus one section per pipeline stage it configures
(`tm`, `mcn`, later `slsbh`/`encoder`). Callers never subclass anything: they pick a name and
optionally override individual parameters.
"""

from __future__ import annotations

import copy
import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, TypeVar

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError

_COUNT = 65535  # synapse and segment counts are stored as uint16
_SEED = 2**63 - 1
M = TypeVar("M", bound=BaseModel)


@dataclass(frozen=True, slots=True)
class TmOptions:
    """A map's Temporal Memory section, typed: each parameter's NuPIC 1.0.5 / htm.core name and
    constructor default (docs/design/science.md §3.1), the one home of both. Build one from untrusted
    values with `of` (checked by `TmParams`); the constructor checks nothing."""

    columnDimensions: int = 2048
    cellsPerColumn: int = 32
    activationThreshold: int = 13
    initialPermanence: float = 0.21
    connectedPermanence: float = 0.50
    minThreshold: int = 10
    maxNewSynapseCount: int = 20
    permanenceIncrement: float = 0.10
    permanenceDecrement: float = 0.10
    predictedSegmentDecrement: float = 0.0
    maxSegmentsPerCell: int = 255
    maxSynapsesPerSegment: int = 255
    seed: int = 42

    @classmethod
    def of(cls, values: Mapping[str, Any] | None = None) -> TmOptions:
        """The section of `values` (a map's `tm` dict, NumPy scalars taken as Python numbers): each
        checked by `TmParams`, the missing ones NuPIC's defaults. Raises ParamsError naming each bad
        parameter."""
        plain = {k: (v.item() if isinstance(v, np.generic) else v) for k, v in (values or {}).items()}
        check_section(TmParams, "tm", plain)
        return cls(**plain)  # as given (an int stays an int: a memory's state stores them as JSON)

    def values(self) -> dict[str, Any]:
        """Every parameter by its NuPIC name (what a map and a memory's state store, as JSON)."""
        return dataclasses.asdict(self)


_TM = TmOptions()


class TmParams(BaseModel):
    """The check of the Temporal Memory section: each parameter's type (JSON numbers only: strict, no
    strings or booleans) and range; names and defaults are `TmOptions`'. Rules between parameters are
    `models.memory.temporal_memory.validate`'s."""

    model_config = ConfigDict(extra="forbid", strict=True, frozen=True)

    columnDimensions: int = Field(_TM.columnDimensions, ge=1, le=2**24)
    cellsPerColumn: int = Field(_TM.cellsPerColumn, ge=1, le=2**16)
    activationThreshold: int = Field(_TM.activationThreshold, ge=1, le=_COUNT)
    initialPermanence: float = Field(_TM.initialPermanence, ge=0.0, le=1.0)
    connectedPermanence: float = Field(_TM.connectedPermanence, ge=0.0, le=1.0)
    minThreshold: int = Field(_TM.minThreshold, ge=1, le=_COUNT)
    maxNewSynapseCount: int = Field(_TM.maxNewSynapseCount, ge=1, le=_COUNT)
    permanenceIncrement: float = Field(_TM.permanenceIncrement, ge=0.0, le=1.0)
    permanenceDecrement: float = Field(_TM.permanenceDecrement, ge=0.0, le=1.0)
    predictedSegmentDecrement: float = Field(_TM.predictedSegmentDecrement, ge=0.0, le=1.0)
    maxSegmentsPerCell: int = Field(_TM.maxSegmentsPerCell, ge=1, le=_COUNT)
    maxSynapsesPerSegment: int = Field(_TM.maxSynapsesPerSegment, ge=1, le=_COUNT)
    seed: int = Field(_TM.seed, ge=0, le=_SEED)


@dataclass(frozen=True, slots=True)
class SlsbhOptions:
    """A map's sLSBH section, typed (docs/design/science.md §7), the one home of its defaults. Build one
    from untrusted values with `of` (checked by `SlsbhParams`)."""

    #: the projected dimension (2k must equal the TM's columnDimensions)
    k: int = 1024
    #: the sparsity: the fraction of the k projections kept on each side
    s: float = 0.25
    #: the projection's seed (None: the TM's)
    seed: int | None = None
    #: the stream adaptation time constant in frames (0: off, models.frontend.adaptation); maps made
    #: before it: none
    adapt_tau: int = 0

    @classmethod
    def of(cls, values: Mapping[str, Any] | None = None) -> SlsbhOptions:
        """The section of `values` (a map's `slsbh` dict): each checked by `SlsbhParams`, the missing
        ones the defaults. Raises ParamsError naming each bad parameter."""
        check_section(SlsbhParams, "slsbh", dict(values or {}))
        return cls(**(values or {}))

    def values(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


_SLSBH = SlsbhOptions()


class SlsbhParams(BaseModel):
    """The check of the sLSBH section (`SlsbhOptions`: names, defaults, meanings): types and ranges."""

    model_config = ConfigDict(extra="forbid", strict=True, frozen=True)

    k: int = Field(_SLSBH.k, ge=1, le=2**16)
    s: float = Field(_SLSBH.s, gt=0.0, le=0.5)
    seed: int | None = Field(_SLSBH.seed, ge=0, le=_SEED)
    adapt_tau: int = Field(_SLSBH.adapt_tau, ge=0, le=100_000)


class ParamsError(ValueError):
    """Invalid parameters of one preset section.

    Attributes:
        section: "tm" or "slsbh".
        errors: (parameter, message) pairs.
    """

    def __init__(self, section: str, errors: list[tuple[str, str]]) -> None:
        self.section = section
        self.errors = errors
        super().__init__("; ".join(f"{section}.{name}: {message}" for name, message in errors))


def check_section(model: type[M], section: str, values: dict[str, Any]) -> M:
    """Check a section's values against its model (names, types, ranges): the validated model.

    Raises:
        ParamsError: every offending parameter, with what was given.
    """
    try:
        return model.model_validate(values)
    except ValidationError as e:
        errors = []
        for err in e.errors(include_url=False):
            name = ".".join(str(p) for p in err["loc"]) or section
            if err["type"] == "extra_forbidden":
                errors.append((name, f"unknown parameter; known: {', '.join(model.model_fields)}"))
            else:
                errors.append((name, f"{err['msg']} (got {repr(err.get('input'))[:40]})"))
        raise ParamsError(section, errors) from None


#: NuPIC 1.0.5 / htm.core constructor defaults, with their parameter names (docs/design/science.md §3.1).
TM_DEFAULTS: dict[str, Any] = _TM.values()

# MCN (docs/design/science.md §4). `nInConPerCol=None` means "round(mean ones per input)", derived from the
# data; `minColumnActivity` is a fraction of nInConPerCol, rounded; `strict` selects `>` instead of `>=`.
MCN_DEFAULTS: dict[str, Any] = {
    "nCellPerCol": 32,
    "nInConPerCol": None,
    "minColumnActivity": 0.25,
    "strict": False,
    "nColsPerPattern": 10,
    "kActiveColumn": None,
    "kMin": 1,
    "creation": "replace",
    "probAdditionalCon": 0.05,
    "max_columns": 100_000,
    "seed": 42,
}

# The predicting 2048x4 Temporal Memory chosen on the grid world (docs/results.md §3).
_PREDICTING_TM: dict[str, Any] = {
    "cellsPerColumn": 4,
    "activationThreshold": 8,
    "initialPermanence": 0.55,
    "minThreshold": 2,
    "maxNewSynapseCount": 28,
    "permanenceIncrement": 0.1,
    "permanenceDecrement": 0.02,
    "predictedSegmentDecrement": 0.0005,
    "maxSegmentsPerCell": 16,
    "maxSynapsesPerSegment": 32,
}

confs: dict[str, dict[str, Any]] = {
    "cba2020-grid": {
        "description": "TM 2048x4 of the paper's grid world (run00.py); never predicts (13 > 3 synapses)",
        "tm": {
            "cellsPerColumn": 4,
            "activationThreshold": 13,
            "initialPermanence": 0.21,
            "minThreshold": 1,
            "maxNewSynapseCount": 3,
            "permanenceIncrement": 0.1,
            "permanenceDecrement": 0.1,
            "predictedSegmentDecrement": 0.0005,
            "maxSegmentsPerCell": 3,
            "maxSynapsesPerSegment": 3,
        },
    },
    "cba2020-nordland": {
        "description": "TM 2048x32 of the paper's Nordland run (run03.py, neoslam); one-shot, 3.7 GiB",
        "tm": {
            "cellsPerColumn": 32,
            "activationThreshold": 4,
            "initialPermanence": 0.55,
            "minThreshold": 1,
            "maxNewSynapseCount": 20,
            "permanenceIncrement": 0.01,
            "permanenceDecrement": 0.01,
            "predictedSegmentDecrement": 0.0005,
            "maxSegmentsPerCell": 100,
            "maxSynapsesPerSegment": 100,
        },
        "slsbh": {"k": 1024, "s": 0.25},
    },
    "numenta-defaults": {
        "description": "NuPIC/htm.core constructor defaults (reference; needs 24 GiB as preallocated)",
        "tm": {},
    },
    "cortexloc-grid": {
        "description": "TM 2048x4 that really predicts (one-shot, threshold 8); chosen by the grid sweep",
        # Chosen by `cortexloc eval grid-sweep` and the follow-up in docs/results.md: the best
        # worst-case clean AUC over the published (a=5, n=0.5) file and generated worlds with and
        # without noise. maxNewSynapseCount near the ~40 winners per step matters: with 20, noiseless
        # loops keep re-learning a new high-order code for the same place (clean AUC 0.88 at n=0).
        "tm": _PREDICTING_TM,
    },
    "cortexloc-default": {
        "description": "service default: one-shot TM 2048x4 (threshold 24), 308-of-2048 sLSBH codes, 62 MiB",
        # Chosen with `cortexloc eval nordland-sweep` on the Nordland `tune` split
        # (docs/results.md §7), then with a sequence filter that let short paths win. With only full
        # paths competing, the winner cells add nothing measurable over the sLSBH codes across seasons
        # (§7.4), so the context argument for minThreshold 2 is gone (§7.7); it stays the default
        # until a configuration earns its place. activationThreshold 24 (of 28 one-shot synapses)
        # keeps chance predictions low on ImageNet features. Known cost: at this density only about a
        # quarter of an exactly repeated sequence is predicted, not the > 90 % of docs/design/science.md §3.7,
        # because chance-matching segments are re-used. Stream adaptation stays off.
        "tm": {**_PREDICTING_TM, "activationThreshold": 24},
        "slsbh": {"k": 1024, "s": 0.15, "adapt_tau": 0},
    },
    "mcn-grid": {
        "description": "MCN of the paper's grid world (run00.py miniColumn.py), predictions carried",
        "mcn": {},
    },
    "mcn-nordland": {
        "description": "MCN of the paper's Nordland run (run03.py), predictions carried",
        "mcn": {
            "nInConPerCol": 200,
            "minColumnActivity": 0.75,
            "strict": True,
            "nColsPerPattern": 50,
            "kActiveColumn": 100,
            "kMin": None,
            "creation": "top_up",
        },
    },
}


def names() -> list[str]:
    """All preset names, in definition order."""
    return list(confs)


def describe(name: str) -> str:
    return get(name)["description"]


def get(name: str) -> dict[str, Any]:
    """The preset `name` (a deep copy). Raises KeyError with the known names."""
    if name not in confs:
        raise KeyError(f"unknown preset {name!r}; known: {', '.join(confs)}")
    return copy.deepcopy(confs[name])


def _merge(defaults: dict[str, Any], section: dict[str, Any], overrides: dict[str, Any] | None) -> dict:
    out = dict(defaults)
    for source in (section, overrides or {}):
        unknown = set(source) - set(defaults)
        if unknown:
            raise ValueError(f"unknown parameter(s) {sorted(unknown)}; known: {sorted(defaults)}")
        out.update(source)
    return out


def tm_params(name: str, overrides: dict[str, Any] | None = None) -> dict[str, Any]:
    """Full Temporal Memory parameters: NuPIC defaults <- preset `name` <- `overrides`.

    Raises:
        KeyError: unknown preset. ValueError: the preset has no `tm` section.
        ParamsError (a ValueError): an unknown parameter, a value of the wrong type or out of range.
    """
    preset = get(name)
    if "tm" not in preset:
        raise ValueError(f"preset {name!r} has no Temporal Memory section")
    params = {**TM_DEFAULTS, **preset["tm"], **(overrides or {})}
    check_section(TmParams, "tm", params)
    return params


def tm_options(name: str, overrides: dict[str, Any] | None = None) -> TmOptions:
    """`tm_params`, typed: what a `TemporalMemory` takes."""
    return TmOptions.of(tm_params(name, overrides))


def slsbh_params(name: str) -> dict[str, Any]:
    """The sLSBH section of preset `name` with every default filled in (`SlsbhParams`, the one home of
    the sLSBH defaults): {"k", "s", "seed", "adapt_tau"}. Raises KeyError for an unknown preset."""
    return {**_SLSBH.values(), **get(name).get("slsbh", {})}


def mcn_params(name: str = "mcn-grid", overrides: dict[str, Any] | None = None) -> dict[str, Any]:
    """Full MCN parameters: defaults <- preset `name` <- `overrides`."""
    preset = get(name)
    if "mcn" not in preset:
        raise ValueError(f"preset {name!r} has no MCN section")
    return _merge(MCN_DEFAULTS, preset["mcn"], overrides)

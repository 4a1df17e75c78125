"""The localiser's options, typed (docs/design/science.md §11.3): `LocaliserOptions`, the frozen section
the localiser, the links and the pipeline read, the one home of each option's name, default and reason;
`LocaliserParams`, the check of a map's stored or requested values (types, ranges), its defaults taken
from `LocaliserOptions`. `LocaliserOptions.of` is the one conversion of a `localiser` dict (a map's
stored JSON, a request's overrides, an evaluation's) into the section: missing names take the defaults,
as a map made before an option existed does.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Annotated, Any

from pydantic import BaseModel, BeforeValidator, ConfigDict, Field

from models.presets import check_section

__all__ = ["LAG_OFF", "LocaliserOptions", "LocaliserParams", "default_conf"]

#: `lag_max` at this bound turns the rule that a revisit's path keeps pace with its stream off (§11.13):
#: the lag, and a path back along the stream's own trail (`localiser.mirrors`).
LAG_OFF = 1_000_000


@dataclass(frozen=True, slots=True)
class LocaliserOptions:
    """A map's localiser options (docs/design/science.md §11.3), with their defaults and why.

    Build one from untrusted values with `of` (checked by `LocaliserParams`); the constructor checks
    nothing."""

    #: candidates per frame that carry evidence and seed hypotheses
    top_k: int = 100
    #: hypotheses kept per stream (the state's fixed size)
    beam: int = 256
    #: cost of advancing 0, 1, 2, ... stored rows in one frame (up to 15 rows a frame)
    move_costs: tuple[float, ...] = (3.0, 0.0, 3.0)
    #: also hypothesise the route driven against its stored direction
    backward: bool = True
    #: weight of the past per frame: memory of 1 / (1 - decay)
    decay: float = 0.95
    #: a new hypothesis's cost below the best state's score
    jump_cost: float = 20.0
    #: frames before the first answer
    warmup: int = 5
    #: rows (links, both ways) around the best no rival may end in
    exclusion: int = 10
    #: score gap per unit of log-odds in the confidence
    temperature: float = 4.0
    #: the null's evidence: this quantile of the candidates'
    null_quantile: float = 0.5
    #: a stream has left its own stored row once a frame's code is less like it than this far from the
    #: map's background likeness to the identical code (0: background, 1: identical; §11.6)
    departure: float = 0.5
    #: a learning stream's confident revisit stores no new row when its code is at least this like the
    #: place's most similar appearance, on the same scale as `departure` (1: never, every frame a row; §11.8)
    consolidate: float = 0.25
    #: a warm-up row its stream's confident path explains (§11.8) that the old row does not represent (under
    #: `consolidate`) but is at least this like, on the same scale, is joined to its place and kept as a
    #: new appearance of it (another season's, a noisier camera's), not left a place of its own; at or
    #: above `consolidate`: never (every such row stays a place of its own)
    join_kept: float = 0.1
    #: an unconfident frame is consolidated into the place its path names only with some sequence
    #: evidence: a confidence of at least this fraction of the map's `revisit_threshold`, on the path
    #: that called its stream's last revisit (a revisit is entered at the threshold and held on its
    #: path at this fraction of it), advancing, off the trail it lays (§11.8). Half the threshold: a pass's
    #: unconfident frames then join the place they pass instead of becoming parallel places, while a
    #: frame the filter barely prefers stays a row of its own (0: any unconfident frame on that path
    #: may be consolidated; 1: only one that is nearly a revisit)
    unsure_fraction: float = 0.5
    #: rows a place keeps; beyond, the least recently used goes
    appearances: int = 8
    #: at the cap on rows held (§11.9) at least this percentage of the cap is forgotten at a time: the cap
    #: binding then costs one forgetting (a durable drop and a compaction's share) per this share of the
    #: cap learned, not one per learned row (0: one row at a time)
    forget_percent: int = 1
    #: a stream's condition (§11.10): the index weighs each query bit by max(0, 1 - discount * how often
    #: it was on in the stream's recent frames), over a time constant of `condition_frames` (0: plain Dice)
    condition_frames: int = 100
    condition_discount: float = 2.0
    #: a stream's short-term memory (§11.6): the rows it made over its last `short_term` moves are never
    #: loop candidates, states of its paths or rows its frames are consolidated into (0: no memory; the
    #: consolidation rules of §11.6 still hold, so 0 is not the code before issue 35)
    short_term: int = 20
    #: the span (§11.11): the places whose best path scores within `span_margin` temperatures of the best
    #: path's score (a path at least e^-margin as likely as the best); a revisit needs at most `span_max`
    #: of them
    span_margin: float = 1.5
    span_max: int = 3
    #: a revisit needs a path that keeps pace with its stream (§11.13): one that fell more than `lag_max` of
    #: the stream's moves behind (it stayed on its rows while the stream moved on, by its poses or its
    #: look) is a row like a whole stretch, not a place come back to (`LAG_OFF` turns the rule off)
    lag_max: int = 3
    #: with poses (`metadata.pose`, §11.6) the memory is the rows made over the last `short_term_metres`
    #: of path (the sum of the moves' lengths; 0: poses play no part, moves by appearance), a move a pose
    #: at least `move_metres` from the last move's, and a step faster than `max_speed` (m/s, from the
    #: stamps) a reset: no distance
    short_term_metres: float = 20.0
    move_metres: float = 1.0
    max_speed: float = 50.0
    #: a posed frame within `stand_metres` of the pose of the frame its stream's localiser last stepped
    #: (none after a flat or unposed frame), no move (`move_metres`) and not unlike that frame's view,
    #: repeats it: no new evidence, the answer is read again off the unchanged state (§11.2 step 2).
    #: RTAB-Map's `RGBD/LinearUpdate`; above a standing robot's pose noise (cm),
    #: under a robot's step at walking speed and 10 frames a second (0.14 m). 0: every frame is evidence
    stand_metres: float = 0.1
    #: odometry's word (§11.12): within one drive of a stream (posed, stamped frames, no gap longer than
    #: `odometry_gap` s, no reset), a row whose pose lies farther from the frame's than `odometry_drift` x
    #: the path driven since plus `odometry_slack` m is no loop candidate (a drift of 10 disables it):
    #: odometry drifts 1-5 % of the distance, 20 % leaves a loop's closure wide room; 5 m is how far apart
    #: two views of one place may be taken; 60 s without a frame is a node stopped or a robot powered off,
    #: whose odometry may start again from zero
    odometry_drift: float = 0.2
    odometry_slack: float = 5.0
    odometry_gap: float = 60.0
    #: a stream's pace (§11.2 step 2): the rows a frame its paths walk for free, learned from its
    #: confident answers' paths, each path's steps averaged at this rate a frame (0: one row a frame)
    pace_rate: float = 0.1

    @classmethod
    def of(cls, values: Mapping[str, Any] | None = None) -> LocaliserOptions:
        """The section of `values` (a map's `localiser` dict): each checked by `LocaliserParams`, the
        missing ones the defaults. Raises presets.ParamsError (a ValueError) naming every bad option."""
        return cls(**check_section(LocaliserParams, "localiser", dict(values or {})).model_dump())

    def values(self) -> dict[str, Any]:
        """Every option by name (the map resource shows them so)."""
        return dataclasses.asdict(self)


def _tuple(v: Any) -> Any:
    return tuple(v) if isinstance(v, list) else v  # JSON (a map's stored params) has lists, not tuples


_D = LocaliserOptions()


class LocaliserParams(BaseModel):
    """The check of the localiser's options: types and ranges (docs/design/science.md §11.3); names,
    defaults and meanings are `LocaliserOptions`'. Strict: ints where ints, finite floats, a bool
    `backward`.

    The upper bounds keep one stream's state and step small whatever a client asks for: the state is
    `beam` hypotheses of HYPOTHESIS_BYTES each (4,096 of them: 228 KiB a stream); a step costs
    O(top_k + beam * len(move_costs)) plus an O(exclusion) walk over the links, and for a learning
    stream, where a path reaches the trail it laid, `exclusion` + 1 code reads plus one per distinct
    row so reached (at most beam * len(move_costs); §11.6). `span_margin` goes up to 100 temperatures
    (beyond, every path in the beam is in the span anyway: no evidence keeps a score that far above
    the background); `span_max` up to `beam`'s bound (a span holds at most `beam` rows; at that bound
    the gate never closes).
    """

    model_config = ConfigDict(extra="forbid", strict=True, frozen=True, allow_inf_nan=False)

    top_k: int = Field(_D.top_k, ge=1, le=1000)
    beam: int = Field(_D.beam, ge=1, le=4096)
    move_costs: Annotated[tuple[Annotated[float, Field(ge=0.0, le=1e6)], ...],
                          BeforeValidator(_tuple)] = Field(_D.move_costs, min_length=1, max_length=16)
    backward: bool = _D.backward
    decay: float = Field(_D.decay, ge=0.0, lt=1.0)
    jump_cost: float = Field(_D.jump_cost, ge=0.0, le=1e6)
    warmup: int = Field(_D.warmup, ge=1, le=1000)
    exclusion: int = Field(_D.exclusion, ge=0, le=1000)
    temperature: float = Field(_D.temperature, gt=0.0, le=1e6)
    null_quantile: float = Field(_D.null_quantile, ge=0.0, le=1.0)
    departure: float = Field(_D.departure, ge=0.0, le=1.0)
    consolidate: float = Field(_D.consolidate, ge=0.0, le=1.0)
    join_kept: float = Field(_D.join_kept, ge=0.0, le=1.0)
    unsure_fraction: float = Field(_D.unsure_fraction, ge=0.0, le=1.0)
    appearances: int = Field(_D.appearances, ge=1, le=1024)
    forget_percent: int = Field(_D.forget_percent, ge=0, le=100)
    condition_frames: int = Field(_D.condition_frames, ge=0, le=100_000)
    condition_discount: float = Field(_D.condition_discount, ge=0.0, le=100.0)
    short_term: int = Field(_D.short_term, ge=0, le=1000)
    span_margin: float = Field(_D.span_margin, ge=0.0, le=100.0)
    span_max: int = Field(_D.span_max, ge=1, le=4096)
    lag_max: int = Field(_D.lag_max, ge=0, le=LAG_OFF)
    short_term_metres: float = Field(_D.short_term_metres, ge=0.0, le=1e5)
    move_metres: float = Field(_D.move_metres, gt=0.0, le=1e4)
    max_speed: float = Field(_D.max_speed, gt=0.0, le=1e4)
    stand_metres: float = Field(_D.stand_metres, ge=0.0, le=1e4)
    odometry_drift: float = Field(_D.odometry_drift, ge=0.0, le=10.0)
    odometry_slack: float = Field(_D.odometry_slack, ge=0.0, le=1e5)
    odometry_gap: float = Field(_D.odometry_gap, gt=0.0, le=1e6)
    pace_rate: float = Field(_D.pace_rate, ge=0.0, le=1.0)


#: Every option's default by name (`LocaliserOptions`; meanings and why: docs/design/science.md §11.3).
default_conf: dict[str, Any] = _D.values()


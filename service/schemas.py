"""The HTTP bodies: the one request model (`CreateMap`) and a response model for every JSON reply
(docs/design/service.md §1), so /openapi.json describes each 2xx body. Routes build them from the
dataclasses of `service.maps.results` (`from_result`)."""

from __future__ import annotations

import dataclasses
from typing import Any, Literal, Self

from pydantic import BaseModel, ConfigDict, Field, create_model, model_validator

from service.maps import results
from service.maps.config import SHOWN_PARAMS, MapConfig, MapOptions
from service.maps.ids import MAP_ID_RE
from service.maps.states import MapState

__all__ = ["BudgetModel", "CreateMap", "Health", "MapList", "MapModel", "MatchModel", "MemoryModel",
           "ObservationModel",
           "PatchMap", "Readiness", "RecentList", "RecentModel", "RestoreModel", "SequenceModel",
           "SnapshotList", "SnapshotModel", "StoredObservationList", "StoredObservationModel",
           "StreamResetModel", "Versions"]

MAP_ID_PATTERN = MAP_ID_RE.pattern  # one home: the catalog enforces it
#: A stream name: ROS-style segments joined by '/' (`robot1/cam0`), at most 8 of 64 characters.
STREAM_PATTERN = r"^[A-Za-z0-9._-]{1,64}(/[A-Za-z0-9._-]{1,64}){0,7}$"


class _Out(BaseModel):
    model_config = ConfigDict(extra="forbid")

    @classmethod
    def from_result(cls, result: Any, **more: Any) -> Self:
        """The model of a `service.maps.results` dataclass, with `more` fields the route adds."""
        return cls.model_validate({**dataclasses.asdict(result), **more})


# ------------------------------------------------------------------------------------------- maps


class CreateMap(MapOptions):
    """A new map: its id (default: `map-` and 12 hex digits) and its options
    (`service.maps.config.MapOptions`, the one home of a map's options: every value is judged where the
    configuration is resolved, a bad one is 422 invalid-configuration naming it)."""

    map_id: str | None = Field(default=None, pattern=MAP_ID_PATTERN)


class PatchMap(BaseModel):
    """The map settings that may change after creation (docs/design/service.md §1.2)."""

    model_config = ConfigDict(extra="forbid", strict=True)  # strict: "0.5" and true are not numbers
    revisit_threshold: float | None = Field(default=None, description="confidence at which an answer is a "
                                            "revisit, in [0, 1] (422 outside)")
    verify_revisit: bool | None = Field(default=None, description="a revisit needs a verified keyframe "
                                        "(422 on a map without keyframes)")

    @model_validator(mode="after")
    def _something(self) -> Self:
        if self.revisit_threshold is None and self.verify_revisit is None:
            raise ValueError("give revisit_threshold or verify_revisit")
        return self


#: The map resource's `params`: the configuration's SHOWN_PARAMS, typed and described as there.
MapParams = create_model("MapParams", __base__=_Out, **{
    name: (MapConfig.model_fields[name].annotation,
           Field(description=MapConfig.model_fields[name].description)) for name in SHOWN_PARAMS})


class MapModel(_Out):
    """A map; `recovery` says what its last rebuild from the store did (docs/design/service.md §4.4)."""

    map_id: str
    created_at: str
    state: MapState
    state_reason: str | None
    preset: str | None
    params: MapParams  # type: ignore[valid-type]
    encoder: str
    projection_sha256: str
    observations: int
    last_seq: int
    streams: list[str]
    warnings: list[str]
    recovery: dict[str, Any] | None
    snapshot_error: dict[str, Any] | None
    backbone: str
    revisit_threshold: float
    verify_revisit: bool = Field(description="a revisit needs a verified keyframe "
                                 "(docs/design/science.md §12)")
    thumbnails: bool = Field(description="a small JPEG is kept with each learned observation")
    snapshot_count: int = Field(description="snapshots of every kind")
    snapshots_bytes: int = Field(description="their bytes on disk")
    places: results.PlacesInfo | None = Field(default=None, description="places, appearances, visits and "
                                              "the forgetting rule (docs/design/science.md §11.8, §11.9); "
                                              "null while the map is not open")


class MapList(_Out):
    maps: list[MapModel]


class RestoreModel(MapModel):
    discarded_observations: int = Field(
        description="learned frames (rows and visits) the map held that the snapshot does not; the "
                    "pre-restore snapshot keeps them. Visits either visit log pruned are not counted: "
                    "then a lower bound")
    restored_observations: int = Field(
        description="learned frames (rows and visits) the snapshot holds that the map did not: a restore "
                    "to another branch (a snapshot taken before an earlier restore) brings them back")


class StreamResetModel(_Out):
    stream: str
    had_context: bool


class MemoryModel(_Out):
    """Sizes of one map (docs/design/service.md §1.4); its parts are the domain's records as they are."""

    tm: results.TmMemory
    index: results.IndexMemory
    streams: results.StreamsMemory
    projection_bytes: int
    storage: results.StorageMemory
    process_rss_bytes: int  # the whole service process's resident size


class BudgetModel(_Out):
    """The process-wide memory budget over every map and the encoders (docs/design/service.md §1.8)."""

    total_bytes: int = Field(description="CORTEXLOC_MEMORY_BUDGET_BYTES, or its default")
    source: str = Field(description="`setting`, or the share of `host` or `cgroup` memory it defaults to")
    used_bytes: int
    reserve_bytes: int = Field(description="kept free for the second memory a recovery builds beside a map's "
                                           "empty one: the largest map's memory")
    free_bytes: int = Field(description="total less used less the reserve: what a new map or learned rows "
                                        "may still take (behind the Ray ingress the shards' sum: a map "
                                        "is made on one shard, which has its own)")
    encoders_bytes: int = Field(description="the encoders' networks, counted once")
    maps: list[results.MapReservation] = Field(description="open maps' reservations, then the maps left "
                                               "closed at start (`open` false) with what they asked")
    process_rss_bytes: int


# ----------------------------------------------------------------------------------- observations


class SequenceModel(_Out):
    step: int
    active_columns: int
    predicted_columns: int
    bursting_columns: int
    winner_cells: int


class MatchModel(_Out):
    rank: int
    observation_id: str
    seq: int
    stream: str
    label: str | None
    created_at: str
    overlap: int = Field(description="winner cells shared; on a frame without context (a stream's first, "
                                     "after a reset) the frame's columns the row holds")
    score: float = Field(description="Dice of the winner-cell sets, each cell weighed by how rarely the "
                                     "stream's recent frames had it (docs/design/science.md §11.10); "
                                     "1: the same cells. On a frame without context: the share of its "
                                     "columns the row holds (§11.2 step 1)")
    metadata: dict[str, Any] | None = Field(description="as stored with that observation")


class Versions(_Out):
    api: str
    code: str
    backbone: str
    encoder: str = Field(description="the map's encoder: backbone, weights and resize mode")
    resize: str = Field(description="the map's resize mode, crop | squash (frozen with the map)")
    weights: str
    runtime: str = Field(description="the backbone's runtime: onnxruntime or torch (the same codes)")
    device: str = Field(description="where the backbone ran: cpu or cuda")
    projection: str
    map_seq: int


class ObservationModel(_Out):
    """One frame's answer (docs/design/service.md §1.2); `timings_ms` per stage, and `total`."""

    request_id: str | None
    map_id: str
    stream: str
    learned: bool
    observation_id: str | None
    seq: int | None
    sequence: SequenceModel
    matches: list[MatchModel]
    place: results.PlaceResult | None = Field(description="the stream's place on the learned routes "
                                              "(docs/design/service.md §1.2); null during its warm-up")
    timings_ms: dict[str, float]
    versions: Versions
    metadata: dict[str, Any] | None = Field(default=None, description="the frame's, as posted")
    consolidated_into: int | None = Field(default=None, description="a learned frame the map already "
                                          "represents: the stored row it was consolidated into (no new "
                                          "row: seq is null; docs/design/science.md §11.8)")
    loop_closure_id: int | None = Field(default=None, description="a revisit's entry in the map's "
                                        "loop-closure log (GET /v1/maps/{map_id}/loop_closures; a "
                                        "retraction names it in `retracts`); null: no revisit, or a "
                                        "localising revisit the log could not take (a read-only map)")


class StoredObservationModel(_Out):
    """A learned observation as stored (`GET /v1/maps/{id}/observations/{seq}`)."""

    seq: int
    observation_id: str
    stream: str
    label: str | None
    created_at: str
    image_sha256: str
    metadata: dict[str, Any] | None
    has_thumbnail: bool
    joined_to: int | None = Field(default=None, description=(
        "the row whose place this row joined (a warm-up join: the row a stream made before it knew where "
        "it was, held no more; its record stays as acknowledged); null: the row is held"))


#: A page's `epoch` (docs/design/service.md §1.2): which map this is (its creation), how many restores
#: rolled it back and how many repairs rewrote it. Seqs and log ids are not handed out twice within it, but
#: a restore takes away what came after its snapshot and brings back what was retracted since, a rewrite
#: may withdraw a closure the log no longer holds, and a map deleted and made again (or moved between
#: shards) starts afresh: a client following a page with a cursor reads it again from 0 when this changes.
EPOCH_DESCRIPTION = ("an opaque token of the map's creation, its restores and its rewrites; when it changes, "
                     "read again from 0: a restore took away what came after its snapshot and undid the "
                     "retractions made since, a repair withdrew closures the log no longer kept (it could "
                     "not retract them), or the map was made anew")


class StoredObservationList(_Out):
    """A page in seq order; `next_after_seq` continues it (None: nothing after this page)."""

    observations: list[StoredObservationModel]
    next_after_seq: int | None
    epoch: str = Field(description=EPOCH_DESCRIPTION)


class StoredRowModel(_Out):
    """A stored row's identity and the metadata stored with it."""

    seq: int
    observation_id: str
    stream: str
    label: str | None
    metadata: dict[str, Any] | None


class LoopClosureModel(_Out):
    """One logged loop closure (docs/design/science.md §11.6): a revisit a stream was told of."""

    id: int = Field(description="its place in the map's log; pages continue `after` it")
    stream: str
    seq: int | None = Field(description="the frame's stored row (null: the stream was localising, or the "
                            "frame was consolidated: `consolidated_into`)")
    observation_id: str | None
    metadata: dict[str, Any] | None = Field(description="the frame's metadata (stamp, pose)")
    place: StoredRowModel = Field(description="the stored row its `place` named")
    confidence: float
    support: int
    created_at: str
    verification: results.VerificationResult | None = Field(
        default=None, description="the place's geometric verification as the reply gave it, with the "
        "relative pose (maps with keyframes; docs/design/science.md §12); null elsewhere")
    consolidated_into: int | None = Field(default=None, description="a learning stream's consolidated "
                                          "frame (a visit, docs/design/science.md §11.8): the row it was "
                                          "consolidated into; null for a frame with its own row, a "
                                          "localising stream's, and one logged before this was recorded")
    retracts: int | None = Field(default=None, description="a retraction entry (a repair, "
                                 "docs/design/science.md §11.6): the id of the closure it withdraws (its "
                                 "pair is that closure's; confidence and support 0); null for a closure")
    span: int | None = Field(default=None, description="how many places the stream may have been at: the "
                             "places whose best path scored within the map's `span_margin` of the best "
                             "(docs/design/science.md §11.11); a back end may divide the edge's information "
                             "by it; null: logged before this was recorded")
    span_seqs: list[int] | None = Field(default=None, description="the best row of each place of the span, "
                                        "best first (at most 16); null: logged before this was recorded")


class SplitVisitModel(_Out):
    """A visit into a row of its stream's own recent trail."""

    visit: int = Field(description="its id in the map's visit log")
    stream: str
    into: int = Field(description="the row it was consolidated into")
    seq: int | None = Field(description="the row the repair re-made it as (null: listed, not repaired)")


class UnjoinModel(_Out):
    """A row that joined a place through a row of its stream's own recent trail."""

    seq: int
    stream: str
    joined: int = Field(description="the row whose place it joined; a repair gives it its own place")


class RetractionModel(_Out):
    """A logged loop closure that named a row of its stream's own recent trail."""

    closure: int = Field(description="its id in the loop-closure log")
    stream: str
    place_seq: int = Field(description="the row it named")


class RepairModel(_Out):
    """The merges made from a stream's own recent trail (docs/design/science.md §11.6): listed (`GET`) or
    undone (`POST`): each visit re-made as its own row, each row given back its own place, each closure
    retracted by a new log entry. A second repair finds nothing."""

    map_id: str
    window: int = Field(description="the moves of a stream's short-term memory the rule read (the map's "
                        "`short_term`, else the default's)")
    repaired: bool = Field(description="false: a listing; true: undone, durably")
    splits: list[SplitVisitModel]
    unjoins: list[UnjoinModel]
    retractions: list[RetractionModel]
    rows_added: int = Field(description="rows the repair added to the map (its re-made visits; a listing: "
                            "the rows it would add)")
    rewrite: bool = Field(description=(
        "true: the repair changes (a listing: would change) the loop-closure log's epoch: its cap pruned "
        "entries logged since the last repair, a closure among them may be withdrawn without a retraction, "
        "so a follower rebuilds its edges from the export"))
    visits_pruned_through: int = Field(description=(
        "the last visit id the visit log pruned (0: none): what was learned up to the oldest visit it keeps "
        "is not judged (the log no longer says how the streams moved there), so a merge there is neither "
        "listed nor undone"))


class LoopClosureList(_Out):
    """A page of the log, oldest first (docs/design/service.md §1.2 says how to follow it)."""

    loop_closures: list[LoopClosureModel]
    next_after: int | None = Field(description=(
        "the `after` of the next page: the last id of this one when it was full. Null: nothing more for "
        "now, not the log's end for ever: poll again with `after` = the last id you read (this page's "
        "last, or your own `after` when it is empty), never 0 or null"))
    oldest: int | None = Field(description=(
        "the oldest log id still kept (the log keeps the last CORTEXLOC_LOOP_CLOSURES entries; null: "
        "empty). A follower whose `after` is below `oldest` - 1 may have missed pruned entries, "
        "retractions among them: it rebuilds its edges from the export"))
    newest: int = Field(description=(
        "the newest log id handed out (0: none yet): a follower of what is logged from now on (the ROS 2 "
        "node's retraction follower) starts with `after` = newest"))
    epoch: str = Field(description=EPOCH_DESCRIPTION)


class RecentModel(_Out):
    """One answer of the recent ring: the observation reply as it was sent, and when."""

    answer_id: int = Field(description="the answer's number in the map's ring (from 1 since the service "
                           "opened the map; `.../recent/{answer_id}/thumbnail`)")
    received_at: str = Field(description="when the reply was sent (UTC, ISO 8601)")
    has_thumbnail: bool = Field(description="the query frame's small JPEG is kept with it (maps with "
                                "thumbnails; the newest answers within the ring's byte budget)")
    reply: ObservationModel


class RecentList(_Out):
    """The map's latest answers, oldest first; in memory only (docs/design/service.md §1.7)."""

    map_id: str
    capacity: int = Field(description="answers the service keeps per map")
    answers: list[RecentModel]


# -------------------------------------------------------------------------------------- snapshots


class SnapshotModel(_Out):
    snapshot_id: str
    seq: int
    kind: str
    created_at: str
    bytes: int
    manifest_sha256: str


class SnapshotList(_Out):
    snapshots: list[SnapshotModel]


# ------------------------------------------------------------------------------------- operations


class Health(_Out):
    status: Literal["ok"]


class Readiness(_Out):
    """Each check's result (`status` pass | warn | fail and its details); the warnings gathered."""

    status: Literal["ready"]
    checks: dict[str, dict[str, Any]]
    warnings: list[str]

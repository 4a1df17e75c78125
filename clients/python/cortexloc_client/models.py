"""Typed replies of the cortexloc HTTP API (the service's docs/design/service.md §1, §2), in one module so
they can be aligned with the server's schemas (`/openapi.json`) in one place.

Every model accepts fields it does not declare (`extra="allow"`, kept in `model_extra`): a newer server
may add members without breaking an older client. Fields the server may not send yet (the sequence-level
`place`, per-observation `metadata`, a map's `revisit_threshold`) are optional and default to None.
"""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field

# The service's limits on a request, for callers that check parameters before posting (the ROS node
# refuses them at start). The client is installed without the service (a robot has no service package),
# so it cannot import them: tests/clients/ros2/test_core.py checks that they equal the service's.
#: A stream's (and a trail's) name: the service's `service.schemas.STREAM_PATTERN`.
STREAM_PATTERN = r"^[A-Za-z0-9._-]{1,64}(/[A-Za-z0-9._-]{1,64}){0,7}$"
#: The most matches an answer may ask for (`top_k`) on a service with the default settings
#: (`CORTEXLOC_MAX_TOP_K`, `service.settings.Settings.max_top_k`).
MAX_TOP_K = 100
#: The largest |x| and |y| of a pose the service accepts: `service.routes.observations.POSE_MAX_ABS`.
POSE_MAX_ABS = 1e9
#: The largest |yaw| of a pose the service accepts, radians: `service.routes.observations.YAW_MAX_ABS`.
YAW_MAX_ABS = 1e6

__all__ = [
    "MAX_TOP_K",
    "POSE_MAX_ABS",
    "STREAM_PATTERN",
    "YAW_MAX_ABS",
    "Budget",
    "CheckResult",
    "Health",
    "IndexMemory",
    "LoopClosure",
    "LoopClosureList",
    "Map",
    "MapList",
    "MapParams",
    "MapReservation",
    "Match",
    "Memory",
    "Metadata",
    "Observation",
    "Place",
    "Pose",
    "Problem",
    "Readiness",
    "RestoredMap",
    "SequenceStats",
    "Snapshot",
    "SnapshotList",
    "StorageMemory",
    "StoredObservation",
    "StoredObservationList",
    "StoredRow",
    "StreamReset",
    "StreamsMemory",
    "TmMemory",
    "Verification",
    "Versions",
]


class _Reply(BaseModel):
    model_config = ConfigDict(extra="allow", frozen=True)


# ------------------------------------------------------------------------------------ operations


class Health(_Reply):
    """`GET /healthz`: the process answers."""

    status: str


class CheckResult(_Reply):
    """One readiness check: `status` is `pass`, `warn` or `fail`; its details are extra fields."""

    status: Literal["pass", "warn", "fail"]
    warning: str | None = None
    error: str | None = None


class Readiness(_Reply):
    """`GET /readyz` when ready (a 503 `not-ready` problem otherwise)."""

    status: str
    checks: dict[str, CheckResult]
    warnings: list[str] = Field(default_factory=list)


class Problem(_Reply):
    """RFC 9457 `application/problem+json`; the slug's members (`errors`, `map_id`, ...) are extra."""

    type: str
    title: str
    status: int
    detail: str
    instance: str | None = None
    request_id: str | None = None


# ------------------------------------------------------------------------------------------ maps


class MapParams(_Reply):
    """The parameters frozen into a map: TM and sLSBH sections with NuPIC names."""

    tm: dict[str, Any]
    slsbh: dict[str, Any]
    seed: int
    #: "tm", or "none" (the sLSBH code stands in for the winner cells: the memory's ablation).
    memory: str | None = None
    #: "dense" or "very-sparse": the sLSBH projection the map's size budget allowed.
    projection: str | None = None
    #: The sequence localiser's options, frozen with the map.
    localiser: dict[str, Any] | None = None
    #: How the map's frames become the backbone's square input: "crop" (the middle) or "squash" (all of
    #: it); frozen with the map (None from an older server).
    resize: str | None = None
    #: {"features", "max"}: the local features kept per learned frame (None: none kept, or an older server).
    keyframes: dict[str, Any] | None = None


class Map(_Reply):
    """A map resource (`POST /v1/maps`, `GET /v1/maps/{map_id}`, `PATCH ...`)."""

    map_id: str
    created_at: str
    state: Literal["ready", "replaying", "recovering", "read-only", "failed"]
    state_reason: str | None = None
    #: The preset the map was made from; None where the server has none on record for it.
    preset: str | None = None
    params: MapParams
    encoder: str
    projection_sha256: str
    observations: int
    last_seq: int
    streams: list[str]
    warnings: list[str] = Field(default_factory=list)
    recovery: dict[str, Any] | None = None
    snapshot_error: dict[str, Any] | None = None
    #: The backbone the map was made with (frozen): e.g. "alexnet", "efficientnet-lite0".
    backbone: str | None = None
    #: Confidence at or above which a place is called a revisit (changeable with `update_map`).
    revisit_threshold: float | None = None
    #: A revisit needs a verified keyframe (changeable with `update_map`; False from an older server).
    verify_revisit: bool = False
    #: A small JPEG is kept with each learned observation (chosen at creation, frozen).
    thumbnails: bool = False
    #: The map's snapshots (every kind) and their bytes on disk.
    snapshot_count: int = 0
    snapshots_bytes: int = 0
    #: Places, appearances, visits and their bounds (None from an older server).
    places: PlacesInfo | None = None


class PlacesInfo(_Reply):
    """A map's places and their bounds: repeated passes are consolidated into visits of known places,
    each place keeps at most `max_appearances` rows, and at `max_rows` the least recently used places
    are forgotten (`forgetting` says the rule)."""

    places: int
    appearances: int
    rows_stored: int
    dropped: int
    forgotten: int
    visits_logged: int
    max_appearances: int
    max_rows: int
    consolidate: float
    forgetting: str


class MapList(_Reply):
    maps: list[Map]


class RestoredMap(Map):
    """`POST .../snapshots/{snapshot_id}/restore`: the map as restored; the learned frames (rows and
    visits) it took away (`discarded_observations`) and brought back from another branch
    (`restored_observations`; 0 from a server before it was answered)."""

    discarded_observations: int
    restored_observations: int = 0


class StreamReset(_Reply):
    """`POST /v1/maps/{map_id}/streams/{stream}/reset`."""

    stream: str
    had_context: bool


class TmMemory(_Reply):
    columns: int
    cells_per_column: int
    cells: int
    max_segments_per_cell: int
    max_synapses_per_segment: int
    segments: int
    segment_capacity: int
    synapses: int
    synapse_capacity: int
    allocated_bytes: int
    evicted_segments_total: int
    overrun_synapses_total: int


class IndexMemory(_Reply):
    observations: int
    max_observations: int
    postings: int
    bytes: int


class StreamsMemory(_Reply):
    count: int
    max: int
    bytes: int


class StorageMemory(_Reply):
    db_bytes: int
    wal_bytes: int
    snapshots_bytes: int
    #: Rows with keyframes and the bytes of their features and cameras, within db_bytes (0: older server).
    keyframes: int = 0
    keyframe_bytes: int = 0


class Memory(_Reply):
    """`GET /v1/maps/{map_id}/memory`: exact sizes, counts and caps."""

    tm: TmMemory
    index: IndexMemory
    streams: StreamsMemory
    projection_bytes: int
    storage: StorageMemory
    process_rss_bytes: int


class MapReservation(_Reply):
    """One map's share of the process-wide memory budget (`open` false: left closed at start)."""

    map_id: str
    open: bool
    reason: str | None = None
    bytes: int
    #: tm, projection (0 where another map holds the same one), localiser, caches, index.
    parts: dict[str, int]


class Budget(_Reply):
    """`GET /v1/memory`: the process-wide memory budget over every map and the encoders."""

    total_bytes: int
    source: str
    used_bytes: int
    reserve_bytes: int = 0  # kept for a recovery's second memory (0 from a server before it was told)
    free_bytes: int  # total less used less the reserve (an older server: the reserve inside it)
    encoders_bytes: int
    maps: list[MapReservation]
    process_rss_bytes: int


# ---------------------------------------------------------------------------------- observations


class Pose(_Reply):
    """A planar pose in a named frame (metres, radians)."""

    x: float
    y: float
    yaw: float | None = None
    frame_id: str | None = None


class Metadata(_Reply):
    """Per-observation metadata: a `stamp`, a `pose`, or any other small JSON members (extra fields).

    Sent with `Client.observe(..., metadata=...)`; stored with the row and returned in matches and places.
    """

    stamp: float | str | None = None
    pose: Pose | None = None


class SequenceStats(_Reply):
    """The stream's Temporal Memory step for this frame."""

    step: int
    active_columns: int
    predicted_columns: int
    bursting_columns: int
    winner_cells: int


class Match(_Reply):
    """One earlier observation, ranked by the Dice score of shared winner cells (weighed by the stream's
    conditions: cells its recent frames share count less); on a stream's first frame (or the first after
    a reset), by the share of the frame's columns the row holds."""

    rank: int
    observation_id: str
    seq: int
    stream: str
    label: str | None = None
    created_at: str
    overlap: int
    score: float
    metadata: Metadata | None = None


class Verification(_Reply):
    """A revisit candidate's geometric check against a stored keyframe (maps with keyframes): inliers of
    the chosen model (homography | fundamental) and, with the stream's camera, the relative pose
    X_query = rotation @ X_keyframe + translation (a unit vector); `reason` says why not verified or why
    no pose."""

    verified: bool
    keyframe_seq: int | None = None
    matches: int = 0
    inliers: int = 0
    inlier_ratio: float = 0.0
    model: str | None = None
    rotation: list[list[float]] | None = None
    rotation_deg: float | None = None
    translation: list[float] | None = None
    reason: str | None = None
    ms: float = 0.0


class Place(_Reply):
    """The sequence-level answer: where the stream is, how sure, and whether it is a revisit."""

    seq: int | None = None
    observation_id: str | None = None
    stream: str | None = None
    label: str | None = None
    confidence: float
    revisit: bool
    support: int | None = None
    metadata: Metadata | None = None
    #: The geometric check of a revisit candidate (None: not checked, or an older server).
    verification: Verification | None = None
    #: The place `seq` belongs to: every pass and appearance of one place answers the same id
    #: (None from an older server).
    place_id: int | None = None
    #: The frame was too flat (near-black, blank, overexposed) to say where it is: never a revisit.
    low_information: bool = False
    #: How many places the stream may be at (the answer's own among them; a revisit needs at most the
    #: map's `span_max`), and their best rows, `seq` first (None from an older server).
    span: int | None = None
    span_seqs: list[int] | None = None
    #: The path fell more than the map's `lag_max` of the robot's moves behind it (it stayed on its rows
    #: while the robot moved on; on its route's last row, through one move): never a revisit (False
    #: from an older server).
    lagging: bool = False


class Versions(_Reply):
    api: str
    code: str
    backbone: str | None = None
    encoder: str
    #: The map's resize mode, "crop" or "squash" (None from an older server).
    resize: str | None = None
    weights: str
    runtime: str | None = None  # the service's backbone runtime and device (servers before issue 24: None)
    device: str | None = None
    projection: str
    map_seq: int


class Observation(_Reply):
    """`POST /v1/maps/{map_id}/observations`: the frame's matches and, with learning, its identity.

    `observation_id` and `seq` are None unless the frame was learned. `timings_ms` has one entry per
    stage (decode, encode, hash, tm, search, store, total).
    """

    request_id: str | None = None
    map_id: str
    stream: str
    learned: bool
    observation_id: str | None = None
    seq: int | None = None
    sequence: SequenceStats
    matches: list[Match]
    timings_ms: dict[str, float]
    versions: Versions
    place: Place | None = None
    metadata: Metadata | None = None
    #: A learned frame consolidated into this stored row (a visit of a known place): the memory learned
    #: it, no row was made, so `seq` and `observation_id` are None.
    consolidated_into: int | None = None
    #: A revisit's entry in the map's loop-closure log (`Client.loop_closures`): a later retraction names it
    #: in `retracts`. None: no revisit, a localising revisit on a read-only map, or an older server.
    loop_closure_id: int | None = None


class StoredObservation(_Reply):
    """`GET /v1/maps/{map_id}/observations/{seq}`: one learned observation as stored."""

    observation_id: str
    seq: int
    stream: str
    label: str | None = None
    created_at: str
    image_sha256: str | None = None
    metadata: Metadata | None = None
    has_thumbnail: bool | None = None
    #: the row whose place this row joined (a warm-up join: made before the stream knew where it was, held
    #: no more, its record kept as acknowledged); None: the row is held
    joined_to: int | None = None


class StoredRow(_Reply):
    """A stored row's identity and what was stored with it (a loop closure's place)."""

    seq: int
    observation_id: str
    stream: str
    label: str | None = None
    metadata: Metadata | None = None


class LoopClosure(_Reply):
    """One logged loop closure: a revisit a stream was told of (`seq` None: the stream was localising, or
    the frame was consolidated into row `consolidated_into`, a visit)."""

    id: int
    stream: str
    seq: int | None = None
    observation_id: str | None = None
    metadata: Metadata | None = None
    place: StoredRow
    confidence: float
    support: int
    created_at: str
    #: The place's geometric verification as the reply gave it (maps with keyframes; None elsewhere).
    verification: Verification | None = None
    #: A consolidated frame's (a visit's): the row it joined (None: a frame with its own row, a
    #: localising stream's, or one logged before the server recorded it).
    consolidated_into: int | None = None
    #: On a retraction entry (a repair withdrew a closure): the id of the closure it withdraws; a back end
    #: drops the edge it made for it (None: a closure).
    retracts: int | None = None
    #: The answer's span and its rows (a back end may divide the edge's information by the span; None:
    #: logged before the server recorded it).
    span: int | None = None
    span_seqs: list[int] | None = None


class SplitVisit(_Reply):
    """A visit into a row of its stream's own recent trail (`seq`: the row a repair re-made it as; None:
    listed, not repaired)."""

    visit: int
    stream: str
    into: int
    seq: int | None = None


class Unjoin(_Reply):
    """A row that joined a place through a row of its stream's own recent trail (`joined`)."""

    seq: int
    stream: str
    joined: int


class Retraction(_Reply):
    """A logged loop closure (`closure`) that named a row (`place_seq`) of its stream's own recent trail."""

    closure: int
    stream: str
    place_seq: int


class Repair(_Reply):
    """`GET`/`POST /v1/maps/{map_id}/repair`: the merges a stream made from its own recent trail, listed
    (`repaired` False) or undone (True): each visit re-made as its own row, each row given back its own
    place, each closure retracted. A second repair finds nothing."""

    map_id: str
    window: int
    repaired: bool
    splits: list[SplitVisit]
    unjoins: list[Unjoin]
    retractions: list[Retraction]
    rows_added: int
    #: The repair changes (listed: would change) the loop-closure log's epoch: its cap pruned entries
    #: logged since the last repair, which it may withdraw without a retraction, so a follower rebuilds
    #: its edges (False from a server before it).
    rewrite: bool = False
    #: The last visit id the visit log pruned (0: none): what was learned up to the oldest visit it keeps is
    #: not judged, so a merge there is neither listed nor undone.
    visits_pruned_through: int = 0


class LoopClosureList(_Reply):
    """`GET /v1/maps/{map_id}/loop-closures`: a page, oldest first. `next_after` continues it; None is
    "nothing more for now": poll again with the last id read (`cursor(after)` gives the next `after`
    either way). `oldest` is the oldest id the log still keeps (None: empty, or a server before it): a
    follower whose `after` is below `oldest - 1` may have missed entries the cap pruned, retractions
    among them (`missed(after)`), and rebuilds its edges from the export. `epoch` is an opaque token of
    the map's creation, restores and rewrites ("" from a server before it): when it changes, read the log
    again from `after=0` (a restore took away what came after its snapshot and undid the retractions made
    since, a repair withdrew closures the log no longer kept, or the map was made anew)."""

    loop_closures: list[LoopClosure]
    next_after: int | None = None
    oldest: int | None = None
    #: The newest log id handed out (0: none yet; None: a server before it): to follow only what is logged
    #: from now on, start with `after=newest`.
    newest: int | None = None
    epoch: str = ""

    def cursor(self, after: int) -> int:
        """The `after` of the next request, given this page's: `next_after`, else the last id on the
        page, else `after` again (never 0: that would read the whole log again)."""
        if self.next_after is not None:
            return self.next_after
        return self.loop_closures[-1].id if self.loop_closures else after

    def missed(self, after: int) -> bool:
        """Entries after `after` (this page's) were pruned before they were read: rebuild from the
        export (`Client.export_loop_closures`) and go on from its last id. A gap in the ids below
        `oldest` (a restore's, a repeated key's) can say so once too often, never too rarely."""
        return self.oldest is not None and after < self.oldest - 1


class StoredObservationList(_Reply):
    """`GET /v1/maps/{map_id}/observations`: a page in seq order; `next_after_seq` continues it (None:
    nothing after this page). `epoch`: as `LoopClosureList`'s."""

    observations: list[StoredObservation]
    next_after_seq: int | None = None
    epoch: str = ""


# ------------------------------------------------------------------------------------- snapshots


class Snapshot(_Reply):
    """A snapshot resource: a consistent cut of the map at `seq`."""

    snapshot_id: str
    seq: int
    kind: Literal["manual", "auto", "pre-restore"]
    created_at: str
    bytes: int
    manifest_sha256: str


class SnapshotList(_Reply):
    """Newest first."""

    snapshots: list[Snapshot]


class RecentAnswer(_Reply):
    """One answer of a map's recent ring: the observation reply as it was sent, and when."""

    #: The answer's number in the map's ring (`Client.recent_thumbnail`); None from an older server.
    answer_id: int | None = None
    received_at: str
    #: The query frame's small JPEG is kept with it (maps created with `thumbnails=True`).
    has_thumbnail: bool = False
    reply: Observation


class RecentAnswers(_Reply):
    """`GET /v1/maps/{map_id}/recent`: the map's latest answers, oldest first (in the service's memory)."""

    map_id: str
    capacity: int
    answers: list[RecentAnswer]

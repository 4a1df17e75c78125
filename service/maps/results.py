"""What the map domain answers, as plain dataclasses; the routes turn them into the response models of
`service/schemas.py` (docs/design/service.md §1)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from service.maps.config import MapConfig
from service.maps.states import serving

__all__ = ["BudgetInfo", "IndexMemory", "LoopClosurePage", "LoopClosureResult", "MapInfo", "MapReservation",
           "Match", "MemoryInfo", "ObservationResult", "PlaceResult", "RestoreResult", "SequenceStats",
           "SnapshotInfo", "StorageMemory", "StoredObservation", "StoredRow", "StreamReset", "StreamsMemory",
           "TmMemory", "VerificationResult"]


@dataclass(frozen=True)
class Match:
    """A stored observation that shares winner cells with the query (docs/design/service.md §5)."""

    rank: int
    observation_id: str
    seq: int
    stream: str
    label: str | None
    created_at: str
    overlap: int
    score: float  # Dice of the two winner-cell sets
    metadata: dict[str, Any] | None = None  # as stored with it (stamp, pose, ...)

    @classmethod
    def of(cls, rank: int, row: Any, overlap: int, score: float) -> Match:
        """The match of rank `rank` (1 = best) on the stored `row` (storage.mapstore.Observation)."""
        return cls(rank=rank, observation_id=row.observation_id, seq=row.seq, stream=row.stream,
                   label=row.label, created_at=row.created_at, overlap=int(overlap), score=float(score),
                   metadata=row.metadata)


@dataclass(frozen=True)
class SequenceStats:
    """The stream's TM step: `step` counts steps since its context was last empty."""

    step: int
    active_columns: int
    predicted_columns: int
    bursting_columns: int
    winner_cells: int

    @classmethod
    def of(cls, step: int, stats: dict[str, int]) -> SequenceStats:
        """From `StreamContext.stats.as_dict()` (models.memory.temporal_memory)."""
        return cls(step=step, **{k: int(stats[k]) for k in ("active_columns", "predicted_columns",
                                                             "bursting_columns", "winner_cells")})


@dataclass(frozen=True)
class VerificationResult:
    """`place.verification` (docs/design/science.md §12, docs/design/service.md §1.2): the query's local
    features against a stored keyframe (the place's or a route neighbour's, `keyframe_seq`).

    `model` is GRIC's choice (homography | fundamental); `rotation` (3 x 3, row-major) and `translation`
    (a unit vector) give X_query = R X_keyframe + t in camera frames when both cameras are known and the
    pose is observable; `reason` says why not verified or why no pose (`too-small`, `too-few-features`,
    `too-few-matches`, `too-few-inliers`, `degenerate`, `no-pose`, `geometry-failed`, `no-keyframe`,
    `no-features`, `no-camera`, `translation-unobservable`);
    `ms` is the time it took in the map's writer."""

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

    @classmethod
    def of(cls, v: Any, *, keyframe_seq: int, ms: float) -> VerificationResult:
        """From a `models.geometry.Verification`."""
        def rounded(a: Any) -> Any:
            return None if a is None else np.round(np.asarray(a, float), 6).tolist()

        return cls(verified=v.verified, keyframe_seq=keyframe_seq, matches=v.matches, inliers=v.inliers,
                   inlier_ratio=round(float(v.inlier_ratio), 4), model=v.model, rotation=rounded(v.rotation),
                   rotation_deg=None if v.rotation_deg is None else round(v.rotation_deg, 3),
                   translation=rounded(v.translation), reason=v.reason, ms=round(ms, 3))


@dataclass(frozen=True)
class PlaceResult:
    """The stream's sequence-level answer (docs/design/science.md §11.2, docs/design/service.md §1.2):
    the stored row it is at, `confidence` in [0, 1], `revisit` = confidence >= the map's threshold and
    the frame informative and the span at most the map's `span_max`, `support` = frames on the path behind
    the answer; `metadata` when the row has any; `low_information`: the frame was too flat (near-black,
    blank, overexposed) to say where it is, so it is no revisit whatever the confidence
    (docs/design/science.md §11.7); `span`: how many places the stream may be at (the places whose best
    path scores within the map's `span_margin` of the best), `span_seqs` their best rows, best first (at
    most 16; docs/design/science.md §11.11); `lagging`: the path has fallen more than the map's `lag_max`
    of the robot's moves behind it (it stayed on its rows while the robot moved on; at its route's last
    row, through one move), so it is no revisit whatever the confidence (docs/design/science.md
    §11.13)."""

    seq: int
    observation_id: str
    stream: str
    label: str | None
    confidence: float
    revisit: bool
    support: int
    metadata: dict[str, Any] | None = None
    # On a map with keyframes, for a revisit candidate (confidence >= threshold) only; None otherwise.
    verification: VerificationResult | None = None
    low_information: bool = False
    # The place `seq` shows: the id of the place's first row; every pass and appearance of one place
    # answers the same id (docs/design/science.md §11.8). `seq` is the row that matched best.
    place_id: int = 0
    # How many places the stream may be at, >= 1 (exact), and their best rows, `seq` first (§11.11).
    span: int = 1
    span_seqs: list[int] = field(default_factory=list)
    lagging: bool = False

    @classmethod
    def of(cls, place: Any, row: Any, revisit_threshold: float) -> PlaceResult:
        """The reply's `place`: the localiser's `Place`, its stored row, and the map's revisit decision."""
        return cls(seq=place.seq, observation_id=row.observation_id, stream=row.stream, label=row.label,
                   confidence=place.confidence, revisit=place.is_revisit(revisit_threshold),
                   support=place.support, metadata=getattr(row, "metadata", None),
                   low_information=not place.informative,
                   place_id=int(place.place) if place.place >= 0 else int(place.seq),
                   span=int(place.span), span_seqs=[int(q) for q in place.span_seqs] or [int(place.seq)],
                   lagging=not place.advancing)


@dataclass(frozen=True)
class ObservationResult:
    """One frame's outcome. `timings_ms`: decode, encode (event loop), hash, tm, search, store (writer)."""

    map_id: str
    stream: str
    learned: bool
    observation_id: str | None
    seq: int | None
    sequence: SequenceStats
    matches: list[Match]
    timings_ms: dict[str, float]
    map_seq: int
    projection_sha256: str
    backbone: str
    place: PlaceResult | None
    metadata: dict[str, Any] | None = None  # the frame's, as posted (stored with a learned row)
    encoder: str = ""  # the map's encoder identity (backbone, weights, resize mode)
    resize: str = "crop"  # the map's resize mode (crop | squash)
    # The frame's small JPEG on a map that keeps thumbnails, learned or not: for the recent ring (the
    # viewer's query thumbnail, docs/design/service.md §1.7), never part of a reply.
    thumbnail: bytes | None = None
    # A learned frame consolidated into this stored row: the memory learned it, no row was made (`seq`
    # and `observation_id` are null; docs/design/science.md §11.8).
    consolidated_into: int | None = None
    # A revisit's entry in the map's loop-closure log (a later retraction names it in `retracts`,
    # docs/design/service.md §1.2); None: no revisit, or a localising revisit the log could not take (a
    # `read-only` map).
    loop_closure_id: int | None = None


@dataclass(frozen=True)
class PlacesInfo:
    """A map's places and their bounds (docs/design/science.md §11.8, §11.9)."""

    places: int  # places with a row held
    appearances: int  # rows held (in the index and their places)
    rows_stored: int  # rows in map.sqlite (held and dropped)
    dropped: int  # rows no longer held: over a place's cap, forgotten, or joined (a warm-up, §11.8)
    forgotten: int  # of those, rows of forgotten places
    visits_logged: int  # consolidated frames in the visit log (bounded; pruned once a snapshot covers them)
    max_appearances: int  # rows a place keeps (the map's localiser option `appearances`)
    max_rows: int  # the hard cap on rows held (CORTEXLOC_MAX_OBSERVATIONS)
    consolidate: float  # the map's localiser option `consolidate`
    forgetting: str  # the rule, in words


@dataclass(frozen=True)
class MapInfo:
    """A map as the API shows it; `recovery` says what the last rebuild did (docs/design/service.md §4.4)."""

    map_id: str
    created_at: str
    state: str
    state_reason: str | None
    preset: str | None
    params: dict[str, Any]
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
    verify_revisit: bool  # a revisit needs a verified keyframe (docs/design/science.md §12.2)
    thumbnails: bool  # a small JPEG is kept with each learned row (frozen with the map)
    snapshot_count: int  # snapshots of every kind, and their bytes on disk (docs/design/service.md §1.5)
    snapshots_bytes: int
    places: PlacesInfo | None  # None: a map that is not open

    @classmethod
    def of(cls, config: MapConfig, record: Any, *, state: str, state_reason: str | None,
           observations: int = 0, last_seq: int = 0, streams: list[str] | None = None,
           recovery: dict[str, Any] | None = None, snapshot_error: dict[str, Any] | None = None,
           snapshot_count: int = 0, snapshots_bytes: int = 0, places: PlacesInfo | None = None) -> MapInfo:
        """The map resource of a map with this configuration and catalog `record` (created_at, map_id);
        `snapshot_count`, `snapshots_bytes`: `service.maps.recovery.snapshots.disk_use`. A map that serves
        no reads (`failed`, `recovering`) says in `warnings` that its counts are not read, not lost."""
        warnings = list(config.warnings)
        if not serving(state).reads:
            warnings.append(NOT_READ)
        return cls(map_id=record.map_id, created_at=record.created_at, state=state, state_reason=state_reason,
                   preset=config.preset, params=config.shown(), encoder=config.encoder_id,
                   projection_sha256=config.projection_sha256, observations=observations, last_seq=last_seq,
                   streams=streams or [], warnings=warnings, recovery=recovery,
                   snapshot_error=snapshot_error, backbone=config.backbone,
                   revisit_threshold=config.revisit_threshold, verify_revisit=config.verify_revisit,
                   thumbnails=config.thumbnails,
                   snapshot_count=snapshot_count, snapshots_bytes=snapshots_bytes, places=places)


#: The warning of a map that serves no reads (`MapInfo.of`): its `observations`, `last_seq` and `streams`
#: say 0 and none because the map is not open, whatever its store holds.
NOT_READ = ("the map is not open: its observations, last_seq and streams are not read (0 and none here), "
            "whatever its store holds")


@dataclass(frozen=True)
class RestoreResult(MapInfo):
    """The map as restored, and what the restore changed of its learned frames (rows and visits;
    `service.maps.recovery.snapshots.learned_difference`)."""

    discarded_observations: int  # those the map held that the snapshot does not (in the pre-restore one)
    restored_observations: int  # those the snapshot holds that the map did not (a restore to another branch)


@dataclass(frozen=True)
class StoredObservation:
    """A learned observation as stored, without its codes (docs/design/service.md §1.2)."""

    seq: int
    observation_id: str
    stream: str
    label: str | None
    created_at: str
    image_sha256: str
    metadata: dict[str, Any] | None
    has_thumbnail: bool
    joined_to: int | None = None


@dataclass(frozen=True)
class LoopClosureResult:
    """One logged loop closure (docs/design/science.md §11.6): the frame (its row when it was learned)
    and the stored row its place named, as `place` answered."""

    id: int
    stream: str
    seq: int | None
    observation_id: str | None
    metadata: dict[str, Any] | None
    place: StoredRow
    confidence: float
    support: int
    created_at: str
    verification: VerificationResult | None = None  # the place's, as the reply gave it (maps with keyframes)
    consolidated_into: int | None = None  # a visit's (a consolidated frame): the row it joined
    retracts: int | None = None  # a retraction entry's: the closure it withdraws (§11.6)
    span: int | None = None  # the answer's span and its rows (§11.11); None: logged before schema 11
    span_seqs: list[int] | None = None


@dataclass(frozen=True)
class LoopClosurePage:
    """A page of the log and the oldest id it still keeps (None: empty), read after the page: a prune
    between the two reads can only make a follower resync once too often, never miss a gap."""

    entries: list[LoopClosureResult]
    oldest: int | None
    newest: int  # the newest id handed out (0: none yet): a follower of what comes next starts after it


@dataclass(frozen=True)
class StoredRow:
    """A stored row's identity and what the client stored with it."""

    seq: int
    observation_id: str
    stream: str
    label: str | None
    metadata: dict[str, Any] | None


@dataclass(frozen=True)
class SnapshotInfo:
    snapshot_id: str
    seq: int
    kind: str
    created_at: str
    bytes: int
    manifest_sha256: str


@dataclass(frozen=True)
class SplitVisit:
    """A visit into a row of its stream's own recent trail (docs/design/science.md §11.6): `visit` its id
    in the visit log, `into` the row it was consolidated into, `seq` the row a repair re-made it as
    (None: listed, not repaired)."""

    visit: int
    stream: str
    into: int
    seq: int | None = None


@dataclass(frozen=True)
class Unjoin:
    """A row that joined a place through a row of its stream's own recent trail: `joined` the row whose
    place it joined; a repair gives it back its own place."""

    seq: int
    stream: str
    joined: int


@dataclass(frozen=True)
class Retraction:
    """A logged loop closure that named a row of its stream's own recent trail (or was logged with a visit
    into one): `closure` its log id, `place_seq` the row it named; a repair logs an entry retracting it."""

    closure: int
    stream: str
    place_seq: int


@dataclass(frozen=True)
class RepairResult:
    """What a repair found, and whether it undid it (docs/design/science.md §11.6).

    Attributes:
        window: the moves of the stream's memory the rule read (the map's `short_term`, else the
            default's). repaired: False for a listing. splits, unjoins, retractions: as listed or undone.
        rows_added: rows the repair added (the re-made visits; listed: would add).
        rewrite: the repair changes (listed: would change) the loop-closure log's epoch: its cap pruned
            entries logged since the last repair, which it may withdraw without a retraction
            (docs/design/service.md §1.2).
        visits_pruned_through: the last visit id the visit log pruned (0: none): what was learned up to
            the oldest visit kept is not judged (`service.maps.repair`).
    """

    map_id: str
    window: int
    repaired: bool
    splits: list[SplitVisit]
    unjoins: list[Unjoin]
    retractions: list[Retraction]
    rows_added: int = 0
    rewrite: bool = False
    visits_pruned_through: int = 0


@dataclass(frozen=True)
class StreamReset:
    stream: str
    had_context: bool


@dataclass(frozen=True)
class TmMemory:
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


@dataclass(frozen=True)
class IndexMemory:
    observations: int
    max_observations: int
    postings: int
    bytes: int


@dataclass(frozen=True)
class StreamsMemory:
    count: int
    max: int
    bytes: int


@dataclass(frozen=True)
class StorageMemory:
    db_bytes: int
    wal_bytes: int
    snapshots_bytes: int
    keyframes: int = 0  # rows with a keyframe, and their features' and cameras' bytes (within db_bytes)
    keyframe_bytes: int = 0


@dataclass(frozen=True)
class MemoryInfo:
    """Sizes of one map in memory and on disk (docs/design/service.md §1.4)."""

    tm: TmMemory
    index: IndexMemory
    streams: StreamsMemory
    projection_bytes: int
    storage: StorageMemory
    process_rss_bytes: int


@dataclass(frozen=True)
class MapReservation:
    """What one map holds (or, closed, would hold) of the memory budget (docs/design/service.md §1.8)."""

    map_id: str
    open: bool
    reason: str | None  # why a map stays closed (`memory-budget`)
    bytes: int  # held, or asked by a closed map
    parts: dict[str, int]  # tm, projection (0 when another map holds the same one), localiser, caches, index


@dataclass(frozen=True)
class BudgetInfo:
    """The process-wide memory budget: `GET /v1/memory` (docs/design/service.md §1.8)."""

    total_bytes: int
    source: str  # `setting`, or the share of `host` or `cgroup` memory it defaults to
    used_bytes: int
    reserve_bytes: int  # kept free for a recovery's second memory (the largest map's)
    free_bytes: int  # total less used less the reserve: what a new map or row may take
    encoders_bytes: int
    maps: list[MapReservation]
    process_rss_bytes: int

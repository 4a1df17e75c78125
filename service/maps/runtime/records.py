"""What one step of the writer makes, built from the pure step and the rows it names: the learned row,
the reply, the loop closure and the visit (docs/design/service.md §1.2, §4.2–§4.3).

Pure: nothing here reads or writes the store, the memory or the clock; the writer
(`service.maps.runtime.writer`) verifies the place, seals the idempotent reply and persists what these
return.
"""

from __future__ import annotations

import dataclasses
from typing import Any

from models import geometry
from models.pipeline import Step
from service.maps import keyframes
from service.maps.config import MapConfig
from service.maps.results import Match, ObservationResult, PlaceResult, SequenceStats
from storage.mapstore import KeyRecord, NewClosure, NewObservation, NewVisit, Observation

__all__ = ["learned_row", "loop_closure", "reply", "visit"]


def learned_row(step: Step, *, stream: str, image_sha256: str, label: str | None,
                metadata: dict[str, Any] | None, thumbnail: bytes | None,
                query: keyframes.QueryFrame | None, resume: bytes | None) -> NewObservation:
    """The row a learned frame that was not consolidated stores: its code, winner cells and the row it
    continues, what it came with (label, metadata, thumbnail, keyframe), its place, the rows the step
    dropped, touched and joined, its stream's resume state and whether its frame was flat (service.md
    §4.2)."""
    kf = None if query is None else (geometry.pack(query.features), query.camera)
    return NewObservation(stream=stream, image_sha256=image_sha256, input_sdr=step.code,
                          winner_cells=step.winners, context_prev_seq=step.prev_seq, label=label,
                          metadata=metadata, thumbnail=thumbnail, keyframe=kf,
                          place=step.joined if step.joined >= 0 else None,
                          drops=step.dropped, touched=step.touched, joins=step.joins, kept=step.kept,
                          resume=resume, flat=step.flat)


def reply(config: MapConfig, map_id: str, step: Step, rows: dict[int, Observation], *, stream: str,
          learn: bool, seq: int | None, row: NewObservation | None, place: PlaceResult | None,
          metadata: dict[str, Any] | None, map_seq: int) -> ObservationResult:
    """The answer as the client gets it (before its store timings): the ranked matches on their stored
    `rows`, the `place` as verified, and what the map and its encoder are."""
    return ObservationResult(
        map_id=map_id, stream=stream, learned=learn, observation_id=row and row.observation_id,
        seq=seq, sequence=SequenceStats.of(step.step, step.stats),
        matches=[Match.of(i + 1, rows[m.seq], m.overlap, m.score) for i, m in enumerate(step.ranked)],
        timings_ms=step.timings_ms, map_seq=map_seq,
        projection_sha256=config.projection_sha256, backbone=config.backbone, metadata=metadata,
        encoder=config.encoder_id, resize=config.resize, place=place, consolidated_into=step.visit)


def loop_closure(result: ObservationResult, *, stream: str, metadata: dict[str, Any] | None,
                 key: str | None) -> NewClosure | None:
    """A revisit is a loop closure (science.md §11.6), with the place's geometric verification where
    there is one (science.md §12); None: no revisit."""
    place = result.place
    if place is None or not place.revisit:
        return None
    verified = None if place.verification is None else dataclasses.asdict(place.verification)
    return NewClosure(stream=stream, place_seq=place.seq, confidence=place.confidence,
                      support=place.support, metadata=metadata, key=key, verification=verified,
                      span=place.span, span_seqs=tuple(place.span_seqs))


def visit(step: Step, *, stream: str, metadata: dict[str, Any] | None, closure: NewClosure | None,
          key: KeyRecord | None, resume: bytes | None) -> NewVisit:
    """A consolidated frame (science.md §11.8): the memory learned it, no row is made; the visit is what
    the replay needs of it (service.md §4.4)."""
    assert step.visit is not None
    return NewVisit(stream=stream, seq=step.visit, context_prev_seq=step.prev_seq, input_sdr=step.code,
                    winner_cells=step.winners, metadata=metadata, closure=closure, touched=step.touched,
                    key=key, resume=resume, joins=step.joins, kept=step.kept, drops=step.dropped)

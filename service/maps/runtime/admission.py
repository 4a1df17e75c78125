"""The streams of one map as its runtime admits them (docs/design/service.md §1.3): a new stream is
refused while it would evict one that posted within the stream window, and a stream's sequence is
broken on request. The streams' states themselves are `models.pipeline.Stream`s, held least recently
used first (`models.pipeline.touch` evicts the oldest); an observation's Idempotency-Key is
`service.maps.runtime.idempotency`'s.
"""

from __future__ import annotations

import math
import time
from collections import OrderedDict
from collections.abc import Callable

from models.pipeline import Stream, eviction_wait, resume_state
from service.maps.errors import InsufficientStorage, MapReadOnly, StreamLimit
from service.maps.results import StreamReset
from service.maps.states import serving
from storage.mapstore import StorageFull, StoreReadOnly

__all__ = ["Admission"]


class Admission:
    """`MapRuntime`'s streams (module docstring). It owns the streams held, the clock of their last
    posts and the count of streams evicted for new ones."""

    #: The clock of the streams' last posts (the stream window, §1.3); tests set their own.
    clock: Callable[[], float] = staticmethod(time.monotonic)

    streams: OrderedDict[str, Stream]
    stream_evictions: int

    def _admit(self, name: str) -> None:
        """Raises StreamLimit while a new stream `name` would evict one that posted within the window
        (docs/design/service.md §1.3)."""
        keep = self.settings.stream_keep_seconds
        wait = eviction_wait(self.streams, name, self.settings.max_streams, keep, self.clock())
        if wait > 0:
            raise StreamLimit(self.settings.max_streams, keep, max(1, math.ceil(wait)))

    def reset_stream(self, name: str) -> StreamReset:
        """Break the stream's sequence (the next frame starts a new one); its adaptation is kept,
        because it describes the camera and the conditions, not where the robot is. Durable before the
        reply, as an observation is, where its sequence continues a stored row: the stream's state is
        stored as the reset leaves it, so a restart, even after a kill, resumes it reset (before, it
        resumed the sequence from its last learned step). A sequence of localised frames only is not
        stored (a restart finds the stream as of its last learned step, as after any localisation), so
        its reset needs no write, and a localising robot resets on a full disk too; nor does a map whose
        storage refuses writes (`read-only`: it learns nothing).

        Raises:
            InsufficientStorage, MapReadOnly: the reset could not be stored; nothing changed.
            MapUnavailable: the map serves nothing (`failed`, `recovering`); there is no stream to reset.
        """
        self.require_ready(learns=False)
        st = self.streams.get(name)
        if self._tail is not None:  # the live state is the stream's from now on (`_replay_tail`)
            self._localised.add(name)
        had = st is not None and st.context.active_cells.size > 0
        if st is not None:
            durable = st.last_learned_seq is not None and not serving(self.state).read_only
            if durable and self.store is not None:
                try:
                    self.store.save_stream_state(name, resume_state(st, reset=True))
                except StorageFull as e:
                    raise InsufficientStorage(f"the reset could not be stored: no room to write ({e}); "
                                              "nothing changed") from e
                except StoreReadOnly as e:
                    self.read_only()
                    raise MapReadOnly(self.map_id, "the reset (nothing changed)") from e
            st.break_sequence()
        return StreamReset(stream=name, had_context=bool(had))

"""A map's memory as arrays and back: the TM, its generator, every stream's context and bookkeeping
(docs/design/service.md §1.3, §4.4). Snapshots store these arrays; recovery loads them. A learned step
also stores what a replay of its stream cannot give back (`resume_state`), so a stream resumes its place
after a crash (§4.4)."""

from __future__ import annotations

import io
import re
from collections import OrderedDict
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from models.frontend.adaptation import RunningMean
from models.localisation import LocaliserState
from models.localisation.condition import Condition
from models.localisation.short_term import Anchor, View
from models.memory.temporal_memory import StreamContext, TemporalMemory

__all__ = ["Stream", "eviction_wait", "load_memory_state", "memory_name", "memory_state", "resume",
           "resume_state", "touch"]

#: `memory_state`'s arrays of each stream, by prefix; the stream's name is hex-encoded (names may hold '.').
_PER_STREAM = ("stream", "streammeta", "streamadapt", "streamcond", "streamloc")
_STREAM_HEX = re.compile(r"(?:[0-9a-f]{2})*")
_LOCALISER_ARRAYS = frozenset(LocaliserState.empty(1).to_arrays())


@dataclass
class Stream:
    """A stream's sequence state in one map (docs/design/service.md §1.3)."""

    context: StreamContext = field(default_factory=StreamContext)
    step: int = 0  # steps since the context was last empty
    last_learned_seq: int | None = None  # the learned observation the context continues
    learning: bool | None = None  # mode of the last step (a switch to learning starts a new sequence)
    adapt: RunningMean | None = None  # the stream's running mean of projections (models.frontend.adaptation)
    localiser: LocaliserState | None = None  # where the stream is on the map (docs/design/science.md §11)
    posted_at: float = 0.0  # time.monotonic() of its last frame (0: none since this process started)
    # The last row the stream made in its current sequence (its own trail, docs/design/science.md §11.6);
    # it differs from `last_learned_seq` after a consolidated frame, which moves the stream onto a row
    # it visited (§11.8).
    own_seq: int | None = None
    # How often each code bit was on in the stream's recent frames (docs/design/science.md §11.10).
    condition: Condition | None = None
    # Its last move, learning or not (docs/design/science.md §11.2 step 2, §11.6): the localiser's steps
    # follow its moves. Not stored: after a restart its first frame is a move.
    mover: Anchor = field(default_factory=Anchor)
    # The code of its last move by its look (and its poses where it has them), learning or not
    # (docs/design/science.md §11.13): its paths keep pace with these. Not stored: after a restart its
    # first frame is the look, no move (as a stream's first frame is).
    look: np.ndarray | None = None
    # The view (code and pose) of the frame its localiser last stepped, where that frame was posed and
    # not flat, else None (docs/design/science.md §11.2 step 2; `PlaceMap.repeats`). Not stored: after a
    # restart its first frame steps.
    seen: View | None = None
    # Its last learned frame was a visit its code earned, at the consolidation level of an appearance
    # (docs/design/science.md §11.8): the stream is in the conditions of the places it passes, so a
    # confident revisit under the level is one frame's noise, not a new appearance. Stored with the
    # stream (snapshots, `resume_state`); a new sequence starts without it.
    represented: bool = False

    def new_sequence(self, context: bool = True) -> None:
        """The one rule of a sequence's start (docs/design/service.md §1.3): no step counted, no learned
        row or own row it continues; `context`: its TM context is emptied too (False: it is already
        empty, nothing to break). The localiser's search, the adaptation and the condition are kept."""
        if context:
            self.context.reset()
        self.step, self.last_learned_seq, self.own_seq = 0, None, None
        self.represented = False

    def break_sequence(self) -> None:
        """The next frame starts a new sequence (and a new search for the place); the adaptation and the
        condition are kept, because they describe the camera and the conditions, not where the robot is."""
        self.new_sequence()
        self.localiser, self.look, self.seen = None, None, None


def eviction_wait(streams: OrderedDict[str, Stream], name: str, max_streams: int, keep_seconds: float,
                  now: float) -> float:
    """Seconds before the stream `name` may be taken in (0: now): a new stream while all `max_streams`
    slots are held waits until the least recently used one has not posted for `keep_seconds`
    (docs/design/service.md §1.3). A stream with no post since the process started (`posted_at` 0)
    may go at once."""
    if name in streams or len(streams) < max_streams:
        return 0.0
    oldest = next(iter(streams.values()))  # least recently used first
    return max(0.0, oldest.posted_at + keep_seconds - now) if oldest.posted_at else 0.0


def touch(streams: OrderedDict[str, Stream], name: str, max_streams: int, now: float) -> tuple[Stream, int]:
    """(the stream `name` as the most recently used and posted at `now`, created if new; how many
    streams were evicted for it): beyond `max_streams` the least recently used context is dropped (for
    it, a reset: docs/design/service.md §1.3). `eviction_wait` says first whether it may be."""
    st = streams.get(name)
    evicted = 0
    if st is None:
        st = streams[name] = Stream()
        while len(streams) > max_streams:
            streams.popitem(last=False)
            evicted += 1
    streams.move_to_end(name)
    st.posted_at = now
    return st, evicted


def memory_state(tm: TemporalMemory, streams: Mapping[str, Stream]) -> dict[str, np.ndarray]:
    """The whole memory as arrays: TM, generator, every stream's context and bookkeeping."""
    names = {name.encode().hex(): name for name in streams}  # stream names may hold '.'
    state = tm.state_dict(streams={h: streams[n].context for h, n in names.items()})
    for h, n in names.items():
        st = streams[n]
        state[f"streammeta.{h}"] = np.array(
            [st.step, -1 if st.last_learned_seq is None else st.last_learned_seq,
             -1 if st.learning is None else int(st.learning),
             -1 if st.own_seq is None else st.own_seq, int(st.represented)], dtype=np.int64)
        if st.adapt is not None:
            state[f"streamadapt.{h}"] = st.adapt.state()
        if st.condition is not None:
            state[f"streamcond.{h}"] = st.condition.state()
        if st.localiser is not None:
            for key, value in st.localiser.to_arrays().items():
                state[f"streamloc.{h}.{key}"] = value
    return state


def memory_name(name: str) -> bool:
    """Whether `memory_state` writes an array of this name: the memory's (`TemporalMemory.state_name`),
    and for each stream `stream.<h>.<field>`, `streammeta.<h>`, `streamadapt.<h>`, `streamcond.<h>` and
    `streamloc.<h>.<key>`, `<h>` its name in hex. A snapshot's loader refuses any other name before
    reading it (docs/design/service.md §4.4)."""
    kind, _, rest = name.partition(".")
    if kind not in _PER_STREAM:
        return TemporalMemory.state_name(name)
    h, _, part = rest.partition(".")
    if not _STREAM_HEX.fullmatch(h):
        return False
    if kind == "stream":
        return TemporalMemory.state_name(name)
    if kind == "streamloc":
        return part in _LOCALISER_ARRAYS
    return rest == h


def load_memory_state(state: Mapping[str, np.ndarray], adapt_tau: int, condition_frames: int = 0
                      ) -> tuple[TemporalMemory, OrderedDict[str, Stream]]:
    """The reverse of `memory_state`: (memory, streams by name). A stream saved without its condition
    (before §11.10, or with it off) starts one afresh at its next frame."""
    tm = TemporalMemory.from_state(dict(state))
    streams: OrderedDict[str, Stream] = OrderedDict()
    for h, ctx in TemporalMemory.load_streams(dict(state)).items():
        meta = [int(v) for v in state[f"streammeta.{h}"]]
        step, last, learning = meta[:3]
        own = meta[3] if len(meta) > 3 else last  # a snapshot before places: every learned row was made
        represented = len(meta) > 4 and bool(meta[4])  # (before §11.8's noise rule: not known)
        adapt = (RunningMean.from_state(adapt_tau, state[f"streamadapt.{h}"])
                 if adapt_tau and f"streamadapt.{h}" in state else None)
        cond = (Condition.from_state(condition_frames, state[f"streamcond.{h}"])
                if condition_frames and f"streamcond.{h}" in state else None)
        prefix = f"streamloc.{h}."
        loc = {k.removeprefix(prefix): v for k, v in state.items() if k.startswith(prefix)}
        streams[bytes.fromhex(h).decode()] = Stream(
            ctx, step, None if last < 0 else last, None if learning < 0 else bool(learning), adapt,
            LocaliserState.from_arrays(loc) if loc else None, own_seq=None if own < 0 else own,
            condition=cond, represented=represented)
    return tm, streams


def resume_state(st: Stream, *, reset: bool = False) -> bytes:
    """What a replay of the stream's rows and visits cannot give back, packed (npz, no pickle): its
    localiser state (where it is on the map, docs/design/science.md §11), its adaptation mean (its
    frames' projections are not stored) and whether its last frame earned the place's conditions
    (`Stream.represented`, §11.8). The context, the step bookkeeping and the condition are
    replayed (docs/design/service.md §4.4). A few KB: beam × 57 bytes, plus k floats with adaptation.
    `reset`: the stream as `Stream.break_sequence` leaves it, marked so that `resume` breaks the
    replayed sequence too (a reset after the stream's last learned step, which no row records)."""
    arrays = {} if st.localiser is None or reset else {
        f"loc.{k}": v for k, v in st.localiser.to_arrays().items()}
    if st.adapt is not None:
        arrays["adapt"] = st.adapt.state()
    arrays["represented"] = np.array([st.represented and not reset], bool)
    if reset:
        arrays["reset"] = np.array([True], bool)
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return buf.getvalue()


def resume(st: Stream, packed: bytes, adapt_tau: int) -> None:
    """Give a replayed stream back what `resume_state` packed after its last learned step (or after a
    reset that followed it: the sequence the replay left it in is broken)."""
    with np.load(io.BytesIO(packed), allow_pickle=False) as z:
        arrays = {name: z[name] for name in z.files}
    loc = {k.removeprefix("loc."): v for k, v in arrays.items() if k.startswith("loc.")}
    st.localiser = LocaliserState.from_arrays(loc) if loc else None
    if adapt_tau and "adapt" in arrays:
        st.adapt = RunningMean.from_state(adapt_tau, arrays["adapt"])
    st.represented = "represented" in arrays and bool(arrays["represented"][0])
    if "reset" in arrays:
        st.break_sequence()


def was_reset(packed: bytes) -> bool:
    """Whether `packed` (`resume_state`) records a reset after the stream's last learned step."""
    with np.load(io.BytesIO(packed), allow_pickle=False) as z:
        return "reset" in z.files

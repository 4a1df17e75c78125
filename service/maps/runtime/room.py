"""A map's learning on a full disk (docs/design/service.md §4.3): refused before its step while the store
is known to have no room, so a full disk costs one recovery, not one per learning post.

Why: a learning step changes the memory before its commit, so a commit that finds no room leaves the
memory ahead of the store, and only a rebuild from the store (§4.4) makes them agree again. That rebuild
replays the rows after the last snapshot, and the map answers nothing meanwhile. On a full disk every
learning post would pay it, and localising robots would get 503 for most of the time. So the first
commit that finds no room marks the map `Room.full`; from then on a learning post is refused (507, the
memory untouched) before its step, until a probe write beside the map's file (`MapStore.has_room`,
at most once per `ROOM_RECHECK_SECONDS`) finds room again: the next post then learns as usual, with no
restart.

A probe cannot see every kind of no room (a file-size limit binds `map.sqlite`, not a small probe file):
where it passes and the post's commit fails anyway, that post costs one more recovery and the probe
waits twice as long before the next one (up to `ROOM_RECHECK_MAX_SECONDS`), so the recoveries stay rare.
"""

from __future__ import annotations

import logging
import time
import uuid
from collections.abc import Callable
from pathlib import Path

from service.maps.errors import InsufficientStorage
from storage.base.files import is_no_room, probe_write

__all__ = ["DATA_DIR_PROBE_BYTES", "ROOM_PROBE_BYTES", "ROOM_RECHECK_MAX_SECONDS", "ROOM_RECHECK_SECONDS",
           "Room", "probe_data_dir"]

#: How often, at most, a map with no room probes for room again (s): room made is seen within this, and
#: a probe (a small write with its fsync) is never paid per post.
ROOM_RECHECK_SECONDS = 5.0
#: The longest wait between probes, reached by doubling after each probe that passed before a commit
#: that found no room anyway (module docstring).
ROOM_RECHECK_MAX_SECONDS = 300.0
#: The probe's size: more than a learned row with its thumbnail, keyframe and WAL pages takes, so that
#: room it finds is room for the post it lets through.
ROOM_PROBE_BYTES = 1 << 20

log = logging.getLogger("cortexloc.runtime")


class Room:
    """Whether a map's store has room to learn (module docstring).

    Args:
        map_id: the map, for the log.
        probe: whether the store's disk takes a write now (`MapStore.has_room`, bound to the store in
            use when it runs: a recovery opens another).
        clock: monotonic seconds (tests set their own).

    The writer calls `admit` before a learning step, `failed` when its commit found no room and `stored`
    when one was stored; `refused` may be asked from any thread (it never probes).
    """

    def __init__(self, map_id: str, probe: Callable[[], bool],
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.map_id = map_id
        self.probe = probe
        self.clock = clock
        self.full: str | None = None  # the error of the commit that found no room; None: room
        self._next_probe = 0.0
        self._wait = ROOM_RECHECK_SECONDS
        self._trial = False  # a learning post goes ahead on a probe that found room

    def refused(self) -> InsufficientStorage | None:
        """Any thread: the refusal of a learning post now, where no room is known and no probe is due
        (an up-front answer spares the post its encoding); None: let it go on to `admit`."""
        if self.full is not None and self.clock() < self._next_probe:
            return self._refusal()
        return None

    def admit(self) -> None:
        """Writer, before a learning step (nothing has changed yet): passes where there is room, or where
        the probe now due finds some.

        Raises:
            InsufficientStorage: no room is known and none was found; nothing changed.
        """
        self._trial = False
        if self.full is None:
            return
        now = self.clock()
        if now >= self._next_probe:
            if self.probe():
                self._trial = True
                return
            self._next_probe = now + self._wait
        raise self._refusal()

    def failed(self, error: str) -> None:
        """Writer: a learning step's commit found no room (`error`: storage's words); its recovery runs
        once, and learning is refused up front from now on."""
        if self._trial:  # the probe found room the commit did not: probe less often
            self._wait = min(self._wait * 2, ROOM_RECHECK_MAX_SECONDS)
        if self.full is None:
            log.error("map %s: no room to write (%s): learning posts are refused (507) before their step "
                      "until room is made (probed every %.0f s at most); localising frames are answered",
                      self.map_id, error, self._wait)
        self.full, self._trial = error, False
        self._next_probe = self.clock() + self._wait

    def stored(self) -> None:
        """Writer: a learning step was stored: there is room."""
        if self.full is not None:
            log.info("map %s: room to write again; learning resumes", self.map_id)
        self.full, self._trial, self._wait = None, False, ROOM_RECHECK_SECONDS

    def _refusal(self) -> InsufficientStorage:
        return InsufficientStorage(f"the observation could not be stored: no room to write ({self.full}); "
                                   "nothing was learned. Learning resumes, with no restart, once room is "
                                   "made")


#: `probe_data_dir`'s write: a page, which a disk with no room refuses at the write.
DATA_DIR_PROBE_BYTES = 4096


def probe_data_dir(data_dir: Path) -> tuple[str, str]:
    """Write, fsync and delete a probe file (`.readyz-*`) in `data_dir` (/readyz, docs/design/service.md
    §1.6): ("pass", ""); ("no-room", the OS's words) where it says there is no room (the maps still
    localise); ("unwritable", its words) where the file cannot be written at all (missing, a permission,
    a read-only mount)."""
    try:
        probe_write(Path(data_dir) / f".readyz-{uuid.uuid4().hex}", DATA_DIR_PROBE_BYTES)
    except OSError as e:
        return ("no-room" if is_no_room(e) else "unwritable"), str(e.strerror or e)
    return "pass", ""

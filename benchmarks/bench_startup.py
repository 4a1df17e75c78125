"""Start-up time of a map with 10^5 observations: snapshot load, replay after it, index rebuild.

Run: `cortexloc bench startup [--observations 100000] [--quick] [--full-replay]`
(`make bench`). Writes benchmarks/results/startup.json.

Setup: a data directory with one map `default` (preset `cortexloc-default`, the real 64,896 x 1,024
projection), built through `MapRuntime.observe` exactly as the service stores observations, except that
the projected features are given (synthetic routes: 100 places, each a random k-vector, driven twice
with Gaussian noise of 0.3 of its scale, then a reset; the map hashes them into its codes) and
the build connection runs with `synchronous=OFF` (building only; the files are the same, and start-up
never writes). Two snapshots are taken during the build: `--long-tail` observations before the end and
`--short-tail` before the end. Then the map is opened as the service does at start
(`MapRegistry(...).start()`: warm-up, catalog, projection load and checksum, quick_check, newest valid
snapshot, replay of the rows after it with verification, index rebuild from all rows):

1. with both snapshots: the replay tail is `--short-tail` observations (a clean shutdown or a recent
   automatic snapshot);
2. with the newer snapshot removed: the tail is `--long-tail` observations (CORTEXLOC_SNAPSHOT_EVERY
   is 1,000 by default, so 10,000 means nine missed snapshots);
3. (`--full-replay`) with no snapshot: every observation is replayed.

Each opening runs in a fresh process; each phase is timed by wrapping the functions recovery calls,
and `registry.start()` is timed around the whole (interpreter and library imports excluded). From the
same start: `first_answer_s`, when a localising frame (a fixed projected vector, `learn=False`, through
the map's writer as the service runs it, the encoding aside) is first answered, retried every 10 ms
while the map refuses it; and `learning_s`, when the map is `ready` again (a tail of more than 50 rows
replays after the service starts serving, docs/design/service.md §4.4 step 8: this is when learning
posts stop getting 503). Issue 40's case: `--observations 100000 --long-tail 1000` (the "long tail"
scenario), target first answer <= 5 s. The
encoder is not part of start-up (replay needs no CNN), so a stub with the real feature dimension
stands in for it.
"""

from __future__ import annotations

import functools
import multiprocessing
import shutil
import tempfile
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

import service.maps.registry as registry_mod
from benchmarks._common import RESULTS, quick_mode, rss_mib, write_json
from models.frontend import slsbh
from models.localisation import PlaceMap
from models.localisation.index import InvertedIndex
from models.memory.temporal_memory import TemporalMemory
from service.maps.encoding.embedders import Embedders
from service.maps.errors import MapUnavailable
from service.maps.recovery import memory as recovery
from service.maps.states import serving
from service.settings import Settings
from storage import snapshots
from storage.mapstore import MapStore

FEATURE_DIM = 64_896  # AlexNet conv3, 384 x 13 x 13: the projection's real size


class StubEncoder:
    """What `MapRegistry` needs from an encoder at start-up: its identity and feature dimension."""

    feature_dim = FEATURE_DIM
    identity = "alexnet-conv3/bench-stub:crop"

    def identity_for(self, resize: str) -> str:
        return f"alexnet-conv3/bench-stub:{resize}"


class PhaseTimer:
    """Wraps functions so every call adds its wall time to a named phase (nested calls excluded)."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = {}
        self.calls: dict[str, int] = {}
        self._undo: list[Callable[[], None]] = []
        self._depth = 0

    def wrap(self, owner: Any, attr: str, phase: str) -> None:
        original = getattr(owner, attr)

        def timed(*args: Any, **kwargs: Any) -> Any:
            outer = self._depth == 0
            self._depth += 1
            t0 = time.perf_counter()
            try:
                return original(*args, **kwargs)
            finally:
                self._depth -= 1
                if outer:
                    self.seconds[phase] = self.seconds.get(phase, 0.0) + time.perf_counter() - t0
                    self.calls[phase] = self.calls.get(phase, 0) + 1

        setattr(owner, attr, timed)
        self._undo.append(lambda: setattr(owner, attr, original))

    def undo(self) -> None:
        for u in reversed(self._undo):
            u()
        self._undo.clear()


def settings_for(data_dir: Path) -> Settings:
    # No automatic snapshots: the benchmark places its own; a map of 10^5 fits the default caps.
    return Settings(data_dir=data_dir, snapshot_every=0, snapshot_keep=10)


def build(data_dir: Path, n: int, short_tail: int, long_tail: int, seed: int = 0) -> dict[str, Any]:
    """Create map `default` with n observations and snapshots at n - long_tail and n - short_tail."""
    reg = registry_mod.MapRegistry(data_dir, Embedders.one(StubEncoder()), settings_for(data_dir))
    reg.start()  # creates `default` with the default preset (and its 266 MB projection)
    rt = reg.get("default")
    assert rt.store is not None and rt.hasher is not None
    rt.store._db().execute("PRAGMA synchronous=OFF")  # building only: start-up never writes
    rng = np.random.Generator(np.random.PCG64(seed))
    snaps_at = {n - long_tail, n - short_tail}
    t0 = time.perf_counter()
    done = 0
    while done < n:
        route = rng.normal(size=(100, rt.hasher.k)).astype(np.float32)
        rt.reset_stream("robot")
        for lap in range(2):
            for p, base in enumerate(route):
                if done == n:
                    break
                projected = base + 0.3 * rng.normal(size=base.shape).astype(np.float32)
                rt.apply(projected, f"{done:064x}", learn=True, stream="robot", top_k=0,
                         label=f"lap {lap} place {p}")
                done += 1
                if done in snaps_at:
                    rt.snapshot("auto")
                if done % 10_000 == 0:
                    el = time.perf_counter() - t0
                    print(f"  built {done}/{n} observations ({el:.0f} s, {done / el:.0f}/s)", flush=True)
    build_s = time.perf_counter() - t0
    rt.store._db().execute("PRAGMA synchronous=FULL")
    reg.close()
    return {"observations": n, "build_s": build_s, "snapshots_at": sorted(snaps_at)}


def first_answer(rt: Any, t0: float) -> tuple[float, int]:
    """Seconds from `t0` until a localising frame is answered through the map's writer (what a client's
    first `learn=false` post waits for, the encoding aside), and how many tries were refused first."""
    assert rt.hasher is not None
    probe = np.random.Generator(np.random.PCG64(1)).normal(size=rt.hasher.k).astype(np.float32)
    refused = 0
    while True:
        try:
            rt.submit(functools.partial(rt.apply, probe, "0" * 64, learn=False, stream="bench-probe",
                                        top_k=5, label=None)).result()
            return time.perf_counter() - t0, refused
        except MapUnavailable:
            refused += 1
            time.sleep(0.01)


def open_once(data_dir: Path) -> dict[str, Any]:
    """`MapRegistry.start()` on the data directory, with the time of each recovery phase, the time to the
    first localising answer and the time until the map learns again (its tail replayed)."""
    timer = PhaseTimer()
    timer.wrap(registry_mod, "warm_up", "kernel warm-up (numba cache load)")
    timer.wrap(slsbh, "load_projection", "projection load + SHA-256")
    timer.wrap(MapStore, "open", "store open")
    timer.wrap(MapStore, "quick_check", "quick_check")
    timer.wrap(snapshots, "verify", "snapshot verify (checksums)")
    timer.wrap(snapshots, "load_memory", "snapshot load (npz)")
    timer.wrap(recovery, "load_memory_state", "snapshot -> TM (reverse index rebuild)")
    timer.wrap(TemporalMemory, "compute", "replay (TM steps, verified)")
    timer.wrap(InvertedIndex, "rebuild", "index rebuild (read rows + build)")
    # Since issue 40 the links' rebuild reads the rows for both, and the index's builds from what it kept.
    timer.wrap(PlaceMap, "rebuild", "links rebuild (read rows + build)")
    rss0 = rss_mib()
    try:
        t0 = time.perf_counter()
        reg = registry_mod.MapRegistry(data_dir, Embedders.one(StubEncoder()), settings_for(data_dir))
        reg.start()
        total = time.perf_counter() - t0
        rt = reg.get("default")
        answered_s, refused = first_answer(rt, t0)
        while not serving(rt.state).learns:  # the tail still replaying: learning posts are refused meanwhile
            time.sleep(0.01)
        learning_s = time.perf_counter() - t0
    finally:
        timer.undo()
    # The probe's own TM step is not a replayed one.
    state, replayed = rt.state, timer.calls.get("replay (TM steps, verified)", 0) - 1
    observations = len(rt.index)
    rss = rss_mib() - rss0
    # No shutdown snapshot (`snapshot_every` 0), so the next scenario finds the same snapshots; the
    # registry lets the data directory's lock go for the next one.
    reg.close()
    replay_s = timer.seconds.get("replay (TM steps, verified)", 0.0)
    return {"start_s": total, "first_answer_s": answered_s, "learning_s": learning_s,
            "refused_before_answer": refused, "recovery": rt.recovery, "state": state,
            "observations": observations, "replayed": replayed,
            "replay_ms_per_step": replay_s / replayed * 1e3 if replayed else None,
            "phases_s": {k: round(v, 4) for k, v in timer.seconds.items()},
            "rss_growth_mib": round(rss, 1)}


def keep_snapshots(data_dir: Path, keep: int) -> int:
    """Remove all but the oldest `keep` snapshots (catalog entries and files); how many are left. A data
    directory reused after an earlier run dropped some is left as it is."""
    from storage.catalog import Catalog

    cat = Catalog.open(data_dir / "catalog.sqlite")
    try:
        snaps = cat.list_snapshots("default")  # newest first
        for rec in snaps[:max(0, len(snaps) - keep)]:
            path = cat.snapshot_dir(rec)
            cat.delete_snapshot("default", rec.snapshot_id)
            shutil.rmtree(path, ignore_errors=True)
        return min(keep, len(snaps))
    finally:
        cat.close()


def main(*, observations: int | None, short_tail: int | None, long_tail: int | None, full_replay: bool,
         data_dir: Path | None, quick: bool, out: Path | None) -> None:
    if out is None:
        out = RESULTS / "startup.json"
    quick = quick_mode(quick)
    n = observations or (2_000 if quick else 100_000)
    short_tail = short_tail or (20 if quick else 100)
    long_tail = long_tail or (500 if quick else 10_000)
    tmp = None
    if data_dir is None:
        tmp = Path(tempfile.mkdtemp(prefix="cortexloc-bench-startup-"))
        data_dir = tmp / "var"
    try:
        built: dict[str, Any] = {"reused": True}
        if not (data_dir / "catalog.sqlite").exists():
            print(f"startup: building a map of {n} observations in {data_dir} (once)", flush=True)
            built = build(data_dir, n, short_tail, long_tail)
        db_mib = (data_dir / "maps" / "default" / "map.sqlite").stat().st_size / 2**20
        scenarios = []
        # The build leaves two snapshots (the long tail's, then the short tail's); each scenario keeps
        # fewer. A directory reused after a run that dropped the newer one runs the long tail only.
        for name, keep in (("short tail", 2), ("long tail", 1), ("no snapshot", 0)):
            if name == "no snapshot" and not full_replay:
                break
            if keep_snapshots(data_dir, keep) < keep:
                print(f"{name:>11}: skipped (an earlier run dropped its snapshot)", flush=True)
                continue
            # A fresh process per opening, as at a real start: numba loads its cached kernels, the page
            # cache is whatever the previous opening left (warm, as after a restart of the service).
            with ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn")) as ex:
                r = {"scenario": name, **ex.submit(open_once, data_dir).result()}
            scenarios.append(r)
            ph = r["phases_s"]
            print(f"{name:>11}: start {r['start_s']:.2f} s, first localising answer "
                  f"{r['first_answer_s']:.2f} s, learning {r['learning_s']:.2f} s, replayed {r['replayed']} "
                  f"({(r['replay_ms_per_step'] or 0):.2f} ms/step), state {r['state']}; phases (s) "
                  + ", ".join(f"{k} {v:.2f}" for k, v in ph.items()), flush=True)
        write_json(out.name, {
            "config": {"observations": n, "short_tail": short_tail, "long_tail": long_tail,
                       "preset": "cortexloc-default", "quick": quick},
            "build": built, "db_mib": db_mib, "scenarios": scenarios}, out)
    finally:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)


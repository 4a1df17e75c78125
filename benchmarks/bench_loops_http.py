"""Loop closure checked from outside (issue 35, "Done when"): one robot mapping while it drives, through
HTTP, at the service's defaults and a new map's seed.

Run: `cortexloc eval loops-http [--data DIR] [--seeds default,1,7] [--quick] [--out FILE]`.
Prints a markdown table; writes JSON (default benchmarks/results/loops_http.json).

Setup: the real service (`cortexloc serve`, default settings, the default backbone as this machine
resolves it, `bench_http.Server`) on a free 127.0.0.1 port with a temporary data directory. Each map is
created by `POST /v1/maps` with no option but its id and, for seeds other than `default`, `seed` (the
`default` maps are made with no seed at all: a new map's, read back from the map resource, 42 today).
Every frame is a PNG posted to `/v1/maps/{id}/observations?top_k=0`; all maps run concurrently (one
sequential stream each, `--concurrency` at a time).

Routes (labels: the truth's place labels; `slam.revisit_truth`: a frame is a true revisit only after the
route went more than 10 labels away and came back; tolerance 1 label):
- `outdoor`: Nordland 64x32, held out (`test` half, files the defaults were not tuned on, docs/results.md
  §10): lap 1 summer files [lo, lo + lap), an unrelated stretch [between, between + gap) of summer,
  lap 2 winter [lo, lo + lap). Labels: file index.
- `corridor`: a rendered indoor corridor 160x120 (`models.evaluation.corridor`: low texture, doors and
  lights repeating): lap 1 along corridor A at 0.12 m per frame through lens 1 (f 100 px), then
  corridor B (other colours and spacing) at 0.14 m, then lap 2 along A at 0.14 m through lens 2 (f 80 px,
  radial distortion k1 0.25). Labels: metres (B's offset by 10,000).
- `slow`: `outdoor` with each frame posted 3 times, each copy with σ 4 pixel noise (`stress.variant`).
- `robots`: two robots on one map, each its own stream (`robot-a`, `robot-b`), on two held-out stretches:
  A's summer lap [lo, lo + lap), then B's [lo + lap + gap, + lap) (ground A never drove), then A's
  winter lap and B's (lap 2, each robot back on its own ground). Found from outside (docs/results.md
  §10.25): one robot's frame consolidated into the other's row of another place became a link that a
  later lap followed to a false revisit.
- `dropped`: `outdoor` with every other frame of lap 1 and the stretch lost (a link that drops frames
  while the robot maps), lap 2 whole.
- `station`: `outdoor` with a station stop on both laps at the lap's middle file: the 3 files before it
  posted 2, 3 and 4 times (slowing), the file itself 40 times, the 3 after it 4, 3 and 2 times; every copy
  after a frame's first with σ 2 pixel noise (`stress.variant`), one stamp per post, a copy's pose its
  file's (the robot stands).
The last two were seen once each, at one seed, by an ad hoc probe (docs/results.md §10.25).
- `faster`: `outdoor` with lap 2 driven at twice the speed it was mapped at (every other file: every
  frame a stored place, the map two rows a frame), as a robot on a faster drive, or one whose frames are
  shed under load, posts it.
- `slower`: `outdoor` with lap 2 at half the speed (each file posted twice, the copy with σ 4 pixel
  noise); `slow` is a slower robot on both laps, this one slower than its own map.

Per route and seed, two maps: `slam` (every frame `learn=true`, one stream: loop closure while mapping;
`robots`: a stream per robot) and `localise` (lap 1 and the stretch learned by one stream, lap 2 posted
`learn=false` by another, `query-a`, `query-b` for the robots: the localise mode on the same lap-2
frames). Measured:
- false revisits while mapping: replies with `place.revisit` on lap 1 or the stretch (`slam.score`,
  lap 0), every one false (the truth has no revisit there);
- merged places: places whose rows' labels differ by more than the tolerance (`stress.merges`), the
  rows' places read from the map's `map.sqlite` read-only after its run (no endpoint lists every row's
  place; a benchmark may, the service never does); wrong consolidations beside it (a frame consolidated,
  `consolidated_into`, into a row of another label);
- lap 2: revisit precision and recall of `place.revisit` (the map's own decision at its threshold), the
  localise mode's recall (revisits called right / true revisits, the same frames), and OpenSeqSLAM run
  online on the route (`slam.openseqslam_online`), its recall at 100 % precision;
- beside them the per-query figures OpenSeqSLAM is read by, for both modes and OpenSeqSLAM: R@1 and
  recall at 100 % precision over the route's truth, each method's own score swept (the service's:
  `Place.decided`, its confidence where the answer may be a revisit at all, 0 for a flat frame, a span
  over `span_max` or a path lagging its stream, as the stress suite ranks it): what the default
  threshold leaves on the table; and the service's confidence alone swept (those gates off: what they
  cost). A sweep after the fact: the map was built at the default threshold (consolidation and joins
  follow it), so a swept point is not one the service runs at;
- with several robots (`robots`), each robot's lap-2 recall in both modes over its own frames (the
  JSON's `by_robot`): which robot's return a mode misses;
- issue 37's count of the localise mode's lap-2 revisits (`span_right`): right only when a true row lies
  inside the revisit's span and the span is at most 3 rows; its precision, and the share of the right
  answers it calls a revisit.
With `--poses` each frame carries `metadata` {stamp, pose}: the corridor's true positions (0.24 s per
frame), outdoors the file index x 280 m along a line (assumed: no poses come with the data), the slow
robot's copies between a frame and the next. Without it (the default) no frame has a pose, as with a
robot that posts none. `--drift S,H` (with `--poses`) posts odometry instead of the true poses: each
step scaled by 1 + N(0, S) and turned by a heading that walks N(0, H degrees) a step (seeded), so the
poses drift from the truth as wheel odometry does; a jump (a new drive) is turned and scaled the same.

Each route's line is the worst seed; `met` is issue 35's bar on every seed: 0 false revisits while
mapping, 0 merged places, precision >= 0.99, recall >= 0.9 x the localise mode's (same seed) and >=
OpenSeqSLAM's recall at 100 % precision + 0.05.
"""

from __future__ import annotations

import asyncio
import json
import os
import shutil
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import httpx
import numpy as np

from benchmarks._common import RESULTS, quick_mode, write_json
from benchmarks.bench_http import Server
from models.evaluation import corridor, datasets, seqslam, sequences, slam
from models.localisation.localiser import reaches
from service.evaluation import stress
from service.evaluation.slam import grey
from storage.layout import Layout
from storage.mapstore import MapStore

TOLERANCE = stress.TOLERANCE
ROUTES = ("outdoor", "corridor", "slow", "robots", "dropped", "station", "faster", "slower")
DEFAULT_SEED = "default"  # a map created with no seed option


@dataclass(frozen=True)
class Sizes:
    """A run's route sizes: `lo` the outdoor lap's first file index, `lap` its files, `between` and `gap`
    the unrelated stretch's; `corridor` and `corridor_b` the corridors' lengths in metres."""

    lo: int = 994
    lap: int = 200
    between: int = 1494
    gap: int = 100
    corridor: float = 36.0
    corridor_b: float = 14.0


QUICK = Sizes(lo=1000, lap=24, between=1494, gap=14, corridor=6.0, corridor_b=3.0)


#: Outdoor poses (`--poses`): metres per Nordland file, assumed (files are 10 s apart at about 100 km/h).
METRES_PER_FILE = 280.0


@dataclass(frozen=True)
class Route:
    """`pngs` (T,) encoded frames in driven order, `labels` (T,) place labels, `laps` (T,) 0 for lap 1 and
    the stretch after it (mapping), 1 for lap 2; `xy` (T, 2) each frame's position in metres and
    `stamps` (T,) its time in seconds, posted as metadata with `--poses`; `robots` (T,) which robot posts
    each frame (its stream's suffix), None: one robot."""

    name: str
    pngs: list[bytes]
    labels: np.ndarray
    laps: np.ndarray
    xy: np.ndarray
    stamps: np.ndarray
    robots: tuple[str, ...] | None = None

    def stream(self, i: int, learn: bool) -> str:
        """Frame i's stream: `robot` (`robot-a`) while learning, `query` (`query-a`) while localising."""
        name = "robot" if learn else "query"
        return name if self.robots is None else f"{name}-{self.robots[i]}"

    def metadata(self, i: int) -> str:
        """Frame i's `metadata` query parameter: its stamp and pose (compact JSON)."""
        x, y = (round(float(v), 3) for v in self.xy[i])
        return json.dumps({"stamp": round(float(self.stamps[i]), 3), "pose": {"x": x, "y": y}},
                          separators=(",", ":"))


def outdoor(data: Path, sizes: Sizes) -> Route:
    """The held-out Nordland loop (module docstring)."""
    names = sequences.paired_names(data / "summer", data / "winter")
    legs = [("summer", range(sizes.lo, sizes.lo + sizes.lap), 0),
            ("summer", range(sizes.between, sizes.between + sizes.gap), 0),
            ("winter", range(sizes.lo, sizes.lo + sizes.lap), 1)]
    pngs, labels, laps = [], [], []
    for season, files, lap in legs:
        for i in files:
            pngs.append((data / season / names[i]).read_bytes())
            labels.append(i)
            laps.append(lap)
    lab = np.asarray(labels, np.int64)
    xy = np.stack([lab * METRES_PER_FILE, np.zeros(lab.size)], axis=1)  # a straight line, assumed
    return Route("outdoor", pngs, lab, np.asarray(laps, np.int64), xy, 10.0 * np.arange(lab.size))


def two_robots(data: Path, sizes: Sizes) -> Route:
    """Two robots on two stretches of held-out ground (module docstring): A's summer lap, B's, then A's
    winter lap and B's. Labels: file index; poses: the file index x METRES_PER_FILE on one line, where
    the stretches lie apart."""
    names = sequences.paired_names(data / "summer", data / "winter")
    b_lo = sizes.lo + sizes.lap + sizes.gap
    legs = [("summer", sizes.lo, "a", 0), ("summer", b_lo, "b", 0), ("winter", sizes.lo, "a", 1),
            ("winter", b_lo, "b", 1)]
    pngs, labels, laps, robots = [], [], [], []
    for season, lo, robot, lap in legs:
        for i in range(lo, lo + sizes.lap):
            pngs.append((data / season / names[i]).read_bytes())
            labels.append(i)
            laps.append(lap)
            robots.append(robot)
    lab = np.asarray(labels, np.int64)
    xy = np.stack([lab * METRES_PER_FILE, np.zeros(lab.size)], axis=1)
    return Route("robots", pngs, lab, np.asarray(laps, np.int64), xy, 10.0 * np.arange(lab.size),
                 tuple(robots))


def _noisy(png: bytes, sigma: float, seed: int) -> bytes:
    """`png` again with σ pixel noise (`stress.variant`, seeded)."""
    img = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    return stress.variant(img, f"noise:{sigma:g}", seed)


def _taken(r: Route, name: str, keep: np.ndarray, pngs: list[bytes], stamps: np.ndarray) -> Route:
    """`r`'s frames `keep` (T',) posted as `pngs` at `stamps`: their labels, laps, poses and robots."""
    return Route(name, pngs, r.labels[keep], r.laps[keep], r.xy[keep], stamps,
                 None if r.robots is None else tuple(r.robots[i] for i in keep))


def _per_post(r: Route, posts: int) -> np.ndarray:
    """(posts,) stamps one of `r`'s first steps apart: a robot posting at its rate whatever it shows."""
    return (float(r.stamps[1] - r.stamps[0]) if len(r.stamps) > 1 else 1.0) * np.arange(posts)


def slower(r: Route, copies: int = 3, sigma: float = 4.0) -> Route:
    """`r` driven by a slower robot: each frame `copies` times, each copy with σ pixel noise (seeded)."""
    pngs: list[bytes] = []
    for i, b in enumerate(r.pngs):
        pngs.extend(_noisy(b, sigma, 1000 * c + i) for c in range(copies))
    # the copies of a frame lie between it and the next (a slower robot), their stamps `copies` times denser
    step = np.diff(r.xy, axis=0, append=r.xy[-1:])
    xy = np.repeat(r.xy, copies, axis=0) + np.tile(np.arange(copies) / copies, r.xy.shape[0])[:, None] * \
        np.repeat(np.where(np.abs(step) <= METRES_PER_FILE, step, 0.0), copies, axis=0)
    dt = float(r.stamps[1] - r.stamps[0]) if len(r.stamps) > 1 else 1.0
    return Route("slow", pngs, np.repeat(r.labels, copies), np.repeat(r.laps, copies), xy,
                 dt / copies * np.arange(len(pngs)))


def dropped(r: Route, every: int = 2) -> Route:
    """`r` with only every `every`-th frame of its mapping laps posted (module docstring); lap 2 whole."""
    keep = np.flatnonzero((r.laps == 1) | (np.arange(len(r.pngs)) % every == 0))
    return _taken(r, "dropped", keep, [r.pngs[i] for i in keep], r.stamps[keep])


def lap2_pace(r: Route, pace: float) -> Route:
    """`r` with lap 2 driven at `pace` x the speed it was mapped at (module docstring): 2 posts every
    other frame of it, 0.5 each frame twice (the copy with σ 4 pixel noise, seeded); lap 1 as it was."""
    if pace >= 1:
        keep = np.flatnonzero((r.laps == 0) | (np.cumsum(r.laps == 1) % int(pace) == 1))
        pngs = [r.pngs[i] for i in keep]
    else:
        copies = round(1 / pace)
        keep = np.repeat(np.arange(len(r.pngs)), np.where(r.laps == 1, copies, 1))
        first = np.r_[True, keep[1:] != keep[:-1]]
        pngs = [r.pngs[i] if new else _noisy(r.pngs[i], 4.0, 1000 + int(i))
                for i, new in zip(keep, first, strict=True)]
    return _taken(r, "faster" if pace > 1 else "slower", keep, pngs, _per_post(r, len(pngs)))


def station(r: Route, at: int, dwell: int = 40, ramp: tuple[int, ...] = (4, 3, 2)) -> Route:
    """`r` with a stop at label `at` on every lap (module docstring): the frame labelled `at` posted
    `dwell` times, those k = 1, 2, .. labels either side `ramp[k - 1]` times; copies after a frame's
    first with σ 2 pixel noise (seeded), one stamp a post (the route's first step apart), a copy's pose
    its frame's."""
    pngs: list[bytes] = []
    idx: list[int] = []
    for i, b in enumerate(r.pngs):
        k = abs(int(r.labels[i]) - at)
        copies = dwell if k == 0 else ramp[k - 1] if k <= len(ramp) else 1
        pngs.append(b)
        pngs.extend(_noisy(b, 2.0, 1000 * c + i) for c in range(1, copies))
        idx.extend([i] * copies)
    return _taken(r, "station", np.asarray(idx, np.int64), pngs, _per_post(r, len(pngs)))


def indoor(sizes: Sizes) -> Route:
    """The rendered corridor loop (module docstring, `models.evaluation.corridor`)."""
    a = corridor.Corridor(sizes.corridor, seed=3)
    b = corridor.Corridor(sizes.corridor_b, seed=11, wall=(120, 185, 210), floor=(60, 80, 115), door=5.0,
                          light=3.0, poster=4.0, label0=10_000)
    # (corridor, metres per frame, first position, lens, lap, where it lies: origin and direction)
    legs = [(a, 0.12, 0.0, corridor.Lens(100.0), 0, (0.0, 0.0), (1.0, 0.0)),
            (b, 0.14, 0.0, corridor.Lens(100.0), 0, (a.length + 2.0, 0.0), (0.0, 1.0)),
            (a, 0.14, 0.05, corridor.Lens(80.0, 0.25), 1, (0.0, 0.0), (1.0, 0.0))]
    pngs, labels, laps, xy = [], [], [], []
    for c, step, start, lens, lap, origin, way in legs:
        for s in np.arange(start, c.length, step):
            pngs.append(stress.png(corridor.render(c, float(s), lens)))
            labels.append(c.label0 + int(s))
            laps.append(lap)
            xy.append((origin[0] + way[0] * s, origin[1] + way[1] * s))
    # a robot at 0.5 m/s: 0.24 s per frame on lap 1; one stamp per frame along the whole drive
    return Route("corridor", pngs, np.asarray(labels, np.int64), np.asarray(laps, np.int64),
                 np.asarray(xy, np.float64), 0.24 * np.arange(len(pngs)))


def drifted(r: Route, scale_sd: float, heading_deg: float, seed: int = 5) -> Route:
    """`r` with odometry for poses (module docstring, `--drift`): its steps (T - 1, 2) each scaled by
    1 + N(0, `scale_sd`) and turned by a heading random walk of N(0, `heading_deg`) a step."""
    rng = np.random.default_rng(seed)
    steps = np.diff(r.xy, axis=0)
    heading = np.cumsum(rng.normal(0.0, np.deg2rad(heading_deg), len(steps)))
    scale = 1.0 + rng.normal(0.0, scale_sd, len(steps))
    c, s = np.cos(heading), np.sin(heading)
    turned = np.stack([c * steps[:, 0] - s * steps[:, 1], s * steps[:, 0] + c * steps[:, 1]], axis=1)
    xy = np.vstack([r.xy[:1], r.xy[:1] + np.cumsum(turned * scale[:, None], axis=0)])
    return Route(r.name, r.pngs, r.labels, r.laps, xy, r.stamps, r.robots)


def build(name: str, data: Path, sizes: Sizes) -> Route:
    if name == "outdoor":
        return outdoor(data, sizes)
    if name == "slow":
        return slower(outdoor(data, sizes))
    if name == "robots":
        return two_robots(data, sizes)
    if name == "corridor":
        return indoor(sizes)
    if name == "dropped":
        return dropped(outdoor(data, sizes))
    if name == "station":
        return station(outdoor(data, sizes), sizes.lo + sizes.lap // 2)
    if name in ("faster", "slower"):
        return lap2_pace(outdoor(data, sizes), 2.0 if name == "faster" else 0.5)
    raise ValueError(f"unknown route {name!r}; known: {', '.join(ROUTES)}")


# ---------------------------------------------------------------------------------------------- HTTP


async def _post(http: httpx.AsyncClient, url: str, body: bytes, params: dict[str, str]) -> dict[str, Any]:
    """One frame's reply (the fields scored); a 503 `overloaded` is retried after its Retry-After."""
    for _ in range(100):
        r = await http.post(url, params=params, content=body, headers={"Content-Type": "image/png"})
        if r.status_code == 503:
            await asyncio.sleep(float(r.headers.get("Retry-After", "1")))
            continue
        if r.status_code != 200:
            raise RuntimeError(f"POST {url} {params}: {r.status_code} {r.text[:500]}")
        j = r.json()
        return {"seq": j["seq"], "consolidated_into": j.get("consolidated_into"), "place": j["place"]}
    raise RuntimeError(f"POST {url}: overloaded 100 times in a row")


async def create_map(http: httpx.AsyncClient, base: str, map_id: str, seed: str,
                     localiser: dict[str, Any] | None = None) -> dict[str, Any]:
    """A new map with no option but `seed` (none for `default`) and, for an ablation, `localiser`
    options; its resource."""
    body: dict[str, Any] = {"map_id": map_id, **({"localiser": localiser} if localiser else {})}
    if seed != DEFAULT_SEED:
        body["seed"] = int(seed)
    r = await http.post(f"{base}/v1/maps", json=body)
    if r.status_code != 201:
        raise RuntimeError(f"create {map_id}: {r.status_code} {r.text[:500]}")
    got = await http.get(f"{base}/v1/maps/{map_id}")
    got.raise_for_status()
    return dict(got.json())


async def run_map(http: httpx.AsyncClient, base: str, map_id: str, seed: str, route: Route, mode: str,
                  gate: asyncio.Semaphore, poses: bool = False,
                  localiser: dict[str, Any] | None = None) -> dict[str, Any]:
    """Drive `route` into a new map: `slam` one learning stream throughout; `localise` the mapping laps
    learned by stream `robot`, lap 2 localised (`learn=false`) by stream `query`; `poses`: each frame
    with its stamp and pose as metadata."""
    async with gate:
        t0 = time.perf_counter()
        resource = await create_map(http, base, map_id, seed, localiser)
        url = f"{base}/v1/maps/{map_id}/observations"
        replies = []
        for i, body in enumerate(route.pngs):
            learn = mode == "slam" or route.laps[i] == 0
            params = {"stream": route.stream(i, learn), "learn": str(learn).lower(), "top_k": "0"}
            if poses:
                params["metadata"] = route.metadata(i)
            replies.append(await _post(http, url, body, params))
        print(f"{map_id}: {len(replies)} frames in {time.perf_counter() - t0:.0f} s", flush=True)
        return {"map_id": map_id, "seed": resource["params"]["seed"], "asked": seed,
                "threshold": float(resource["revisit_threshold"]), "backbone": resource["backbone"],
                "span_max": int(resource["params"]["localiser"]["span_max"]), "replies": replies}


# ---------------------------------------------------------------------------------------------- scoring


def answers(replies: list[dict[str, Any]], threshold: float, span_max: int) -> dict[str, Any]:
    """The replies as `slam.score` reads them: (T,) `best` frame the place names (-1: none), a confidence
    at or above `threshold` exactly where the reply said `place.revisit` (the decisions as replied);
    `decided` (T,), the confidence the decision compares (`Place.decided`: 0 for a frame too flat, a
    span over `span_max` or a path lagging its stream, as the stress suite ranks the service's answers),
    the score a threshold is swept on, and `raw` (T,) the confidence alone (the gates' ablation); the
    rows made (seq -> frame) and the frames consolidated (frame -> the row's seq)."""
    T = len(replies)
    frame_of = {r["seq"]: i for i, r in enumerate(replies) if r["seq"] is not None}
    best, conf, decided, raw = np.full(T, -1, np.int64), np.zeros(T), np.zeros(T), np.zeros(T)
    below = float(np.nextafter(threshold, -np.inf))
    for i, r in enumerate(replies):
        p = r["place"]
        if p is None or p["seq"] not in frame_of:
            continue
        best[i] = frame_of[p["seq"]]
        decidable = not p.get("low_information") and not p.get("lagging") and int(p["span"]) <= span_max
        raw[i] = float(p["confidence"])
        decided[i] = raw[i] if decidable else 0.0
        conf[i] = max(decided[i], threshold) if p["revisit"] else min(decided[i], below)
    consolidated = {i: int(r["consolidated_into"]) for i, r in enumerate(replies)
                    if r.get("consolidated_into") is not None}
    # each answer's span: the frames its `span_seqs` name (rows this run made) and its `span` count
    spans = [([frame_of[q] for q in (r["place"] or {}).get("span_seqs") or [] if q in frame_of],
              int((r["place"] or {}).get("span") or 0)) for r in replies]
    return {"best": best, "confidence": conf, "decided": decided, "raw": raw, "frame_of": frame_of,
            "consolidated": consolidated,
            "spans": spans, "revisit": np.array([bool(r["place"] and r["place"]["revisit"])
                                                 for r in replies], bool)}


def span_right(labels: np.ndarray, laps: np.ndarray, a: dict[str, Any], span_max: int = 3) -> dict[str, Any]:
    """Issue 37's count of the localise mode's lap-2 revisits: one is right when a true row (a row of
    lap 0 within the tolerance of the frame's label) lies inside its span and the span is at most
    `span_max` rows. "precision": right / revisits called; "called": right / right answers (frames whose
    best row is a true one), the share of its right places the mode calls."""
    lab = np.asarray(labels, np.int64)
    lap2 = np.asarray(laps) == 1
    called = lap2 & a["revisit"]
    ok = np.array([span <= span_max and any(abs(int(lab[f]) - int(lab[i])) <= TOLERANCE for f in frames)
                   for i, (frames, span) in enumerate(a["spans"])], bool)
    named = (a["best"] >= 0) & (np.abs(lab[np.maximum(a["best"], 0)] - lab) <= TOLERANCE)
    right_answers = int((lap2 & named).sum())
    return {"span_precision": float((called & ok).sum() / called.sum()) if called.any() else None,
            "span_called": float((called & ok).sum() / right_answers) if right_answers else None}


def row_places(db: Path) -> dict[int, int]:
    """Row seq -> its place (the id of the place's first row) of the map database `db`, read-only: a row's
    stored `place` (the row whose place it joined; a row a repair unjoined: its own) followed to its root
    (docs/design/science.md §11.8)."""
    with MapStore.open(db, readonly=True) as store:
        unjoined = {r.seq for r in store.repairs() if r.kind == "unjoin"}
        return roots({row.seq: None if row.place is None or row.seq in unjoined else int(row.place)
                      for row in store.rows()})


def roots(joined: dict[int, int | None]) -> dict[int, int]:
    """Row -> the root of its chain of joins (`joined`: row -> the row whose place it joined, None: its
    own); a row joined to a row not listed ends there."""
    out: dict[int, int] = {}
    for seq in joined:
        root, hops = seq, 0
        while (up := joined.get(root)) is not None and hops <= len(joined):
            root, hops = up, hops + 1
        out[seq] = root
    return out


def merge_trace(frame_of: dict[int, int], consolidated: dict[int, int], places: dict[int, int],
                frames: int) -> dict[str, np.ndarray]:
    """`stress.merges`' trace of an HTTP run: rows in seq order renumbered 1..R (its `visit` indexes
    `row_frame` by seq - 1), each row's place, each consolidated frame's row."""
    seqs = sorted(frame_of)
    pos = {q: k + 1 for k, q in enumerate(seqs)}
    visit = np.full(frames, -1, np.int64)
    for i, q in consolidated.items():
        visit[i] = pos[q]
    return {"row_frame": np.array([frame_of[q] for q in seqs], np.int64),
            "row_place": np.array([places.get(q, q) for q in seqs], np.int64), "visit": visit}


def score_seed(route: Route, slam_run: dict[str, Any], loc_run: dict[str, Any],
               places: dict[int, int]) -> dict[str, Any]:
    """One seed's figures on one route (module docstring); `false_revisit_lags`: for each revisit called
    while mapping, how many frames and labels back the row it named lies (an echo of the stream's own
    trail is a few frames back, aliasing far); `by_robot` (routes with several robots): each robot's
    lap-2 recall in both modes, over its own frames."""
    thr = slam_run["threshold"]
    a = answers(slam_run["replies"], thr, slam_run["span_max"])
    s = slam.score(a["best"], a["confidence"], route.labels, thr, TOLERANCE, route.laps)
    m = stress.merges(route.labels, merge_trace(a["frame_of"], a["consolidated"], places, len(route.pngs)))
    # the localise map: its lap-2 answers name rows the mapping laps made
    la = answers(loc_run["replies"], loc_run["threshold"], loc_run["span_max"])
    lap2 = route.laps == 1
    best = np.where(lap2, la["best"], -1)
    conf = np.where(lap2, la["confidence"], 0.0)
    loc_truth = slam.localise_truth(route.labels, route.laps, TOLERANCE)
    ls = slam.score(best, conf, route.labels, loc_run["threshold"], TOLERANCE, route.laps, loc_truth)
    mapping, second, loc2 = s["lap"][0], s["lap"].get(1, {}), ls["lap"].get(1, {})
    # swept as OpenSeqSLAM is (`openseqslam`), over the route's truth: each mode's decided confidence,
    # and its confidence alone (the span, pace and flatness gates off: what they cost)
    def sweep(b: np.ndarray, c: np.ndarray) -> float | None:
        lap = slam.score(b, c, route.labels, thr, TOLERANCE, route.laps)["lap"].get(1, {})
        return lap.get("recall_at_100p")

    swept, loc_swept = sweep(a["best"], a["decided"]), sweep(best, np.where(lap2, la["decided"], 0.0))
    ungated, loc_ungated = sweep(a["best"], a["raw"]), sweep(best, np.where(lap2, la["raw"], 0.0))
    # each robot's lap 2 alone (`robots`): the other robots' frames scored as no lap of interest
    by_robot: dict[str, dict[str, float | None]] = {}
    for robot in sorted(set(route.robots or ())):
        laps = np.where(np.asarray(route.robots) == robot, route.laps, -1)
        own = slam.score(a["best"], a["confidence"], route.labels, thr, TOLERANCE, laps)["lap"].get(1, {})
        own_loc = slam.score(best, conf, route.labels, loc_run["threshold"], TOLERANCE, laps,
                             loc_truth)["lap"].get(1, {})
        by_robot[robot] = {"recall": own.get("recall"), "localise_recall": own_loc.get("recall")}
    called = np.flatnonzero((route.laps == 0) & (a["best"] >= 0) & reaches(a["confidence"], thr))
    lags = {"frames": (called - a["best"][called]).tolist(),
            "labels": np.abs(route.labels[called] - route.labels[a["best"][called]]).tolist()}
    return {"seed": slam_run["seed"], "asked": slam_run["asked"], "threshold": thr,
            "false_revisits_mapping": mapping["false_revisits"], "merged_places": m["merged_places"],
            "wrong_consolidations": m["wrong_consolidations"], "rows": len(a["frame_of"]),
            "consolidated": len(a["consolidated"]),
            "frames": len(route.pngs), "revisits_true": second.get("revisits_true"),
            "revisits_called": second.get("revisits_called"), "precision": second.get("precision"),
            "recall": second.get("recall"), "localise_recall": loc2.get("recall"),
            "localise_precision": loc2.get("precision"),
            # the per-query figures OpenSeqSLAM is read by, the threshold swept: what the default leaves
            # (a sweep after the fact: the map was built at the default, so no point the service runs at)
            "recall_at_1": second.get("recall_at_1"), "recall_at_100p": swept,
            "localise_recall_at_1": loc2.get("recall_at_1"), "localise_recall_at_100p": loc_swept,
            "recall_at_100p_ungated": ungated, "localise_recall_at_100p_ungated": loc_ungated,
            **{f"localise_{k}": v for k, v in span_right(route.labels, route.laps, la).items()},
            "false_revisit_lags": lags, "by_robot": by_robot}


def openseqslam(route: Route) -> dict[str, float | None]:
    """OpenSeqSLAM run online on the whole route: lap 2's recall at 100 % precision (its threshold swept,
    as it is read) and R@1."""
    F = grey(route.pngs)
    best, conf = slam.openseqslam_online(seqslam.mean_abs_difference(F, F))
    s = slam.score(best, conf, route.labels, float("inf"), TOLERANCE, route.laps)
    lap2 = s["lap"].get(1, {})
    return {"recall_at_100p": lap2.get("recall_at_100p"), "recall_at_1": lap2.get("recall_at_1")}


def verdict(entry: dict[str, Any], osl: float | None) -> dict[str, bool]:
    """Issue 35's bar on one seed (module docstring)."""
    p, r, lr = entry["precision"], entry["recall"] or 0.0, entry["localise_recall"] or 0.0
    return {"no_false_revisits": entry["false_revisits_mapping"] == 0,
            "no_merges": entry["merged_places"] == 0,
            "precision": p is None or p >= 0.99, "recall_vs_localise": r >= 0.9 * lr,
            "recall_vs_openseqslam": r >= (osl or 0.0) + 0.05}


def worst(per_seed: list[dict[str, Any]], osl: float | None) -> dict[str, Any]:
    """A route's line: the worst seed of each figure, and `met` on every seed."""
    def lo(k: str) -> float | None:
        vals = [e[k] for e in per_seed if e[k] is not None]
        return min(vals) if vals else None

    checks = [verdict(e, osl) for e in per_seed]
    return {"false_revisits_mapping": max(e["false_revisits_mapping"] for e in per_seed),
            "merged_places": max(e["merged_places"] for e in per_seed),
            "wrong_consolidations": max(e["wrong_consolidations"] for e in per_seed),
            "precision": lo("precision"), "recall": lo("recall"), "localise_recall": lo("localise_recall"),
            "localise_span_precision": lo("localise_span_precision"),
            "localise_span_called": lo("localise_span_called"),
            **{k: lo(k) for k in ("recall_at_100p", "localise_recall_at_100p", "recall_at_1",
                                  "localise_recall_at_1", "recall_at_100p_ungated",
                                  "localise_recall_at_100p_ungated")},
            "recall_to_localise": min((e["recall"] or 0.0) / e["localise_recall"] if e["localise_recall"]
                                      else float("inf") for e in per_seed),
            "openseqslam_recall_at_100p": osl,
            "checks": {k: all(c[k] for c in checks) for k in checks[0]},
            "met": all(all(c.values()) for c in checks)}


def _f(v: float | None) -> str:
    return "–" if v is None else f"{v:.3f}"


def table(result: dict[str, Any]) -> str:
    """The routes' worst-seed lines, then every seed, as markdown."""
    head = ("| route | frames | false revisits while mapping | merged places | wrong consolidations | "
            "lap-2 precision | lap-2 recall | localise recall | recall / localise | OpenSeqSLAM R@100P | "
            "met | R@100P: mapping / localise / OpenSeqSLAM | R@100P, gates off: mapping / localise | "
            "R@1: mapping / localise / OpenSeqSLAM |\n"
            "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|\n")
    lines = []
    for name, r in result["routes"].items():
        w = r["worst"]
        failed = [k for k, ok in w["checks"].items() if not ok]
        lines.append(f"| {name} | {r['frames']} | {w['false_revisits_mapping']} | {w['merged_places']} | "
                     f"{w['wrong_consolidations']} | {_f(w['precision'])} | {_f(w['recall'])} | "
                     f"{_f(w['localise_recall'])} | {_f(w['recall_to_localise'])} | "
                     f"{_f(w['openseqslam_recall_at_100p'])} | "
                     f"{'yes' if w['met'] else 'no: ' + ', '.join(failed)} | "
                     f"{_f(w['recall_at_100p'])} / {_f(w['localise_recall_at_100p'])} / "
                     f"{_f(r['openseqslam_recall_at_100p'])} | {_f(w['recall_at_100p_ungated'])} / "
                     f"{_f(w['localise_recall_at_100p_ungated'])} | {_f(w['recall_at_1'])} / "
                     f"{_f(w['localise_recall_at_1'])} / {_f(r['openseqslam_recall_at_1'])} |")
    seeds = ["", "| route | seed | false revisits while mapping | merged places | wrong consolidations | "
             "rows | lap-2 called / true | precision | recall | localise recall | localise span precision | "
             "localise span called |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for name, r in result["routes"].items():
        for e in r["seeds"]:
            seed = f"{e['seed']}" + (" (new map's)" if e["asked"] == DEFAULT_SEED else "")
            seeds.append(f"| {name} | {seed} | {e['false_revisits_mapping']} | {e['merged_places']} | "
                         f"{e['wrong_consolidations']} | {e['rows']} | {e['revisits_called']} / "
                         f"{e['revisits_true']} | {_f(e['precision'])} | {_f(e['recall'])} | "
                         f"{_f(e['localise_recall'])} | {_f(e['localise_span_precision'])} | "
                         f"{_f(e['localise_span_called'])} |")
    return head + "\n".join(lines) + "\n" + "\n".join(seeds) + "\n"


async def _drive_all(base: str, routes: dict[str, Route], seeds: list[str], concurrency: int,
                     poses: bool, localiser: dict[str, Any] | None) -> dict[str, list[dict[str, Any]]]:
    gate = asyncio.Semaphore(concurrency)
    limits = httpx.Limits(max_connections=concurrency, max_keepalive_connections=concurrency)
    jobs: list[tuple[str, Any]] = []
    async with httpx.AsyncClient(limits=limits, timeout=300) as http:
        for name, r in routes.items():
            for seed in seeds:
                for mode in ("slam", "localise"):
                    jobs.append((name, run_map(http, base, f"{name}-{mode}-{seed}", seed, r, mode, gate,
                                                poses, localiser)))
        done = await asyncio.gather(*(j for _, j in jobs))
    out: dict[str, list[dict[str, Any]]] = {}
    for (name, _), run in zip(jobs, done, strict=True):
        out.setdefault(name, []).append(run)
    return out


def run(*, data: Path, routes: list[str], seeds: list[str], sizes: Sizes, concurrency: int,
        keep: bool = False, poses: bool = False, localiser: dict[str, Any] | None = None,
        drift: tuple[float, float] | None = None) -> dict[str, Any]:
    """Build the routes, start the server, drive every map, score: {"config", "routes": {name: {frames,
    seeds: [per seed], openseqslam_recall_at_100p, worst}}, "wall_s"}. `drift`: (scale σ, heading σ in
    degrees a step) of the posted odometry (`drifted`), None: the true poses."""
    t0 = time.perf_counter()
    built = {name: build(name, data, sizes) for name in routes}
    if drift is not None:
        built = {name: drifted(r, *drift) for name, r in built.items()}
    tmp = Path(tempfile.mkdtemp(prefix="cortexloc-bench-loops-"))
    # the service's defaults on this machine: its own weights directory, not bench_http's empty one
    server = Server(tmp, extra_env={"CORTEXLOC_WEIGHTS_DIR": os.environ.get("CORTEXLOC_WEIGHTS_DIR", "")})
    try:
        server.wait_ready()
        ready = httpx.get(f"{server.base}/readyz", timeout=30).json()["checks"]["encoder"]
        t_drive = time.perf_counter()
        runs = asyncio.run(_drive_all(server.base, built, seeds, concurrency, poses, localiser))
        drive_s = time.perf_counter() - t_drive
        layout = Layout(tmp / "var")
        result: dict[str, Any] = {"config": {
            "data": str(data), "sizes": sizes.__dict__, "seeds": seeds, "tolerance": TOLERANCE,
            "backbone": ready.get("backbone"), "runtime": ready.get("runtime"), "concurrency": concurrency,
            "poses": poses, "localiser": localiser, "drift": drift},
            "routes": {}}
        for name, r in built.items():
            by_seed: dict[str, dict[str, Any]] = {}
            for rn in runs[name]:
                by_seed.setdefault(rn["asked"], {})[rn["map_id"].split("-")[1]] = rn
            per_seed = [score_seed(r, pair["slam"], pair["localise"],
                                   row_places(layout.map_db(pair["slam"]["map_id"])))
                        for pair in by_seed.values()]
            osl = openseqslam(r)
            result["routes"][name] = {"frames": len(r.pngs), "revisits_true": int(slam.revisit_truth(
                r.labels, TOLERANCE).sum()), "seeds": per_seed,
                "openseqslam_recall_at_100p": osl["recall_at_100p"],
                "openseqslam_recall_at_1": osl["recall_at_1"],
                "worst": worst(per_seed, osl["recall_at_100p"])}
    finally:
        server.stop()
        if not keep:
            shutil.rmtree(tmp, ignore_errors=True)
    result["drive_s"] = drive_s
    # every frame twice per seed: the slam map and the localise map
    result["posts"] = sum(2 * len(r.pngs) for r in built.values()) * len(seeds)
    result["wall_s"] = time.perf_counter() - t0
    return result


def main(*, data: Path | None, routes: list[str], seeds: list[str], concurrency: int, quick: bool, keep: bool,
         poses: bool, localiser: dict[str, Any] | None, out: Path | None,
         drift: tuple[float, float] | None = None) -> None:
    """`cortexloc eval loops-http`: `run` at the full or the quick sizes, then the table, JSON under
    benchmarks/results/loops_http.json (or `out`) and each route's verdict."""
    out = out or RESULTS / "loops_http.json"
    sizes = QUICK if quick_mode(quick) else Sizes()
    result = run(data=data or datasets.nordland_dir(), routes=routes, seeds=seeds, sizes=sizes,
                 concurrency=concurrency, keep=keep, poses=poses, localiser=localiser, drift=drift)
    print(table(result), flush=True)
    print(f"{result['posts']} posts, driven in {result['drive_s']:.0f} s; {result['wall_s']:.0f} s in all",
          flush=True)
    write_json(out.name, result, out)
    print(json.dumps({name: r["worst"]["met"] for name, r in result["routes"].items()}), flush=True)


"""Growth of a map driven pass after pass over one held-out route while it learns (issue 36; docs/design/
science.md §11.7-§11.9, docs/results.md §11): rows made and held per pass, revisit precision and recall
per pass, the visit log and the loop-closure log.

    cortexloc bench growth [--passes 10] [--lo 894] [--frames 400] [--seed 42] [--http] [--quick] [--anywhere]
                           [--routes exact,noise8,winter]

The route is files [lo, lo + frames) of ../shared/data/nordland_tiny_64x32's summer half (default the
first 400 files of the held-out `test` half; labels = file index), driven `passes` times as ONE learning
stream through the service's step (`models.pipeline.observe` on a served map's model at the defaults and
a new map's seed, 42, as `service.evaluation.service_path.slam_replay` drives it; `--http`: the service
itself through HTTP, `drive_http`, which also measures contrast at decode), the drive restarted
before every pass (`Stream.break_sequence`, what `POST .../streams/{s}/reset` does: a new warm-up), the
frames' contrast measured as the service measures it at decode (§11.7). Two routes: `exact` (every pass
the same PNGs) and `noise8` (pass 1 the PNGs, every later pass new pixel noise of σ 8); `--routes` may add
`winter` (pass 1 the summer PNGs, every later pass the same files' winter PNGs: one winter drive repeated
exactly, another season's warm-ups, §11.8). `--anywhere`: every
pass after the first starts part-way along the route (pass p, counted from 1, at file
`lo + ((p − 1) · 7919) mod (frames / 2)`) and drives to its end; its recall is over the frames it drove
(written to growth-anywhere.json).

Per pass: `rows` made (seqs handed out), `stored` (`--http`: the change in map.sqlite's rows, `rows_stored`:
the rows made less the warm-up rows a join turned into visits, schema 12), `held` (the change in rows held:
the index and the places' appearances), `new_places` (the change in places with a row held; `places`: at the
pass's end), `visits` (consolidated frames: the visit log's growth, pruned to `max_visits` once snapshots
cover them), `joins` (warm-up joins, §11.8; `--http`: `dropped`, the rows dropped, joins or cap), `closures`
(revisits called: the loop-closure log's growth, bounded by `max_closures`), and `precision`, `recall` of
the revisits called (right: the named row's file within 1 of the frame's; recall over every frame of the
pass, all true revisits after pass 1). Pass 1 must call no revisit. One JSON line per route and pass,
then a summary line per route; results/growth.json (`--http`: growth-http.json).
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from benchmarks._common import machine, quick_mode, write_json
from models.evaluation import datasets
from models.pipeline import Stream, observe
from service.evaluation import service_path, stress
from service.evaluation.slam import encoder_setup


def drive(feats: list[np.ndarray], contrast: list[np.ndarray], passes: list[np.ndarray],
          seed: int, localiser: dict | None = None) -> list[dict]:
    """`feats[p]` (T_p, D) the features of pass p's frames, `passes[p]` (T_p,) their labels: one map (its
    `localiser` options over the defaults), one stream, the drive restarted before each pass. Returns one
    dict per pass."""
    backbone, preset = ENC["backbone"], ENC["preset"]
    model, hasher, config = service_path._model(int(feats[0].shape[1]),
                                                max_observations=sum(len(y) for y in passes),
                                                backbone=backbone, preset=preset, seed=seed, memory="tm",
                                                localiser=localiser, create=None)
    thr = config.revisit_threshold
    robot, codes, label_of = Stream(), {}, {}
    out, visits, closures = [], 0, 0
    for p, (f, c, labels) in enumerate(zip(feats, contrast, passes, strict=True)):
        robot.break_sequence()  # a new drive: a new warm-up
        held0, places0 = model.place_map.held, model.place_map.places()
        made, v0, c0, joins, right, called = len(codes), visits, closures, 0, 0, 0
        t0 = time.perf_counter()
        for i, y in enumerate(hasher.project(f)):
            seq = len(codes) + 1
            step = observe(model, robot, y, learn=True, stream="robot", top_k=0, seq=seq,
                           code_of=codes.__getitem__, threshold=thr, contrast=float(c[i]))
            if step.visit is None:
                codes[seq], label_of[seq] = step.code, int(labels[i])
            else:
                visits += 1
            joins += len(step.joins) + len(step.kept)
            if step.place is not None and step.place.is_revisit(thr):
                closures += 1
                called += 1
                right += abs(label_of[step.place.seq] - int(labels[i])) <= 1
        out.append({"pass": p + 1, "rows": len(codes) - made, "held": model.place_map.held - held0,
                    "new_places": model.place_map.places() - places0, "places": model.place_map.places(),
                    "visits": visits - v0, "joins": joins,
                    "closures": closures - c0, "visit_log": visits, "closure_log": closures,
                    "called": called, "right": right,
                    "precision": round(right / called, 4) if called else None,
                    "recall": round(right / len(labels), 4), "seconds": round(time.perf_counter() - t0, 1)})
        print(out[-1], flush=True)
    return out


def drive_http(pngs: list[list[bytes]], passes: list[np.ndarray], seed: int,
               localiser: dict | None = None) -> list[dict]:
    """`drive` through HTTP: the service itself (`create_app` at the defaults, its own encoder, a fresh
    data directory), a new map of `seed`, each pass's PNGs posted as one learning stream, `POST
    .../streams/robot/reset` before each pass; the sizes read from `GET /v1/maps/{id}` (`places`)."""
    import tempfile

    from fastapi.testclient import TestClient

    from service.app import create_app
    from service.settings import Settings

    out, visits0, closures = [], 0, 0
    with tempfile.TemporaryDirectory() as d, TestClient(create_app(Settings(data_dir=Path(d)))) as c:
        made = {"map_id": "growth", "seed": seed, **({"localiser": localiser} if localiser else {})}
        assert c.post("/v1/maps", json=made).status_code == 201
        label_of: dict[int, int] = {}
        before = c.get("/v1/maps/growth").json()["places"]
        for p, (bodies, labels) in enumerate(zip(pngs, passes, strict=True)):
            c.post("/v1/maps/growth/streams/robot/reset")
            t0, made, joins0, right, called = time.perf_counter(), 0, before["dropped"], 0, 0
            for i, body in enumerate(bodies):
                b = c.post("/v1/maps/growth/observations", content=body,
                           headers={"Content-Type": "image/png"},
                           params={"stream": "robot", "learn": "true", "top_k": 0}).json()
                if b["seq"] is not None:
                    made += 1
                    label_of[b["seq"]] = int(labels[i])
                if b["place"] is not None and b["place"]["revisit"]:
                    called += 1
                    right += abs(label_of[b["place"]["seq"]] - int(labels[i])) <= 1
            closures += called
            now = c.get("/v1/maps/growth").json()["places"]
            out.append({"pass": p + 1, "rows": made, "stored": now["rows_stored"] - before["rows_stored"],
                        "held": now["appearances"] - before["appearances"],
                        "new_places": now["places"] - before["places"], "places": now["places"],
                        "visits": now["visits_logged"] - visits0, "dropped": now["dropped"] - joins0,
                        "closures": called, "visit_log": now["visits_logged"], "closure_log": closures,
                        "called": called, "right": right,
                        "precision": round(right / called, 4) if called else None,
                        "recall": round(right / len(labels), 4),
                        "seconds": round(time.perf_counter() - t0, 1)})
            print(out[-1], flush=True)
            before, visits0 = now, now["visits_logged"]
    return out


#: The routes a run drives (`--routes`): `main`'s names, the first two the default.
ROUTES = ("exact", "noise8", "winter")


def main(*, passes: int, lo: int, frames: int, seed: int, quick: bool, http: bool,
         anywhere: bool = False, routes: tuple[str, ...] = ROUTES[:2], localiser: dict | None = None) -> None:
    """`cortexloc bench growth`: `passes` passes over files lo..lo+frames, in process or through HTTP,
    of each of `routes` (ROUTES); `anywhere`: passes after the first start part-way along the route;
    `localiser`: the map's localiser options over the defaults (an ablation)."""
    passes, n = (3, 100) if quick_mode(quick) else (passes, frames)
    starts = [(p * 7919) % max(n // 2, 1) if anywhere and p else 0 for p in range(passes)]
    enc, cache, conf = encoder_setup(None, None)
    ENC.update(conf)
    source = stress.Frames(datasets.nordland_dir(), enc, cache)
    idx = range(lo, lo + n)
    labels = np.asarray(list(idx))
    imgs = [source.image("summer", i) for i in idx]
    clean = [stress.png(im) for im in imgs]
    winter = [stress.png(source.image("winter", i)) for i in idx] if "winter" in routes else []

    def pass_pngs(name: str, p: int) -> list[bytes]:
        """Pass p's (p >= 1) PNGs of route `name`."""
        if name == "noise8":
            return [stress.variant(im, "noise:8", 1000 * p + j) for j, im in enumerate(imgs)]
        return winter if name == "winter" else clean

    results = {}
    for name in routes:
        pngs = [(clean if p == 0 else pass_pngs(name, p))[starts[p]:] for p in range(passes)]
        ys = [labels[o:] for o in starts]
        if http:
            rows = drive_http(pngs, ys, seed, localiser)
        else:
            feats = [source.features(ps) for ps in pngs]
            rows = drive(feats, [service_path.contrasts(ps) for ps in pngs], ys, seed, localiser)
        p2 = rows[1]["recall"] if len(rows) > 1 else 0.0
        later = rows[2:]
        summary = {"route": name, "rows_per_pass_3_on": [r["rows"] for r in later],
                   **({"stored_per_pass_3_on": [r["stored"] for r in later]} if http else {}),
                   "held_per_pass_3_on": [r["held"] for r in later],
                   "new_places_per_pass_3_on": [r["new_places"] for r in later],
                   "max_rows_3_on": max((r["rows"] for r in later), default=0),
                   "max_held_3_on": max((r["held"] for r in later), default=0),
                   "pass1_false": rows[0]["called"] - rows[0]["right"],
                   "min_recall_ratio_3_on": round(min((r["recall"] for r in later), default=0) / p2, 3)
                   if p2 else None,
                   "min_precision_2_on": min((r["precision"] or 1.0 for r in rows[1:]), default=None)}
        print(summary, flush=True)
        results[name] = {"passes": rows, "summary": summary}
    write_json(f"growth{'-http' if http else ''}{'-anywhere' if anywhere else ''}.json",
               {"machine": machine(), "route": [lo, lo + n], "seed": seed, "starts": starts,
                "localiser": localiser or {},
                "results": results})


ENC: dict = {}

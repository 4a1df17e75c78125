"""False revisits on places the map never stored, and the decision on the places it did, through the
service's path (docs/results.md §9.2).

    cortexloc eval unknown --db ../shared/data/nordland_tiny_64x32/summer \
        --query ../shared/data/nordland_tiny_64x32/winter --split 894 --thresholds 0.639,0.8,0.951
    cortexloc eval unknown ... --limit 894 --split 447 --thresholds 0.9   # inside `tune` only

The route is the paired frames `--offset` to `--offset + --limit` (default: all).

The route is cut at `--split` into two halves of different places. For each half, the database half is
learned and the query traverse of the OTHER half is localised as one stream (`service_path.replay`: the
service's path, `models.pipeline.observe`): every answer with confidence >= a threshold is a false
revisit. Then the same half of both traverses (the places the map stored): precision and recall of
`revisit` per threshold, recall = right answers called revisits / right answers.
"""

from __future__ import annotations

import os
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from models.evaluation import sequences
from models.frontend.embedding import Embedder
from models.localisation.localiser import reaches
from service.evaluation import service_path
from service.maps.config import DEFAULT_RESIZE
from service.settings import Settings


def route_names(db: Path, query: Path, *, split: int, offset: int = 0, limit: int | None = None) -> list[str]:
    """The route's paired frame names, `offset` to `offset + limit`, checked to cut at `split`.

    Raises:
        ValueError: the folders share no frame, `offset` leaves none, or `split` does not cut the
            route into two non-empty halves.
    """
    names = sequences.paired_names(db, query, offset, limit)
    if not 0 < split < len(names):
        raise ValueError(f"--split {split} must cut the route's {len(names)} frames into two halves")
    return names


def unknown(db: Path, query: Path, *, split: int, thresholds: list[float], backbone: str | None = None,
            seed: int = 1, offset: int = 0, limit: int | None = None) -> None:
    """The experiment (module docstring), printed.

    Raises:
        ValueError: as `route_names`.
    """
    args = SimpleNamespace(db=db, query=query, split=split, thresholds=thresholds, backbone=backbone,
                           seed=seed)
    from service.frontend import resolve_backbone  # the service's own resolution of its default

    settings = Settings.from_env()
    backbone = args.backbone or resolve_backbone(settings).backbone
    names = route_names(args.db, args.query, split=split, offset=offset, limit=limit)
    enc = Embedder({"backbone": backbone, "resize": DEFAULT_RESIZE})  # a new map's
    cache = Path(os.environ.get("CORTEXLOC_CACHE_DIR", Path.home() / ".cache" / "cortexloc")) / "features"
    db = sequences.cached_features(enc, [args.db / n for n in names], cache)
    q = sequences.cached_features(enc, [args.query / n for n in names], cache)
    halves = (slice(0, args.split), slice(args.split, len(names)))
    # each frame's contrast, as the service measures it at decode (docs/design/science.md §11.7)
    db_c = service_path.contrasts((args.db / n).read_bytes() for n in names)
    q_c = service_path.contrasts((args.query / n).read_bytes() for n in names)

    def replay(a: slice, b: slice) -> service_path.OnlineAnswers:
        return service_path.replay(db[a], q[b], encoder_id=enc.identity, backbone=backbone,
                                   preset=settings.default_preset, seed=args.seed,
                                   contrast=np.r_[db_c[a], q_c[b]])

    print(f"backbone {backbone}, preset {settings.default_preset}, map seed {args.seed}")
    for a, b in (halves, halves[::-1]):
        found = replay(a, b)
        c = found.confidence[found.best >= 0]
        if not c.size:
            print(f"never stored (rows {offset + a.start}-{offset + a.stop} learned): no answer (too few "
                  "frames for the localiser's warm-up)")
            continue
        counts = ", ".join(f">= {t}: {int((c >= t).sum())}" for t in args.thresholds)
        print(f"never stored (rows {offset + a.start}-{offset + a.stop} learned, "
              f"{offset + b.start}-{offset + b.stop} driven): {c.size} answers, "
              f"max confidence {c.max():.3f}, mean {c.mean():.3f}; false revisits {counts}")
    for h in halves:
        found = replay(h, h)
        answered = found.best >= 0
        right = answered & (found.best == np.arange(len(found.best)))
        for t in args.thresholds:
            said = answered & reaches(found.confidence, t)
            precision = right[said].mean() if said.any() else float("nan")
            print(f"stored (rows {offset + h.start}-{offset + h.stop}) at {t}: precision {precision:.3f}, "
                  f"recall {said[right].sum() / max(int(right.sum()), 1):.3f} (R@1 {right.mean():.3f})")


"""A flat frame is stored once per place at most (issue 36; docs/design/science.md §11.7, §11.8): a map
knows which rows were flat (`PlaceMap.flat`), and a later learning frame that is flat is a visit of a flat
row its path names (its place's, else a neighbouring place's) whatever its code: a flat frame's code is
noise, and before, on a noisy pass, each made a new place every few passes."""

from __future__ import annotations

import numpy as np
import pytest

from models.localisation import MIN_CONTRAST, Place
from models.pipeline import MapModel, Stream, observe
from tests.models.pipeline.test_core import REVISIT, model, on_a_revisit, route, slow_route

FLAT = 0.0  # a frame's contrast under MIN_CONTRAST (a tunnel, a lens cap)


def learn(m: MapModel, frames: np.ndarray, flat: set[int], codes: dict[int, np.ndarray],
          stream: str = "a", threshold: float | None = None) -> list:
    """One learning stream over `frames` (the frames at indexes `flat` flat); `codes`: the stored rows'."""
    st, steps = Stream(), []
    for i, y in enumerate(frames):
        seq = max(codes, default=0) + 1
        steps.append(observe(m, st, y, learn=True, stream=stream, top_k=3, seq=seq,
                             code_of=codes.__getitem__, threshold=threshold,
                             contrast=FLAT if i in flat else None))
        if steps[-1].visit is None:
            codes[seq] = steps[-1].code
    return steps


def flat_map() -> tuple[MapModel, dict[int, np.ndarray]]:
    """Rows 1-6 of stream `a`, row 3 flat."""
    m, codes = model("none"), {}
    learn(m, route(6), {2}, codes)
    assert m.place_map.flat[1:7].tolist() == [False, False, True, False, False, False]
    return m, codes


@pytest.mark.parametrize(("seq", "contrast", "confidence", "visit"), [
    (3, FLAT, 0.6, 3),     # the path's place's flat row, whatever the frame's code (before: a new row)
    (4, FLAT, 0.6, 3),     # the flat row just before the path's row
    (5, FLAT, 0.6, None),  # two rows away: no neighbour of the path's row is flat
    (3, None, 0.6, None),  # an informative frame: its code decides (unlike row 3's)
    (3, FLAT, 0.3, None),  # no sequence evidence (under `unsure_fraction` of the threshold)
])
def test_a_flat_frame_is_a_visit_of_the_flat_row_its_path_names_whatever_its_code(
        seq: int, contrast: float | None, confidence: float, visit: int | None,
        monkeypatch: pytest.MonkeyPatch) -> None:
    m, codes = flat_map()
    place = Place(seq=seq, confidence=confidence, support=5, informative=contrast is None,
                  place=m.place_map.place_of(seq))
    monkeypatch.setattr(m.place_map, "step", lambda *args, **kwargs: place)
    # (on the path that called the stream's last revisit, §11.8: where the place may be held unsure)
    step = observe(m, on_a_revisit(m, seq), route(1, seed=9)[0], learn=True, stream="b", top_k=3, seq=7,
                   code_of=codes.__getitem__, threshold=REVISIT, contrast=contrast)
    assert step.visit == visit and step.flat is (contrast == FLAT)
    if visit is None:  # a row of its own, flat where the frame was
        assert m.place_map.flat[7] == (contrast == FLAT)


def test_a_flat_frame_never_visits_a_flat_row_of_its_own_short_term_memory(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """The stream that made the flat row a few moves ago: the row is in its short-term memory (§11.6),
    no consolidation target, so its flat frame makes a row (another stream's is a visit of it)."""
    m, codes = flat_map()
    assert 3 in m.place_map.short_term_rows("a").tolist()
    place = Place(seq=3, confidence=0.6, support=5, informative=False, place=m.place_map.place_of(3))
    monkeypatch.setattr(m.place_map, "step", lambda *args, **kwargs: place)
    step = observe(m, on_a_revisit(m), route(1, seed=9)[0], learn=True, stream="a", top_k=3, seq=7,
                   code_of=codes.__getitem__, threshold=REVISIT, contrast=FLAT)
    assert step.visit is None


def test_a_second_laps_tunnel_is_visits_of_the_first_laps_flat_rows() -> None:
    """The localiser's own paths (no evidence from a flat frame: they move on along the links, so the
    confidence the frames before the tunnel gave it decays but stays above `unsure_fraction` of the
    threshold over a short tunnel): a 40-place loop driven twice, places 20-22 a tunnel whose frames'
    codes are new noise each lap. Lap 2's tunnel frames are visits of lap 1's flat rows (before: each a
    new row, its code unlike every stored one)."""
    tunnel = {20, 21, 22}
    for seed in range(3):
        lap = slow_route(40, 1, 0.8, seed)
        rng = np.random.default_rng(seed + 100)
        again = lap + 0.3 * rng.normal(size=lap.shape).astype(np.float32)
        for i in tunnel:  # a flat frame's code is noise: new every lap
            lap[i], again[i] = rng.normal(size=lap.shape[1]), rng.normal(size=lap.shape[1])
        m, codes = model("none"), {}
        learn(m, lap, tunnel, codes, threshold=REVISIT)
        flat_rows = {int(r) for r in np.flatnonzero(m.place_map.flat)}
        assert flat_rows == {i + 1 for i in tunnel}
        second = learn(m, again, tunnel, codes, stream="a", threshold=REVISIT)
        for i in sorted(tunnel):
            assert second[i].place is not None and not second[i].place.informative
            assert second[i].place.confidence >= REVISIT * m.place_map.options.unsure_fraction
            assert second[i].visit in flat_rows, (seed, i, second[i].visit)


def test_a_frames_flat_candidates_keep_the_share_of_evidence_its_contrast_gives(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """§11.7: a flat row shows no scene. Among a frame's candidates it keeps `flat_share` of its evidence:
    all of it from a frame as flat as it (or one whose contrast was not measured), a tenth from a frame
    of contrast 0.3; every other row all of it."""
    m, codes = flat_map()
    real, seen = m.place_map.localiser.step, []

    def spy(state, graph, seqs, scores, own, informative, moved, departed, shares, repeat):
        seen.append((np.asarray(seqs).tolist(), shares))
        return real(state, graph, seqs, scores, own, informative, moved, departed, shares, repeat)

    monkeypatch.setattr(m.place_map.localiser, "step", spy)
    for contrast in (None, MIN_CONTRAST, 0.3):
        observe(m, Stream(), route(6)[2], learn=False, stream="b", top_k=3, code_of=codes.__getitem__,
                contrast=contrast)
    (seqs, unmeasured), (_, as_flat), (_, lit) = seen
    assert 3 in seqs and np.all(unmeasured == 1.0)
    assert np.all(as_flat == 1.0)
    assert lit.tolist() == [pytest.approx(0.1) if s == 3 else 1.0 for s in seqs]

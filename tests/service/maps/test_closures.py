"""The loop-closure exports (service/maps/closures.py, docs/design/service.md §1.2): stamps in seconds as
JSON can carry them, whatever a robot sent as `metadata.stamp`; a g2o edge weighed by its span, in the
vertices' body axes (x ahead, y left, z up), every id it names declared."""

from __future__ import annotations

import json
import math
from types import SimpleNamespace

import numpy as np
import pytest

from models.evaluation.geometry import rotation
from service.maps.closures import G2O_ROTATION_INFORMATION, g2o_lines, render, stamp_seconds
from storage.mapstore import LoopClosure


@pytest.mark.parametrize("stamp", ["NaN", "nan", "1e999", "-inf", "Infinity", float("nan"), float("inf")])
def test_a_stamp_that_is_no_finite_number_is_no_stamp(stamp):
    assert stamp_seconds({"stamp": stamp}) is None


def test_iso_text_without_an_offset_is_utc_whatever_the_servers_zone(monkeypatch):
    import time

    monkeypatch.setenv("TZ", "America/New_York")
    time.tzset()
    try:
        assert stamp_seconds({"stamp": "2026-11-26T12:00:00"}) == 1_795_694_400.0
        assert stamp_seconds({"stamp": "2026-11-26T12:00:00+01:00"}) == 1_795_690_800.0
    finally:
        monkeypatch.delenv("TZ")
        time.tzset()


def test_numbers_and_numeric_text_are_seconds_and_serialise_as_json():
    for stamp, want in ((12.5, 12.5), (7, 7.0), ("1700000000.25", 1_700_000_000.25)):
        got = stamp_seconds({"stamp": stamp})
        assert got == want and math.isfinite(json.loads(json.dumps(got)))
    assert stamp_seconds({"stamp": True}) is None and stamp_seconds({}) is None
    assert stamp_seconds({"stamp": "yesterday"}) is None


def test_a_g2o_edge_s_information_is_divided_by_its_span():
    # docs/design/science.md §11.11: an answer that could have been any of k places is a k times weaker
    # constraint; an entry logged before the span (schema 11) counts as 1.
    def closure(span):
        return LoopClosure(id=1, stream="a", seq=10, observation_id="o10", metadata=None, place_seq=3,
                           place_observation_id="o3", place_stream="a", place_label=None, place_metadata=None,
                           confidence=0.95, support=8, created_at="2026-11-28T00:00:00+00:00",
                           verification={"verified": True, "keyframe_seq": 3,
                                         "rotation": np.eye(3).tolist(), "translation": [1.0, 0.0, 0.0]},
                           span=span, span_seqs=None if span is None else tuple(range(3, 3 + span)))

    def rotation_information(span):
        values = (g2o_lines(closure(span)) or "").splitlines()[-1].split()[3:]
        info = np.zeros((6, 6))
        info[np.triu_indices(6)] = [float(v) for v in values[7:]]
        return np.diag(info)[3:]

    assert np.all(rotation_information(None) == G2O_ROTATION_INFORMATION)
    assert np.all(rotation_information(1) == G2O_ROTATION_INFORMATION)
    assert np.allclose(rotation_information(3), G2O_ROTATION_INFORMATION / 3)


def _closure(cid=1, seq=10, keyframe=3, place_seq=3, R=None, t=None, metadata=None, place_metadata=None,
             verified=True):
    return LoopClosure(id=cid, stream="b", seq=seq, observation_id=f"o{seq}", metadata=metadata,
                       place_seq=place_seq, place_observation_id=f"o{place_seq}", place_stream="a",
                       place_label=None, place_metadata=place_metadata, confidence=0.95, support=8,
                       created_at="2026-11-28T00:00:00+00:00", span=1,
                       verification={"verified": verified, "keyframe_seq": keyframe,
                                     "rotation": (np.eye(3) if R is None else R).tolist(),
                                     "translation": t})


def _se3(values):
    """(4, 4) of g2o's x y z qx qy qz qw."""
    x, y, z, qx, qy, qz, qw = values
    T = np.eye(4)
    T[:3, :3] = [[1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy - qz * qw), 2 * (qx * qz + qy * qw)],
                 [2 * (qx * qy + qz * qw), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz - qx * qw)],
                 [2 * (qx * qz - qy * qw), 2 * (qy * qz + qx * qw), 1 - 2 * (qx * qx + qy * qy)]]
    T[:3, 3] = x, y, z
    return T


def _parse(text):
    """{id: (4, 4)} of the VERTEX lines and [(i, j, (4, 4))] of the EDGE lines, as a g2o reader loads
    them: an edge whose ids are not declared before it is refused (g2o's `load` skips it)."""
    vertices, edges = {}, []
    for line in text.splitlines():
        f = line.split()
        if not f or f[0].startswith("#"):
            continue
        if f[0] == "VERTEX_SE3:QUAT":
            assert int(f[1]) not in vertices, line
            vertices[int(f[1])] = _se3(map(float, f[2:9]))
        else:
            assert f[0] == "EDGE_SE3:QUAT" and len(f) == 3 + 7 + 21, line
            i, j = int(f[1]), int(f[2])
            assert i in vertices and j in vertices, f"edge {i} -> {j} names an undeclared vertex"
            edges.append((i, j, _se3(map(float, f[3:10]))))
    return vertices, edges


def _edge_pose(text):
    """(4, 4) of the measurement of the one EDGE line in `text`."""
    edge, = (line.split() for line in text.splitlines() if line.startswith("EDGE_SE3:QUAT"))
    return _se3(map(float, edge[3:10]))


def _yaw(T):
    return math.degrees(math.atan2(T[1, 0], T[0, 0]))


@pytest.mark.parametrize("turn", [8.0, -8.0, 30.0])
def test_a_camera_turned_by_yaw_is_a_g2o_edge_of_that_yaw_about_z_as_its_vertices(turn):
    """The outside probe's revisit: the robot back at a place with its camera turned `turn` degrees to the
    left (the image is the keyframe's turned about the camera's vertical, optical y: X_query = R
    X_keyframe, R = Ry(turn), as models.evaluation.geometry.warp renders it). The vertices are z-up
    body poses, so the edge must be a rotation of `turn` degrees about z, the difference of their
    yaws: before, it was the optical relative pose, `turn` about y, which a back end reading the file in
    its vertices' frame took for pitch (0.3 degrees of yaw for 8)."""
    yaw = math.radians(turn)
    c = _closure(R=rotation(turn, 0, 0), metadata={"pose": {"x": 10.0, "y": 0.0, "yaw": yaw}},
                 place_metadata={"pose": {"x": 10.0, "y": 0.0, "yaw": 0.0}})
    text = g2o_lines(c)
    Z = _edge_pose(text)
    axis_angle = math.degrees(math.acos(min(1.0, (np.trace(Z[:3, :3]) - 1) / 2)))
    assert _yaw(Z) == pytest.approx(turn) and axis_angle == pytest.approx(abs(turn))
    assert np.allclose(Z[:3, :3] @ [0, 0, 1], [0, 0, 1])  # about z: no pitch, no roll
    # the edge and the vertices agree: keyframe's pose . edge = the frame's pose
    vertices, ((i, j, _),) = _parse(text)
    assert np.allclose(vertices[i] @ Z, vertices[j], atol=1e-9)


def test_a_g2o_edge_s_translation_is_in_the_vertices_axes_too():
    """The query camera 1 m to the keyframe's left (optical: -x; X_query = X_keyframe + (1, 0, 0)) is +y in
    body axes; 1 m ahead (optical +z) is +x."""
    for t, want in (([1.0, 0.0, 0.0], [0.0, 1.0, 0.0]), ([0.0, 0.0, -1.0], [1.0, 0.0, 0.0]),
                    ([0.0, 1.0, 0.0], [0.0, 0.0, 1.0])):  # and 1 m up (optical -y)
        Z = _edge_pose(g2o_lines(_closure(t=t)))
        assert np.allclose(Z[:3, 3], want), (t, Z[:3, 3])
    # unobservable: zero, with zero information
    assert np.allclose(_edge_pose(g2o_lines(_closure(t=None)))[:3, 3], 0.0)


class _Store:
    """What `render` reads of a MapStore: the log, the retracted ids, rows' metadata."""

    def __init__(self, entries, rows, retracted=()):
        self.entries, self.rows, self._retracted = entries, rows, set(retracted)

    def closures(self, after, limit):
        return [c for c in self.entries if c.id > after][:limit]

    def retracted(self):
        return self._retracted

    def get_many(self, seqs):
        return {s: SimpleNamespace(metadata=self.rows[s]) for s in seqs if s in self.rows}


def test_every_id_a_g2o_edge_names_is_a_declared_vertex_once_or_the_file_says_why():
    """The export loads on its own (g2o's `load`, GTSAM's readG2o): each vertex an edge names is declared
    before its first edge, once, at its posted pose; the keyframe may be a route neighbour of the place
    (its pose read from its row); a vertex with no pose is declared at a placeholder after `# NOPOSE id`.
    Before, rows were never declared, only visits."""
    pose = {"pose": {"x": 1.0, "y": 2.0, "yaw": 0.5}}
    rows = {5: {"pose": {"x": 7.0, "y": -1.0, "yaw": 0.25}}, 6: None}
    entries = [
        _closure(cid=1, seq=10, keyframe=3, place_seq=3, metadata=pose, place_metadata=pose),
        _closure(cid=2, seq=11, keyframe=5, place_seq=4, metadata={"stamp": 1.0}, place_metadata=pose),
        _closure(cid=3, seq=12, keyframe=3, place_seq=3, metadata=pose, place_metadata=pose),  # 3 again
        _closure(cid=4, seq=13, keyframe=6, place_seq=6, metadata=pose, place_metadata=None),  # retracted
        _closure(cid=5, seq=14, keyframe=8, place_seq=4, metadata=pose, place_metadata=pose),  # row gone
        _closure(cid=6, seq=15, keyframe=4, place_seq=4, metadata=pose, verified=False),  # no edge
    ]
    with render(_Store(entries, rows, retracted={4}), "g2o") as f:
        text = f.read().decode()
    vertices, edges = _parse(text)
    assert [(i, j) for i, j, _ in edges] == [(3, 10), (5, 11), (3, 12), (8, 14)]
    assert sorted(vertices) == [3, 5, 8, 10, 11, 12, 14]  # not 6, 13 (retracted) nor 4, 15 (no edge)
    assert np.allclose(vertices[5][:2, 3], [7.0, -1.0]) and _yaw(vertices[5]) == pytest.approx(14.3239, 1e-4)
    assert np.allclose(vertices[3][:2, 3], [1.0, 2.0]) and _yaw(vertices[3]) == pytest.approx(28.6479, 1e-4)
    comments = [line for line in text.splitlines() if line.startswith("#")]
    assert comments == ["# NOPOSE 11", "# RETRACTED 6 13 closure 4", "# NOPOSE 8"]
    assert np.allclose(vertices[8], np.eye(4)) and np.allclose(vertices[11], np.eye(4))

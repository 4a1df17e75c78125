"""Client tests of server features that are being built (issue 15): the sequence-level `place` and
`PATCH` of a map. They fail until the service has them; once it does, they belong with the others
(test_client.py, test_openapi_contract.py; the `PENDING_CONTRACT` rows of conftest.py into `CONTRACT`).
"""

from __future__ import annotations

from cortexloc_client import Client, models


def test_the_map_patch_reply_matches_the_servers_schema(openapi, pending_contract) -> None:
    assert pending_contract(openapi) == []


def _drive_a_loop(client: Client, map_id: str, make_frame, **kw) -> dict[int, int]:
    seqs = {}
    for place in range(5):
        pose = {"x": float(place), "y": 0.0, "yaw": 0.0, "frame_id": "map"}
        answer = client.observe(map_id, make_frame(place), label=f"place {place}",
                                metadata={"stamp": 100.0 + place, "pose": pose}, **kw)
        seqs[place] = answer.seq
    client.reset_stream(map_id, "default")
    return seqs


def test_a_revisit_names_its_place(client: Client, tiny_map: str, make_frame) -> None:
    seqs = _drive_a_loop(client, tiny_map, make_frame)
    for place in range(3):
        answer = client.observe(tiny_map, make_frame(place), learn=False)
    place = answer.place
    assert isinstance(place, models.Place)
    assert place.seq == seqs[2] and place.label == "place 2" and place.stream == "default"
    assert 0.0 <= place.confidence <= 1.0 and place.revisit is True and (place.support or 0) >= 1
    assert place.metadata is not None and place.metadata.pose is not None and place.metadata.pose.x == 2.0


def test_the_revisit_threshold_can_be_changed(client: Client, tiny_map: str) -> None:
    changed = client.update_map(tiny_map, revisit_threshold=0.7)
    assert changed.revisit_threshold == 0.7
    assert client.get_map(tiny_map).revisit_threshold == 0.7

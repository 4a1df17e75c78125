"""The real thing: `cortexloc serve` in a subprocess on a free loopback port, a robot driving a loop."""

from __future__ import annotations


def test_a_looping_route_finds_its_revisit_first(server, http, make_frame):
    call, frame = http, make_frame
    obs = f"{server}/v1/maps/default/observations?learn=true&top_k=3"
    seqs = {}
    for place in range(6):
        status, body = call(obs, frame(place))
        assert status == 200, body
        seqs[place] = body["seq"]
        # no AlexNet weights installed: the default backbone is EfficientNet-Lite0's stage 5, pretrained
        versions = body["versions"]
        assert (versions["backbone"], versions["weights"]) == ("efficientnet-lite0-s5", "pretrained")
    for place in range(3):  # the robot drives the loop again
        status, body = call(obs, frame(place))
        assert status == 200, body
    assert body["matches"][0]["seq"] == seqs[2]
    assert body["matches"][0]["score"] > 0.9
    status, problem = call(obs, b"not an image")
    assert status == 415 and problem["type"] == "urn:cortexloc:problem:unsupported-media-type"

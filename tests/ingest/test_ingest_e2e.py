"""`cortexloc ingest --url` (a subprocess) against a real `cortexloc serve` (another): a folder and a ROS 2
bag give the answers of posting the same frames one by one."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from typing import Any

from tests.e2e.conftest import call
from tests.ingest.data import ROUTE, TOPICS, comparable, write_folder, write_ros2_bag

#: A small map (tests/conftest.py's tiny preset, as overrides): the real code paths without 266 MB maps.
SMALL = {"seed": 3, "slsbh": {"k": 64},
         "tm": {"columnDimensions": 128, "maxSegmentsPerCell": 8, "maxSynapsesPerSegment": 16,
                "maxNewSynapseCount": 8, "activationThreshold": 4, "minThreshold": 2}}


def _create(base: str, map_id: str) -> None:
    status, body = call(f"{base}/v1/maps", json.dumps({"map_id": map_id, **SMALL}).encode(),
                        "application/json")
    assert status == 201, body


def _by_hand(base: str, map_id: str, bodies: list[bytes]) -> list[dict[str, Any]]:
    _create(base, map_id)
    out = []
    for body in bodies:
        ctype = "image/png" if body.startswith(b"\x89PNG") else "image/jpeg"
        status, answer = call(f"{base}/v1/maps/{map_id}/observations?stream=s", body, ctype)
        assert status == 200, answer
        out.append(answer)
    return out


def _ingest(base: str, source: Path, map_id: str, *args: str) -> tuple[list[dict[str, Any]], str]:
    _create(base, map_id)
    p = subprocess.run([sys.executable, "-m", "service.cli", "ingest", str(source), "--map", map_id,
                        "--stream", "s", "--url", base, "--json", *args],
                       capture_output=True, text=True, timeout=300, cwd=Path(__file__).resolve().parents[2])
    assert p.returncode == 0, p.stderr
    return [json.loads(line) for line in p.stdout.splitlines()], p.stderr


def test_a_folder_ingested_over_http_answers_as_posting_it_by_hand(served, tmp_path):
    bodies = write_folder(tmp_path / "frames")
    lines, log = _ingest(served.base, tmp_path / "frames", "ingested")
    want = _by_hand(served.base, "by-hand", bodies)
    assert [comparable(x["answer"]) for x in lines] == [comparable(a) for a in want]
    assert f"posted {len(ROUTE)}/{len(ROUTE)} frames, learned {len(ROUTE)}" in log


def test_a_ros2_bag_ingested_over_http_answers_as_posting_its_frames_by_hand(served, tmp_path):
    bag = write_ros2_bag(tmp_path / "bag", topics=["/cam/rgb", "/cam/compressed"])
    for topic, every in (("/cam/rgb", 2), ("/cam/compressed", 1)):
        name = topic.rsplit("/", 1)[1]
        lines, log = _ingest(served.base, bag, f"{name}-ingested", "--topic", topic, "--every", str(every))
        frames = list(range(0, len(ROUTE), every))
        assert [x["frame"] for x in lines] == frames
        want = _by_hand(served.base, f"{name}-by-hand", [TOPICS[topic][1](ROUTE[i]) for i in frames])
        assert [comparable(x["answer"]) for x in lines] == [comparable(a) for a in want], topic
        assert f"topic {topic}" in log and "errors 0" in log

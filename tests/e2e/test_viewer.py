"""The map viewer at /ui in a real headless browser (Debian's `chromium`): what a person sees.

Two services: a real `cortexloc serve` with frames posted (the maps, the recent answers, their order
and columns), and a stub API that answers with the fields other parts of the service add (a sequence
`place`, per-observation `metadata` poses, thumbnails, the stored rows), so the page is checked with them
present as well as absent. Each test saves the browser's screenshot under `out/` for a person to look at.
"""

from __future__ import annotations

import json
import math
import shutil
import subprocess
import threading
from collections.abc import Iterator
from html.parser import HTMLParser
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from urllib.parse import parse_qs, urlparse

import cv2
import numpy as np
import pytest

from service.ui import STATIC_DIR

OUT = Path(__file__).resolve().parents[2] / "out"


@pytest.fixture
def chromium() -> str:
    """The browser's path; the test skips without one (asked first, before any server starts)."""
    found = shutil.which("chromium") or shutil.which("chromium-browser")
    if found is None:
        pytest.skip("no headless browser: install Debian's `chromium` (.ci/run does)")
    return found


def browse(chromium: str, url: str, profile: Path, screenshot: Path | None = None) -> str:
    """The page's DOM after its scripts ran (virtual time: polls included), and optionally a screenshot."""
    base = [chromium, "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
            "--disable-background-networking", "--disable-component-update", "--disable-sync",
            f"--user-data-dir={profile}", "--virtual-time-budget=8000"]
    dom = subprocess.run([*base, "--dump-dom", url], capture_output=True, text=True, timeout=120, check=True)
    if screenshot is not None:
        screenshot.parent.mkdir(parents=True, exist_ok=True)
        screenshot.unlink(missing_ok=True)
        subprocess.run([*base, f"--screenshot={screenshot}", "--window-size=1280,1000", url],
                       capture_output=True, timeout=120, check=True)
        assert screenshot.stat().st_size > 10_000
    return dom.stdout


class Rows(HTMLParser):
    """The rows of one table (by id) of a DOM dump: each row's attributes and its cells' text."""

    def __init__(self, html: str, table_id: str) -> None:
        super().__init__()
        self.table_id, self.depth, self.in_body = table_id, 0, False
        self.rows: list[tuple[dict[str, str | None], list[str]]] = []
        self.header: list[str] = []
        self._cell: list[str] | None = None
        self._head = False
        self.feed(html)

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        a = dict(attrs)
        if tag == "table":
            self.depth += 1 if (self.depth or a.get("id") == self.table_id) else 0
        elif self.depth and tag in ("thead", "tbody"):
            self._head = tag == "thead"
        elif self.depth and tag == "tr" and not self._head:
            self.rows.append((a, []))
        elif self.depth and tag in ("td", "th"):
            self._cell = []
        elif self.depth and tag == "img" and self._cell is not None:
            self._cell.append("[img]")

    def handle_endtag(self, tag: str) -> None:
        if tag == "table" and self.depth:
            self.depth -= 1
        elif self.depth and tag in ("td", "th") and self._cell is not None:
            value = " ".join("".join(self._cell).split())
            if tag == "th" and self._head:
                self.header.append(value)
            elif self.rows:
                self.rows[-1][1].append(value)
            self._cell = None

    def handle_data(self, data: str) -> None:
        if self._cell is not None:
            self._cell.append(data)


def by_header(rows: Rows) -> list[dict[str, str]]:
    """Each data row as {column: text}; the recent table's two header rows name the last columns."""
    names = rows.header[-len(rows.rows[0][1]):] if rows.rows else []
    out = []
    for _, cells in rows.rows:
        row: dict[str, str] = {}
        for name, cell in zip(names, cells, strict=True):
            row[name if name not in row else f"match {name}"] = cell
        out.append(row)
    return out


# ------------------------------------------------------------------------------- a real service


def test_the_viewer_shows_a_running_services_map_and_its_answers_in_order(chromium, server, http,
                                                                       make_frame, tmp_path):
    assert http(f"{server}/v1/maps", json.dumps({"map_id": "yard"}).encode(), "application/json")[0] == 201
    sent = []
    for place in range(5):  # a mapping run, then a revisit of places 1-3 without learning
        status, body = http(f"{server}/v1/maps/yard/observations?learn=true&stream=robot1&label=p{place}",
                            make_frame(place))
        assert status == 200
        sent.append(body)
    for place in (1, 2, 3):
        status, body = http(f"{server}/v1/maps/yard/observations?learn=false&stream=robot1",
                            make_frame(place))
        assert status == 200
        sent.append(body)

    dom = browse(chromium, f"{server}/ui/?map=yard", tmp_path / "profile", OUT / "viewer.png")

    maps = {a["data-map-id"]: cells for a, cells in Rows(dom, "maps").rows}
    assert set(maps) == {"default", "yard"}
    header = Rows(dom, "maps").header
    assert maps["yard"][header.index("observations")] == "5"
    assert maps["yard"][header.index("state")] == "ready"
    assert maps["yard"][header.index("preset")] == "cortexloc-default"
    assert maps["yard"][header.index("TM")].endswith("MiB")  # sizes from /memory

    recent = Rows(dom, "recent")
    assert {"time", "stream", "mode", "seq", "place", "confidence", "revisit", "match", "score", "query",
            "matched"} <= set(recent.header)
    rows = by_header(recent)
    assert len(rows) == len(sent)
    # newest first: the three localisations, then the learned frames from the last to the first
    assert [r["mode"] for r in rows] == ["localised"] * 3 + ["learned"] * 5
    assert [r["seq"] for r in rows[3:]] == [str(b["seq"]) for b in reversed(sent[:5])]
    for row, body in zip(rows, reversed(sent), strict=True):
        assert row["stream"] == "robot1"
        top = body["matches"][0] if body["matches"] else None
        assert row["match"] == (str(top["seq"]) if top else "—")
        assert row["score"] == (f"{top['score']:.3f}" if top else "—")
        if "place" not in body:  # a service without the sequence place: shown as absent
            assert row["place"] == row["confidence"] == row["revisit"] == "—"
    assert "trajectory-panel" in dom and 'class="panel empty"' in dom  # no poses: the panel says why
    assert dom.count('class="match-point"') == sum(1 for b in sent if b["matches"])


def test_the_viewer_asks_for_the_key_when_reads_need_one(chromium, server_proc, tmp_path):
    server_proc.extra_env = {"CORTEXLOC_API_KEY": "k3y", "CORTEXLOC_API_KEY_READS": "true"}
    base = server_proc.start()
    dom = browse(chromium, f"{base}/ui/", tmp_path / "profile")
    assert 'data-state="error"' in dom and "the service needs the API key for reads" in dom
    assert 'id="api-key"' in dom  # where the person types it


# ---------------------------------------------------------------------- a service with every field


def _thumb(seq: int) -> bytes:
    img = np.zeros((48, 64, 3), np.uint8)
    img[:] = ((seq * 37) % 200 + 40, (seq * 11) % 200 + 40, 120)
    cv2.putText(img, str(seq), (6, 34), cv2.FONT_HERSHEY_SIMPLEX, 0.9, (255, 255, 255), 2)
    return cv2.imencode(".jpg", img)[1].tobytes()


def _stub_data() -> dict:
    """A loop driven once while mapping (seqs 1-24 on a circle), then localised along its first part."""
    def pose(t: float) -> dict:
        return {"x": round(10 * math.cos(t), 3), "y": round(6 * math.sin(t), 3), "yaw": t + math.pi / 2,
                "frame_id": "map"}

    rows, answers = [], []
    for seq in range(1, 25):
        meta = {"stamp": 1700000000.0 + seq, "pose": pose(2 * math.pi * (seq - 1) / 24)}
        rows.append({"seq": seq, "stream": "robot1", "label": f"p{seq}", "metadata": meta})
        answers.append({"received_at": f"2026-01-01T10:00:{seq:02d}.000+00:00", "reply": {
            "stream": "robot1", "learned": True, "seq": seq, "observation_id": f"o{seq}", "metadata": meta,
            "sequence": {"step": seq - 1}, "place": None,
            "matches": [{"rank": 1, "seq": max(seq - 1, 1), "label": f"p{max(seq - 1, 1)}", "score": 0.55,
                         "metadata": rows[max(seq - 2, 0)]["metadata"]}] if seq > 1 else []}})
    for i, (target, conf, revisit) in enumerate([(3, 0.31, False), (4, 0.62, True), (5, 0.81, True),
                                                 (6, 0.9, True), (7, 0.93, True), (8, 0.95, True)]):
        near = pose(2 * math.pi * (target - 1) / 24 + 0.05)  # the second lap runs a little wider
        meta = {"stamp": 1700000100.0 + i, "pose": {**near, "x": near["x"] * 1.15, "y": near["y"] * 1.25}}
        place = {"seq": target, "observation_id": f"o{target}", "stream": "robot1", "label": f"p{target}",
                 "confidence": conf, "revisit": revisit, "support": 3 + i}
        answers.append({"received_at": f"2026-01-01T10:01:{i:02d}.000+00:00", "reply": {
            "stream": "robot1", "learned": False, "seq": None, "observation_id": None, "metadata": meta,
            "sequence": {"step": i}, "place": place,
            "matches": [{"rank": 1, "seq": target, "label": f"p{target}", "score": conf}]}})
    maps = [{"map_id": "yard", "state": "ready", "state_reason": None, "preset": "cortexloc-default",
             "backbone": "alexnet", "encoder": "alexnet-conv3/imagenet:crop", "observations": 24,
             "last_seq": 24, "streams": ["robot1"], "thumbnails": True}]
    memory = {"tm": {"allocated_bytes": 65_536_000}, "index": {"bytes": 38_000},
              "projection_bytes": 265_000_000, "storage": {"db_bytes": 120_000, "wal_bytes": 4_096}}
    return {"rows": rows, "answers": answers, "maps": maps, "memory": memory}


@pytest.fixture
def stub_service() -> Iterator[str]:
    """The viewer's files and an API that answers with every optional field, on a free loopback port."""
    data = _stub_data()

    class Handler(BaseHTTPRequestHandler):
        def log_message(self, *args) -> None:  # quiet
            pass

        def _send(self, status: int, body: bytes, ctype: str) -> None:
            self.send_response(status)
            self.send_header("Content-Type", ctype)
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            self.wfile.write(body)

        def do_GET(self) -> None:
            url = urlparse(self.path)
            q = parse_qs(url.query)
            parts = url.path.strip("/").split("/")
            if url.path.startswith("/ui/"):
                f = STATIC_DIR / (url.path[4:] or "index.html")
                types = {".html": "text/html", ".css": "text/css", ".js": "text/javascript"}
                if f.is_file():
                    return self._send(200, f.read_bytes(), types[f.suffix])
                return self._send(404, b"{}", "application/json")
            if parts == ["v1", "maps"]:
                return self._send(200, json.dumps({"maps": data["maps"]}).encode(), "application/json")
            if parts[:3] == ["v1", "maps", "yard"]:
                rest = parts[3:]
                if rest == ["memory"]:
                    return self._send(200, json.dumps(data["memory"]).encode(), "application/json")
                if rest == ["recent"]:
                    body = {"map_id": "yard", "capacity": 256, "answers": data["answers"]}
                    return self._send(200, json.dumps(body).encode(), "application/json")
                if rest == ["observations"]:
                    after, limit = int(q["after_seq"][0]), int(q["limit"][0])
                    page = [r for r in data["rows"] if r["seq"] > after][:limit]
                    return self._send(200, json.dumps({"observations": page}).encode(), "application/json")
                if len(rest) == 3 and rest[0] == "observations" and rest[2] == "thumbnail":
                    return self._send(200, _thumb(int(rest[1])), "image/jpeg")
            return self._send(404, b'{"type": "urn:cortexloc:problem:not-found"}', "application/problem+json")

    httpd = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    thread = threading.Thread(target=httpd.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{httpd.server_address[1]}"
    finally:
        httpd.shutdown()
        httpd.server_close()


def test_the_viewer_shows_places_poses_and_thumbnails_when_the_service_gives_them(chromium, stub_service,
                                                                                 tmp_path):
    dom = browse(chromium, f"{stub_service}/ui/?map=yard", tmp_path / "profile", OUT / "viewer-full.png")

    maps = Rows(dom, "maps")
    assert maps.rows[0][1][maps.header.index("backbone")] == "alexnet"
    rows = by_header(Rows(dom, "recent"))
    newest = rows[0]  # the last localisation: place 8, confident, a revisit, with both thumbnails
    assert (newest["mode"], newest["place"], newest["label"], newest["revisit"], newest["support"]) == \
        ("localised", "8", "p8", "revisit", "8")
    assert newest["confidence"] == "0.95"
    assert (newest["query"], newest["matched"]) == ("—", "[img]")  # a localisation stores no image
    first_localisation = rows[5]
    assert (first_localisation["place"], first_localisation["revisit"]) == ("3", "new")
    learned = rows[6]
    assert (learned["mode"], learned["seq"], learned["query"], learned["matched"]) == \
        ("learned", "24", "[img]", "[img]")
    assert 'class="panel empty"' not in dom  # poses exist: the trajectory is drawn
    assert dom.count("<polyline") == 1  # one stream's path
    assert "24 stored pose(s) in 1 stream(s); 5 link(s) from recent answers, 5 revisit(s)" in dom

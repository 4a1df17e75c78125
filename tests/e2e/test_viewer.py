"""The map viewer at /ui in a real headless browser (Debian's `chromium`) against a real `cortexloc serve`:
what a person sees (docs/design/service.md §1.7).

A robot maps a loop with poses on a map that keeps thumbnails, then drives its first part again,
localising; the page must show the map with its exact revisit threshold, every answer in order with its
sequence place (— while it has none; "below threshold" when it is not a revisit), the query frames'
thumbnails (localised ones from the recent ring) beside their places', the trajectory with the revisit
links and the sequence-match picture, each counted against the replies the service sent. The screenshot
is saved as `out/viewer.png` for a person to look at.
"""

from __future__ import annotations

import json
import math
import re
import shutil
import subprocess
from html.parser import HTMLParser
from pathlib import Path
from urllib.parse import quote

import pytest

from models.localisation import default_conf

OUT = Path(__file__).resolve().parents[2] / "out"
NONE = "—"
SPAN_MAX = default_conf["span_max"]  # the viewer's map takes the default (docs/design/science.md §11.11)


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
        subprocess.run([*base, f"--screenshot={screenshot}", "--window-size=1280,1100", url],
                       capture_output=True, timeout=120, check=True)
        assert screenshot.stat().st_size > 10_000
    return dom.stdout


class Table(HTMLParser):
    """One table (by id) of a DOM dump: each body row as {column: text}, a column named by its group
    header where it has one ("sequence place/label"); an <img> cell reads "[img]"."""

    def __init__(self, html: str, table_id: str) -> None:
        super().__init__()
        self.table_id, self.inside, self.part = table_id, False, ""
        self.head: list[list[tuple[str, int]]] = []
        self.body: list[list[str]] = []
        self._cell: list[str] | None = None
        self._span = 1
        self.feed(html)

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        a = dict(attrs)
        if tag == "table":
            self.inside = a.get("id") == self.table_id
        elif self.inside and tag in ("thead", "tbody"):
            self.part = tag
        elif self.inside and tag == "tr":
            (self.head if self.part == "thead" else self.body).append([])
        elif self.inside and tag in ("td", "th"):
            self._cell, self._span = [], int(a.get("colspan") or 1)
        elif self.inside and tag == "img" and self._cell is not None:
            self._cell.append("[img]")

    def handle_endtag(self, tag: str) -> None:
        if tag == "table":
            self.inside = False
        elif self.inside and tag in ("td", "th") and self._cell is not None:
            value = " ".join("".join(self._cell).split())
            rows = self.head if self.part == "thead" else self.body
            rows[-1].append((value, self._span) if self.part == "thead" else value)
            self._cell = None

    def handle_data(self, data: str) -> None:
        if self._cell is not None:
            self._cell.append(data)

    @property
    def columns(self) -> list[str]:
        names = [n for n, _ in self.head[-1]]
        if len(self.head) == 2:
            groups = [g for g, span in self.head[0] for _ in range(span)]
            names = [f"{g}/{n}" if g else n for g, n in zip(groups, names, strict=True)]
        return names

    @property
    def rows(self) -> list[dict[str, str]]:
        return [dict(zip(self.columns, cells, strict=True)) for cells in self.body]


def svg_elements(dom: str, svg_id: str, cls: str) -> list[str]:
    """The tags of class `cls` inside the <svg id=svg_id> of a DOM dump."""
    inner = re.search(rf'<svg id="{svg_id}".*?</svg>', dom, re.S)
    assert inner is not None, svg_id
    return re.findall(rf'<\w+ [^>]*class="{cls}"[^>]*>', inner.group(0))


def post(http, base: str, map_id: str, frame: bytes, **query) -> dict:
    meta = query.pop("metadata", None)
    q = "&".join(f"{k}={v}" for k, v in query.items())
    if meta is not None:
        q += "&metadata=" + quote(json.dumps(meta, separators=(",", ":")))
    status, body = http(f"{base}/v1/maps/{map_id}/observations?{q}", frame)
    assert status == 200, body
    return body


def loop_pose(i: int, radius: float) -> dict:
    """The i-th of 12 poses on a loop around the origin, heading along it (the map frame, metres)."""
    t = 2 * math.pi * i / 12
    return {"x": round(radius * math.cos(t), 3), "y": round(radius * math.sin(t), 3),
            "yaw": round(t + math.pi / 2, 3), "frame_id": "map"}


def _bytes(v: int) -> str:
    """The page's size spelling (format.js `bytes`)."""
    units, f, i = ["B", "KiB", "MiB", "GiB", "TiB"], float(v), 0
    while f >= 1024 and i < len(units) - 1:
        f, i = f / 1024, i + 1
    return f"{f:.{0 if i == 0 else 1}f} {units[i]}"


def test_the_viewer_shows_a_mapped_loop_its_revisits_poses_and_thumbnails(chromium, server, http,
                                                                        make_frame, tmp_path):
    # A threshold that two decimals would misquote ("0.50"): the page shows it as it is.
    threshold = 0.9549
    body = {"map_id": "yard", "thumbnails": True, "revisit_threshold": threshold}
    assert http(f"{server}/v1/maps", json.dumps(body).encode(), "application/json")[0] == 201
    sent = [post(http, server, "yard", make_frame(i), learn="true", stream="robot1", label=f"p{i}",
                 metadata={"stamp": 100.0 + i, "pose": loop_pose(i, 10.0)}) for i in range(12)]
    # a second robot drives the loop's first part again, a little wider, localising: past its warm-up each
    # answer has a place, a new one until the path behind it is long enough (another stream: a loop of 12
    # frames is within the own-trail exclusion of the robot that drove it, docs/design/science.md §11.6)
    sent += [post(http, server, "yard", make_frame(i), learn="false", stream="robot2",
                  metadata={"stamp": 200.0 + i, "pose": loop_pose(i, 12.0)}) for i in range(8)]
    places = [b["place"] for b in sent]
    revisits = [b for b in sent if b["place"] and b["place"]["revisit"]]
    assert None in places and revisits and any(p and not p["revisit"] for p in places)  # every kind shown
    _, the_map = http(f"{server}/v1/maps/yard")
    _, memory = http(f"{server}/v1/maps/yard/memory")

    dom = browse(chromium, f"{server}/ui/?map=yard", tmp_path / "profile", OUT / "viewer.png")
    assert f"{len(sent)} recent answer(s)" in dom

    # the maps, the selected one with its backbone, revisit threshold, count and sizes
    maps = {r["map"]: r for r in Table(dom, "maps").rows}
    assert set(maps) == {"default", "yard"}
    yard = maps["yard"]
    assert (yard["state"], yard["backbone"], yard["observations"], yard["streams"]) == \
        ("ready", the_map["backbone"], "12", "2")
    assert yard["revisit at"] == "0.9549"
    assert (yard["TM"], yard["index"], yard["projection"]) == (
        _bytes(memory["tm"]["allocated_bytes"]), _bytes(memory["index"]["bytes"]),
        _bytes(memory["projection_bytes"]))
    assert re.fullmatch(r"\d+(\.\d)? (B|KiB|MiB)", yard["store"])

    # every answer, newest first, with its place where the reply had one and — where it was null
    rows = Table(dom, "recent").rows
    assert len(rows) == len(sent)
    for row, body in zip(rows, reversed(sent), strict=True):
        place, top = body["place"], body["matches"][0] if body["matches"] else None
        assert (row["stream"], row["mode"]) == (body["stream"], "learned" if body["learned"] else "localised")
        assert row["seq"] == (str(body["seq"]) if body["learned"] else NONE)
        got = [row[f"sequence place/{c}"] for c in ("place", "label", "revisit", "support", "span")]
        # confident, but more places than the map's span_max score near the best (science.md §11.11)
        wide = bool(place) and not place["revisit"] and place["span"] > SPAN_MAX \
            and place["confidence"] >= threshold
        # confident, but the path fell behind the robot (science.md §11.13)
        lagging = bool(place) and not place["revisit"] and place["lagging"] \
            and place["confidence"] >= threshold
        assert got == ([str(place["seq"]), place["label"] or NONE,
                        "low information" if place["low_information"] else "wide span" if wide
                        else "lagging" if lagging else "revisit" if place["revisit"] else "below threshold",
                        str(place["support"]),
                        str(place["span"])]
                       if place else [NONE] * 5)
        if place:  # two decimals at least, as many more as keep it on its side of the threshold
            shown = row["sequence place/confidence"]
            assert re.fullmatch(r"\d\.\d{2,}", shown) and abs(float(shown) - place["confidence"]) < 0.005
            assert (float(shown) >= threshold) is (place["revisit"] or wide or lagging), (shown, place)
        assert row["top frame match/match"] == (str(top["seq"]) if top else NONE)
        assert row["top frame match/score"] == (f"{top['score']:.3f}" if top else NONE)
        # the thumbnails: the query frame's (localised ones too: the recent ring keeps it), the place's
        assert row["thumbnails/query"] == "[img]"
        assert row["thumbnails/place"] == ("[img]" if place else NONE)
    thumbs = re.findall(r'<img [^>]*data-thumb="([^"]+)"', dom)
    _, recent = http(f"{server}/v1/maps/yard/recent?limit={len(sent)}")
    queries = {f"/v1/maps/yard/recent/{a['answer_id']}/thumbnail" for a in recent["answers"]}
    assert all(a["has_thumbnail"] for a in recent["answers"]) and len(queries) == len(sent)
    assert set(thumbs) == queries | {f"/v1/maps/yard/observations/{p['seq']}/thumbnail" for p in places if p}
    assert "Below threshold: the map's best place" in dom and "(0.9549)" in dom
    assert all(src.startswith("blob:") for src in re.findall(r'<img [^>]*src="([^"]+)"', dom))  # loaded

    # the trajectory: the 12 stored poses of one stream, the 8 localised poses, a link per revisit
    assert len(svg_elements(dom, "trajectory", "stored-pose")) == 12
    assert len(svg_elements(dom, "trajectory", "query-pose")) == 8
    assert len(svg_elements(dom, "trajectory", "revisit-link")) == len(revisits)
    assert (f"12 stored pose(s) in 1 stream(s) · 8 localised pose(s) · {len(revisits)} revisit link(s)"
            in dom)

    # the sequence-match picture (all streams): a square per learned answer at its seq, a dot per
    # answer with a place at the place's seq, in the answers' order, a ring per revisit
    assert len(svg_elements(dom, "seqmatch", "learned-point")) == 12
    dots = svg_elements(dom, "seqmatch", "match-point")
    assert [re.search(r'data-seq="(\d+)"', d).group(1) for d in dots] == [str(p["seq"]) for p in places if p]
    assert len(svg_elements(dom, "seqmatch", "revisit-ring")) == len(revisits)


def test_the_viewer_shows_a_map_without_thumbnails_or_poses_as_such(chromium, server, http, make_frame,
                                                                    tmp_path):
    sent = [post(http, server, "default", make_frame(i), learn="true", stream="robot1") for i in range(2)]
    sent.append(post(http, server, "default", make_frame(0), learn="false", stream="robot2"))
    assert not any(b["place"] or b["metadata"] for b in sent)  # all in their warm-up, nothing posed
    dom = browse(chromium, f"{server}/ui/?map=default", tmp_path / "profile")
    rows = Table(dom, "recent").rows
    assert [(r["mode"], r["seq"]) for r in rows] == [("localised", NONE), ("learned", "2"), ("learned", "1")]
    for row in rows:
        assert row["sequence place/place"] == row["thumbnails/query"] == row["thumbnails/place"] == NONE
    assert len(svg_elements(dom, "seqmatch", "learned-point")) == 2
    assert not svg_elements(dom, "seqmatch", "match-point")
    assert len(svg_elements(dom, "seqmatch", "no-place")) == 1  # the localised answer without a place
    assert "Thumbnails are off for this map." in dom and "the stream is in its warm-up" in dom
    assert 'class="panel empty"' in dom and "No poses yet" in dom  # the trajectory panel says why


def test_the_viewer_asks_for_the_key_when_reads_need_one(chromium, server_proc, tmp_path):
    server_proc.extra_env = {"CORTEXLOC_API_KEY": "k3y", "CORTEXLOC_API_KEY_READS": "true"}
    base = server_proc.start()
    dom = browse(chromium, f"{base}/ui/", tmp_path / "profile")
    assert 'data-state="error"' in dom and "the service needs the API key for reads" in dom
    assert 'id="api-key"' in dom  # where the person types it


def csp_violations(chromium: str, url: str, profile: Path) -> tuple[str, list[str]]:
    """The page's DOM after its scripts ran, and the policy violations the browser logged."""
    args = [chromium, "--headless", "--no-sandbox", "--disable-gpu", "--no-first-run",
            "--disable-background-networking", "--disable-component-update", "--disable-sync",
            f"--user-data-dir={profile}", "--virtual-time-budget=8000", "--enable-logging=stderr", "--v=0",
            "--dump-dom", url]
    done = subprocess.run(args, capture_output=True, text=True, timeout=120, check=True)
    return done.stdout, [line for line in done.stderr.splitlines() if "Content Security Policy" in line]


def test_the_pages_work_under_their_content_security_policy(chromium, server, http, make_frame, tmp_path):
    """Issue 19 item 6 (docs/design/service.md §1.9): /ui/, /docs and /redoc served offline run with a
    self-only policy: nothing the pages need is refused; only ReDoc's logo from its CDN is (offline, it
    would not load anyway, and a page that fetches nothing outside is the point)."""
    body = {"map_id": "yard", "thumbnails": True}
    assert http(f"{server}/v1/maps", json.dumps(body).encode(), "application/json")[0] == 201
    for i in range(10):
        post(http, server, "yard", make_frame(i), learn="true", stream="robot1")
    for i in range(10):  # localised answers with a place: confidence bars (a style) and thumbnails (blob:)
        post(http, server, "yard", make_frame(i), learn="false", stream="robot2")
    dom, refused = csp_violations(chromium, f"{server}/ui/?map=yard", tmp_path / "ui")
    assert refused == [] and 'class="bar"' in dom and "blob:" in dom, refused
    dom, refused = csp_violations(chromium, f"{server}/docs", tmp_path / "docs")
    assert refused == [] and 'id="operations-tag-maps"' in dom, refused
    dom, refused = csp_violations(chromium, f"{server}/redoc", tmp_path / "redoc")
    assert 'id="tag/maps"' in dom and "Something went wrong" not in dom
    assert all("cdn.redoc.ly" in line for line in refused), refused

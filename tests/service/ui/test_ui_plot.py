"""The viewer's plot code on any finite input (issue 19 item 4; docs/design/service.md §1.7): run in Node
with a stand-in DOM, under a time limit, since the failure was an endless loop (a pose of 1e16 froze the
page's tick generator)."""

from __future__ import annotations

import json
import math
import shutil
import subprocess

import pytest

from service.ui import STATIC_DIR

HUGE = 1.7e308

# A stand-in for the few DOM calls the plot modules make; the script prints one JSON line.
_PRELUDE = """
class N { constructor(t) { this.t = t; this.a = {}; this.c = []; }
  setAttribute(k, v) { this.a[k] = v; }
  append(...c) { this.c.push(...c); }
  replaceChildren() { this.c = []; } }
globalThis.document = { createElementNS: (ns, t) => new N(t), createElement: (t) => new N(t),
                        querySelector: () => ({ namespaceURI: "svg" }) };
const all = (n, t) => (n.t === t ? [n] : []).concat(...(n.c || []).map((c) => all(c, t)));
const plot = await import(%(dir)s + "/js/plot.js");
const trajectory = await import(%(dir)s + "/js/trajectory.js");
"""


def run_js(body: str) -> object:
    node = shutil.which("node")
    if node is None:
        pytest.skip("no node: the plot code is checked in Node")
    script = _PRELUDE % {"dir": json.dumps(STATIC_DIR.as_uri())} + body
    done = subprocess.run([node, "--input-type=module", "-e", script], capture_output=True, text=True,
                          timeout=20)  # an endless tick loop is the failure; 20 s is 1000x the run
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout)


RANGES = [(1e16 - 1, 1e16 + 1), (1e16, 1e16), (0, 1e16), (-HUGE, HUGE), (HUGE, HUGE), (-HUGE, -HUGE),
          (5e-324, 1e-323), (-3, 2.5), (0, 0.3), (1e9 - 1e-7, 1e9)]


@pytest.mark.parametrize(("lo", "hi"), RANGES)
def test_the_axes_are_bounded_and_drawn_for_any_finite_range(lo, hi):
    out = run_js(f"""
const root = new N("svg");
const {{ X, Y }} = plot.frame(root, [{lo!r}, {hi!r}], [{lo!r}, {hi!r}],
                            {{ xLabel: "x", yLabel: "y", equal: true }});
const labels = all(root, "text").map((t) => t.c[0]);
console.log(JSON.stringify({{ x: [X({lo!r}), X({hi!r})], y: [Y({lo!r}), Y({hi!r})], labels,
                              ticks: plot.ticks({lo!r}, {hi!r}, 8) }}));
""")
    assert all(math.isfinite(v) and -1 <= v <= 601 for v in out["x"] + out["y"]), out  # on the 600x400 plot
    assert 1 <= len(out["ticks"]) <= 17 and out["ticks"] == sorted(set(out["ticks"])), out
    assert all(lo - abs(lo) * 1e-9 - 1e-300 <= t <= hi + abs(hi) * 1e-9 + 1e-300 for t in out["ticks"]), out
    assert len(out["labels"]) <= 2 * 17 + 2


def test_ordinary_ranges_keep_their_round_ticks():
    out = run_js("""console.log(JSON.stringify([plot.ticks(-3, 2.5, 8), plot.ticks(0, 0.3, 6),
                                              plot.ticks(0, 1e16, 8)]));""")
    assert out == [[-3, -2, -1, 0, 1, 2], [0, 0.05, 0.1, 0.15, 0.2, 0.25, 0.3],
                   [0, 2e15, 4e15, 6e15, 8e15, 1e16]]


@pytest.mark.parametrize("x", [1e16, HUGE, -HUGE])
def test_the_trajectory_draws_stored_and_localised_poses_far_out(x):
    """The viewer's path: a stored row's pose and a localising answer's pose (from `/recent`) at x."""
    out = run_js(f"""
const root = new N("svg");
const stored = [{{ seq: 0, stream: "mapper", pose: {{ x: {x!r}, y: 0 }} }},
                {{ seq: 1, stream: "mapper", pose: {{ x: {x!r}, y: 1 }} }}];
const reply = {{ learned: false, stream: "robot", place: {{ seq: 0, confidence: 0.9, revisit: true }} }};
const queries = [{{ e: {{ reply }}, pose: {{ x: {x!r}, y: 0.5, yaw: 0.3 }} }}];
const note = trajectory.drawTrajectory(root, stored, queries, (seq) => stored[seq].pose);
const circles = all(root, "circle").map((c) => [Number(c.a.cx), Number(c.a.cy)]);
console.log(JSON.stringify({{ note, circles }}));
""")
    assert "2 stored pose(s)" in out["note"] and "1 revisit link(s)" in out["note"]
    assert len(out["circles"]) == 4 and all(math.isfinite(v) for c in out["circles"] for v in c), out

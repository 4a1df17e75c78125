"""The viewer's number formatting (service/ui/static/js/format.js), run in Node: a revisit threshold is
shown as it is, and a confidence never reads as reaching a threshold it is below (issue 23: an answer at
0.9496 showed "0.95" and "new" beside a threshold shown as "0.95")."""

from __future__ import annotations

import json
import shutil
import subprocess

import pytest

from service.ui import STATIC_DIR


def formatted(calls: list[tuple[str, list[float | None]]]) -> list[str]:
    """Each `format.js` function called with its arguments, in Node."""
    node = shutil.which("node")
    if node is None:
        pytest.skip("no node: the viewer's formatting is checked in Node")
    script = (f"const f = await import({json.dumps((STATIC_DIR / 'js' / 'format.js').as_uri())});\n"
              f"console.log(JSON.stringify({json.dumps(calls)}.map(([name, args]) => f[name](...args))));")
    done = subprocess.run([node, "--input-type=module", "-e", script], capture_output=True, text=True,
                          timeout=20)
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout)


def test_a_threshold_is_shown_exactly_and_a_confidence_on_its_own_side_of_it():
    assert formatted([("exact", [0.95]), ("exact", [0.9496]), ("exact", [0.5049]), ("exact", [None]),
                      ("beside", [0.9496, 0.95]), ("beside", [0.94999999, 0.95]), ("beside", [0.951, 0.95]),
                      ("beside", [0.95, 0.95]), ("beside", [0.5, 0.95]), ("beside", [0.5, None]),
                      ("beside", [None, 0.95])]) == [
        "0.95", "0.9496", "0.5049", "—",
        "0.9496", "0.94999999", "0.95", "0.95", "0.50", "0.50", "—"]


def test_a_closure_of_a_consolidated_frame_reads_visit_not_localising():
    """Issue 34 item 9: a learning stream's consolidated frame has no row, and it is no localising one."""
    assert formatted([("closureFrame", [{"seq": 7, "consolidated_into": None}]),
                      ("closureFrame", [{"seq": None, "consolidated_into": 3}]),
                      ("closureFrame", [{"seq": None, "consolidated_into": None}]),
                      ("closureFrame", [{"seq": None}]),
                      ("closureFrame", [{"seq": 7, "consolidated_into": None, "retracts": 12}])]) == [
        "7", "visit", "localising", "localising", "retracts 12"]

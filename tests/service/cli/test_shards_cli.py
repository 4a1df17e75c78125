"""`cortexloc shards list | move` without the `ray` extra: one line and exit 2, as the docs say
(service/cli/shards.py)."""

from __future__ import annotations

import sys
from types import SimpleNamespace

import pytest
from typer.testing import CliRunner

from service.cli import app as cli_app


@pytest.mark.parametrize("args", [["shards", "list"], ["shards", "move", "m", "--to", "shard-1"]])
def test_without_ray_each_shards_command_says_so_and_exits_2(monkeypatch, args):
    """Found from outside: `shards move` caught its own exit as the deployment's error, printed
    "error: 2" after the reason and exited 1."""
    monkeypatch.setitem(sys.modules, "ray", None)  # `import ray` raises ImportError
    r = CliRunner().invoke(cli_app, args)
    assert r.exit_code == 2, r.output
    assert r.stderr.strip().splitlines() == ["error: Ray is not installed: pip install 'cortexloc[ray]'"]


def test_shards_move_without_a_cluster_is_one_line_and_exit_1(monkeypatch):
    """Found in review: the fix above let `ray.init`'s ConnectionError (no cluster at the address) escape
    as a traceback; it is one line again."""
    def no_cluster(**kwargs):
        raise ConnectionError("could not find any running Ray instance")

    monkeypatch.setitem(sys.modules, "ray", SimpleNamespace(init=no_cluster))
    r = CliRunner().invoke(cli_app, ["shards", "move", "m", "--to", "shard-1"])
    assert r.exit_code == 1 and isinstance(r.exception, SystemExit), (r.exception, r.output)
    assert r.stderr.strip().splitlines() == ["error: could not find any running Ray instance"]

"""`cortexloc shards list | move` without the `ray` extra: one line and exit 2, as the docs say
(service/cli/shards.py)."""

from __future__ import annotations

import sys

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

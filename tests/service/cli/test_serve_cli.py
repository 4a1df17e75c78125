"""`cortexloc serve` on an address it cannot bind (service/cli/serve.py)."""

from __future__ import annotations

import socket

from typer.testing import CliRunner

from service.cli import app as cli_app
from service.cli.serve import command_settings, process_settings


def test_a_port_in_use_is_one_line_and_exit_3_before_anything_is_loaded_or_written(tmp_path):
    """Found from outside: on a port in use the server loaded the encoder, made the data directory and its
    `default` map, then failed on the bind."""
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        data = tmp_path / "new"
        r = CliRunner().invoke(cli_app, ["serve", "--port", str(port), "--data-dir", str(data)])
    assert r.exit_code == 3, r.output
    said = f"error: cannot listen on 127.0.0.1:{port}: Address already in use"
    assert r.stderr.strip().splitlines() == [said]
    assert not data.exists()


def test_a_one_shot_command_waits_for_no_lock_unless_told(monkeypatch, tmp_path):
    """Found from outside: `ingest`, `repair` and `import` in process beside a server on the same data
    directory sat 30 s (a restart's lock wait) on a frozen progress bar before they said so."""
    monkeypatch.delenv("CORTEXLOC_LOCK_WAIT_S", raising=False)
    monkeypatch.delenv("CORTEXLOC_LOG_LEVEL", raising=False)
    settings = command_settings(tmp_path)
    assert settings.lock_wait_s == 0 and settings.log_level == "WARNING"
    assert process_settings(data_dir=tmp_path).lock_wait_s == 30  # a server still waits for a restart
    monkeypatch.setenv("CORTEXLOC_LOCK_WAIT_S", "5")
    assert command_settings(tmp_path).lock_wait_s == 5

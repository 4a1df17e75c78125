"""Settings: read once from CORTEXLOC_* at startup, validated, errors name the variable
(docs/design/service.md §8)."""

from __future__ import annotations

import logging
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from typer.testing import CliRunner

from service.app import create_app
from service.settings import ConfigError, Settings, env_name
from tests.service.helpers import frame, make_client, post, tiny_encoder

REPO = Path(__file__).resolve().parents[2]


def spec_table() -> dict[str, str]:
    """docs/design/service.md §8's settings table: variable -> its default as written (`unset`: none)."""
    text = (REPO / "docs/design/service.md").read_text()
    section = text[text.index("## 8. Configuration"):text.index("## 9.")]
    table: dict[str, str] = {}
    for line in section.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) < 3 or not cells[0].startswith("`CORTEXLOC_"):
            continue
        names = re.findall(r"`(CORTEXLOC_[A-Z_]+)`", cells[0])
        # `unset` (or `unset: what it means then`): no value; else each default in backticks
        defaults = ["unset"] if cells[1].startswith("unset") else re.findall(r"`([^`]*)`", cells[1])
        assert len(names) == len(defaults), line
        table.update(zip(names, defaults, strict=True))
    return table


def test_defaults_match_the_spec_table():
    """The table names every setting and no other, and each default as written is the code's (both
    ways: a setting added without a row, a row left behind by a removed setting, a changed default)."""
    table = spec_table()
    fields = {f"CORTEXLOC_{name.upper()}" for name in Settings.model_fields}
    assert set(table) == fields
    defaults = Settings.from_env({})
    for var, written in table.items():
        name = var.removeprefix("CORTEXLOC_").lower()
        if written == "unset":
            assert getattr(defaults, name) is None, var
        else:
            assert getattr(Settings.from_env({var: written}), name) == getattr(defaults, name), var
    assert Settings.from_env({}) == Settings()


def test_the_backbone_lists_of_the_docs_are_the_registry():
    """The design's list of backbones and the default of new maps, against the registry, both ways."""
    from models.frontend import backbones

    text = (REPO / "docs/design/service.md").read_text()
    listed = re.search(r"\*\*Backbone\*\* \(`backbone`: ([^,]*),", text)
    assert listed is not None
    assert set(re.findall(r"`([a-z0-9-]+)`", listed.group(1))) == set(backbones.names())
    row = next(line for line in text.splitlines() if line.startswith("| `CORTEXLOC_BACKBONE`"))
    assert f"`{backbones.PAPER}` when its real weights are installed, else `{backbones.PRETRAINED}`" in row
    assert {backbones.PAPER, backbones.PRETRAINED} <= set(backbones.names())


def test_values_are_read_and_converted():
    s = Settings.from_env({
        "CORTEXLOC_DATA_DIR": "/srv/cortexloc", "CORTEXLOC_PORT": " 9000 ", "CORTEXLOC_LOG_LEVEL": "debug",
        "CORTEXLOC_LOG_FORMAT": "TEXT", "CORTEXLOC_ALLOW_RANDOM_WEIGHTS": "false",
        "CORTEXLOC_WEIGHTS_PATH": "/w/alexnet.pt", "CORTEXLOC_MAX_TOP_K": "0",
        "CORTEXLOC_SNAPSHOT_EVERY": "0",
        "CORTEXLOC_API_KEY": "s3cret", "PATH": "/usr/bin"})
    assert s.data_dir == Path("/srv/cortexloc")
    assert s.port == 9000
    assert (s.log_level, s.log_format) == ("DEBUG", "text")
    assert s.allow_random_weights is False
    assert s.weights_path == Path("/w/alexnet.pt")
    assert (s.max_top_k, s.snapshot_every) == (0, 0)
    assert s.api_key == "s3cret"
    assert "s3cret" not in repr(s)


def test_empty_value_means_unset():
    s = Settings.from_env({"CORTEXLOC_WEIGHTS_PATH": "", "CORTEXLOC_PORT": "  "})
    assert s.weights_path is None and s.port == 8000


@pytest.mark.parametrize(("var", "value"), [
    ("CORTEXLOC_PORT", "http"),
    ("CORTEXLOC_PORT", "70000"),
    ("CORTEXLOC_ALLOW_RANDOM_WEIGHTS", "perhaps"),
    ("CORTEXLOC_LOG_LEVEL", "LOUD"),
    ("CORTEXLOC_LOG_FORMAT", "xml"),
    ("CORTEXLOC_DEVICE", "tpu"),
    ("CORTEXLOC_RUNTIME", "tensorrt"),
    ("CORTEXLOC_MAX_UPLOAD_BYTES", "-1"),
    ("CORTEXLOC_TORCH_THREADS", "0"),
    ("CORTEXLOC_SNAPSHOT_KEEP", "three"),
    # past the upper bounds (docs/design/service.md §8), some met later as a crash or a host brought
    # down: a thread per worker, torch's C int of threads, int32 index rows, a wait that never ends
    ("CORTEXLOC_ENCODER_WORKERS", "10000000000000000000000000"),
    ("CORTEXLOC_TORCH_THREADS", str(2**63)),
    ("CORTEXLOC_MAX_OBSERVATIONS", str(2**31)),
    ("CORTEXLOC_RANDOM_WEIGHTS_SEED", str(2**64)),
    ("CORTEXLOC_LOOP_CLOSURES", str(2**63)),
    ("CORTEXLOC_LOCK_WAIT_S", "inf"),
    ("CORTEXLOC_STREAM_KEEP_SECONDS", "1e300"),
])
def test_invalid_value_names_the_variable(var, value):
    with pytest.raises(ConfigError) as info:
        Settings.from_env({var: value})
    assert var in str(info.value)
    assert repr(value) in str(info.value)
    assert info.value.variables == [var]


def _upper_bound(name: str) -> float | None:
    return next((m.le for m in Settings.model_fields[name].metadata if getattr(m, "le", None) is not None),
                None)


def test_every_number_has_an_upper_bound():
    """An absurd number is refused at startup naming its variable, whatever setting is added next."""
    numeric = [name for name, f in Settings.model_fields.items()
               if f.annotation in (int, float, int | None, float | None)]
    assert "encoder_workers" in numeric and "lock_wait_s" in numeric
    assert [name for name in numeric if _upper_bound(name) is None] == []
    for name in numeric:  # the bound itself is a value the settings take
        var, bound = env_name(name), _upper_bound(name)
        taken = Settings.from_env({var: str(bound), **({"CORTEXLOC_MAX_INFLIGHT_UPLOAD_BYTES": str(bound)}
                                                        if name == "max_upload_bytes" else {})})
        assert getattr(taken, name) == bound, var


@pytest.mark.parametrize("name", ["encoder_workers", "encoder_queue", "torch_threads", "max_observations",
                                  "random_weights_seed", "idempotency_keys", "loop_closures", "visits",
                                  "snapshot_every", "max_top_k", "stream_keep_seconds",
                                  "lock_wait_s", "max_import_bytes", "snapshot_manual_bytes"])
def test_the_service_runs_at_an_upper_bound(tmp_path, name):
    """A setting at its bound is served, not met as a crash: frames learned and localised, a snapshot
    taken, a second map made."""
    bound = _upper_bound(name)
    with make_client(tmp_path, **{name: bound}) as c:
        for i in range(3):
            assert post(c, frame(i), learn="true", stream="s").status_code == 200
        assert c.post("/v1/maps/default/snapshots").status_code == 201
        found = post(c, frame(1), learn="false", top_k="5")
        assert found.status_code == 200 and found.json()["matches"], name
        assert c.post("/v1/maps", json={"map_id": "second"}).status_code == 201
        assert c.get("/metrics").status_code == 200


def test_every_invalid_variable_is_reported():
    with pytest.raises(ConfigError) as info:
        Settings.from_env({"CORTEXLOC_PORT": "x", "CORTEXLOC_MAX_MAPS": "0"})
    assert set(info.value.variables) == {"CORTEXLOC_PORT", "CORTEXLOC_MAX_MAPS"}


def test_unknown_variables_warn_and_are_ignored(caplog):
    with caplog.at_level(logging.WARNING, logger="cortexloc.settings"):
        s = Settings.from_env({"CORTEXLOC_PROT": "9000", "CORTEXLOC_BANANA": "1",
                               "CORTEXLOC_WEIGHTS_DIR": "/w", "OTHER_THING": "1"})
    assert s.port == 8000
    messages = [r.getMessage() for r in caplog.records]
    assert any("CORTEXLOC_PROT" in m and "did you mean CORTEXLOC_PORT" in m for m in messages)
    assert any("CORTEXLOC_BANANA" in m for m in messages)
    assert not any("CORTEXLOC_WEIGHTS_DIR" in m or "OTHER_THING" in m for m in messages)
    assert all(r.levelno == logging.WARNING for r in caplog.records)


def test_settings_are_immutable():
    s = Settings()
    with pytest.raises(ValueError, match="frozen"):
        s.port = 1  # type: ignore[misc]


def test_import_reads_nothing():
    env = {**os.environ, "CORTEXLOC_PORT": "not-a-port", "CORTEXLOC_DATA_DIR": "/nonexistent/x"}
    code = "import service.app, service.deps, service.routes; service.app.create_app(); print('ok')"
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO, env=env, capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "ok"
    assert not Path("/nonexistent/x").exists()


def test_env_is_read_at_startup_not_in_create_app(monkeypatch, tmp_path):
    app = create_app(encoder_factory=tiny_encoder)  # nothing read yet
    monkeypatch.setenv("CORTEXLOC_DATA_DIR", str(tmp_path / "data"))
    monkeypatch.setenv("CORTEXLOC_MAX_TOP_K", "7")
    with TestClient(app) as client:
        assert app.state.settings.max_top_k == 7
        assert app.state.settings.data_dir == tmp_path / "data"
        assert (tmp_path / "data").is_dir()
        assert client.get("/healthz").status_code == 200
        monkeypatch.setenv("CORTEXLOC_MAX_TOP_K", "9")  # read once: later changes are not seen
        assert app.state.settings.max_top_k == 7


def test_invalid_env_stops_startup(monkeypatch, tmp_path):
    monkeypatch.setenv("CORTEXLOC_DATA_DIR", str(tmp_path))
    monkeypatch.setenv("CORTEXLOC_MAX_PIXELS", "lots")
    app = create_app(encoder_factory=tiny_encoder)
    with pytest.raises(ConfigError, match="CORTEXLOC_MAX_PIXELS"), TestClient(app):
        pass


def test_unusable_weights_file_stops_startup(tmp_path):
    bad = tmp_path / "alexnet.pt"
    bad.write_bytes(b"not a checkpoint")
    app = create_app(Settings(data_dir=tmp_path / "data", weights_path=bad), encoder_factory=tiny_encoder)
    with pytest.raises(ConfigError, match="CORTEXLOC_WEIGHTS_PATH"), TestClient(app):
        pass


def test_serve_refuses_an_invalid_environment(monkeypatch):
    from service.cli import app as cli

    monkeypatch.setenv("CORTEXLOC_LOG_FORMAT", "xml")
    result = CliRunner().invoke(cli, ["serve", "--port", "8123"])
    assert result.exit_code == 2
    assert "CORTEXLOC_LOG_FORMAT" in result.output


def test_serve_passes_options_to_uvicorn(monkeypatch, tmp_path):
    import uvicorn

    from service.cli import app as cli

    seen = {}

    def fake_run(app, **kwargs):
        seen["app"], seen["kwargs"] = app, kwargs

    monkeypatch.setattr(uvicorn, "run", fake_run)
    result = CliRunner().invoke(cli, ["serve", "--host", "0.0.0.0", "--port", "8123", "--data-dir",
                                      str(tmp_path / "d")])
    assert result.exit_code == 0, result.output
    assert seen["kwargs"]["host"] == "0.0.0.0" and seen["kwargs"]["port"] == 8123
    assert seen["kwargs"]["workers"] == 1
    settings = seen["app"].state.settings
    assert settings.data_dir == tmp_path / "d" and settings.port == 8123


def test_reading_settings_loads_no_opencv():
    """`cortexloc serve` sets OPENCV_IO_MAX_IMAGE_PIXELS from the settings, so they must be read before cv2
    is imported (docs/design/service.md §3): the settings module takes its defaults from a cv2-free home."""
    import subprocess
    import sys

    code = ("import sys, service.settings as s; s.Settings.from_env({}); "
            "print('cv2' in sys.modules, 'torch' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["False", "False"]


def test_a_relative_data_directory_is_made_absolute_once_and_snapshots_work(tmp_path, monkeypatch):
    """Found from outside: with `--data-dir ./rel` (the default `./var` is relative too) every snapshot was
    unreadable (409) and recovery looked under rel/rel; with `../data` snapshots were a 500."""
    from tests.service.helpers import frame, make_client, post

    monkeypatch.chdir(tmp_path)
    (tmp_path / "cwd").mkdir()
    monkeypatch.chdir(tmp_path / "cwd")
    for rel in ("rel", "../data"):
        with make_client(Path(rel)) as c:
            assert c.app.state.settings.data_dir == (tmp_path / "cwd" / rel).resolve()
            assert post(c, frame(0)).status_code == 200
            snap = c.post("/v1/maps/default/snapshots")
            assert snap.status_code == 201, snap.text
            assert post(c, frame(1)).status_code == 200
            sid = snap.json()["snapshot_id"]
            assert c.get(f"/v1/maps/default/snapshots/{sid}/download").status_code == 200
            assert c.post(f"/v1/maps/default/snapshots/{sid}/restore").status_code == 200
        with make_client(Path(rel)) as c:  # recovery finds the snapshots where they are
            assert not c.app.state.registry.get("default").recovery["skipped_snapshots"]


@pytest.mark.parametrize(("value", "device"), [("CUDA", "cuda"), (" cpu ", "cpu"), ("Auto", "auto")])
def test_device_is_read_case_insensitively(value, device):
    assert Settings.from_env({"CORTEXLOC_DEVICE": value}).device == device


def test_device_cuda_without_cuda_stops_startup_naming_the_variable(tmp_path):
    """This machine (and CI) has no CUDA provider: `cuda` must not quietly serve from the CPU."""
    app = create_app(Settings(data_dir=tmp_path, backbone="alexnet", device="cuda"),
                     encoder_factory=tiny_encoder)
    with pytest.raises(ConfigError) as info, TestClient(app):
        pass
    assert info.value.variables == ["CORTEXLOC_DEVICE"] and "gpu` extra" in str(info.value)


@pytest.mark.parametrize("runtime", ["onnxruntime", "torch"])
def test_device_auto_falls_back_to_the_cpu_and_says_so(tmp_path, caplog, runtime):
    app = create_app(Settings(data_dir=tmp_path, backbone="alexnet", device="auto", runtime=runtime),
                     encoder_factory=tiny_encoder)
    with caplog.at_level(logging.INFO, "cortexloc"), TestClient(app) as c:
        enc = c.get("/readyz").json()["checks"]["encoder"]
    assert (enc["runtime"], enc["device"]) == (runtime, "cpu")
    assert any("device auto" in r.getMessage() and "CPU" in r.getMessage() for r in caplog.records)

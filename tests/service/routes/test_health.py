"""Liveness, readiness and metrics (docs/design/service.md §1.6)."""

from __future__ import annotations

import os
from types import SimpleNamespace

import pytest
from fastapi.testclient import TestClient

from service.errors import PROBLEM_MEDIA_TYPE
from service.metrics import Metrics
from tests.service.helpers import make_app


@pytest.fixture
def app(tmp_path):
    return make_app(tmp_path / "data")


@pytest.fixture
def client(app):
    with TestClient(app) as c:
        yield c


def assert_not_ready(r) -> dict:
    assert r.status_code == 503, r.text
    assert r.headers["content-type"] == PROBLEM_MEDIA_TYPE
    body = r.json()
    assert body["type"] == "urn:cortexloc:problem:not-ready"
    assert body["request_id"] == r.headers["x-request-id"]
    return body


def test_healthz(client):
    r = client.get("/healthz")
    assert r.status_code == 200 and r.json() == {"status": "ok"}


def test_healthz_touches_nothing(tmp_path):
    data = tmp_path / "data"
    app = make_app(data)
    with TestClient(app) as c:
        before = sorted(p.name for p in data.iterdir())
        app.state.encoder, encoder = None, app.state.encoder  # even with nothing loaded
        assert c.get("/healthz").json() == {"status": "ok"}
        app.state.encoder = encoder
        assert sorted(p.name for p in data.iterdir()) == before


def test_readyz_ready_with_a_random_weights_warning(client, tmp_path):
    r = client.get("/readyz")
    assert r.status_code == 200
    body = r.json()
    assert body["status"] == "ready"
    checks = body["checks"]
    assert checks["data_dir"] == {"status": "pass", "path": str(tmp_path / "data")}
    enc = checks["encoder"]
    assert enc["status"] == "warn" and enc["weights"] == "random" and enc["seed"] == 0
    assert enc["encoder"] == "alexnet-conv3/random-seed0:squash"
    assert enc["backbone"] == "alexnet" and enc["backbones"] == {"alexnet": enc["encoder"]}
    assert (enc["runtime"], enc["device"]) == ("onnxruntime", "cpu")  # the defaults, without CUDA
    assert "random weights" in enc["warning"]
    assert body["warnings"] == [enc["warning"]]
    # a fresh install serves the `default` map with no other step
    assert checks["maps"] == {"status": "pass", "count": 1,
                              "maps": {"default": {"state": "ready", "state_reason": None,
                                                   "backbone": "alexnet"}}}
    names = {p.name for p in (tmp_path / "data").iterdir()}
    assert {"catalog.sqlite", "maps", "projections"} <= names
    assert not [n for n in names if "probe" in n]  # the writability probe file is gone


def test_readyz_not_ready_when_random_weights_are_not_allowed(tmp_path):
    with TestClient(make_app(tmp_path / "data", allow_random_weights=False)) as c:
        body = assert_not_ready(c.get("/readyz"))
    enc = body["checks"]["encoder"]
    assert enc["status"] == "fail" and "CORTEXLOC_ALLOW_RANDOM_WEIGHTS" in enc["error"]
    assert body["checks"]["data_dir"]["status"] == "pass"
    assert "encoder" in body["detail"]


def test_readyz_not_ready_when_data_dir_is_a_file(tmp_path):
    not_a_dir = tmp_path / "file"
    not_a_dir.write_text("x")
    with TestClient(make_app(not_a_dir)) as c:
        assert c.get("/healthz").status_code == 200  # alive, just not ready
        body = assert_not_ready(c.get("/readyz"))
    assert body["checks"]["data_dir"]["status"] == "fail"
    assert "not writable" in body["checks"]["data_dir"]["error"]
    assert body["checks"]["encoder"]["status"] == "warn"


@pytest.mark.skipif(hasattr(os, "geteuid") and os.geteuid() == 0, reason="root ignores directory permissions")
def test_readyz_not_ready_when_data_dir_is_read_only(tmp_path):
    data = tmp_path / "data"
    data.mkdir()
    with TestClient(make_app(data)) as c:
        assert c.get("/readyz").status_code == 200
        data.chmod(0o500)
        try:
            body = assert_not_ready(c.get("/readyz"))
        finally:
            data.chmod(0o700)
    assert body["checks"]["data_dir"]["status"] == "fail"


def test_readyz_not_ready_when_data_dir_disappears(client, app, tmp_path):
    import shutil

    data = tmp_path / "data"
    shutil.rmtree(data)
    body = assert_not_ready(client.get("/readyz"))
    assert body["checks"]["data_dir"]["status"] == "fail"


def test_readyz_is_ready_with_a_warning_when_the_data_dir_has_no_room(client, app, monkeypatch):
    """A full disk: the maps localise and serve reads (what writes gets 507), so a readiness-gated
    balancer must keep the service; before, the data directory's probe failed it (503)."""
    import errno

    probes: set[int] = set()
    real_open, real_write = os.open, os.write

    def opened(path, flags, *args, **kw):
        fd = real_open(path, flags, *args, **kw)
        if os.path.basename(str(path)).startswith(".readyz-"):
            probes.add(fd)
        return fd

    def write(fd, data):  # the OS's words for a full disk, for the probe file alone
        if fd in probes:
            raise OSError(errno.ENOSPC, "No space left on device")
        return real_write(fd, data)

    monkeypatch.setattr(os, "open", opened)
    monkeypatch.setattr(os, "write", write)
    r = client.get("/readyz")
    monkeypatch.undo()
    assert r.status_code == 200, r.text
    data_dir = r.json()["checks"]["data_dir"]
    assert data_dir["status"] == "warn" and "no room" in data_dir["warning"], data_dir
    assert data_dir["warning"] in r.json()["warnings"]
    assert not list(app.state.settings.data_dir.glob(".readyz-*"))  # the probe file is gone
    # a map whose commit found no room says so too (it stays ready: it localises)
    app.state.maps = {"lab": SimpleNamespace(state="ready", state_reason=None,
                                             no_room="database or disk is full",
                                             config=SimpleNamespace(backbone="alexnet"))}
    maps = client.get("/readyz").json()["checks"]["maps"]
    assert maps["status"] == "warn" and "no room" in maps["warning"]
    assert maps["maps"]["lab"]["no_room"] == "database or disk is full"


def test_readyz_reports_map_states(client, app):
    app.state.maps = {}  # the states /readyz reads, apart from the runtime's own maps
    app.state.maps["lab"] = SimpleNamespace(state="ready", state_reason=None,
                                           config=SimpleNamespace(backbone="alexnet"))
    app.state.maps["old"] = SimpleNamespace(state="failed", state_reason="database-corrupt",
                                           config=SimpleNamespace(backbone="efficientnet-lite0"))
    r = client.get("/readyz")
    assert r.status_code == 200  # a failed map does not make the service unready
    maps = r.json()["checks"]["maps"]
    assert maps["status"] == "warn" and maps["count"] == 2
    assert maps["maps"]["old"] == {"state": "failed", "state_reason": "database-corrupt",
                                   "backbone": "efficientnet-lite0"}
    assert maps["maps"]["lab"] == {"state": "ready", "state_reason": None, "backbone": "alexnet"}

    app.state.maps["new"] = SimpleNamespace(state="recovering", state_reason="replaying",
                                           config=SimpleNamespace(backbone="alexnet"))
    body = assert_not_ready(client.get("/readyz"))
    assert body["checks"]["maps"]["status"] == "fail" and "new" in body["checks"]["maps"]["error"]


def test_readyz_checks_the_catalog_and_a_crashing_check_is_a_failure(client, app, monkeypatch):
    assert client.get("/readyz").json()["checks"]["catalog"]["status"] == "pass"

    def broken():
        raise OSError("disk on fire")

    monkeypatch.setattr(app.state.registry.catalog, "check", broken)
    body = assert_not_ready(client.get("/readyz"))
    assert body["checks"]["catalog"] == {"status": "fail", "error": "OSError: disk on fire"}


# ------------------------------------------------------------------------------------------ metrics


def test_metrics_count_requests_and_report_the_encoder(client):
    client.get("/healthz")
    client.get("/healthz")
    client.get("/nowhere/at/all")
    r = client.get("/metrics")
    assert r.status_code == 200
    assert r.headers["content-type"].startswith("text/plain")
    text = r.text
    assert 'cortexloc_requests_total{method="GET",route="/healthz",status="200"} 2.0' in text
    assert 'cortexloc_requests_total{method="GET",route="<unmatched>",status="404"} 1.0' in text
    bucket = ('cortexloc_request_duration_seconds_bucket{le="0.001",method="GET",route="/healthz",'
              'status="200"}')
    assert bucket in text
    assert 'cortexloc_encoder_info{encoder="alexnet-conv3/random-seed0:squash",weights="random"} 1.0' in text
    assert "cortexloc_requests_in_flight" in text


def test_metrics_use_route_templates(client, app):
    @app.get("/test/things/{thing_id}")
    def thing(thing_id: str) -> dict:
        return {"id": thing_id}

    for i in range(3):
        client.get(f"/test/things/{i}")
    text = client.get("/metrics").text
    assert 'route="/test/things/{thing_id}",status="200"} 3.0' in text
    assert "/test/things/1" not in text


def test_stage_helper_and_separate_registries(tmp_path):
    a, b = make_app(tmp_path / "a"), make_app(tmp_path / "b")
    assert a.state.metrics.registry is not b.state.metrics.registry
    m: Metrics = a.state.metrics
    m.observe_stage("encode", 0.02)
    with m.time_stage("tm"):
        pass
    with TestClient(a) as ca, TestClient(b) as cb:
        text_a, text_b = ca.get("/metrics").text, cb.get("/metrics").text
    assert 'cortexloc_stage_duration_seconds_count{stage="encode"} 1.0' in text_a
    assert 'cortexloc_stage_duration_seconds_count{stage="tm"} 1.0' in text_a
    assert 'stage="encode"' not in text_b

"""Weights download / import / verify / cache (docs/design/service.md §7), without the network.

A fake "full" checkpoint (the six conv tensors with random values plus classifier keys) stands in for
torchvision's file. Its real SHA-256 cannot start with 7be5be79, so the tests pass the fake file's own
prefix as `expected_prefix`; it is served from a loopback HTTP server.
"""

from __future__ import annotations

import hashlib
import http.server
import io
import json
import socket
import struct
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import ClassVar

import numpy as np
import pytest
import torch

import models.frontend.weights as weights_module
from models.frontend import weights
from models.frontend.backbones.alexnet import AlexNetConv3, alexnet_conv3, load_alexnet_state
from models.frontend.weights import (
    ALEXNET_CONV3_SHAPES,
    ALEXNET_SHA256_PREFIX,
    ALEXNET_URL,
    WeightsError,
    default_cache_dir,
    download_alexnet,
    find_alexnet,
    import_alexnet,
    read_sidecar,
    sidecar_path,
)


def _fake_checkpoint(seed: int = 0, bad_key: str | None = None) -> tuple[dict[str, torch.Tensor], bytes]:
    """A torchvision-like AlexNet state dict and its `torch.save` bytes.

    The classifier tensors are small (the real ones hold 57 M values): they only have to be there and be
    ignored.
    """
    g = torch.Generator().manual_seed(seed)
    state = {k: torch.randn(s, generator=g) * 0.05 for k, s in ALEXNET_CONV3_SHAPES.items()}
    if bad_key is not None:
        state[bad_key] = torch.zeros(7, 7)
    full = dict(state)
    full.update({
        "features.8.weight": torch.randn(256, 384, 3, 3, generator=g),
        "features.8.bias": torch.randn(256, generator=g),
        "classifier.1.weight": torch.randn(16, 32, generator=g),
        "classifier.1.bias": torch.randn(16, generator=g),
        "classifier.6.weight": torch.randn(10, 16, generator=g),
        "classifier.6.bias": torch.randn(10, generator=g),
    })
    buf = io.BytesIO()
    torch.save(full, buf)
    return state, buf.getvalue()


def _other_prefix(digest: str) -> str:
    """An 8-hex prefix that the digest does not start with."""
    first = "0" if digest[0] != "0" else "1"
    return first + digest[1:8]


@pytest.fixture(scope="module")
def fake() -> dict[str, object]:
    state, data = _fake_checkpoint()
    digest = hashlib.sha256(data).hexdigest()
    return {"state": state, "data": data, "sha256": digest, "prefix": digest[:8]}


class _Handler(http.server.BaseHTTPRequestHandler):
    routes: ClassVar[dict[str, tuple[bytes, int | None]]] = {}  # path -> (body, Content-Length to announce)

    def do_GET(self) -> None:
        if self.path not in self.routes:
            self.send_error(404)
            return
        body, announced = self.routes[self.path]
        if announced == -1:  # reset: half the body, then an RST (SO_LINGER 0) instead of a clean close
            self.send_response(200)
            self.send_header("Content-Length", str(2 * len(body)))
            self.end_headers()
            self.wfile.write(body)
            self.wfile.flush()
            self.connection.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
            self.close_connection = True
            return
        self.send_response(200)
        self.send_header("Content-Type", "application/octet-stream")
        self.send_header("Content-Length", str(len(body) if announced is None else announced))
        self.end_headers()
        self.wfile.write(body)
        # HTTP/1.0 handler: the connection closes here, short of an announced length when cut off.
        self.close_connection = True

    def log_message(self, format: str, *args: object) -> None:  # keep pytest output clean
        pass


@pytest.fixture()
def server(fake: dict[str, object], monkeypatch: pytest.MonkeyPatch) -> Iterator[str]:
    """Loopback server: /full.pth, /cut.pth (announces 1000 bytes more), /reset.pth (RST), else 404."""
    for var in ("no_proxy", "NO_PROXY"):  # a proxy in the environment must not see loopback traffic
        monkeypatch.setenv(var, "*")
    data = fake["data"]
    assert isinstance(data, bytes)
    _Handler.routes = {"/full.pth": (data, None), "/cut.pth": (data[: len(data) // 2], len(data) + 1000),
                       "/reset.pth": (data[: len(data) // 2], -1)}
    httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), _Handler)
    thread = threading.Thread(target=httpd.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{httpd.server_address[1]}"
    finally:
        httpd.shutdown()
        httpd.server_close()
        thread.join(timeout=5)


def _files(d: Path) -> list[str]:
    return sorted(p.name for p in d.iterdir()) if d.exists() else []


def test_constants_and_cache_dir(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    assert ALEXNET_URL == "https://download.pytorch.org/models/alexnet-owt-7be5be79.pth"
    assert ALEXNET_SHA256_PREFIX == "7be5be79"
    assert weights.trimmed_name(ALEXNET_SHA256_PREFIX) == "alexnet-conv3-7be5be79.pt"
    assert sum(int(np.prod(s)) for s in ALEXNET_CONV3_SHAPES.values()) == weights.ALEXNET_CONV3_PARAMETERS
    monkeypatch.setenv("CORTEXLOC_WEIGHTS_DIR", str(tmp_path / "w"))
    assert default_cache_dir() == tmp_path / "w"
    monkeypatch.delenv("CORTEXLOC_WEIGHTS_DIR")
    monkeypatch.setenv("HOME", str(tmp_path))
    assert default_cache_dir() == tmp_path / ".cache" / "cortexloc" / "weights"


def test_download_installs_verified_trimmed_file(server: str, fake: dict, tmp_path: Path) -> None:
    dest = tmp_path / "weights"
    seen: list[tuple[int, int | None]] = []
    path = download_alexnet(dest, url=f"{server}/full.pth", expected_prefix=fake["prefix"],
                            progress=lambda n, total: seen.append((n, total)))
    assert path == dest / f"alexnet-conv3-{fake['prefix']}.pt"
    assert _files(dest) == sorted([path.name, sidecar_path(path).name])  # no temp files left
    assert seen and seen[-1] == (len(fake["data"]), len(fake["data"]))

    meta = json.loads(sidecar_path(path).read_text())
    assert meta["original_sha256"] == fake["sha256"]
    assert meta["original_bytes"] == len(fake["data"])
    assert meta["trimmed_sha256"] == hashlib.sha256(path.read_bytes()).hexdigest()
    assert meta["source"] == f"{server}/full.pth"
    assert meta["parameters"] == 994_624
    assert read_sidecar(path) == meta

    state, digest = load_alexnet_state(path)
    assert digest == meta["trimmed_sha256"]
    assert list(state) == list(ALEXNET_CONV3_SHAPES)  # classifier and features.8 dropped
    for key, value in fake["state"].items():
        assert torch.equal(state[key], value)
    assert path.stat().st_size < 4_100_000  # about 4 MB: the six tensors only

    # The trimmed file keeps the identity of the original, and computes the same descriptors. Only
    # torchvision's digest is called ImageNet: the fake checkpoint is named as a file...
    model, wid = alexnet_conv3(path)
    assert wid == f"file-{fake['prefix']}"
    # ...unless its digest is the one expected of torchvision's checkpoint.
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(weights_module, "ALEXNET_SHA256_PREFIX", fake["prefix"])
        assert alexnet_conv3(path)[1] == f"imagenet-{fake['prefix']}"
    reference = AlexNetConv3().eval()
    reference.load_state_dict(fake["state"])
    x = torch.from_numpy(np.random.Generator(np.random.PCG64(0)).standard_normal((2, 3, 224, 224),
                                                                                 dtype=np.float32))
    with torch.inference_mode():
        assert torch.equal(model(x), reference(x))

    assert find_alexnet(dest, expected_prefix=fake["prefix"]) == path


def test_download_refuses_wrong_checksum(server: str, fake: dict, tmp_path: Path) -> None:
    dest = tmp_path / "weights"
    with pytest.raises(WeightsError, match="does not start with"):
        download_alexnet(dest, url=f"{server}/full.pth", expected_prefix=_other_prefix(fake["sha256"]))
    assert _files(dest) == []


def test_download_refuses_cut_off_transfer(server: str, fake: dict, tmp_path: Path) -> None:
    dest = tmp_path / "weights"
    with pytest.raises(WeightsError, match="cut off"):
        download_alexnet(dest, url=f"{server}/cut.pth", expected_prefix=fake["prefix"])
    assert _files(dest) == []


def test_download_refuses_reset_connection(server: str, fake: dict, tmp_path: Path) -> None:
    dest = tmp_path / "weights"
    # Usually seen while reading the body; if the RST overtakes the headers, urlopen reports it instead.
    with pytest.raises(WeightsError, match=r"cut off|reset by peer"):
        download_alexnet(dest, url=f"{server}/reset.pth", expected_prefix=fake["prefix"])
    assert _files(dest) == []


def test_download_reports_http_and_connection_errors(server: str, tmp_path: Path) -> None:
    with pytest.raises(WeightsError, match="HTTP 404"):
        download_alexnet(tmp_path, url=f"{server}/missing.pth")
    # A loopback port that was just free: the connection is refused without touching the network.
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    with pytest.raises(WeightsError, match="cannot reach"):
        download_alexnet(tmp_path, url=f"http://127.0.0.1:{port}/x.pth", timeout=5)
    with pytest.raises(ValueError, match="http"):
        download_alexnet(tmp_path, url="file:///etc/passwd")
    assert _files(tmp_path) == []


def test_import_from_local_file(fake: dict, tmp_path: Path) -> None:
    src = tmp_path / "alexnet-owt.pth"
    src.write_bytes(fake["data"])
    dest = tmp_path / "cache"
    with pytest.raises(WeightsError, match="does not start with"):
        import_alexnet(src, dest, expected_prefix=_other_prefix(fake["sha256"]))
    assert _files(dest) == []

    path = import_alexnet(src, dest, expected_prefix=fake["prefix"])
    meta = read_sidecar(path)
    assert meta is not None and meta["original_sha256"] == fake["sha256"]
    assert meta["source"] == str(src.resolve())
    state, _ = load_alexnet_state(path)
    for key, value in fake["state"].items():
        assert torch.equal(state[key], value)
    # Loading the full checkpoint directly gives the same id as its trimmed copy.
    assert alexnet_conv3(src)[1] == alexnet_conv3(path)[1] == f"file-{fake['prefix']}"
    # Importing again is idempotent: same bytes, same digests.
    again = import_alexnet(src, dest, expected_prefix=fake["prefix"])
    assert again == path and read_sidecar(again)["trimmed_sha256"] == meta["trimmed_sha256"]
    assert _files(dest) == sorted([path.name, sidecar_path(path).name])


def test_import_refuses_wrong_shape_naming_the_key(tmp_path: Path) -> None:
    _, data = _fake_checkpoint(seed=1, bad_key="features.6.weight")
    src = tmp_path / "bad.pth"
    src.write_bytes(data)
    dest = tmp_path / "cache"
    prefix = hashlib.sha256(data).hexdigest()[:8]
    with pytest.raises(WeightsError, match=r"features\.6\.weight has shape \(7, 7\).*\(384, 192, 3, 3\)"):
        import_alexnet(src, dest, expected_prefix=prefix)
    assert _files(dest) == []
    with pytest.raises(WeightsError, match=r"features\.6\.weight"):
        load_alexnet_state(src)


def test_import_missing_file(tmp_path: Path) -> None:
    with pytest.raises(WeightsError, match="does not exist"):
        import_alexnet(tmp_path / "nope.pth", tmp_path / "cache")


def test_find_alexnet_absent_installed_and_corrupted(fake: dict, tmp_path: Path,
                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("CORTEXLOC_WEIGHTS_DIR", str(tmp_path / "cache"))
    assert find_alexnet() is None  # nothing installed, directory absent: no error
    assert find_alexnet(expected_prefix=fake["prefix"]) is None
    src = tmp_path / "full.pth"
    src.write_bytes(fake["data"])
    path = import_alexnet(src, expected_prefix=fake["prefix"])  # default dir from the environment
    assert path.parent == tmp_path / "cache"
    assert find_alexnet(expected_prefix=fake["prefix"]) == path
    assert find_alexnet() is None  # the real 7be5be79 file is not installed

    # A corrupted trimmed file is reported, not used.
    good = path.read_bytes()
    path.write_bytes(good[:-1] + bytes([good[-1] ^ 0xFF]))
    with pytest.raises(WeightsError, match="corrupted"):
        find_alexnet(expected_prefix=fake["prefix"])
    # ...and loading it directly fails too, because its sidecar no longer matches.
    with pytest.raises(WeightsError, match="changed after install"):
        alexnet_conv3(path)

    # A trimmed file without its sidecar cannot be verified.
    path.write_bytes(good)
    sidecar_path(path).unlink()
    with pytest.raises(WeightsError, match="no sidecar"):
        find_alexnet(expected_prefix=fake["prefix"])

    # An interrupted install (sidecar written, weights not yet) counts as not installed.
    path.unlink()
    import_alexnet(src, expected_prefix=fake["prefix"])
    path.unlink()
    assert find_alexnet(expected_prefix=fake["prefix"]) is None


def test_malformed_sidecar_is_reported(fake: dict, tmp_path: Path) -> None:
    src = tmp_path / "full.pth"
    src.write_bytes(fake["data"])
    path = import_alexnet(src, tmp_path / "cache", expected_prefix=fake["prefix"])
    sidecar_path(path).write_text("{not json")
    with pytest.raises(WeightsError, match="unreadable"):
        find_alexnet(tmp_path / "cache", expected_prefix=fake["prefix"])
    meta = {"format": weights.SIDECAR_FORMAT, "original_sha256": "xyz", "trimmed_sha256": "0" * 64}
    sidecar_path(path).write_text(json.dumps(meta))
    with pytest.raises(WeightsError, match="original_sha256"):
        read_sidecar(path)


def test_expected_prefix_is_validated(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="hex"):
        import_alexnet(tmp_path / "x.pth", tmp_path, expected_prefix="7be5")
    with pytest.raises(ValueError, match="hex"):
        find_alexnet(tmp_path, expected_prefix="not-hex!")

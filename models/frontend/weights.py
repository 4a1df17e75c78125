"""AlexNet conv1..conv3 weights: download, import, verify, trim and cache (docs/design/science.md §6,
docs/design/service.md §7).

torchvision publishes the ImageNet AlexNet as `alexnet-owt-7be5be79.pth` (about 233 MB); the 8 hex
digits are the start of the file's SHA-256, which is how a copy is verified. The front end needs only
the six conv1..conv3 tensors (994,624 float32 values, about 4 MB), so an installed copy is *trimmed*:

    <cache>/alexnet-conv3-7be5be79.pt    the six tensors, `torch.save` of a dict
    <cache>/alexnet-conv3-7be5be79.json  sidecar: SHA-256 of the original and of the trimmed file, source

The sidecar is what lets the trimmed file keep the identity of the original (`imagenet-7be5be79`, see
`models.frontend.backbones.alexnet.alexnet_conv3`) and lets `find_alexnet` detect a corrupted copy.

Nothing here runs at import time and nothing is downloaded unless `download_alexnet` is called: tests
and offline machines never touch the network. Only the standard library is used for HTTP.

The download follows torch.hub's convention (the file name's 8 hex digits are a prefix of its SHA-256,
checked while streaming into a temporary file that is moved into place only when it verifies) but is
not `torch.hub.download_url_to_file(hash_prefix=...)` (torch 2.13): that call has no socket timeout (a
stalled server hangs the CLI forever), no size cap (`MAX_DOWNLOAD_BYTES`), reports a cut-off transfer
as a hash mismatch instead of saying it was cut off, offers a tqdm bar instead of a progress callback,
and does not return the digest the sidecar records (a second pass over 233 MB).
`load_state_dict_from_url(check_hash=True)` wraps the same call and adds torch's hub cache, which the
trimmed install replaces.

Example:
    >>> path = download_alexnet()                      # connected machine
    >>> path = import_alexnet("alexnet-owt-7be5be79.pth")  # offline machine, file copied by hand
    >>> find_alexnet()                                 # what the encoder uses when no path is configured
    PosixPath('/home/me/.cache/cortexloc/weights/alexnet-conv3-7be5be79.pt')
"""

from __future__ import annotations

import contextlib
import hashlib
import http.client
import io
import json
import os
import re
import tempfile
import urllib.error
import urllib.parse
import urllib.request
from collections.abc import Callable, Mapping
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, BinaryIO

import torch

from storage.base.files import atomic_write, sha256_file

ALEXNET_URL = "https://download.pytorch.org/models/alexnet-owt-7be5be79.pth"
ALEXNET_SHA256_PREFIX = "7be5be79"

#: torchvision state-dict keys of conv1..conv3 and their shapes (docs/design/science.md §6 table), in forward
#: order.
ALEXNET_CONV3_SHAPES: dict[str, tuple[int, ...]] = {
    "features.0.weight": (64, 3, 11, 11),
    "features.0.bias": (64,),
    "features.3.weight": (192, 64, 5, 5),
    "features.3.bias": (192,),
    "features.6.weight": (384, 192, 3, 3),
    "features.6.bias": (384,),
}
ALEXNET_CONV3_PARAMETERS = 994_624

#: Marks a sidecar as ours; bump the number if its fields change meaning.
SIDECAR_FORMAT = "cortexloc-alexnet-conv3/1"

#: A download larger than this is refused: the real file is about 233 MB, so 1 GiB only stops a
#: misbehaving server from filling the disk.
MAX_DOWNLOAD_BYTES = 2**30

_CHUNK = 1 << 20
_HEX64 = re.compile(r"[0-9a-f]{64}")
_HEX_PREFIX = re.compile(r"[0-9a-f]{8,64}")

ProgressFn = Callable[[int, int | None], None]


class WeightsError(RuntimeError):
    """A weights file is missing, unverifiable, corrupted, of the wrong shape, or cannot be fetched.

    The message says which file, what was expected, what was found, and how to fix it.
    """


# ---------------------------------------------------------------------------------------------- paths


def default_cache_dir() -> Path:
    """Directory that holds installed weights.

    Returns:
        `$CORTEXLOC_WEIGHTS_DIR` if set and non-empty, else `~/.cache/cortexloc/weights`. The
        environment is read on every call, never at import time, so tests and the service's settings
        can change it.
    """
    env = os.environ.get("CORTEXLOC_WEIGHTS_DIR", "").strip()
    if env:
        return Path(env).expanduser()
    return Path.home() / ".cache" / "cortexloc" / "weights"


def trimmed_name(prefix: str) -> str:
    """File name of an installed trimmed checkpoint, e.g. `alexnet-conv3-7be5be79.pt`.

    Args:
        prefix: at least 8 hex digits of the ORIGINAL checkpoint's SHA-256; the first 8 are used.
    """
    return f"alexnet-conv3-{_check_prefix(prefix)[:8]}.pt"


def sidecar_path(path: str | Path) -> Path:
    """The sidecar JSON of a weights file: the same name with the suffix replaced by `.json`."""
    return Path(path).with_suffix(".json")


def _check_prefix(prefix: str) -> str:
    p = prefix.strip().lower()
    if not _HEX_PREFIX.fullmatch(p):
        raise ValueError(f"expected_prefix must be 8 to 64 hex digits of a SHA-256, got {prefix!r}")
    return p


def _resolve_dir(dest_dir: str | Path | None) -> Path:
    return Path(dest_dir).expanduser() if dest_dir is not None else default_cache_dir()


# ------------------------------------------------------------------------------- checkpoint content


def load_checkpoint(source: str | Path | BinaryIO, label: str | None = None) -> Any:
    """`torch.load(source, map_location="cpu", weights_only=True)` with errors turned into WeightsError.

    `weights_only=True` is a security boundary: a downloaded or user-supplied pickle must not be able to
    run code. It accepts torchvision's checkpoint (an OrderedDict of tensors) and our trimmed files.

    Args:
        source: a path or a binary file object.
        label: how to name the file in messages (defaults to the path).
    """
    name = label if label is not None else str(source)
    try:
        return torch.load(source, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises UnpicklingError, RuntimeError, EOFError, ... for bad files
        raise WeightsError(
            f"{name} is not a loadable PyTorch checkpoint ({type(exc).__name__}: {exc}); expected the "
            f"torchvision AlexNet file or a trimmed conv1..conv3 file") from exc


def _fmt_shape(shape: Any) -> str:
    return "(" + ", ".join(str(int(s)) for s in shape) + ")"


def extract_conv3_state(obj: Any, label: str) -> dict[str, torch.Tensor]:
    """The six conv1..conv3 tensors of a loaded checkpoint, checked.

    Other keys (torchvision's classifier) are ignored. Every tensor is copied into its own contiguous
    float32 storage so the rest of a full checkpoint can be freed.

    Args:
        obj: what `load_checkpoint` returned: a mapping from state-dict keys to tensors.
        label: the file's name, for messages.

    Returns:
        dict with the keys of `ALEXNET_CONV3_SHAPES`, in that order, float32 tensors of those shapes.

    Raises:
        WeightsError: not a mapping, a key missing, a value not a floating tensor, a shape different
            from docs/design/science.md §6 (the message names the key, its shape and the expected one), or a
            non-finite value (it would turn every descriptor into NaN).
    """
    if not isinstance(obj, Mapping):
        raise WeightsError(
            f"{label}: expected a state dict (mapping of key -> tensor), got {type(obj).__name__}")
    missing = [k for k in ALEXNET_CONV3_SHAPES if k not in obj]
    if missing:
        raise WeightsError(
            f"{label}: missing {', '.join(missing)}; an AlexNet checkpoint with torchvision key names "
            f"(features.{{0,3,6}}.{{weight,bias}}) is required")
    state: dict[str, torch.Tensor] = {}
    for key, want in ALEXNET_CONV3_SHAPES.items():
        t = obj[key]
        if not isinstance(t, torch.Tensor):
            raise WeightsError(f"{label}: {key} is a {type(t).__name__}, not a tensor")
        if tuple(t.shape) != want:
            raise WeightsError(
                f"{label}: {key} has shape {_fmt_shape(t.shape)} but AlexNet conv1..conv3 needs "
                f"{_fmt_shape(want)}")
        if not t.is_floating_point():
            raise WeightsError(f"{label}: {key} has dtype {t.dtype}, expected a floating-point tensor")
        t = t.detach().to(device="cpu", dtype=torch.float32).contiguous().clone()
        if not bool(torch.isfinite(t).all()):
            raise WeightsError(f"{label}: {key} contains NaN or infinite values")
        state[key] = t
    return state


# --------------------------------------------------------------------------------------------- sidecar


def read_sidecar(path: str | Path) -> dict[str, Any] | None:
    """The sidecar of a weights file, if it has one of ours.

    Args:
        path: the weights file (not the sidecar).

    Returns:
        The sidecar's fields, or None when there is no sidecar or the JSON file next to it is not one of
        ours (no `"format": SIDECAR_FORMAT`), so an unrelated `foo.json` beside `foo.pth` is ignored.

    Raises:
        WeightsError: the sidecar is unreadable, not JSON, or ours but with malformed digests.
    """
    side = sidecar_path(path)
    if not side.is_file():
        return None
    try:
        meta = json.loads(side.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise WeightsError(
            f"sidecar {side} is unreadable ({exc}); delete it and reinstall the weights") from exc
    if not isinstance(meta, dict) or meta.get("format") != SIDECAR_FORMAT:
        return None
    for field in ("original_sha256", "trimmed_sha256"):
        if not isinstance(meta.get(field), str) or not _HEX64.fullmatch(meta[field]):
            raise WeightsError(f"sidecar {side}: field {field!r} is not a SHA-256 hex digest; reinstall")
    return meta


# ------------------------------------------------------------------------------------ atomic install


def _write_bytes(target: Path, data: bytes) -> None:
    atomic_write(target, lambda f: f.write(data))


def _install(full: Path, original_sha256: str, original_bytes: int, source: str, dest: Path) -> Path:
    """Trim a verified full checkpoint and install trimmed file + sidecar into `dest`."""
    state = extract_conv3_state(load_checkpoint(full, label=source), label=source)
    # Serialised in memory, not to a named file: torch.save names the zip's root folder after the file,
    # which would make the bytes (and their digest) depend on the temporary name.
    buf = io.BytesIO()
    torch.save(state, buf)
    data = buf.getvalue()
    target = dest / trimmed_name(original_sha256)
    meta = {
        "format": SIDECAR_FORMAT,
        "original_sha256": original_sha256,
        "original_bytes": original_bytes,
        "trimmed_sha256": hashlib.sha256(data).hexdigest(),
        "trimmed_bytes": len(data),
        "trimmed_file": target.name,
        "keys": list(ALEXNET_CONV3_SHAPES),
        "parameters": ALEXNET_CONV3_PARAMETERS,
        "source": source,
        "installed_at": datetime.now(UTC).isoformat(timespec="seconds"),
    }
    # Sidecar first, weights second: the trimmed file's presence marks a complete install, so a crash in
    # between leaves a sidecar without weights, which `find_alexnet` reports as "not installed".
    _write_bytes(sidecar_path(target), (json.dumps(meta, indent=2) + "\n").encode("utf-8"))
    _write_bytes(target, data)
    return target


def _refuse_digest(digest: str, prefix: str, source: str) -> WeightsError:
    return WeightsError(
        f"{source}: SHA-256 {digest} does not start with {prefix}; refusing it (corrupted, truncated or "
        f"not torchvision's AlexNet checkpoint). Nothing was installed.")


# ----------------------------------------------------------------------------------------- public API


def download_alexnet(dest_dir: str | Path | None = None, url: str = ALEXNET_URL,
                     expected_prefix: str = ALEXNET_SHA256_PREFIX, timeout: float = 60.0,
                     progress: ProgressFn | None = None) -> Path:
    """Download torchvision's AlexNet checkpoint, verify it, and install the trimmed conv1..conv3 file.

    The SHA-256 is computed while streaming into a temporary file inside `dest_dir` (same filesystem, so
    nothing is copied twice); the temporary file is always removed.

    Args:
        dest_dir: install directory; None: `default_cache_dir()`. Created if missing.
        url: http(s) address of the full checkpoint.
        expected_prefix: hex digits the file's SHA-256 must start with (8 to 64).
        timeout: socket timeout in seconds for connecting and for each read.
        progress: called as `progress(bytes_so_far, total_or_None)` after each chunk.

    Returns:
        Path of the installed trimmed file (its sidecar is `sidecar_path(returned)`).

    Raises:
        WeightsError: unreachable server, HTTP error, transfer cut off (fewer bytes than Content-Length,
            IncompleteRead, connection reset, timeout), digest mismatch, or unexpected content. Nothing
            is installed in any of these cases.
        ValueError: `url` is not http(s) or `expected_prefix` is not hex.
    """
    prefix = _check_prefix(expected_prefix)
    if urllib.parse.urlsplit(url).scheme not in ("http", "https"):
        raise ValueError(f"url must be http(s), got {url!r}")
    dest = _resolve_dir(dest_dir)
    try:
        request = urllib.request.Request(url, headers={"User-Agent": "cortexloc-weights/1"})
        response = urllib.request.urlopen(request, timeout=timeout)  # scheme checked above
    except urllib.error.HTTPError as exc:
        raise WeightsError(f"download of {url} failed: HTTP {exc.code} {exc.reason}") from exc
    except (urllib.error.URLError, http.client.HTTPException, OSError) as exc:
        reason = getattr(exc, "reason", exc)
        raise WeightsError(
            f"cannot reach {url} ({reason}). On a machine without internet, copy "
            f"alexnet-owt-{ALEXNET_SHA256_PREFIX}.pth over and run `cortexloc weights import PATH`.") from exc
    with response:
        header = response.headers.get("Content-Length")
        total = int(header) if header is not None and header.strip().isdigit() else None
        if total is not None and total > MAX_DOWNLOAD_BYTES:
            raise WeightsError(f"{url} announces {total} bytes, more than the {MAX_DOWNLOAD_BYTES} allowed")
        dest.mkdir(parents=True, exist_ok=True)
        fd, tmp_name = tempfile.mkstemp(dir=dest, prefix=".alexnet-download-", suffix=".part")
        tmp = Path(tmp_name)
        try:
            h = hashlib.sha256()
            n = 0
            with os.fdopen(fd, "wb") as f:
                try:
                    while chunk := response.read(_CHUNK):
                        h.update(chunk)
                        f.write(chunk)
                        n += len(chunk)
                        if n > MAX_DOWNLOAD_BYTES:
                            raise WeightsError(f"{url} sent more than {MAX_DOWNLOAD_BYTES} bytes; refused")
                        if progress is not None:
                            progress(n, total)
                except (http.client.HTTPException, OSError) as exc:
                    # IncompleteRead (chunked), ConnectionResetError, TimeoutError, ...
                    raise WeightsError(
                        f"transfer of {url} was cut off after {n} bytes ({type(exc).__name__}: {exc}); "
                        f"nothing was installed, try again") from exc
            # http.client returns b"" instead of raising when the peer closes before Content-Length
            # bytes arrived, so the count is checked here; the digest would catch it too, but this says why.
            if total is not None and n != total:
                raise WeightsError(
                    f"transfer of {url} was cut off: received {n} of {total} bytes; nothing was installed, "
                    f"try again")
            digest = h.hexdigest()
            if not digest.startswith(prefix):
                raise _refuse_digest(digest, prefix, url)
            return _install(tmp, digest, n, url, dest)
        finally:
            with contextlib.suppress(OSError):
                tmp.unlink()


def import_alexnet(path: str | Path, dest_dir: str | Path | None = None,
                   expected_prefix: str = ALEXNET_SHA256_PREFIX) -> Path:
    """Verify a local copy of torchvision's AlexNet checkpoint and install the trimmed file.

    For machines without internet: copy `alexnet-owt-7be5be79.pth` over by other means, then import.

    Args:
        path: the full checkpoint.
        dest_dir: install directory; None: `default_cache_dir()`. Created if missing.
        expected_prefix: hex digits the file's SHA-256 must start with (8 to 64).

    Returns:
        Path of the installed trimmed file.

    Raises:
        WeightsError: the file is missing, its digest does not match, or its content is wrong (a shape
            error names the key). Nothing is installed then.
    """
    prefix = _check_prefix(expected_prefix)
    src = Path(path).expanduser()
    if not src.is_file():
        raise WeightsError(f"weights file {src} does not exist")
    digest = sha256_file(src)
    if not digest.startswith(prefix):
        raise _refuse_digest(digest, prefix, str(src))
    dest = _resolve_dir(dest_dir)
    dest.mkdir(parents=True, exist_ok=True)
    return _install(src, digest, src.stat().st_size, str(src.resolve()), dest)


def find_alexnet(dest_dir: str | Path | None = None,
                 expected_prefix: str = ALEXNET_SHA256_PREFIX) -> Path | None:
    """The installed, verified trimmed file, or None when nothing is installed.

    Args:
        dest_dir: install directory; None: `default_cache_dir()`.
        expected_prefix: which original checkpoint to look for (its first 8 hex digits name the file).

    Returns:
        Path of `alexnet-conv3-<prefix>.pt`, or None when it does not exist (an interrupted install that
        left only the sidecar counts as not installed).

    Raises:
        WeightsError: the file exists but has no sidecar of ours, the sidecar names another original, or
            the file's SHA-256 differs from the one recorded at install time (corrupted: reinstall).
    """
    prefix = _check_prefix(expected_prefix)
    target = _resolve_dir(dest_dir) / trimmed_name(prefix)
    if not target.is_file():
        return None
    meta = read_sidecar(target)
    if meta is None:
        raise WeightsError(
            f"{target} has no sidecar {sidecar_path(target).name}, so it cannot be verified; reinstall with "
            f"`cortexloc weights download` or `cortexloc weights import PATH`")
    if not meta["original_sha256"].startswith(prefix):
        raise WeightsError(
            f"sidecar of {target} records original SHA-256 {meta['original_sha256']}, which does not start "
            f"with {prefix}; reinstall")
    actual = sha256_file(target)
    if actual != meta["trimmed_sha256"]:
        raise WeightsError(
            f"{target} is corrupted: SHA-256 {actual} but {meta['trimmed_sha256']} was recorded at install; "
            f"delete it and reinstall with `cortexloc weights download` or `cortexloc weights import PATH`")
    return target

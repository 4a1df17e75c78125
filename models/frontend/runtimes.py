"""Where a backbone runs: the torch reference, or its ONNX export on ONNX Runtime (docs/design/science.md
§6.1).

The torch module built from the shipped weights (`models.frontend.backbones`) is the reference: it
defines the descriptor. The `onnxruntime` runtime runs the same module exported to ONNX, built from
those weights on first use (nothing is downloaded) and stored content-addressed beside the weights:

    <cache>/onnx/<sha256>.onnx                        the exported graph, named by its own SHA-256
    <cache>/onnx/<arch>.<weights_id>.json             which file holds that backbone's export, for which
                                                      torch and opset (a new torch re-exports)

`<cache>` is `models.frontend.weights.default_cache_dir()`. A file whose bytes no longer hash to its
name is exported again, never run. Both runtimes take (N, 3, 224, 224) float32 and give (N, D) float32
rows of unit L2 norm, the same descriptors up to float rounding (tests/models/frontend/test_runtimes.py
checks the exported graph's TF-'SAME' padding and inference-mode BatchNorm, and codes on real frames).

Devices: `cpu`, `cuda` or `auto`. CUDA is ONNX Runtime's CUDA execution provider (the `gpu` extra
installs `onnxruntime-gpu`); the torch reference stays on the CPU (the pinned wheel is the CPU build).
`auto` takes CUDA where a session really runs on it and falls back to the CPU with a log line; `cuda`
refuses to start without it (`DeviceUnavailableError`), because a team that asked for a GPU must not be
served from the CPU without knowing.

Example:
    >>> runner = make_runner(backbone, runtime="onnxruntime", device="auto", threads=1)
    >>> runner.device, runner(np.zeros((2, 3, 224, 224), np.float32)).shape
    ('cpu', (2, 5488))
"""

from __future__ import annotations

import hashlib
import json
import logging
import re
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import torch

from models.frontend.backbones import Backbone
from storage.base.files import atomic_write

__all__ = ["DEVICES", "OPSET", "RUNTIMES", "DeviceUnavailableError", "OnnxRunner", "Runner", "TorchRunner",
           "export_onnx", "make_runner", "onnx_model"]

log = logging.getLogger("cortexloc.encoder")

#: Backbone runtimes; the first is the default (the fastest that computes the same codes,
#: docs/benchmarks.md §10).
RUNTIMES = ("onnxruntime", "torch")
DEVICES = ("cpu", "cuda", "auto")
#: ONNX opset of the exports (torch 2.13's exporter supports 18 natively).
OPSET = 18
MANIFEST_FORMAT = "cortexloc-onnx/1"

#: Exports made by this process, by (arch, weights id, torch, opset): a store in another directory
#: (a test's, a second data directory) costs a write, not a second export.
_EXPORTS: dict[tuple[str, str, str, int], bytes] = {}

_CUDA = "CUDAExecutionProvider"
_CPU = "CPUExecutionProvider"
_SHA_RE = re.compile(r"[0-9a-f]{64}")


class DeviceUnavailableError(RuntimeError):
    """`device="cuda"` was asked for and cannot be given here (the message says why and what to do)."""


class Runner(Protocol):
    """A backbone ready to run: `runner(batch)` (N, 3, 224, 224) float32 -> (N, D) float32."""

    runtime: str
    device: str

    def __call__(self, batch: np.ndarray) -> np.ndarray: ...


class TorchRunner:
    """The reference: the backbone's torch module on the CPU, under `torch.inference_mode()`."""

    runtime = "torch"
    device = "cpu"

    def __init__(self, describe: Callable[[torch.Tensor], torch.Tensor]) -> None:
        self._describe = describe

    def __call__(self, batch: np.ndarray) -> np.ndarray:
        with torch.inference_mode():
            return self._describe(torch.from_numpy(np.ascontiguousarray(batch))).numpy()


class OnnxRunner:
    """An exported backbone in an ONNX Runtime session.

    Args:
        model: the ONNX bytes (`onnx_model`).
        providers: execution providers in order of preference (`providers_for`).
        threads: intra-op threads (the encoder's `torch_threads`: one thread budget whatever the runtime).
    """

    runtime = "onnxruntime"

    def __init__(self, model: bytes, providers: Sequence[str], threads: int) -> None:
        import onnxruntime as ort

        options = ort.SessionOptions()
        options.intra_op_num_threads = int(threads)
        options.inter_op_num_threads = 1
        options.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
        # Idle pool threads would spin on cores the decode threads and the map writers need.
        options.add_session_config_entry("session.intra_op.allow_spinning", "0")
        self.session = ort.InferenceSession(model, options, providers=list(providers))
        # ONNX Runtime drops a provider it cannot load with only a warning: what the session really
        # runs on is read back, not assumed from what was asked.
        self.device = "cuda" if self.session.get_providers()[0] == _CUDA else "cpu"
        self._input = self.session.get_inputs()[0].name

    def __call__(self, batch: np.ndarray) -> np.ndarray:
        return self.session.run(None, {self._input: np.ascontiguousarray(batch, np.float32)})[0]


# ---------------------------------------------------------------------------------------- export


class _Describe(torch.nn.Module):
    # torch.onnx.export takes a module; the descriptor is a method (or the module itself).
    def __init__(self, backbone: Backbone) -> None:
        super().__init__()
        self.module = backbone.module
        # Not a second submodule name for the same parameters (AlexNet's describe is its module).
        object.__setattr__(self, "_describe", backbone.describe)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self._describe(x)


def export_onnx(backbone: Backbone) -> bytes:
    """The backbone's descriptor exported to ONNX (opset `OPSET`, batch size dynamic): serialised bytes.

    torch's `dynamo` exporter (the supported one; the TorchScript exporter is deprecated) traces the
    module in eval mode: BatchNorm is exported with its running statistics (inference mode) and the
    TF-'SAME' stride-2 convolutions as an explicit asymmetric Pad before the Conv, as torch computes them.
    """
    module = _Describe(backbone).eval()
    example = torch.zeros(2, 3, 224, 224)
    batch = torch.export.Dim("batch", min=1, max=4096)
    program = torch.onnx.export(module, (example,), dynamo=True, verbose=False, opset_version=OPSET,
                                input_names=["x"], output_names=["descriptor"],
                                dynamic_shapes={"x": {0: batch}})
    assert program is not None
    return program.model_proto.SerializeToString()


def _manifest_path(directory: Path, backbone: Backbone) -> Path:
    return directory / f"{backbone.arch}.{backbone.weights_id}.json"


def _stored(directory: Path, backbone: Backbone) -> tuple[bytes, str] | None:
    """The export recorded for this backbone, torch and opset, if its bytes still hash to its name."""
    try:
        meta = json.loads(_manifest_path(directory, backbone).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    want = {"format": MANIFEST_FORMAT, "torch": torch.__version__, "opset": OPSET}
    sha = meta.get("sha256") if isinstance(meta, dict) else None
    if (not isinstance(sha, str) or not _SHA_RE.fullmatch(sha)
            or any(meta.get(k) != v for k, v in want.items())):
        return None
    try:
        data = (directory / f"{sha}.onnx").read_bytes()
    except OSError:
        return None
    if hashlib.sha256(data).hexdigest() != sha:
        log.warning("%s/%s.onnx does not match its SHA-256; exporting the backbone again", directory, sha)
        return None
    return data, sha


def onnx_model(backbone: Backbone, directory: Path | None) -> tuple[bytes, str]:
    """The ONNX export of `backbone`: read from `directory` when stored and intact, else exported from
    the torch module (a few seconds, once per process) and stored there.

    Args:
        backbone: the built torch backbone (its `arch` and `weights_id` key the store).
        directory: the content-addressed store; None: export in memory, store nothing.

    Returns:
        (ONNX bytes, their SHA-256).
    """
    if directory is not None:
        found = _stored(directory, backbone)
        if found is not None:
            return found
    key = (backbone.arch, backbone.weights_id, torch.__version__, OPSET)
    data = _EXPORTS.get(key)
    if data is None:
        data = _EXPORTS[key] = export_onnx(backbone)
    sha = hashlib.sha256(data).hexdigest()
    if directory is not None:
        meta = {"format": MANIFEST_FORMAT, "sha256": sha, "arch": backbone.arch,
                "weights_id": backbone.weights_id, "torch": torch.__version__, "opset": OPSET}
        try:
            directory.mkdir(parents=True, exist_ok=True)
            # The graph first, then the manifest that names it: a crash in between leaves an unnamed file.
            atomic_write(directory / f"{sha}.onnx", lambda f: f.write(data))
            atomic_write(_manifest_path(directory, backbone),
                         lambda f: f.write((json.dumps(meta, indent=2) + "\n").encode()))
        except OSError as e:  # a read-only cache costs an export per start, not the service
            log.warning("cannot store the ONNX export of %s in %s (%s); it is kept in memory",
                        backbone.arch, directory, e)
    return data, sha


# ---------------------------------------------------------------------------------------- devices


def providers_for(device: str, available: Sequence[str]) -> list[str]:
    """ONNX Runtime execution providers for `device`, given the ones this install offers.

    Raises:
        DeviceUnavailableError: `cuda` asked for and this ONNX Runtime has no CUDA provider.
        ValueError: not one of `DEVICES`.
    """
    if device not in DEVICES:
        raise ValueError(f"device must be one of {', '.join(DEVICES)}, got {device!r}")
    if device == "cpu":
        return [_CPU]
    if _CUDA in available:
        return [_CUDA, _CPU]
    if device == "cuda":
        raise DeviceUnavailableError(
            f"CORTEXLOC_DEVICE=cuda but this ONNX Runtime offers only {', '.join(available)}: install the "
            f"`gpu` extra (onnxruntime-gpu in place of onnxruntime) on a machine with CUDA, or use auto/cpu")
    return [_CPU]


def make_runner(backbone: Backbone, runtime: str, device: str, threads: int,
                export_dir: Path | None = None, available: Sequence[str] | None = None) -> Runner:
    """The backbone on `runtime` and `device`.

    Args:
        backbone: the built torch backbone (the reference, and the source of the export).
        runtime: one of `RUNTIMES`.
        device: one of `DEVICES`; `auto` falls back to the CPU with an INFO log line.
        threads: intra-op threads.
        export_dir: the ONNX store (`onnx_model`); None: export in memory.
        available: ONNX Runtime's available providers (None: ask it; tests pass a list).

    Raises:
        DeviceUnavailableError: `cuda` asked for, and no CUDA here (not installed, or the session fell back).
        ValueError: unknown runtime or device.
    """
    if runtime not in RUNTIMES:
        raise ValueError(f"runtime must be one of {', '.join(RUNTIMES)}, got {runtime!r}")
    if device not in DEVICES:
        raise ValueError(f"device must be one of {', '.join(DEVICES)}, got {device!r}")
    if runtime == "torch":
        if device == "cuda":
            raise DeviceUnavailableError("CORTEXLOC_DEVICE=cuda needs the onnxruntime runtime: the torch "
                                         "reference runs on the CPU (the pinned wheel is the CPU build)")
        if device == "auto":
            log.info("device auto: the torch reference runtime runs on the CPU")
        return TorchRunner(backbone.describe)
    import onnxruntime as ort

    offered = list(ort.get_available_providers() if available is None else available)
    providers = providers_for(device, offered)
    data, sha = onnx_model(backbone, export_dir)
    runner = OnnxRunner(data, providers, threads)
    if device != "cpu" and runner.device != "cuda":
        why = ("no CUDA execution provider in this install" if _CUDA not in providers
               else "ONNX Runtime could not start its CUDA provider (driver or CUDA libraries missing)")
        if device == "cuda":
            raise DeviceUnavailableError(f"CORTEXLOC_DEVICE=cuda: {why}; install the `gpu` extra on a "
                                         f"machine with CUDA, or use auto/cpu")
        log.info("device auto: %s; the encoder runs on the CPU", why)
    log.debug("backbone %s on onnxruntime (%s), export sha256 %s", backbone.arch, runner.device, sha)
    return runner


def describe_runner(runner: Runner) -> dict[str, Any]:
    """{"runtime", "device"}: what /readyz and every reply's `versions` report."""
    return {"runtime": runner.runtime, "device": runner.device}

"""A real local Ray cluster and `cortexloc serve --ray` on it, for the scale-out's tests and benchmark.

`ray start --head --block` in its own session with its own temp directory (a short path: Ray's socket
names must fit in 107 bytes), few logical CPUs, a small object store and no dashboard; torn down by
ending that session's processes, whatever the test did.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import httpx

ROOT = Path(__file__).resolve().parents[2]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _stop(proc: subprocess.Popen | None, timeout: float = 60) -> None:
    """End a process we started and everything in its session."""
    if proc is None:
        return
    for sig in (signal.SIGTERM, signal.SIGKILL):
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.killpg(proc.pid, sig)
        try:
            proc.wait(timeout=timeout)
            break
        except subprocess.TimeoutExpired:
            continue


class RayCluster:
    """`start()` the head, `serve(...)` the application, `stop()` both (idempotent)."""

    def __init__(self, work: Path, env: dict[str, str]) -> None:
        self.work = work
        self.env = {**{k: v for k, v in os.environ.items() if not k.startswith("CORTEXLOC_")}, **env,
                    "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])),
                    "RAY_USAGE_STATS_ENABLED": "0", "RAY_DEDUP_LOGS": "0",
                    # a throwaway loopback cluster: a token the user keeps in ~/.ray (token
                    # authentication) is not this cluster's, and with it the CLI could not connect
                    "RAY_AUTH_MODE": "disabled"}
        self.temp = Path(tempfile.mkdtemp(prefix="cxray-", dir="/tmp"))
        self.head: subprocess.Popen | None = None
        self.server: subprocess.Popen | None = None
        self.address = ""
        self.base = ""
        self.data_dir = work / "var"

    def start(self, num_cpus: int = 4) -> str:
        gcs_port = free_port()
        self.address = f"127.0.0.1:{gcs_port}"
        ray = Path(sys.executable).with_name("ray")
        self.head_log = (self.work / "ray-head.log").open("a")
        self.head = subprocess.Popen(
            [str(ray), "start", "--head", "--block", f"--port={gcs_port}", "--node-ip-address=127.0.0.1",
             f"--num-cpus={num_cpus}", "--num-gpus=0", "--object-store-memory=80000000",
             "--include-dashboard=false", "--disable-usage-stats", f"--temp-dir={self.temp}"],
            env=self.env, stdout=self.head_log, stderr=self.head_log, start_new_session=True)
        return self.address

    def serve(self, shards: int = 2, encoder_replicas: int = 1, timeout: float = 420) -> str:
        port = free_port()
        self.server_log = (self.work / "serve.log").open("a")
        self.server = subprocess.Popen(
            [sys.executable, "-m", "service.cli", "serve", "--ray", "--ray-address", self.address,
             "--host", "127.0.0.1", "--port", str(port), "--data-dir", str(self.data_dir),
             "--shards", str(shards), "--encoder-replicas", str(encoder_replicas)],
            env=self.env, stdout=self.server_log, stderr=self.server_log, cwd=ROOT, start_new_session=True)
        self.base = f"http://127.0.0.1:{port}"
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.server.poll() is not None:
                raise RuntimeError(f"`cortexloc serve --ray` exited: {self.logs()}")
            with contextlib.suppress(httpx.HTTPError):
                if httpx.get(f"{self.base}/readyz", timeout=10).status_code == 200:
                    return self.base
            time.sleep(1)
        raise RuntimeError(f"the Ray application was not ready within {timeout} s: {self.logs()}")

    def logs(self, tail: int = 4000) -> str:
        out = []
        for name in ("serve.log", "ray-head.log"):
            p = self.work / name
            if p.exists():
                out.append(f"--- {name}\n{p.read_text(errors='replace')[-tail:]}")
        for p in sorted(self.temp.glob("session_latest/logs/serve/*.log"))[-6:]:
            out.append(f"--- {p.name}\n{p.read_text(errors='replace')[-tail:]}")
        return "\n".join(out)

    def cli(self, *args: str, timeout: float = 300) -> subprocess.CompletedProcess:
        return subprocess.run([sys.executable, "-m", "service.cli", *args], env=self.env, cwd=ROOT,
                              capture_output=True, text=True, timeout=timeout)

    def pids(self, *deployments: str) -> dict[str, int]:
        """The process id of each deployment's replica (`shard-<i>`, `Encoder`, `Ingress`: one replica
        each here), asked through Ray from one separate driver."""
        code = ("import ray, sys; from ray import serve; "
                "ray.init(address=sys.argv[1], logging_level='ERROR', log_to_driver=False); "
                "print(*(serve.get_deployment_handle(d, 'cortexloc').pid.remote().result(timeout_s=120) "
                "for d in sys.argv[2:]))")
        out = subprocess.run([sys.executable, "-c", code, self.address, *deployments], env=self.env,
                             capture_output=True, text=True, timeout=300)
        if out.returncode != 0:
            raise RuntimeError(out.stderr[-2000:])
        return dict(zip(deployments, map(int, out.stdout.strip().splitlines()[-1].split()), strict=True))

    def routes(self) -> dict[str, tuple[str, str]]:
        """`cortexloc shards list`: map -> (shard, state)."""
        out = self.cli("shards", "list", "--address", self.address)
        if out.returncode != 0:
            raise RuntimeError(out.stderr[-2000:])
        return {m: (s, st) for m, s, st in (line.split("\t") for line in out.stdout.splitlines())}

    def stop(self) -> None:
        _stop(self.server)
        self.server = None
        _stop(self.head)
        self.head = None
        shutil.rmtree(self.temp, ignore_errors=True)

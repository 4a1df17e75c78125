"""What the client needs installed: pydantic 2, said plainly where an older one shadows it (ROS 2's apt
packages ship pydantic 1)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import cortexloc_client

CLIENT_DIR = Path(cortexloc_client.__file__).resolve().parents[1]


def test_pydantic_1_is_named_at_import(tmp_path: Path) -> None:
    fake = tmp_path / "pydantic"
    fake.mkdir()
    (fake / "__init__.py").write_text('VERSION = "1.10.14"\n')  # Ubuntu 24.04's python3-pydantic
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path), str(CLIENT_DIR)])}
    run = subprocess.run([sys.executable, "-c", "import cortexloc_client"], env=env, capture_output=True,
                         text=True, timeout=60)
    assert run.returncode != 0
    assert "ImportError: cortexloc_client needs pydantic 2, found pydantic 1.10.14" in run.stderr
    assert "Beside ROS 2" in run.stderr


def test_the_service_limits_the_client_states_are_the_services():
    # the client states them for the ROS node and robots (installed without the service); they must not
    # drift from the service's own homes
    from service.routes.observations import POSE_MAX_ABS, YAW_MAX_ABS
    from service.schemas import STREAM_PATTERN as SERVICE_STREAM_PATTERN
    from service.settings import Settings

    assert cortexloc_client.STREAM_PATTERN == SERVICE_STREAM_PATTERN
    assert Settings.model_fields["max_top_k"].default == cortexloc_client.MAX_TOP_K
    assert (cortexloc_client.POSE_MAX_ABS, cortexloc_client.YAW_MAX_ABS) == (POSE_MAX_ABS, YAW_MAX_ABS)


def test_the_client_and_cortexloc_ingest_resend_the_same_proxy_pages():
    from cortexloc_client import _core
    from service.ingest.poster import PROXY_STATUSES

    assert _core.PROXY_STATUSES == PROXY_STATUSES


def test_the_client_expects_the_media_types_the_service_sends():
    from cortexloc_client import _core
    from service.maps.closures import EXPORT_FORMATS
    from service.media_types import TAR_MEDIA_TYPE

    assert {f: t.split(";")[0] for f, t in EXPORT_FORMATS.items()} == _core.EXPORT_MEDIA_TYPES
    assert _core.TAR_MEDIA_TYPE == TAR_MEDIA_TYPE

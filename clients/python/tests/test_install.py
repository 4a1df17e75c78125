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

"""The README's "With ROS 2" leads with three commands, from install to loop closures on a topic: this runs
exactly those lines (the first bash block of that section), in a loopback-only network namespace, with
the service's data in a temporary folder, and reads the loop closures the demo prints."""

from __future__ import annotations

import os
import re
import signal
import subprocess

import pytest

from tests.clients.ros2.harness import REPO, WEIGHTS_ENV, in_loopback_netns


def readme_commands() -> str:
    """The first ```bash block under '## With ROS 2' in README.md, as written."""
    text = (REPO / "README.md").read_text()
    section = text[text.index("## With ROS 2\n"):]
    return re.search(r"```bash\n(.*?)```", section, re.DOTALL).group(1)


def test_the_section_leads_with_three_commands_from_install_to_loop_closures():
    lines = [line for line in readme_commands().splitlines() if line.strip()]
    assert [line.split("#")[0].strip() for line in lines] == [
        "make install-ros", ".venv/bin/cortexloc serve &", ".venv/bin/cortexloc-ros-demo"]


@in_loopback_netns
def test_the_readmes_three_commands_print_loop_closures_from_the_topic(tmp_path):
    if subprocess.run(["make", "-q", "install-ros"], cwd=REPO, capture_output=True).returncode != 0:
        pytest.skip("make install-ros is not up to date: run it first (the namespace reaches no registry)")
    # the block as written; then the backgrounded service ($!) is ended by its PID
    script = readme_commands() + 'status=$?\nkill "$!" 2>/dev/null\nwait "$!" 2>/dev/null\nexit "$status"\n'
    env = {k: v for k, v in os.environ.items() if not k.startswith("CORTEXLOC_")}
    env.update({"CORTEXLOC_DATA_DIR": str(tmp_path / "var"), "CORTEXLOC_WEIGHTS_DIR": os.environ[WEIGHTS_ENV],
                "CORTEXLOC_LOG_FORMAT": "text"})
    proc = subprocess.Popen(["sh", "-c", script], cwd=REPO, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, start_new_session=True)
    try:
        out, _ = proc.communicate(timeout=300)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)  # the shell, the service and the demo's node
        out, _ = proc.communicate()
        pytest.fail(f"the README's commands did not finish in 300 s:\n{out[-6000:]}")
    assert proc.returncode == 0, out[-6000:]
    closures = re.findall(r"^loop closure: .* confidence (\d\.\d\d)", out, re.MULTILINE)
    print(f"{len(closures)} loop closures printed; confidences {closures}")
    assert len(closures) >= 5, out[-6000:]
    summary = re.search(r"^60/60 frames answered, (\d+) revisits, (\d+) loop closures on "
                        r"/cortexloc/loop_closures", out, re.MULTILINE)
    assert summary and int(summary[1]) == int(summary[2]) == len(closures), out[-3000:]

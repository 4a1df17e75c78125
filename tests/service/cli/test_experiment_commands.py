"""Every `cortexloc eval` and `cortexloc bench` command answers `--help` (exit 0), and the help imports
no heavy library: each command imports its run logic only when it runs (benchmarks/__init__.py)."""

from __future__ import annotations

import subprocess
import sys

import typer.main
from typer.testing import CliRunner

from service.cli import app


def group_commands(name: str) -> list[str]:
    """The names of the sub-commands of group `name` of the `cortexloc` app."""
    group = typer.main.get_command(app)
    return sorted(getattr(group, "commands", {})[name].commands)


def test_every_eval_and_bench_command_answers_help() -> None:
    runner = CliRunner()
    checked = []
    for group in ("eval", "bench"):
        commands = group_commands(group)
        assert commands, group
        for name in commands:
            result = runner.invoke(app, [group, name, "--help"])
            assert result.exit_code == 0, (group, name, result.output)
            assert "Usage:" in result.output
            checked.append(f"{group} {name}")
    # the experiments and benchmarks that were argparse scripts are among them
    for expected in ("eval grid-sweep", "eval nordland-tables", "eval geometry", "eval slam-seasons",
                     "bench http", "bench all", "bench tm-suite", "bench profile-service"):
        assert expected in checked


def test_help_of_every_experiment_and_benchmark_imports_no_torch_or_cv2() -> None:
    code = ("import sys\n"
            "from typer.testing import CliRunner\n"
            "from service.cli import app\n"
            "import typer, click\n"
            "group = typer.main.get_command(app)\n"
            "for g in ('eval', 'bench'):\n"
            "    for name in group.commands[g].commands:\n"
            "        assert CliRunner().invoke(app, [g, name, '--help']).exit_code == 0, name\n"
            "print('torch' in sys.modules, 'cv2' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["False", "False"]


def test_an_unknown_window_is_refused_before_any_frame_is_encoded() -> None:
    # found by a review: `eval runtime-parity --windows 9-99` encoded nothing and ended in a KeyError
    r = CliRunner().invoke(app, ["eval", "runtime-parity", "--windows", "1-200,9-99"])
    assert r.exit_code == 2 and "no window 9-99" in " ".join(r.output.split()), r.output


def test_an_unknown_growth_route_is_refused_before_any_frame_is_encoded() -> None:
    r = CliRunner().invoke(app, ["bench", "growth", "--routes", "exact,autumn"])
    assert r.exit_code == 2 and "unknown route(s) autumn" in " ".join(r.output.split()), r.output

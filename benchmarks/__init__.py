"""Experiments and benchmarks: the run logic behind `cortexloc eval <name>` and `cortexloc bench <name>`.

One home for every measurement, with one rule for where it goes (docs/benchmarks.md opens with it):

- an **experiment** (what a table of docs/results.md comes from: recall, precision, AUC, merged places)
  is `cortexloc eval <name>`;
- a **speed or memory measurement** (medians, throughput, RSS; docs/benchmarks.md) is
  `cortexloc bench <name>`.

Each is a typer command with typed options and `--help`, declared in `service/cli/` (`bench.py` for
`bench`, `evaluate.py` and `experiments.py` for `eval`). A command's body imports its module here (or in
`models/evaluation/`, `service/evaluation/`) only when it runs, so `cortexloc --help` and every
`--help` import no torch or cv2. The modules here hold functions with keyword arguments (a `run(...)`
per command, the option defaults in the command only) and parse no command line: argparse appears
nowhere in models/, service/ or benchmarks/ (tests/test_architecture.py).

Why a package: the installed `cortexloc` must reach this code from any working directory, so the folder
is installed with the project (pyproject.toml `packages.find`), and import-linter's contracts cover it:
only `service.cli` imports it, and it never imports `service.cli`. It stays out of `models/` (pure core)
and `service/` (what is served): a benchmark drives the service from outside, through HTTP or its runtime.
JSON results go under benchmarks/results/ (ignored by git).
"""

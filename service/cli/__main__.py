"""`python -m service.cli`: the `cortexloc` command (tests and benchmarks start the server this way)."""

from service.cli import main

main()

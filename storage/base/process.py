"""Facts about this process that several layers report (the memory resource, benchmarks, evaluation)."""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["rss_bytes"]


def rss_bytes() -> int:
    """Resident set size of this process in bytes (Linux /proc; 0 where unavailable)."""
    try:
        pages = int(Path("/proc/self/statm").read_text().split()[1])
    except (OSError, IndexError, ValueError):
        return 0
    return pages * os.sysconf("SC_PAGE_SIZE")

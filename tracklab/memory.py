"""Memory an experiment needs, checked before anything compiles.

Each kind of experiment (and each command: run, sweep, tune) estimates the bytes of the
arrays it cannot do without — the random draws of one chunk of runs, the per-step outputs
of a closed-loop chunk, the residuals reverse mode keeps for every step of a tuning batch
(forward mode keeps none), the per-point statistics of a sweep. These are lower bounds:
intermediate values come on top. ``check`` refuses an experiment whose lower bound already
passes the machine's memory (or ``--max-memory``), in one line that says how much it would
need and what to shrink.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

from tracklab.errors import ConfigError

_SIZE_RE = re.compile(r"^\s*(\d+(?:\.\d*)?|\.\d+)\s*([kKmMgGtT]?)(i?[bB])?\s*$")
_UNITS = {"": 1, "k": 2**10, "m": 2**20, "g": 2**30, "t": 2**40}


def parse_size(text: str) -> int:
    """'512M', '8G', '8GiB', '1.5T' or a number of bytes -> bytes (ValueError if malformed)."""
    m = _SIZE_RE.match(text)
    if not m:
        raise ValueError("must be a size such as 512M, 8G or 1.5T (bytes with no unit)")
    v = float(m.group(1)) * _UNITS[m.group(2).lower()]
    if not v >= 1:
        raise ValueError("must be at least one byte")
    return int(v)


def machine_bytes() -> int:
    """Physical memory, or the control group's limit where that is lower."""
    try:
        total = os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        total = 2**62
    for path in ("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory/memory.limit_in_bytes"):
        try:
            text = Path(path).read_text().strip()
        except OSError:
            continue
        if text.isdigit():
            total = min(total, int(text))
    return total


def gib(n: float) -> str:
    return f"{n / 2**30:.3g} GiB" if n >= 2**30 else f"{n / 2**20:.3g} MiB"


def check(file, need: float, limit: int | None, what: str, shrink: str):
    """Refuse (ConfigError) when ``need`` bytes pass ``limit`` (default: the machine's memory)."""
    have = limit if limit is not None else machine_bytes()
    if need > have:
        source = "--max-memory" if limit is not None else "this machine's memory"
        raise ConfigError(file, "memory", gib(need),
                          f"{what} needs at least {gib(need)}, more than {source} ({gib(have)}): {shrink}")

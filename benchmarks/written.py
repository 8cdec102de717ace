"""A benchmark's Markdown file, written so that nothing else in it is lost.

Each script's run is one block between two comments that name the script. Writing a run
replaces that script's earlier block, or (``keep_earlier``, for a file that is a history of
runs) adds the new block above the earlier ones. Everything else the file holds — analysis
written beside the numbers, a table of earlier runs — stays where it was. A file without the
script's block gets the block right under its title, and keeps the rest below it.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path


def markers(script: str) -> tuple[str, str]:
    return f"<!-- {script}: a run, written by the script -->", f"<!-- {script}: end of the run -->"


def merged(old: str, text: str, script: str, keep_earlier: bool = False) -> str:
    """``old`` (the file's text, "" if none) with ``text`` (a run: its ``# title`` line, then the
    block) written in as ``script``'s run."""
    title, _, block = text.partition("\n")
    begin, end = markers(script)
    run = f"{begin}\n{block.strip()}\n{end}"
    if not old.strip():
        return f"{title}\n\n{run}\n"
    if not keep_earlier and begin in old and end in old[old.index(begin):]:
        i = old.index(begin)
        j = old.index(end, i) + len(end)
        return old[:i] + run + old[j:]
    first, _, rest = old.partition("\n")
    if first.startswith("# "):
        return f"{first}\n\n{run}\n\n{rest.lstrip(chr(10))}"
    return f"{title}\n\n{run}\n\n{old}"


def write_run(path, text: str, script: str, keep_earlier: bool = False) -> None:
    """Write ``text`` into ``path`` as ``script``'s run (see ``merged``), atomically."""
    path = Path(path)
    old = path.read_text() if path.exists() else ""
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w") as f:
            f.write(merged(old, text, script, keep_earlier))
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise

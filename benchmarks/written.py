"""A benchmark's Markdown file, written so that nothing else in it is lost.

Each script's run is one block between two comments that name the script. Writing a run
replaces that script's earlier block, or (``keep_earlier``, for a file that is a history of
runs) adds the new block above the earlier ones. Everything else the file holds — analysis
written beside the numbers, a table of earlier runs — stays where it was. A file without the
script's block gets the block right under its title, and keeps the rest below it.
"""

from __future__ import annotations

from pathlib import Path

from tracklab.output import write_text_atomically


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
    i = old.find(begin)
    j = old.find(end, i) if i >= 0 else -1
    if not keep_earlier and j >= 0:
        return old[:i] + run + old[j + len(end):]
    first, _, rest = old.partition("\n")
    if first.startswith("# "):
        rest = rest.lstrip("\n")
        return f"{first}\n\n{run}\n\n{rest}"
    return f"{title}\n\n{run}\n\n{old}"


def write_run(path, text: str, script: str, keep_earlier: bool = False) -> None:
    """Write ``text`` into ``path`` as ``script``'s run (see ``merged``), atomically."""
    path = Path(path)
    old = path.read_text() if path.exists() else ""
    write_text_atomically(path, merged(old, text, script, keep_earlier))

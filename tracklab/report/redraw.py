"""Figures drawn again from a results folder's stored statistics (``tracklab plot``): in other
formats (PDF, SVG for a paper), or figure kinds the experiment file did not ask for, without
running anything. The folder is replaced whole (``tracklab.output.atomic_folder``): its files are
copied into a temporary folder, the figures drawn there, and the two swapped."""

from __future__ import annotations

import shutil
from pathlib import Path

from tracklab.errors import ConfigError
from tracklab.output import atomic_folder, listed_files
from tracklab.report.airborne import plot_airborne
from tracklab.report.document import read_results, world_of
from tracklab.report.figures import chosen_kinds, plot_figures
from tracklab.report.servo import plot_servo


def redraw(folder, formats=("png",), kinds=None, field="FOLDER") -> list[str]:
    """Draw a run's results folder's figures again in ``formats``: the tracking world's kinds
    ``kinds`` (``FIGURE_KINDS``; default those its experiment file names, or every one), a
    closed-loop world's all. Returns the names of the figures written. A folder that is not a
    run's results (a sweep's, a tuning's, not tracklab's) is refused in one line."""
    folder = Path(folder)
    if not (folder / "stats.json").is_file():
        raise ConfigError("tracklab plot", field, str(folder), "must be a run's results folder (one holding stats.json: "
                          "tracklab run, tracklab reproduce)")
    doc = read_results(folder)
    world = world_of(doc)
    if kinds is not None and world != "tracking":
        raise ConfigError("tracklab plot", "--figures", ",".join(kinds), f"chooses among a tracking run's figures; "
                          f"a {world} folder's are drawn all")
    asked = set(kinds or ()) & {"run0", "run0_error"}
    if asked and "estimates" not in (doc.get("example_run") or {}):
        raise ConfigError("tracklab plot", "--figures", ",".join(sorted(asked)), "needs run 0's estimates, which this "
                          "folder did not keep (its experiment file's [report] figures names neither run0 nor "
                          "run0_error): name them there and run it again")
    with atomic_folder(folder, None, field, "tracklab plot") as tmp:
        for name in sorted(listed_files(folder) or (p.name for p in folder.iterdir() if p.is_file())):
            shutil.copy2(folder / name, tmp / name)
        before = {p.name: p.stat().st_mtime_ns for p in tmp.iterdir()}
        if world == "airborne":
            plot_airborne(doc, tmp, formats)
        elif world == "servo":
            plot_servo(doc, tmp, formats)
        else:
            plot_figures(doc, tmp, formats, chosen_kinds(doc, kinds))
        return sorted(p.name for p in tmp.iterdir() if before.get(p.name) != p.stat().st_mtime_ns)

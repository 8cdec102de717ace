"""What the command tells the user while it works, on stderr: each phase named as it starts
(compiling or loading the program, the runs with a progress bar and a time estimate, the figures
and files), through tqdm. Silent when stderr is not a terminal or with ``--quiet``: the table
on stdout and the exit status are then all there is."""

from __future__ import annotations

import shutil
import sys
import time


class Phases:
    """A command's phases and its runs' progress bar (``progress(done, total)``, the runner's
    callback). ``enabled``: False to stay silent."""

    def __init__(self, name: str, enabled: bool = True, unit: str = "runs"):
        self.name, self.unit = name, unit
        self.enabled = bool(enabled)
        self.bar = None
        self.started = time.perf_counter()

    def phase(self, what: str):
        """A phase starts: one line (the bar, if any, closed first)."""
        if not self.enabled:
            return
        self._close()
        print(f"{self.name}: {what}", file=sys.stderr, flush=True)

    def progress(self, done: int, total: int):
        """The runner's callback after each chunk: the bar (made at the first chunk, the program
        then compiled or loaded), its rate and time estimate; at the end the next phase."""
        if not self.enabled:
            return
        if self.bar is None:
            from tqdm import tqdm

            width = shutil.get_terminal_size((100, 24)).columns  # a terminal that reports no size: 100
            self.bar = tqdm(total=total, initial=0, unit=f" {self.unit}", unit_scale=True, file=sys.stderr,
                            desc=f"{self.name}: running", leave=True, ncols=min(width, 120))
        self.bar.total = total  # a run to a target precision learns its total as it goes
        self.bar.update(done - self.bar.n)
        if done >= total:
            self._close()

    def _close(self):
        if self.bar is not None:
            self.bar.close()
            self.bar = None

    def done(self, what: str):
        """The last phase's line, with the command's elapsed time."""
        if self.enabled:
            self._close()
            print(f"{self.name}: {what} ({time.perf_counter() - self.started:.1f} s in all)", file=sys.stderr,
                  flush=True)


def wanted(quiet: bool) -> bool:
    """Whether to tell the user what is happening: stderr is a terminal and --quiet was not given."""
    try:
        return not quiet and sys.stderr.isatty()
    except (AttributeError, ValueError):  # a closed or replaced stream
        return False

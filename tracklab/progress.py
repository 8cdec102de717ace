"""What the command tells the user while it works, on stderr: each phase named as it starts
(compiling or loading the program, the runs with a progress bar and a time estimate, the figures
and files), through tqdm. Silent when stderr is not a terminal or with ``--quiet``: the table
on stdout and the exit status are then all there is."""

from __future__ import annotations

import shutil
import sys
import time

from tracklab.interrupts import raise_if_interrupted


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
            self.bar = _bar(f"{self.name}: running", total, self.unit, scale=total >= 10**4)
        self.bar.total = total  # a run to a target precision learns its total as it goes
        self.bar.update(done - self.bar.n)
        if done >= total:
            self._close()

    def train(self, label: str, done: int, total: int, loss: float):
        """A training's bar (a DEKF trained before the runs): its Adam steps, rate, time estimate and
        the latest loss; closed at the last step."""
        if not self.enabled:
            return
        desc = f"{self.name}: training {label}"
        if self.bar is None or self.bar.desc != desc:
            self._close()
            self.bar = _bar(desc, total, "steps")
        self.bar.set_postfix_str(f"loss {loss:.4g}", refresh=False)
        self.bar.update(done - self.bar.n)
        if done >= total:
            self._close()

    def callback(self, then=None):
        """The runner's ``progress(done, total)``: a Ctrl-C swallowed inside a callback still stops
        the command; the bar; once every run is done, the next phase ``then`` (its line). A DEKF
        trained before the runs reports through its ``train``."""
        def progress(done, total):
            raise_if_interrupted()
            self.progress(done, total)
            if done >= total and then:
                self.phase(then)

        progress.train = self.train
        return progress

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


def _bar(desc: str, total: int, unit: str, scale: bool = False):
    """A tqdm bar on stderr, at most 120 wide. A terminal that reports no size (0 × 0, where tqdm
    would hide every bar) counts as 100 × 24."""
    from tqdm import tqdm

    cols, rows = shutil.get_terminal_size((100, 24))
    return tqdm(total=total, unit=f" {unit}", unit_scale=scale, file=sys.stderr, desc=desc, leave=True,
                ncols=min(cols, 120), nrows=rows)


def wanted(quiet: bool) -> bool:
    """Whether to tell the user what is happening: stderr is a terminal and --quiet was not given."""
    try:
        return not quiet and sys.stderr.isatty()
    except (AttributeError, ValueError):  # a closed or replaced stream
        return False

"""Ctrl-C: every SIGINT recorded, so that an interrupted command exits 130 with one line.

``catch_interrupts`` is the ``tracklab`` command's first call, made before anything heavy
(JAX, the engine) is imported; a library user need not call it. From then on every SIGINT is
recorded and raises ``KeyboardInterrupt``, except inside XLA's garbage-collection callback
and inside an import (``_may_raise``): the command then stops at the next
``raise_if_interrupted``, which it calls once its modules are imported, before an output is
checked or written, and which long loops call between chunks. A ``KeyboardInterrupt`` that
ends up swallowed (in a finaliser, a callback of C code) is recorded all the same, and
Python's "Exception ignored" report of it is left out. ``hold_interrupts`` makes later ones
recorded only, while the command ends: it looks at the record last of all.

Writers check the record before putting an output in place and block SIGINT across the swap
itself (``sigint_blocked``); ``written`` lists the outputs put in place since
``catch_interrupts``. This module imports nothing but the standard library's ``signal`` and
``sys``, so that the command can install its handler first.
"""

from __future__ import annotations

import signal
import sys

_interrupted = False
_raising = True
_written: list = []
_next_unraisable_hook = None  # the hook that was in place before ours


def _may_raise(frame) -> bool:
    """Whether a KeyboardInterrupt may be raised where ``frame`` runs: not inside XLA's
    garbage-collection callback (the exception would only be printed, "Exception ignored in …"
    with a traceback), nor inside an import (a module cut short there may print a traceback of
    its own, or leave a C extension half-initialised and crash the process)."""
    f = frame
    while f is not None:
        code = f.f_code
        if code.co_name == "_xla_gc_callback" or code.co_filename.startswith("<frozen importlib._bootstrap"):
            return False
        f = f.f_back
    return True


def _on_sigint(signum, frame):
    global _interrupted
    _interrupted = True
    if _raising and _may_raise(frame):
        raise KeyboardInterrupt


def _unraisable(info):
    if _interrupted and info.exc_type is not None and issubclass(info.exc_type, KeyboardInterrupt):
        return  # recorded: the command stops in one line at its next look at the record
    (_next_unraisable_hook or sys.__unraisablehook__)(info)


def catch_interrupts():
    """Record every SIGINT from now on (the command line calls this first; a library user need
    not). Returns a function that puts back the handler and hook it replaced (for the command
    run inside another program, e.g. a test)."""
    global _interrupted, _raising, _next_unraisable_hook
    _interrupted = False
    _raising = True
    _written.clear()
    try:
        previous = signal.getsignal(signal.SIGINT)
        if previous is not signal.SIG_IGN:  # an ignored one (a background job) stays so
            signal.signal(signal.SIGINT, _on_sigint)
    except ValueError:  # not the main thread: its SIGINT is the main thread's business
        return lambda: None
    hook = sys.unraisablehook
    if hook is not _unraisable:
        _next_unraisable_hook = hook
        sys.unraisablehook = _unraisable

    def put_back():
        if previous is not None and signal.getsignal(signal.SIGINT) is _on_sigint:
            signal.signal(signal.SIGINT, previous)
        if sys.unraisablehook is _unraisable and hook is not _unraisable:
            sys.unraisablehook = hook

    return put_back


def hold_interrupts():
    """From now on a SIGINT is recorded without raising ``KeyboardInterrupt`` (the command is ending)."""
    global _raising
    _raising = False


def interrupted() -> bool:
    """Whether a SIGINT arrived since ``catch_interrupts``."""
    return _interrupted


def raise_if_interrupted():
    """KeyboardInterrupt if a SIGINT was recorded (its own may have been swallowed): long loops
    call this between chunks so that Ctrl-C stops them."""
    if _interrupted:
        raise KeyboardInterrupt


class sigint_blocked:
    """SIGINT held back (delivered at the end) across a step that must not be cut in two."""

    def __enter__(self):
        if hasattr(signal, "pthread_sigmask"):
            signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
        return self

    def __exit__(self, *exc):
        if hasattr(signal, "pthread_sigmask"):
            signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})
        return False


def note_written(path):
    """Record an output put in place (``written``)."""
    _written.append(path)


def written() -> list:
    """The outputs put in place since ``catch_interrupts``."""
    return list(_written)

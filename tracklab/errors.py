"""The one error users see for bad input: file, field, value and what is allowed."""

from __future__ import annotations


def first_line(e: BaseException) -> str:
    """An exception as one line: its type and the first line of its message."""
    lines = str(e).strip().splitlines()
    return f"{type(e).__name__}: {lines[0]}" if lines else type(e).__name__


def exit_call(e: BaseException) -> str | None:
    """A ``SystemExit`` as the call that raised it (``sys.exit(0)``, ``sys.exit('bye')``); None for
    any other exception."""
    if not isinstance(e, SystemExit):
        return None
    return "sys.exit()" if e.code is None else f"sys.exit({e.code!r})"


def failure(e: BaseException) -> str:
    """What code of the user's did, in one line: ``it called sys.exit(0)``, or ``first_line(e)``."""
    call = exit_call(e)
    return f"it called {call}" if call else first_line(e)


def shown(value) -> str:
    """A value as a refusal quotes it: as the file writes it (true, false; a missing one as such)."""
    if value is None:
        return "(missing)"
    if isinstance(value, bool):
        return "true" if value else "false"
    return repr(value)


class ConfigError(ValueError):
    """Bad input: ``file: field = value: what is allowed``, one line."""

    def __init__(self, file, field, value, allowed):
        self.file, self.field, self.value, self.allowed = str(file), field, value, allowed
        super().__init__(f"{self.file}: {field} = {shown(value)}: {allowed}")

"""The one error users see for bad input: file, field, value and what is allowed."""

from __future__ import annotations


def first_line(e: BaseException) -> str:
    """An exception as one line: its type and the first line of its message."""
    lines = str(e).strip().splitlines()
    return f"{type(e).__name__}: {lines[0]}" if lines else type(e).__name__


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

"""The one error users see for bad input: file, field, value and what is allowed."""

from __future__ import annotations


class ConfigError(ValueError):
    def __init__(self, file, field, value, allowed):
        self.file, self.field, self.value, self.allowed = str(file), field, value, allowed
        super().__init__(f"{self.file}: {field} = {value!r}: {allowed}")

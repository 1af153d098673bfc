"""rotcal's exception hierarchy.

Domain code raises these; only the CLI (and the batch runner) turns them into
a one-line message and an exit status. Every message names the file and the
problem, and where it helps, what to do next.
"""

from __future__ import annotations

from pathlib import Path


class RotcalError(Exception):
    """Root of every error rotcal reports to a user."""

    exit_code = 1

    def __init__(self, problem: str, *, path: str | Path | None = None, hint: str | None = None):
        self.problem = " ".join(str(problem).split())
        self.path = None if path is None else str(path)
        self.hint = hint
        super().__init__(str(self))

    def __str__(self) -> str:
        text = f"{self.path}: {self.problem}" if self.path else self.problem
        return f"{text} ({self.hint})" if self.hint else text


class InputError(RotcalError):
    """A capture file or dataset.toml that cannot be read as a dataset."""

    exit_code = 2


class LimitError(InputError):
    """An input that exceeds a configured safety limit (line length, record size)."""


class ConfigError(RotcalError):
    """A run configuration or simulation request that is not valid."""

    exit_code = 2


class UndeterminedError(RotcalError):
    """What remains after failed segments cannot determine the result."""

    exit_code = 3

"""rotcal's exception hierarchy and its exit statuses.

Domain code raises these; only the CLI (and the batch runner) turns them into
a one-line message and an exit status. Every message names the file and the
problem, and where it helps, what to do next.
"""

from __future__ import annotations

import re
from enum import IntEnum
from pathlib import Path


class ExitCode(IntEnum):
    """Every exit status of the ``rotcal`` command, in one table:

    ======  ==============  ==================================================
    status  name            meaning
    ======  ==============  ==================================================
    0       OK              done (``rotcal batch``: every dataset published)
    1       FAILED          an unexpected failure: a bug, or (``rotcal batch``)
                            a dataset that failed unexpectedly, retried next run
    2       BAD_INPUT       an input, configuration or option that is not valid
                            (also the command line's usage errors)
    3       UNDETERMINED    what remains after failed segments cannot
                            determine the result
    4       QUARANTINED     ``rotcal batch``: a dataset is in quarantine
    5       LOCKED          ``rotcal batch``: another run holds the output lock
    ======  ==============  ==================================================
    """

    OK = 0
    FAILED = 1
    BAD_INPUT = 2
    UNDETERMINED = 3
    QUARANTINED = 4
    LOCKED = 5


class RotcalError(Exception):
    """Root of every error rotcal reports to a user."""

    exit_code = ExitCode.FAILED

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

    exit_code = ExitCode.BAD_INPUT


class LimitError(InputError):
    """An input that exceeds a configured safety limit (line length, record size)."""


class ConfigError(RotcalError):
    """A run configuration or simulation request that is not valid."""

    exit_code = ExitCode.BAD_INPUT


class UndeterminedError(RotcalError):
    """What remains after failed segments cannot determine the result."""

    exit_code = ExitCode.UNDETERMINED


def decoded(text: str) -> str:
    """``text`` (a file name) with the bytes that are not UTF-8 shown as ``\\xNN``."""
    return text.encode("utf-8", "surrogateescape").decode("utf-8", "backslashreplace")


_CONTROL = re.compile(r"[\x00-\x1f\x7f-\x9f]")


def printable(text: str) -> str:
    """``text`` as it may be printed: bytes that are not UTF-8 and control
    characters escaped (``\\n``, ``\\x1b``), so that a file name cannot
    forge log lines or colour a terminal."""
    return _CONTROL.sub(lambda m: repr(m.group())[1:-1], decoded(text))

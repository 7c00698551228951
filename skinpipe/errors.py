"""Exceptions that carry the offending file and value, mapped to CLI exit codes."""

from __future__ import annotations

from pathlib import Path

EXIT_OK = 0
EXIT_CHECK_FAILED = 1
EXIT_BAD_INPUT = 2


class SkinpipeError(Exception):
    """Base class: every error skinpipe raises on purpose derives from it."""

    exit_code = EXIT_CHECK_FAILED


class InputError(SkinpipeError, ValueError):
    """Input that cannot be used: names the file (if any) and the offending value.

    The CLI turns it into exit code 2 and a one-line message on stderr.
    """

    exit_code = EXIT_BAD_INPUT

    def __init__(self, message: str, path: str | Path | None = None) -> None:
        self.path = None if path is None else Path(path)
        super().__init__(f"{self.path}: {message}" if self.path is not None else message)


class FitError(SkinpipeError, RuntimeError):
    """The optimiser could not produce a fit we trust (status and residual given)."""

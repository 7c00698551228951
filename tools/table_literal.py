"""Python literals for the generated tables (tools/tabulate_*.py): tuples of floats
broken into lines of at most 100 characters, so that the table modules pass ruff."""

from __future__ import annotations

import textwrap
from collections.abc import Sequence


def wrapped(values: Sequence[float]) -> str:
    """A tuple literal of ``values``, four spaces in, a line of at most 96 characters."""
    body = textwrap.fill(", ".join(repr(v) for v in values), width=92,
                         initial_indent="    ", subsequent_indent="    ")
    return f"(\n{body},\n)"


def rows_literal(rows: Sequence[Sequence[float]]) -> str:
    """The body of a tuple of :func:`wrapped` rows, indented one level more."""
    return textwrap.indent(",\n".join(wrapped(r) for r in rows), "    ")

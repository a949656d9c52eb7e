"""One error type for bad input: it names the file, the field and the expectation; and
:func:`as_number`, the validators' reading of a value that should be a number."""

from __future__ import annotations

import math
from pathlib import Path

__all__ = ["InputError", "as_number"]


class InputError(ValueError):
    """Raised for malformed input files, shapes or configuration values.

    The message is a single line: ``<file>: <field>: expected <expectation>, got <what>``.
    Entry points catch it and print only the message (no deep traceback).

    >>> str(InputError("events/00.npz", "p", "values in {-1, +1}", "3"))
    'events/00.npz: p: expected values in {-1, +1}, got 3'
    """

    def __init__(self, where: str | Path, field: str, expected: str, got: object | None = None):
        self.where = str(where)
        self.field = field
        self.expected = expected
        self.got = got
        msg = f"{self.where}: {field}: expected {expected}"
        if got is not None:
            msg += f", got {got}"
        super().__init__(msg)


def as_number(value: object) -> float:
    """``value`` as a float; NaN (which fails every range check) for a bool, ``None`` or
    anything ``float`` refuses, so a validator raises one :class:`InputError` for both a
    value out of range and a value that is no number.

    >>> as_number(3), as_number("abc"), as_number(True)
    (3.0, nan, nan)
    """
    if isinstance(value, bool):
        return math.nan
    try:
        return float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        return math.nan

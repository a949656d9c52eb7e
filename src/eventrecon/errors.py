"""One error type for bad input: it names the file, the field and the expectation."""

from __future__ import annotations

from pathlib import Path


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

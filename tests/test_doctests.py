"""Every ``>>>`` example in a docstring of the library and the zoo is a test."""

from __future__ import annotations

import doctest
import importlib
import pkgutil

import pytest

import baselines
import eventrecon

SKIP = {"eventrecon.__main__"}


def _modules() -> list[str]:
    names = []
    for pkg in (eventrecon, baselines):
        names.append(pkg.__name__)
        for info in pkgutil.walk_packages(pkg.__path__, prefix=f"{pkg.__name__}."):
            if info.name not in SKIP and not info.name.endswith("__main__"):
                names.append(info.name)
    return sorted(names)


@pytest.mark.parametrize("name", _modules())
def test_docstring_examples(name: str) -> None:
    module = importlib.import_module(name)
    result = doctest.testmod(module, optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE,
                             verbose=False)
    assert result.failed == 0, f"{name}: {result.failed} of {result.attempted} examples failed"

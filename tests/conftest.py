"""Shared test settings: CPU, at most two threads, torch's global seed fixed per test.

NumPy's global RNG is deliberately not seeded: library code must not use it (every
random draw goes through an explicit generator), and seeding it here would hide that.
"""

from __future__ import annotations

import os

import pytest
import torch

import eventrecon  # noqa: F401 - registers the config resolvers (${paper_steps:...})

torch.set_num_threads(max(1, min(2, os.cpu_count() or 1)))


@pytest.fixture(autouse=True)
def _seed() -> None:
    torch.manual_seed(0)

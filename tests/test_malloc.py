"""glibc's thresholds are fixed on request and left alone when asked (in a child process:
the setting is process-wide and would change what other tests measure)."""

from __future__ import annotations

import ctypes.util
import os
import subprocess
import sys

import pytest

CHILD = "from eventrecon.common.malloc import retain_freed_memory as r; print(r())"


def _child(env: dict[str, str]) -> str:
    out = subprocess.run([sys.executable, "-c", CHILD], env={**os.environ, **env},
                         capture_output=True, text=True, check=True)
    return out.stdout.strip()


@pytest.mark.skipif(ctypes.util.find_library("c") is None, reason="no libc to load")
def test_thresholds_are_set_unless_default_is_asked() -> None:
    assert _child({"EVENTRECON_MALLOC": "default"}) == "False"
    assert _child({"EVENTRECON_MALLOC": ""}) == "True"

"""glibc's thresholds are fixed on request and left alone when asked."""

from __future__ import annotations

import ctypes.util

import pytest

from eventrecon.common.malloc import retain_freed_memory


@pytest.mark.skipif(ctypes.util.find_library("c") is None, reason="no libc to load")
def test_thresholds_are_set_unless_default_is_asked(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("EVENTRECON_MALLOC", "default")
    assert retain_freed_memory() is False
    monkeypatch.delenv("EVENTRECON_MALLOC")
    assert retain_freed_memory() is True

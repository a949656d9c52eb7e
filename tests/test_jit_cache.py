"""numba's cache is dropped when any compiled module of the simulator changes
(:func:`eventrecon.sim.jit.drop_stale_cache`), not only the file of the cached function,
and when the decorators that decide how kernels and helpers are compiled change."""

from pathlib import Path

from eventrecon.sim.jit import SOURCES, drop_stale_cache


def _package(tmp_path: Path) -> Path:
    for name in SOURCES:
        (tmp_path / name).write_text(f"# {name}\n")
    (tmp_path / "__pycache__").mkdir()
    return tmp_path


def _cache_files(package: Path) -> list[str]:
    return sorted(p.name for p in (package / "__pycache__").glob("*.nb?"))


def test_an_edit_of_an_inlined_helper_drops_the_caches_of_every_compiled_module(tmp_path):
    pkg = _package(tmp_path)
    cached = ["compiled_core._step-161.py311.1.nbc", "compiled_core._step-161.py311.nbi"]
    for name in cached:
        (pkg / "__pycache__" / name).write_bytes(b"x")
    assert drop_stale_cache(pkg) is True          # no stamp yet: unknown sources
    assert _cache_files(pkg) == []
    for name in cached:                           # numba compiles and caches again
        (pkg / "__pycache__" / name).write_bytes(b"x")
    assert drop_stale_cache(pkg) is False         # same sources: the cache is kept
    assert _cache_files(pkg) == sorted(cached)
    (pkg / "compiled_paths.py").write_text("# an edited helper\n")
    assert drop_stale_cache(pkg) is True          # another module changed: dropped
    assert _cache_files(pkg) == []
    assert drop_stale_cache(pkg) is False


def test_the_fused_rank_sums_hash_their_own_files():
    """The baselines' fused passes inline helpers of ``fused_kernels.py``: the three files
    exist under the names hashed (a renamed one would silently leave the hash), and an
    edit of the shared helpers drops a fused kernel's cache."""
    import baselines.fused_kernels as fused_kernels

    pkg = Path(fused_kernels.__file__).parent
    assert all((pkg / name).is_file() for name in fused_kernels.SOURCES)
    assert {"fused_kernels.py", "cp_fused.py", "hex_fused.py"} == set(fused_kernels.SOURCES)


def test_another_package_with_its_own_sources(tmp_path):
    sources = ("shared.py", "kernel.py")
    for name in sources:
        (tmp_path / name).write_text(f"# {name}\n")
    (tmp_path / "__pycache__").mkdir()
    assert drop_stale_cache(tmp_path, sources) is False    # nothing cached yet: stamped
    (tmp_path / "__pycache__" / "kernel._fwd-10.py311.nbi").write_bytes(b"x")
    assert drop_stale_cache(tmp_path, sources) is False    # same sources: kept
    (tmp_path / "unrelated.py").write_text("# not hashed\n")
    assert drop_stale_cache(tmp_path, sources) is False
    (tmp_path / "shared.py").write_text("# an edited helper\n")
    assert drop_stale_cache(tmp_path, sources) is True
    assert _cache_files(tmp_path) == []


def test_an_edit_of_the_decorators_drops_the_cache(tmp_path):
    """How a helper is compiled (``jit.njit``: inlined by LLVM or copied as IR) is part of
    every kernel's machine code, so an edit of the decorators' file drops the caches too."""
    sources = ("kernel.py",)
    (tmp_path / "kernel.py").write_text("# kernel\n")
    decorators = tmp_path / "jit.py"
    decorators.write_text("# inline by LLVM\n")
    (tmp_path / "__pycache__").mkdir()
    assert drop_stale_cache(tmp_path, sources, decorators) is False   # stamped
    (tmp_path / "__pycache__" / "kernel._fwd-10.py311.nbi").write_bytes(b"x")
    assert drop_stale_cache(tmp_path, sources, decorators) is False   # kept
    decorators.write_text("# inline as numba IR\n")
    assert drop_stale_cache(tmp_path, sources, decorators) is True
    assert _cache_files(tmp_path) == []

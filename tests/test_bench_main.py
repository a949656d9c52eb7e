"""``python -m benchmarks`` warns when it would time another checkout's code."""

from __future__ import annotations

from pathlib import Path

from benchmarks.__main__ import foreign_package


def _checkout(root: Path) -> Path:
    (root / "src" / "eventrecon").mkdir(parents=True)
    (root / "src" / "eventrecon" / "__init__.py").write_text("")
    (root / "benchmarks").mkdir()
    return root


def test_a_worktree_importing_the_main_checkouts_package_is_named(tmp_path) -> None:
    main, tree = _checkout(tmp_path / "main"), _checkout(tmp_path / "tree")
    main_pkg = main / "src" / "eventrecon" / "__init__.py"
    assert foreign_package(main / "benchmarks", main_pkg) is None
    warning = foreign_package(tree / "benchmarks", main_pkg)
    assert warning is not None
    assert f"PYTHONPATH={(tree / 'src').resolve()}" in warning
    assert str((main / "src" / "eventrecon").resolve()) in warning
    assert foreign_package(tree / "benchmarks", tree / "src" / "eventrecon" / "__init__.py") is None


def test_an_installed_package_without_a_source_checkout_is_not_flagged(tmp_path) -> None:
    (tmp_path / "benchmarks").mkdir()                    # no src/ beside the benchmarks
    site = tmp_path / "site-packages" / "eventrecon"
    site.mkdir(parents=True)
    assert foreign_package(tmp_path / "benchmarks", site / "__init__.py") is None

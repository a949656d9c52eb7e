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


def test_running_every_benchmark_skips_those_that_read_finished_runs(caplog, monkeypatch) -> None:
    """``python -m benchmarks`` alone runs each benchmark with its defaults; the two that
    need run folders are skipped with a line naming how to run them (argparse would
    otherwise stop the whole sequence at the first)."""
    import importlib
    import logging

    import benchmarks.__main__ as bm

    ran: list[str] = []
    for name in bm.available():
        module = importlib.import_module(f"benchmarks.bench_{name}")
        monkeypatch.setattr(module, "main", lambda args, name=name: ran.append(name))
    level = logging.getLogger("eventrecon").level
    try:
        with caplog.at_level(logging.INFO, logger="benchmarks"):
            assert bm.main([]) == 0
    finally:
        logging.getLogger("eventrecon").setLevel(level)
    assert "heldout" in set(bm.available())
    assert sorted(ran) == sorted(set(bm.available()) - {"heldout"})
    assert "python -m benchmarks heldout RUN_DIR" in caplog.text


def test_a_run_folder_without_a_saved_config_is_one_error_line(caplog, tmp_path) -> None:
    """``python -m benchmarks heldout DIR`` on a folder that is not a run: one line
    naming the missing ``.hydra/config.yaml`` and exit status 2, no traceback
    (``eventrecon.engine.run_folder.run_config``); ``image --run`` raises the same error."""
    import logging

    import pytest

    import benchmarks.__main__ as bm
    from benchmarks import bench_image
    from eventrecon.common.errors import InputError

    level = logging.getLogger("eventrecon").level
    try:
        for name in ("heldout",):
            caplog.clear()
            with caplog.at_level(logging.ERROR, logger="benchmarks"):
                assert bm.main([name, str(tmp_path)]) == 2
            errors = [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR]
            assert errors == [f"{tmp_path / '.hydra' / 'config.yaml'}: <file>: expected the "
                              "run's saved Hydra config"], name
    finally:
        logging.getLogger("eventrecon").setLevel(level)
    with pytest.raises(InputError, match=r"config\.yaml: <file>: expected the run's saved"):
        bench_image._config(tmp_path, [], tmp_path)

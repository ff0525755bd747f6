"""The test command's progress plugin: what its hang guard reads, and the skips of a rerun."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from tests.container_support import REPO

_TESTS = '''
import pytest

def test_passes():
    pass

def test_fails():
    assert False

@pytest.mark.timeout(7)
def test_skipped():
    pytest.skip("no")
'''


def _pytest(tmp_path: Path, **env: str) -> subprocess.CompletedProcess[str]:
    (tmp_path / "test_sample.py").write_text(_TESTS, encoding="utf-8")
    # Not the test command's own: under .ci/test this sample's failure went
    # into the guard's progress file, where a rerun after a hang reads failures.
    inherited = {k: v for k, v in os.environ.items() if k not in ("CI_PROGRESS_FILE", "CI_SKIP_FILE")}
    return subprocess.run(
        [sys.executable, "-m", "pytest", "-p", "tests.ci_progress", "-q", "-p", "no:cacheprovider",
         "--rootdir", str(tmp_path), "-c", os.devnull, str(tmp_path / "test_sample.py")],
        cwd=REPO, env={**inherited, **env}, capture_output=True, text=True, timeout=120, check=False,
    )


def test_each_test_writes_its_start_with_its_timeout_and_its_end_with_its_worst_outcome(tmp_path: Path) -> None:
    progress = tmp_path / "progress"
    result = _pytest(tmp_path, CI_PROGRESS_FILE=str(progress))
    assert result.returncode == 1, result.stdout + result.stderr
    lines = progress.read_text(encoding="utf-8").splitlines()
    name = "test_sample.py"
    assert lines == [
        f"start 0 {name}::test_passes",
        f"done passed {name}::test_passes",
        f"start 0 {name}::test_fails",
        f"done failed {name}::test_fails",
        f"start 7 {name}::test_skipped",
        f"done skipped {name}::test_skipped",
    ]


def test_the_tests_named_in_the_skip_file_are_deselected(tmp_path: Path) -> None:
    skip = tmp_path / "skip"
    skip.write_text("test_sample.py::test_fails\ntest_sample.py::test_skipped\n", encoding="utf-8")
    result = _pytest(tmp_path, CI_SKIP_FILE=str(skip))
    assert result.returncode == 0, result.stdout + result.stderr
    assert "1 passed, 2 deselected" in result.stdout


def test_without_its_variables_it_writes_nothing(tmp_path: Path) -> None:
    result = _pytest(tmp_path)
    assert result.returncode == 1
    assert "1 failed, 1 passed, 1 skipped" in result.stdout
    assert sorted(p.name for p in tmp_path.iterdir()) == ["test_sample.py"]

"""The README's plugin example type-checks under strict mypy, with the rclpy installed here.

A plugin author who runs ``mypy --strict`` on the README's ``async def
on_configure`` must not get "incompatible with supertype" on Kilted's rclpy 9
(whose annotations say transition callbacks return a value) nor anything on
Jazzy's rclpy 7. Run on every leg of CI, so both are covered.
"""

from __future__ import annotations

import re
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from tests.container_support import REPO

#: What the README tells plugin authors to put in their mypy configuration.
MYPY_CONFIG = """\
[mypy]
strict = True
warn_unreachable = True

[mypy-std_msgs.*]
ignore_missing_imports = True
"""


def _plugin_example() -> str:
    """The Python blocks of the README's "Writing a plugin" section, as one module."""
    readme = (REPO / "README.md").read_text(encoding="utf-8")
    section = readme.split("\n## Writing a plugin\n", 1)[1].split("\n## ", 1)[0]
    blocks = re.findall(r"```python\n(.*?)```", section, flags=re.DOTALL)
    assert len(blocks) >= 2, "the README's plugin example moved: update this test"
    return "\n\n".join(textwrap.dedent(block) for block in blocks)


def test_the_readme_plugin_example_passes_strict_mypy(tmp_path: Path) -> None:
    module = tmp_path / "greeter_example.py"
    module.write_text(_plugin_example(), encoding="utf-8")
    assert "async def on_configure" in module.read_text()  # what the check is about
    config = tmp_path / "mypy.ini"
    config.write_text(MYPY_CONFIG, encoding="utf-8")
    version = "{}.{}".format(*sys.version_info[:2])
    result = subprocess.run(
        [
            sys.executable, "-m", "mypy", "--config-file", str(config), "--python-version", version,
            "--cache-dir", str(Path(sys.prefix) / ".mypy_cache_readme"), str(module),
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    if "No module named mypy" in result.stderr:
        pytest.skip("mypy is not installed (the test extra)")
    assert result.returncode == 0, result.stdout + result.stderr

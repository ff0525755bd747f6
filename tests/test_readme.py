"""The plugin guide's example type-checks under strict mypy, with the rclpy installed here.

A plugin author who runs ``mypy --strict`` on the example's ``async def
on_configure`` (``docs/guide/plugins.md``) must not get "incompatible with
supertype" on Kilted's rclpy 9 (whose annotations say transition callbacks
return a value) nor anything on Jazzy's rclpy 7. Run on every leg of CI, so
both are covered.
"""

from __future__ import annotations

import re
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from tests.container_support import REPO

#: The page of the documentation that holds the plugin example.
PLUGIN_GUIDE = REPO / "docs" / "guide" / "plugins.md"

#: What the plugin guide tells plugin authors to put in their mypy configuration.
MYPY_CONFIG = """\
[mypy]
strict = True
warn_unreachable = True

[mypy-std_msgs.*]
ignore_missing_imports = True
"""


def _plugin_example() -> str:
    """The Python blocks of the plugin guide, as one module."""
    guide = PLUGIN_GUIDE.read_text(encoding="utf-8")
    blocks = re.findall(r"```python\n(.*?)```", guide, flags=re.DOTALL)
    assert len(blocks) >= 2, "the plugin guide's example moved: update this test"
    return "\n\n".join(textwrap.dedent(block) for block in blocks)


def test_the_plugin_guide_example_passes_strict_mypy(tmp_path: Path) -> None:
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

"""DDS security on a Fast DDS without it: one line from every command, no traceback.

The PyPI wheels' Fast DDS (2.14 on Jazzy) is built without the security
plugins; with ``ROS_SECURITY_ENABLE=true`` and a keystore, creating any node
fails. The enclave's files here are placeholders: rmw hands their paths to
Fast DDS, which refuses before reading them.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from tests.container_support import REPO

MESSAGE = (
    "container: ROS_SECURITY_ENABLE is true, but this Fast DDS is built without its security plugins "
    "(the PyPI wheels' Fast DDS is): use a ROS 2 whose Fast DDS was built with -DSECURITY=ON, "
    "or unset ROS_SECURITY_ENABLE\n"
)


@pytest.fixture
def secure_env(tmp_path: Path) -> dict[str, str]:
    enclave = tmp_path / "keystore" / "enclaves"
    enclave.mkdir(parents=True)
    for name in ("identity_ca.cert.pem", "cert.pem", "key.pem", "permissions_ca.cert.pem",
                 "governance.p7s", "permissions.p7s"):
        (enclave / name).write_text("placeholder\n")
    return {
        **os.environ,
        "ROS_SECURITY_ENABLE": "true",
        "ROS_SECURITY_STRATEGY": "Enforce",
        "ROS_SECURITY_KEYSTORE": str(tmp_path / "keystore"),
    }


@pytest.mark.parametrize(
    "args",
    [
        ("run", "examples/demo.yaml"),
        ("list",),
        ("load", "/ComponentManager", "lifecycle_container", "Talker"),
        ("lifecycle", "get", "/talker"),
        ("manager",),
    ],
    ids=lambda args: args[0],
)
def test_every_command_says_so_in_one_line(secure_env: dict[str, str], args: tuple[str, ...]) -> None:
    result = subprocess.run(
        [sys.executable, "-m", "container", *args],
        cwd=REPO, env=secure_env, capture_output=True, text=True, timeout=60,
    )

    assert result.returncode == 1
    assert "Traceback" not in result.stderr
    errors = [line for line in result.stderr.splitlines(keepends=True) if not line.startswith("[INFO]")]
    assert errors == [MESSAGE]

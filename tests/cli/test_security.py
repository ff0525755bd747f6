"""DDS security from every command: secured, or said in one line, never a traceback.

Each row of the table in docs/guide/security.md ("Asking for security") is
a case here, run as real child processes of ``container run`` (stopped once
ready) and ``container list``, with the environment set and keystores made
by hand (their layout is all rcl looks at; the enclave's files are
placeholders, which the wheels' Fast DDS refuses before reading). Then one
refusal and one warning through every other command that starts ROS.
What a Fast DDS with security would do is decided by the same function,
tested in ``tests/test_security.py``.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from tests.container_support import REPO
from tests.process_support import LoggedProcess

#: The one line for a Fast DDS built without security that is handed an enclave.
NO_PLUGINS = (
    "[ERROR] [container]: ROS_SECURITY_ENABLE is true, but this Fast DDS is built without its security plugins "
    "(the PyPI wheels' Fast DDS is): use a ROS 2 whose Fast DDS was built with -DSECURITY=ON, "
    "or unset ROS_SECURITY_ENABLE"
)
ENCLAVE = "/lifecycle_container"
FILES = ("identity_ca.cert.pem", "cert.pem", "key.pem", "permissions_ca.cert.pem", "governance.p7s", "permissions.p7s")
WARNING = "[WARN] [container]: "
ERROR = "[ERROR] [container]: "
#: The time stamp of rcutils' console lines, taken out before they are compared.
STAMP = re.compile(r"^(\[[A-Z]+\]) \[\d+\.\d+\] ")


def unstamped(line: str) -> str:
    """``line`` without rcutils' time stamp: ``[ERROR] [container]: ...``."""
    return STAMP.sub(r"\1 ", line)


@dataclass(frozen=True)
class Case:
    """One row: the environment (``{keystore}``: the test's keystore), and what must be said."""

    env: Mapping[str, str]
    #: The one line's start (WARNING or ERROR), or ``None``: nothing is said.
    said: str | None
    #: What the line must hold, in order (``{keystore}`` filled in).
    holds: tuple[str, ...] = ()
    code: int = 0
    ros_args: tuple[str, ...] = ()
    #: How the keystore is made: "none", "empty" (no enclave), "bare" (the enclave, no files), "full".
    keystore: str = "none"
    extra: Mapping[str, str] = field(default_factory=dict)


ENFORCE = {"ROS_SECURITY_ENABLE": "true", "ROS_SECURITY_STRATEGY": "Enforce"}
PERMISSIVE = {"ROS_SECURITY_ENABLE": "true", "ROS_SECURITY_STRATEGY": "Permissive"}
AT_KEYSTORE = {"ROS_SECURITY_KEYSTORE": "{keystore}"}
WITH_ENCLAVE = ("--ros-args", "--enclave", ENCLAVE)
UNSECURED = "running WITHOUT DDS security"

CASES = {
    "off-unset": Case({}, None),
    "off-false": Case({"ROS_SECURITY_ENABLE": "false", **AT_KEYSTORE}, None, keystore="full"),
    "spelling-True": Case(
        {"ROS_SECURITY_ENABLE": "True", "ROS_SECURITY_STRATEGY": "Enforce"},
        WARNING,
        ("ROS_SECURITY_ENABLE='True' is not 'true'", UNSECURED, "set ROS_SECURITY_ENABLE=true"),
    ),
    "spelling-1": Case({"ROS_SECURITY_ENABLE": "1"}, WARNING, ("ROS_SECURITY_ENABLE='1' is not 'true'", UNSECURED)),
    "spelling-yes": Case({"ROS_SECURITY_ENABLE": "yes"}, WARNING, ("ROS_SECURITY_ENABLE='yes' is not", UNSECURED)),
    "spelling-space": Case(
        {"ROS_SECURITY_ENABLE": " true", **AT_KEYSTORE}, WARNING, ("ROS_SECURITY_ENABLE=' true' is not", UNSECURED),
        keystore="full",
    ),
    "enforce-keystore-unset": Case(
        ENFORCE, ERROR, ("Enforce, but ROS_SECURITY_KEYSTORE is not set: DDS security cannot start",), code=1
    ),
    "enforce-keystore-missing": Case(
        {**ENFORCE, "ROS_SECURITY_KEYSTORE": "{keystore}/absent"}, ERROR,
        ("Enforce, but the keystore '{keystore}/absent' (ROS_SECURITY_KEYSTORE) does not exist",), code=1,
    ),
    "enforce-no-enclave": Case(
        {**ENFORCE, **AT_KEYSTORE}, ERROR,
        (f"has no directory '{{keystore}}/enclaves{ENCLAVE}' for enclave '{ENCLAVE}'", "cannot start"),
        code=1, ros_args=WITH_ENCLAVE, keystore="empty",
    ),
    "enforce-no-enclave-override": Case(
        {**ENFORCE, **AT_KEYSTORE, "ROS_SECURITY_ENCLAVE_OVERRIDE": "/other"}, ERROR,
        ("has no directory '{keystore}/enclaves/other' for enclave '/other' (ROS_SECURITY_ENCLAVE_OVERRIDE)",),
        code=1, ros_args=WITH_ENCLAVE, keystore="full",
    ),
    "enforce-enclave-without-files": Case(
        {**ENFORCE, **AT_KEYSTORE}, ERROR, (NO_PLUGINS[len(ERROR):],), code=1, ros_args=WITH_ENCLAVE, keystore="bare"
    ),
    "enforce-enclave-with-files": Case(
        {**ENFORCE, **AT_KEYSTORE}, ERROR, (NO_PLUGINS[len(ERROR):],), code=1, ros_args=WITH_ENCLAVE, keystore="full"
    ),
    "enforce-root-enclave-with-files": Case(
        {**ENFORCE, **AT_KEYSTORE}, ERROR, (NO_PLUGINS[len(ERROR):],), code=1, keystore="full"
    ),
    "permissive-keystore-unset": Case(
        PERMISSIVE, WARNING,
        ("ROS_SECURITY_ENABLE is true, but ROS_SECURITY_KEYSTORE is not set", UNSECURED,
         "as rcl does under ROS_SECURITY_STRATEGY=Permissive"),
    ),
    "strategy-unset-keystore-unset": Case(
        {"ROS_SECURITY_ENABLE": "true"}, WARNING,
        ("ROS_SECURITY_KEYSTORE is not set", UNSECURED, "when ROS_SECURITY_STRATEGY is unset (Permissive)"),
    ),
    "strategy-spelling-keystore-unset": Case(
        {"ROS_SECURITY_ENABLE": "true", "ROS_SECURITY_STRATEGY": "enforce"}, WARNING,
        ("ROS_SECURITY_KEYSTORE is not set", UNSECURED, "ROS_SECURITY_STRATEGY='enforce', which it reads"),
    ),
    "permissive-keystore-missing": Case(
        {**PERMISSIVE, "ROS_SECURITY_KEYSTORE": "{keystore}/absent"}, WARNING,
        ("the keystore '{keystore}/absent' (ROS_SECURITY_KEYSTORE) does not exist", UNSECURED),
    ),
    "permissive-no-enclave": Case(
        {**PERMISSIVE, **AT_KEYSTORE}, WARNING,
        (f"has no directory '{{keystore}}/enclaves{ENCLAVE}' for enclave '{ENCLAVE}'", UNSECURED),
        ros_args=WITH_ENCLAVE, keystore="empty",
    ),
    "permissive-enclave-with-files": Case(
        {**PERMISSIVE, **AT_KEYSTORE}, ERROR, (NO_PLUGINS[len(ERROR):],), code=1, ros_args=WITH_ENCLAVE, keystore="full"
    ),
    "invalid-enclave-name": Case(
        ENFORCE, ERROR, ("ROS error: failed to initialize rcl: Enclave name is not valid",), code=1,
        ros_args=("--ros-args", "--enclave", "no_slash"),
    ),
}


def make_keystore(root: Path, kind: str) -> Path:
    """A keystore laid out as ``ros2 security`` lays it out, as far as rcl looks: ``enclaves/<name>/``."""
    keystore = root / "keystore"
    if kind == "none":
        return keystore
    (keystore / "enclaves").mkdir(parents=True)
    for enclave in ((keystore / "enclaves" / ENCLAVE[1:],) if kind in ("bare", "full") else ()):
        enclave.mkdir()
    if kind == "full":
        for directory in (keystore / "enclaves", keystore / "enclaves" / ENCLAVE[1:]):
            for name in FILES:
                (directory / name).write_text("placeholder\n")
    return keystore


def environment(case: Case, keystore: Path) -> dict[str, str]:
    env = {name: value for name, value in os.environ.items() if not name.startswith("ROS_SECURITY_")}
    env.update({name: value.format(keystore=keystore) for name, value in case.env.items()})
    return env


def said(lines: list[str]) -> list[str]:
    """What a command said besides its INFO logs (the demo's, rcl's)."""
    return [line for line in lines if line.strip() and not line.startswith("[INFO]")]


def check(case: Case, keystore: Path, lines: list[str], code: int) -> None:
    output = "\n".join(lines)
    assert "Traceback" not in output
    assert code == case.code, output
    if case.said is None:
        assert said(lines) == [], output
        return
    (line,) = said(lines)
    line = unstamped(line)
    assert line.startswith(case.said), output
    position = 0
    for part in case.holds:
        found = line.find(part.format(keystore=keystore), position)
        assert found >= 0, f"{part!r} not in {line!r}"
        position = found


def container_run(case: Case, env: dict[str, str]) -> tuple[list[str], int]:
    """``container run`` of the demo until ready (then SIGTERM), or until it exits by itself."""
    process = LoggedProcess(
        [sys.executable, "-m", "container", "run", "examples/demo.yaml", *case.ros_args], env=env, name="container"
    )
    try:
        if case.code == 0:
            process.wait_for_line("ready with 2 node(s)")
            return process.lines, process.stop(sig=signal.SIGTERM)
        return process.lines, process.process.wait(timeout=30)
    finally:
        process.close()


def container_list(case: Case, env: dict[str, str]) -> tuple[list[str], int]:
    result = subprocess.run(
        [sys.executable, "-m", "container", "list", "--spin-time", "0.3", *case.ros_args],
        cwd=REPO, env=env, capture_output=True, text=True, timeout=60,
    )
    return (result.stdout + result.stderr).splitlines(), result.returncode


@pytest.mark.parametrize("case_id", list(CASES))
def test_run_says_what_security_it_gets(tmp_path: Path, case_id: str) -> None:
    case = CASES[case_id]
    keystore = make_keystore(tmp_path, case.keystore)

    lines, code = container_run(case, environment(case, keystore))

    check(case, keystore, lines, code)


# The table once more through a client command, and a warning through every
# other command: forty child processes, each starting ROS (about a minute).
@pytest.mark.slow
@pytest.mark.parametrize("case_id", list(CASES))
def test_a_client_command_says_what_security_it_gets(tmp_path: Path, case_id: str) -> None:
    case = CASES[case_id]
    keystore = make_keystore(tmp_path, case.keystore)

    lines, code = container_list(case, environment(case, keystore))

    check(case, keystore, lines, code)


#: Every other command that starts ROS, with what it says and returns on an empty graph.
COMMANDS = {
    "manager": (("manager", "-p", "node_names:=[/nobody]", "-p", "autostart:=true"), 0, "STARTUP: configure"),
    "load": (("load", "/ComponentManager", "lifecycle_container", "Talker", "--spin-time", "0.2"), 1,
             "Unable to find container node"),
    "unload": (("unload", "/ComponentManager", "1", "--spin-time", "0.2"), 1, "Unable to find container node"),
    "lifecycle-get": (("lifecycle", "get", "/talker", "--spin-time", "0.2"), 1, "Node not found"),
    "lifecycle-set": (("lifecycle", "set", "/talker", "configure", "--spin-time", "0.2"), 1, "Node not found"),
    "lifecycle-list": (("lifecycle", "list", "/talker", "--spin-time", "0.2"), 1, "Node not found"),
    "lifecycle-nodes": (("lifecycle", "nodes", "--spin-time", "0.2"), 0, None),
    "top": (("top", "--once", "--timeout", "0.2"), 1, "no load report"),
}


def run_command(args: tuple[str, ...], env: dict[str, str], *, server_ready: str | None) -> tuple[list[str], int]:
    """A command to its end; a server (``manager``) until ``server_ready``, then SIGTERM."""
    if server_ready is None:
        result = subprocess.run(
            [sys.executable, "-m", "container", *args], cwd=REPO, env=env, capture_output=True, text=True, timeout=60
        )
        return (result.stdout + result.stderr).splitlines(), result.returncode
    process = LoggedProcess([sys.executable, "-m", "container", *args], env=env)
    try:
        process.wait_for_line(server_ready)
        return process.lines, process.stop(sig=signal.SIGTERM)
    finally:
        process.close()


@pytest.mark.parametrize("name", list(COMMANDS))
def test_every_command_refuses_in_one_line(tmp_path: Path, name: str) -> None:
    args, _, _ = COMMANDS[name]
    case = CASES["enforce-enclave-with-files"]
    keystore = make_keystore(tmp_path, case.keystore)

    result = subprocess.run(
        [sys.executable, "-m", "container", *args, *case.ros_args],
        cwd=REPO, env=environment(case, keystore), capture_output=True, text=True, timeout=60,
    )

    assert (result.returncode, result.stdout, unstamped(result.stderr)) == (1, "", NO_PLUGINS + "\n")


@pytest.mark.slow
@pytest.mark.parametrize("name", list(COMMANDS))
def test_every_command_warns_in_one_line_and_runs_on(tmp_path: Path, name: str) -> None:
    args, code, answer = COMMANDS[name]
    case = CASES["strategy-unset-keystore-unset"]
    server_ready = answer if name == "manager" else None

    lines, returned = run_command(args, environment(case, tmp_path), server_ready=server_ready)

    output = "\n".join(lines)
    assert "Traceback" not in output
    assert returned == code, output
    warnings = [line for line in lines if "ROS_SECURITY" in line]
    assert len(warnings) == 1 and unstamped(warnings[0]).startswith(WARNING), output
    if answer is not None:
        assert answer in output

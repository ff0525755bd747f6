"""The device boundary: what a port parameter may make the container open, decided on what is opened.

Real pseudo-terminals, real device nodes, real symlinks and directories;
each refusal is checked to have opened nothing (:class:`OpenWatch`: no open
asked for the target, no descriptor left on it), and, for the controlling
terminal, to have left the terminal as it was, from a child process whose
controlling terminal is a pseudo-terminal of the test's.
"""

from __future__ import annotations

import contextlib
import fcntl
import fnmatch
import json
import os
import shutil
import subprocess
import sys
import termios
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest

from container import ConfigError, DeviceError
from container._ttys import classify
from container.devices import DEFAULT_SERIAL_PATTERNS, DevicePolicy, PortRefused
from tests.container_support import REPO
from tests.device_support import OpenWatch

#: The default of before, as a container file may still spell it.
OLD_DEFAULT = ("/dev/tty*", "/dev/serial/*", "/dev/ldlidar")


@pytest.fixture
def pty() -> Iterator[tuple[int, str]]:
    """A pseudo-terminal: its master's descriptor and its slave's path (the slave is not held open)."""
    master, slave = os.openpty()
    path = os.ttyname(slave)
    os.close(slave)
    yield master, path
    os.close(master)


def refused(policy: DevicePolicy, port: str, *targets: str) -> str:
    """Refuse *port* through :meth:`DevicePolicy.open_serial`, opening none of *targets*; return the reason."""
    with OpenWatch() as watch, pytest.raises(PortRefused) as info:
        policy.open_serial(port)
    assert watch.opens_of(*targets) == [], f"{port} opened {watch.opens_of(*targets)}"
    assert watch.left_open_on(*targets) == []
    assert info.value.port == port
    return info.value.reason


def usable_strace() -> str | None:
    """strace, if it is installed and may trace here (a container may forbid ptrace)."""
    strace = shutil.which("strace")
    if strace is None:
        return None
    probe = subprocess.run([strace, "-qq", "-e", "trace=none", "true"], capture_output=True, timeout=30, check=False)
    return strace if probe.returncode == 0 else None


def device(path: str) -> str:
    if not os.path.exists(path):
        pytest.skip(f"{path} does not exist here")
    return path


def test_the_default_admits_usb_and_acm_adapters_and_their_links_not_terminals() -> None:
    assert DEFAULT_SERIAL_PATTERNS == (
        "/dev/ttyUSB*",
        "/dev/ttyACM*",
        "/dev/serial/by-id/*",
        "/dev/serial/by-path/*",
        "/dev/ldlidar",
    )
    policy = DevicePolicy()
    for port in ("/dev/tty", "/dev/ttyS0", "/dev/tty0", "/dev/console", "/dev/null"):
        if os.path.exists(port):
            assert "not a serial device the default device policy allows" in refused(policy, port, port)


def test_dot_dot_after_a_symlinked_directory_goes_where_the_kernel_goes(
    tmp_path: Path, pty: tuple[int, str]
) -> None:
    """``/dev/shm/s/../../ttyV`` reads as ``/dev/ttyV``; the kernel reaches ``<x>/ttyV``, a link elsewhere."""
    shm = Path("/dev/shm")
    if not (shm.is_dir() and os.access(shm, os.W_OK)):
        pytest.skip("/dev/shm is not writable here")
    x = tmp_path / "x"
    (x / "a" / "b").mkdir(parents=True)
    s = shm / f"s-{uuid.uuid4().hex[:8]}"
    s.symlink_to(x / "a" / "b")
    try:
        port = f"{s}/../../ttyV"
        assert os.path.normpath(port) == "/dev/ttyV"  # what a string check sees
        policy = DevicePolicy(serial=("/dev/tty*",))
        _, pts = pty
        for target in ("/dev/null", pts):
            link = x / "ttyV"
            with contextlib.suppress(FileNotFoundError):
                link.unlink()
            link.symlink_to(target)
            assert os.path.realpath(port) == target
            reason = refused(policy, port, target)
            assert reason.startswith("not a serial device") and reason.endswith(f"it resolves to {target}"), reason
            with pytest.raises(PortRefused, match="not a serial device"):
                policy.check_port(port)
    finally:
        s.unlink()


def test_the_controlling_terminal_is_never_opened_and_stays_as_it_was(tmp_path: Path) -> None:
    """What ``comm.serial_port:=/dev/tty`` did: set the operator's terminal to 230400 baud, raw, without ISIG."""
    master, slave = os.openpty()
    try:
        before = termios.tcgetattr(slave)
        trace = tmp_path / "strace.txt"
        command = [sys.executable, "-c", CONTROLLING_TERMINAL_CHILD, os.ttyname(slave)]
        strace = usable_strace()
        if strace is not None:
            command = [strace, "-f", "-qq", "-e", "trace=open,openat,openat2", "-o", str(trace), *command]
        child = subprocess.run(command, cwd=REPO, capture_output=True, text=True, timeout=50, check=False)
        assert child.returncode == 0, child.stderr
        report = json.loads(child.stdout.splitlines()[-1])
        assert report["controlling_terminal"], "the child's controlling terminal is not the test's pty"
        for how in ("policy", "source"):
            assert "the controlling terminal, never opened" in report[how], report
        assert report["opened"] == [], report
        assert termios.tcgetattr(slave) == before  # speed, ISIG, ICANON, ECHO: untouched
        if strace is not None:
            calls = trace.read_text()
            assert os.ttyname(slave) in calls, "strace saw no open at all"
            assert '"/dev/tty"' not in calls, [line for line in calls.splitlines() if '"/dev/tty"' in line]
    finally:
        os.close(master)
        os.close(slave)


# A session leader of its own (setsid): opening the pty without O_NOCTTY
# makes it the child's controlling terminal, as the operator's terminal is
# the container's. Then /dev/tty is asked for, listed literally
# and by the old default, through the policy and through the LiDAR's source.
CONTROLLING_TERMINAL_CHILD = """
import asyncio, json, os, sys
os.setsid()
terminal = os.open(sys.argv[1], os.O_RDWR)
with open("/proc/self/stat") as f:
    tty_nr = int(f.read().rsplit(")", 1)[1].split()[4])
opened = []
sys.addaudithook(lambda event, args: opened.append(str(args[0])) if event == "open" and args[0] == "/dev/tty" else None)
from container.devices import DevicePolicy, PortRefused
from ldlidar import DeviceRefused, SerialSource
policy = DevicePolicy(serial=("/dev/tty", "/dev/tty*", "/dev/pts/*"))
report = {"controlling_terminal": tty_nr == os.fstat(terminal).st_rdev}
try:
    policy.open_serial("/dev/tty")
    report["policy"] = "opened"
except PortRefused as exc:
    report["policy"] = str(exc)
try:
    asyncio.run(SerialSource("/dev/tty", baudrate=230400, policy=policy).open())
    report["source"] = "opened"
except DeviceRefused as exc:
    report["source"] = str(exc)
report["opened"] = opened
print(json.dumps(report))
"""


@pytest.mark.parametrize(
    ("port", "what"),
    [
        ("/dev/tty0", "a virtual console, never opened"),
        ("/dev/tty1", "a virtual console, never opened"),
        ("/dev/console", "the system console, never opened"),
        ("/dev/ptmx", "the pseudo-terminal multiplexer, never opened"),
        ("/dev/null", "not a terminal, never opened"),
        ("/dev/zero", "not a terminal, never opened"),
    ],
)
def test_consoles_and_devices_that_are_no_serial_port_are_never_opened_even_if_listed(port: str, what: str) -> None:
    device(port)
    for patterns in ((port,), ("/dev/*",), OLD_DEFAULT):
        if not any(fnmatch.fnmatchcase(port, pattern) for pattern in patterns):
            continue
        policy = DevicePolicy(serial=patterns)
        reason = refused(policy, port, port)
        assert reason.startswith(what), reason
        assert f"character device {os.major(os.stat(port).st_rdev)}:" in reason


def test_a_ttys_port_only_where_it_is_named_explicitly() -> None:
    port = device("/dev/ttyS0")
    for patterns in (OLD_DEFAULT, ("/dev/*",)):
        reason = refused(DevicePolicy(serial=patterns), port, port)
        assert reason.startswith("an 8250/16550 serial port (often the machine's serial console)"), reason
        assert "names it explicitly (container.devices.serial: /dev/ttyS* or the path itself" in reason
    # Named: admitted (only looked at here: it may be this machine's console).
    for patterns in (("/dev/ttyS*",), ("/dev/ttyS0",), ("/dev/ttyS[0-3]",)):
        assert DevicePolicy(serial=patterns).check_port(port) == port


def test_a_pseudo_terminal_only_where_pseudo_terminals_are_named(tmp_path: Path, pty: tuple[int, str]) -> None:
    _, pts = pty
    link = tmp_path / "lidar"
    link.symlink_to(pts)
    # Not named at all, by the old default included.
    for patterns in (DEFAULT_SERIAL_PATTERNS, OLD_DEFAULT):
        assert refused(DevicePolicy(serial=patterns), pts, pts).startswith("not a serial device")
    # Named by a wildcard that is not about pseudo-terminals: still refused, saying how to name one.
    for port, pattern in ((str(link), f"{tmp_path}/*"), (pts, "/dev/*")):
        reason = refused(DevicePolicy(serial=(pattern,)), port, pts)
        assert reason.startswith("a pseudo-terminal"), reason
        assert "/dev/pts/* or the path itself" in reason
    # Named: by /dev/pts/*, by itself, or by a wildcard-free link to it.
    for port, pattern in ((pts, "/dev/pts/*"), (pts, pts), (str(link), str(link))):
        with OpenWatch() as watch:
            fd = DevicePolicy(serial=(pattern,)).open_serial(port)
        try:
            assert os.readlink(f"/proc/self/fd/{fd}") == pts
            assert watch.opens_of(pts) == [pts]  # the resolved path, once, not the link
            flags = fcntl.fcntl(fd, fcntl.F_GETFL)
            assert flags & os.O_NONBLOCK and flags & os.O_ACCMODE == os.O_RDWR
            assert not os.get_inheritable(fd)
        finally:
            os.close(fd)


def test_a_policy_trusting_its_own_pty_admits_that_one_only(pty: tuple[int, str]) -> None:
    _, pts = pty
    other_master, other_slave = os.openpty()
    try:
        own = os.stat(pts).st_rdev
        policy = DevicePolicy().with_own_devices(lambda device: device == own)
        os.close(policy.open_serial(pts))
        other = os.ttyname(other_slave)
        assert refused(policy, other, other).startswith("not a serial device the default device policy allows")
        assert policy == DevicePolicy()  # what it trusts is no part of the operator's policy
    finally:
        os.close(other_master)
        os.close(other_slave)


def test_files_fifos_and_missing_paths(tmp_path: Path) -> None:
    secret = tmp_path / "shadow"
    secret.write_text("root:x:\n")
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    policy = DevicePolicy(serial=(f"{tmp_path}/*",))
    assert refused(policy, str(secret), str(secret)) == "not a character device: a regular file"
    assert refused(policy, str(fifo), str(fifo)) == "not a character device: a named pipe"
    with pytest.raises(DeviceError, match="cannot open: No such file or directory"):
        policy.open_serial(f"{tmp_path}/ttyUSB9")
    with pytest.raises(PortRefused, match="cannot open: No such file or directory"):
        policy.check_port(f"{tmp_path}/ttyUSB9")
    # Outside the patterns, a missing path is refused as any other: nothing says whether it exists.
    for port in ("/nonexistent/ttyUSB0", "/dev/tty/../null"):
        with pytest.raises(PortRefused, match="not a serial device"):
            DevicePolicy().check_port(port)
    with pytest.raises(PortRefused, match="must be an absolute path"):
        policy.check_port("ttyUSB0")


def test_patterns_match_resolved_places_not_strings(tmp_path: Path, pty: tuple[int, str]) -> None:
    """A link admitted where it really is (``/dev/serial/by-id/...``); a string that only reads as one, not."""
    _, pts = pty
    other_master, other_slave = os.openpty()
    try:
        by_id = tmp_path / "serial" / "by-id"
        by_id.mkdir(parents=True)
        (by_id / "usb-LiDAR").symlink_to(pts)
        inner = tmp_path / "elsewhere" / "inner"
        inner.mkdir(parents=True)
        (inner.parent / "usb-LiDAR").symlink_to(os.ttyname(other_slave))
        (by_id / "up").symlink_to(inner)
        policy = DevicePolicy(serial=(str(by_id / "usb-LiDAR"), "/dev/ttyUSB*"))
        os.close(policy.open_serial(str(by_id / "usb-LiDAR")))
        sneaky = f"{by_id}/up/../usb-LiDAR"
        assert os.path.normpath(sneaky) == str(by_id / "usb-LiDAR")  # what a string check sees
        assert os.path.realpath(sneaky) == os.ttyname(other_slave)  # what the kernel opens
        reason = refused(policy, sneaky, os.ttyname(other_slave))
        assert reason.startswith("not a serial device"), reason
    finally:
        os.close(other_master)
        os.close(other_slave)


def test_a_replay_is_decided_on_the_file_it_resolves_to(tmp_path: Path) -> None:
    captures = tmp_path / "captures"
    captures.mkdir()
    good = captures / "good.bin"
    good.write_bytes(b"\x54" * 100)
    outside = tmp_path / "shadow"
    outside.write_text("root:x:\n")
    (captures / "link.bin").symlink_to(outside)
    os.mkfifo(captures / "fifo.bin")
    (captures / "zero.bin").symlink_to("/dev/zero")
    policy = DevicePolicy(replay_dirs=(captures,), replay_max_bytes=100)
    fd = policy.open_replay(str(good))
    try:
        assert os.read(fd, 200) == b"\x54" * 100
    finally:
        os.close(fd)
    for name, words, target in (
        ("link.bin", "replays are allowed only of files under the directories", str(outside)),
        ("fifo.bin", "a replay must be a regular file", str(captures / "fifo.bin")),
        ("zero.bin", "replays are allowed only of files under the directories", "/dev/zero"),
    ):
        with OpenWatch() as watch, pytest.raises(PortRefused, match=words):
            policy.open_replay(str(captures / name))
        assert watch.opens_of(target) == [] and watch.left_open_on(target) == []
    good.write_bytes(b"\x54" * 101)
    with pytest.raises(PortRefused, match="the capture is 101 bytes, over the 100 allowed"):
        policy.open_replay(str(good))
    with pytest.raises(DeviceError, match="cannot read capture: No such file"):
        policy.open_replay(str(captures / "missing.bin"))


def test_a_path_longer_than_the_kernel_takes_is_refused_before_it_is_resolved() -> None:
    """Resolving 600 kB of ``/a/a/...`` took 22 s, on the event loop of a configure."""
    policy = DevicePolicy()
    for port in ("/" + "a/" * 300_000, "/dev/ttyUSB" + "x" * 1_000_000, "file://" + "/a" * 300_000):
        with pytest.raises(PortRefused, match=r"a path of \d+ bytes: longer than the 4095 a path may have"):
            policy.check_port(port)
    with pytest.raises(PortRefused, match="longer than the 4095"):
        policy.open_serial("/" + "a/" * 300_000)


def test_the_old_default_still_reads_and_admits_no_terminal() -> None:
    policy = DevicePolicy.from_mapping({"serial": list(OLD_DEFAULT)}, source="old.yaml: container.devices")
    assert policy.serial == OLD_DEFAULT
    for port in ("/dev/tty", "/dev/tty0", "/dev/ttyS0"):  # each matches /dev/tty*
        if os.path.exists(port):
            with pytest.raises(PortRefused, match=r"never opened|names it explicitly"):
                policy.check_port(port)
    with pytest.raises(ConfigError, match="expected a list of strings"):
        DevicePolicy.from_mapping({"serial": "/dev/ttyUSB*"}, source="x")


DRIVERS = """\
/dev/tty             /dev/tty        5       0 system:/dev/tty
/dev/console         /dev/console    5       1 system:console
/dev/ptmx            /dev/ptmx       5       2 system
/dev/vc/0            /dev/vc/0       4       0 system:vtmaster
usbserial            /dev/ttyUSB   188 0-511 serial
acm                  /dev/ttyACM   166 0-255 serial
ttyAMA               /dev/ttyAMA   204 64-77 serial
serial               /dev/ttyS       4 64-111 serial
pty_slave            /dev/pts      136 0-1048575 pty:slave
pty_master           /dev/ptm      128 0-1048575 pty:master
unknown              /dev/tty        4 1-63 console
"""


@pytest.mark.parametrize(
    ("major", "minor", "kind"),
    [
        (5, 0, "terminal"),
        (5, 1, "terminal"),
        (5, 2, "terminal"),
        (4, 0, "terminal"),
        (4, 63, "terminal"),
        (4, 64, "ttyS"),
        (188, 0, "serial"),
        (166, 3, "serial"),
        (204, 64, "serial"),
        (136, 7, "pty"),
        (128, 7, "terminal"),
        (1, 3, "other"),
        (189, 0, "other"),
    ],
)
def test_devices_are_classified_by_their_drivers_numbers(tmp_path: Path, major: int, minor: int, kind: str) -> None:
    drivers = tmp_path / "drivers"
    drivers.write_text(DRIVERS)
    assert classify(os.makedev(major, minor), drivers=str(drivers)).kind == kind
    # The kernel's fixed numbers stand in when the list cannot be read (ttyAMA is not among them).
    if (major, minor) != (204, 64):
        assert classify(os.makedev(major, minor), drivers=str(tmp_path / "missing")).kind == kind

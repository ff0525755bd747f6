"""Which ports and files a plugin may open: the operator's choice, not a peer's.

A node's parameters come from whoever loads it, and any participant on the
ROS domain may call ``load_node``: a parameter naming a port
(``comm.serial_port``) is input from the network. So what such a parameter
may name is decided by the operator, in the container file, and plugins open
through this module::

    container:
      devices:
        serial: ["/dev/ttyUSB*", "/dev/ttyACM*", "/dev/serial/by-id/*",
                 "/dev/serial/by-path/*", "/dev/ldlidar"]   # the default
        replay_dirs: [/var/lib/lidar-captures]   # file:// replays only below these (default: none)
        replay_max_bytes: 67108864               # and at most this big (default 64 MiB)
        network: false                           # socket:// and rfc2217:// ports (default: refused)

The decision is on what would be opened, never on the string. A string is
not what the kernel opens: ``/dev/shm/s/../../ttyV`` reads as ``/dev/ttyV``
but, ``s`` being a symlinked directory, reaches wherever the kernel's walk
goes; a symlink allowed yesterday may point at ``/etc/shadow`` today; and
``/dev/tty`` is whichever terminal the process happens to have. So, for a
serial port:

1. the path is resolved as the kernel resolves it (:func:`os.path.realpath`,
   strictly); a pattern matches the resolved path, or the real location of
   a symlink followed on the way (``/dev/serial/by-id/...``,
   ``/dev/ldlidar``), never the string as given;
2. the device's numbers say what it is (:mod:`container._ttys`, from
   ``/proc/tty/drivers``): a serial port's driver is admitted; a
   pseudo-terminal or an 8250 port (``/dev/ttyS*``) only where a pattern
   names them explicitly; the controlling terminal, the console, virtual
   consoles and any device that is not a terminal's (``/dev/null``), never;
3. :meth:`DevicePolicy.open_serial` opens the resolved path without
   following a symlink swapped in since (``O_NOFOLLOW``), without it becoming
   the controlling terminal (``O_NOCTTY``), without waiting (``O_NONBLOCK``),
   and checks the descriptor (``fstat``, ``/proc/self/fd``) is the very device
   admitted before anything touches it. A refusal at steps 1 and 2 opens
   nothing; one at step 3 closes the descriptor before any ``ioctl``.

Plugins open through :meth:`DevicePolicy.open_serial` on every open, a
reconnect's included, so a symlink re-pointed meanwhile is decided anew.
The ``container run`` process installs the file's policy with
:func:`set_device_policy`; a plugin calls :func:`device_policy`.
"""

from __future__ import annotations

import dataclasses
import errno
import fnmatch
import os
import re
import stat
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Final
from urllib.parse import unquote, urlsplit

from ._errors import ConfigError, DeviceError
from ._text import clip
from ._ttys import TtyClass, classify

__all__ = ["DEFAULT_SERIAL_PATTERNS", "DevicePolicy", "PortRefused", "device_policy", "set_device_policy"]

#: Serial devices a plugin may open unless the container file says otherwise:
#: USB serial and CDC-ACM adapters, by their kernel names, by udev's stable
#: links, and the LiDAR driver's udev link. Not ``/dev/tty*``: that admits
#: the controlling terminal, the virtual consoles and the serial console.
DEFAULT_SERIAL_PATTERNS: Final = (
    "/dev/ttyUSB*",
    "/dev/ttyACM*",
    "/dev/serial/by-id/*",
    "/dev/serial/by-path/*",
    "/dev/ldlidar",
)

_DEFAULT_REPLAY_MAX: Final = 64 * 1024 * 1024
#: pyserial URL schemes that open network connections.
_NETWORK_SCHEMES: Final = frozenset({"socket", "rfc2217"})

#: How a serial port is opened: never as the controlling terminal, never
#: through a symlink, never waiting for a modem's carrier, never inherited.
_SERIAL_FLAGS: Final = os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK | os.O_CLOEXEC | os.O_NOFOLLOW
_REPLAY_FLAGS: Final = os.O_RDONLY | os.O_NOCTTY | os.O_NONBLOCK | os.O_CLOEXEC | os.O_NOFOLLOW

#: Symlinks followed at most, as the kernel (MAXSYMLINKS).
_MAX_SYMLINKS: Final = 40
#: The longest path the kernel takes (PATH_MAX, its NUL included). Longer is
#: refused before resolving: os.path.realpath on a 600 kB path of short
#: components took 22 s, on the event loop of a configure.
_PATH_MAX: Final = 4096

#: Kinds of device a pattern admits only when it names them on purpose: it
#: has no wildcard (one path, the device or a link to it), or its fixed part
#: starts with one of these. ``/dev/tty*`` names neither.
_EXPLICIT: Final = {"pty": "/dev/pts/", "ttyS": "/dev/ttyS"}

_WILDCARD: Final = re.compile(r"[*?\[]")


class PortRefused(ConfigError):
    """A port or file the device policy does not allow; the message says why and what would.

    :param port: what was asked for, as given (the message shows it clipped).
    """

    def __init__(self, message: str, *, port: str) -> None:
        # A peer's parameter: a 1 MB port must not make a 1 MB log line.
        super().__init__(message, source=f"port {clip(port, quote=True)}")
        self.port = port


@dataclass(frozen=True, slots=True)
class _Admitted:
    """A serial device the policy admits: the path to open and what must be there."""

    path: str
    device: int
    tty: TtyClass


@dataclass(frozen=True)
class DevicePolicy:
    """What a port parameter may name.

    :param serial: glob patterns of serial devices; a pattern matches the
        device's resolved path or the real location of a symlink on the way
        to it. Pseudo-terminals and ``/dev/ttyS*`` only where a pattern names
        them explicitly (``/dev/pts/*``, ``/dev/ttyS1``, or a wildcard-free
        path that resolves to one); the controlling terminal, the console and
        the virtual consoles never.
    :param replay_dirs: directories whose regular files may be replayed
        (``file://`` ports); none by default.
    :param replay_max_bytes: the largest replay file.
    :param network: whether ``socket://`` and ``rfc2217://`` ports may connect.
    :param own_devices: whether a device number is a pseudo-terminal this
        process made for itself (a plugin's built-in emulator); such a
        pseudo-terminal is admitted whatever the patterns say. A peer names
        paths; it cannot make a pseudo-terminal someone else opened pass as
        one of these. See :meth:`with_own_devices`.
    """

    serial: tuple[str, ...] = DEFAULT_SERIAL_PATTERNS
    replay_dirs: tuple[Path, ...] = ()
    replay_max_bytes: int = _DEFAULT_REPLAY_MAX
    network: bool = False
    #: Where the policy came from, for messages (a container file, "the default").
    origin: str = field(default="the default device policy", compare=False)
    own_devices: Callable[[int], bool] | None = field(default=None, compare=False, repr=False)

    @classmethod
    def from_mapping(cls, values: Mapping[str, Any], *, source: str, base_dir: Path | None = None) -> DevicePolicy:
        """The ``container.devices`` section of a container file.

        :param base_dir: what relative ``replay_dirs`` are relative to (the file's directory).
        :raises ConfigError: an unknown key or a value of the wrong kind.
        """
        known = {"serial", "replay_dirs", "replay_max_bytes", "network"}
        unknown = sorted(set(values) - known)
        if unknown:
            raise ConfigError(f"unknown key(s) {', '.join(unknown)}; known: {', '.join(sorted(known))}", source=source)
        serial = _strings(values.get("serial", DEFAULT_SERIAL_PATTERNS), source=f"{source}.serial")
        dirs = _strings(values.get("replay_dirs", ()), source=f"{source}.replay_dirs")
        size = values.get("replay_max_bytes", _DEFAULT_REPLAY_MAX)
        if isinstance(size, bool) or not isinstance(size, int) or size <= 0:
            raise ConfigError(f"expected a positive number of bytes, got {size!r}", source=f"{source}.replay_max_bytes")
        network = values.get("network", False)
        if not isinstance(network, bool):
            raise ConfigError(f"expected true or false, got {network!r}", source=f"{source}.network")
        base = base_dir or Path.cwd()
        return cls(
            serial=serial,
            replay_dirs=tuple((base / d).resolve() for d in dirs),
            replay_max_bytes=size,
            network=network,
            origin=source,
        )

    def with_own_devices(self, owns: Callable[[int], bool]) -> DevicePolicy:
        """This policy, also admitting the pseudo-terminals *owns* says this process made.

        The LiDAR node that starts its emulator opens the emulator's
        pseudo-terminal through such a policy; the operator's patterns need
        not admit pseudo-terminals for it, and a peer naming some other
        pseudo-terminal is still refused.
        """
        return dataclasses.replace(self, own_devices=owns)

    def check_port(self, port: str) -> str:
        """Check a serial device path or pyserial URL; return it unchanged.

        Only looks (``lstat``, ``readlink``, ``stat``), never opens or reads:
        a named pipe or a terminal is refused before anything could block on
        it or change it. What is finally opened is checked again by
        :meth:`open_serial`, which a plugin opens serial ports with.

        :raises PortRefused: with the reason and what the policy allows.
        """
        if "\x00" in port:
            raise PortRefused("must not contain a NUL character", port=port)
        parts = urlsplit(port)
        scheme = parts.scheme.lower()
        if scheme == "file":
            self.check_replay(unquote(parts.netloc + parts.path))
            return port
        if scheme in _NETWORK_SCHEMES:
            if not self.network:
                raise PortRefused(
                    f"network ports ({scheme}://) are not allowed by {self.origin}; "
                    "the container file may allow them (container.devices.network: true)",
                    port=port,
                )
            return port
        if scheme and "://" in port:
            raise PortRefused(
                f"pyserial URL scheme {scheme!r} is not allowed (allowed: serial device paths, file:// replays"
                f"{', socket://, rfc2217://' if self.network else ''})",
                port=port,
            )
        try:
            self._admit(port, hide_missing=True)
        except OSError as exc:
            raise PortRefused(f"cannot open: {exc.strerror or exc}", port=port) from None
        return port

    def open_serial(self, port: str) -> int:
        """Open the serial device *port* names, if admitted; return its descriptor.

        The descriptor is open read-write, non-blocking, close-on-exec, and
        not the process's controlling terminal; nothing has been done to the
        device beyond opening it (no ``ioctl``, no ``termios``). The caller
        owns it.

        :raises PortRefused: the policy does not admit what *port* names, or
            what was opened is not what was admitted (a symlink or a
            directory swapped in between): then it is closed untouched.
        :raises DeviceError: the device is missing or cannot be opened
            (unplugged, busy, no permission).
        """
        try:
            admitted = self._admit(port, hide_missing=False)
        except OSError as exc:
            raise DeviceError(f"cannot open: {exc.strerror or exc}", device=port) from exc
        try:
            fd = os.open(admitted.path, _SERIAL_FLAGS)
        except OSError as exc:
            if exc.errno == errno.ELOOP:
                raise PortRefused(
                    f"{admitted.path} became a symlink after it was checked: not opened", port=port
                ) from None
            raise DeviceError(f"cannot open {admitted.path}: {exc.strerror or exc}", device=port) from exc
        try:
            info = os.fstat(fd)
            opened = _opened_path(fd)
            if opened != admitted.path or not stat.S_ISCHR(info.st_mode) or info.st_rdev != admitted.device:
                now = classify(info.st_rdev).describe() if stat.S_ISCHR(info.st_mode) else _file_kind(info.st_mode)
                raise PortRefused(
                    f"{admitted.path} changed between the check and the open (opened {opened}, {now}): "
                    "closed untouched",
                    port=port,
                )
        except BaseException:
            os.close(fd)
            raise
        return fd

    def _admit(self, port: str, *, hide_missing: bool) -> _Admitted:
        """Decide on the device *port* resolves to; open nothing.

        :param hide_missing: refuse a missing path the patterns would not
            admit anyway as any other path, so that a peer's answer says
            nothing of which paths exist (:meth:`check_port`, at configure).
            Otherwise a missing device is missing (a reopen while it is away).
        :raises PortRefused: not admitted.
        :raises OSError: a component of the path is missing (or a symlink loop).
        """
        if "\x00" in port:
            raise PortRefused("must not contain a NUL character", port=port)
        if not os.path.isabs(port):
            raise PortRefused("a serial device must be an absolute path (or 'auto')", port=port)
        _check_length(port)
        try:
            hops = _hops(port)
        except OSError:
            if hide_missing and not self._matching(_hops(port, strict=False)):
                raise self._not_allowed(port, port) from None
            raise
        path = hops[-1]
        resolved = "" if path == port else f" (resolves to {path})"
        info = os.stat(path, follow_symlinks=False)
        tty = classify(info.st_rdev) if stat.S_ISCHR(info.st_mode) else None
        if tty is not None and tty.kind == "pty" and self.own_devices is not None and self.own_devices(info.st_rdev):
            return _Admitted(path, info.st_rdev, tty)
        matching = self._matching(hops)
        if not matching:
            raise self._not_allowed(port, path)
        if tty is None:
            raise PortRefused(f"not a character device{resolved}: {_file_kind(info.st_mode)}", port=port)
        if tty.kind in ("terminal", "other"):
            raise PortRefused(f"{tty.what}, never opened{resolved}: {tty.describe()}", port=port)
        explicit = _EXPLICIT.get(tty.kind)
        if explicit is not None and not any(_names_explicitly(pattern, explicit) for pattern in matching):
            raise PortRefused(
                f"{tty.what}{resolved}: opened only where {self.origin} names it explicitly "
                f"(container.devices.serial: {explicit}* or the path itself; "
                f"matched only {', '.join(matching)})",
                port=port,
            )
        return _Admitted(path, info.st_rdev, tty)

    def _matching(self, names: Iterable[str]) -> list[str]:
        names = list(names)
        return [pattern for pattern in self.serial if any(fnmatch.fnmatchcase(name, pattern) for name in names)]

    def _not_allowed(self, port: str, path: str) -> PortRefused:
        return PortRefused(
            f"not a serial device {self.origin} allows ({', '.join(self.serial) or 'none'}; "
            f"container.devices.serial in the container file){'' if path == port else f': it resolves to {path}'}",
            port=port,
        )

    def check_replay(self, path: str) -> Path:
        """Check a capture file to replay; return its resolved path.

        :raises PortRefused: not a regular file under :attr:`replay_dirs`, or too big.
        """
        try:
            return self._admit_replay(path)
        except OSError as exc:
            raise PortRefused(f"cannot read capture: {exc.strerror or exc}", port=path) from None

    def open_replay(self, path: str) -> int:
        """Open a capture file to replay, if admitted; return its descriptor (read-only).

        The same checks as :meth:`check_replay` before the open (a named pipe
        or a device is refused unopened), then again on the open descriptor:
        a symlink, pipe or device swapped in since is closed before a byte
        is read.

        :raises PortRefused: not admitted, or changed since it was checked.
        :raises DeviceError: it is missing or cannot be opened.
        """
        try:
            real = self._admit_replay(path)
            fd = os.open(real, _REPLAY_FLAGS)
        except OSError as exc:
            if exc.errno == errno.ELOOP:
                raise PortRefused("became a symlink after it was checked: not opened", port=path) from None
            raise DeviceError(f"cannot read capture: {exc.strerror or exc}", device=path) from exc
        try:
            opened = _opened_path(fd)
            if not self._replayable(Path(opened)):
                raise PortRefused(f"{real} changed between the check and the open (opened {opened})", port=path)
            self._check_capture(path, os.fstat(fd))
        except BaseException:
            os.close(fd)
            raise
        return fd

    def _admit_replay(self, path: str) -> Path:
        """Decide on the capture *path* resolves to; open nothing.

        :raises PortRefused: not admitted.
        :raises OSError: it is missing.
        """
        _check_length(path)
        real = Path(os.path.realpath(path))
        if not self._replayable(real):
            where = ", ".join(str(d) for d in self.replay_dirs) or "none"
            raise PortRefused(
                f"replays are allowed only of files under the directories {self.origin} names "
                f"(container.devices.replay_dirs: {where})",
                port=path,
            )
        self._check_capture(path, os.stat(real))
        return real

    def _replayable(self, real: Path) -> bool:
        return any(real.is_relative_to(directory) for directory in self.replay_dirs)

    def _check_capture(self, path: str, info: os.stat_result) -> None:
        if not stat.S_ISREG(info.st_mode):
            raise PortRefused("a replay must be a regular file (not a pipe or device)", port=path)
        if info.st_size > self.replay_max_bytes:
            raise PortRefused(
                f"the capture is {info.st_size} bytes, over the {self.replay_max_bytes} allowed "
                "(container.devices.replay_max_bytes)",
                port=path,
            )


def _hops(port: str, *, strict: bool = True) -> list[str]:
    """Where each name the kernel follows from *port* really is; the last is the resolved path.

    Each name's directory is resolved first, so ``..`` after a symlinked
    directory goes where the kernel goes, not where the string points.

    :param strict: raise if the walk cannot complete; if false, stop where
        it cannot go on (for telling which names a missing device had).
    :raises OSError: (strict) a component is missing, a symlink loop, or
        the path changed while it was walked.
    """
    hops: list[str] = []
    path = port
    for _ in range(_MAX_SYMLINKS + 1):
        head, tail = os.path.split(path)
        if tail in ("", ".", ".."):
            where = os.path.realpath(path, strict=strict)
        else:
            where = os.path.join(os.path.realpath(head, strict=strict), tail)
        hops.append(where)
        if not os.path.islink(where):
            break
        try:
            path = os.path.join(os.path.dirname(where), os.readlink(where))
        except OSError:
            if strict:
                raise
            break
    else:
        if strict:
            raise OSError(errno.ELOOP, os.strerror(errno.ELOOP), port)
    if strict and os.path.realpath(port, strict=True) != hops[-1]:
        raise OSError(errno.EAGAIN, "the path changed while it was checked", port)
    return hops


def _check_length(path: str) -> None:
    size = len(os.fsencode(path))
    if size >= _PATH_MAX:
        raise PortRefused(f"a path of {size} bytes: longer than the {_PATH_MAX - 1} a path may have", port=path)


def _names_explicitly(pattern: str, prefix: str) -> bool:
    fixed = _WILDCARD.split(pattern, maxsplit=1)[0]
    return fixed == pattern or fixed.startswith(prefix)


def _opened_path(fd: int) -> str:
    """The path of what *fd* is open on, as the kernel reports it."""
    try:
        return os.readlink(f"/proc/self/fd/{fd}")
    except OSError as exc:
        return f"<unknown: {exc.strerror or exc}>"


def _file_kind(mode: int) -> str:
    for test, name in (
        (stat.S_ISREG, "a regular file"),
        (stat.S_ISDIR, "a directory"),
        (stat.S_ISFIFO, "a named pipe"),
        (stat.S_ISSOCK, "a socket"),
        (stat.S_ISBLK, "a block device"),
        (stat.S_ISCHR, "a character device"),
    ):
        if test(mode):
            return name
    return "not a device"


def _strings(value: object, *, source: str) -> tuple[str, ...]:
    if isinstance(value, str) or not isinstance(value, Iterable):
        raise ConfigError(f"expected a list of strings, got {value!r}", source=source)
    items = tuple(value)
    if not all(isinstance(item, str) and item for item in items):
        raise ConfigError(f"expected a list of non-empty strings, got {list(items)!r}", source=source)
    return items


_policy = DevicePolicy()


def device_policy() -> DevicePolicy:
    """The policy of this process: the container file's, else the default."""
    return _policy


def set_device_policy(policy: DevicePolicy) -> DevicePolicy:
    """Install ``policy`` for this process; return the one it replaces.

    The process that runs the container calls it once, from the operator's
    configuration; tests and embedding programs may too.
    """
    global _policy
    previous, _policy = _policy, policy
    return previous

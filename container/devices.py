"""Which ports and files a plugin may open: the operator's choice, not a peer's.

A node's parameters come from whoever loads it, and any participant on the
ROS domain may call ``load_node``: a parameter naming a port
(``comm.serial_port``) is input from the network. So what such a parameter
may name is decided by the operator, in the container file, and plugins ask
this module before they open anything::

    container:
      devices:
        serial: ["/dev/tty*", "/dev/serial/*", "/dev/ldlidar"]   # the default
        replay_dirs: [/var/lib/lidar-captures]   # file:// replays only below these (default: none)
        replay_max_bytes: 67108864               # and at most this big (default 64 MiB)
        network: false                           # socket:// and rfc2217:// ports (default: refused)

The default lets a plugin open serial devices and nothing else: no file, no
named pipe, no other device, no network connection. The ``container run``
process installs the file's policy with :func:`set_device_policy`; a plugin
calls :func:`device_policy` and :meth:`DevicePolicy.check_port`.
"""

from __future__ import annotations

import fnmatch
import os
import stat
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Final
from urllib.parse import unquote, urlsplit

from ._errors import ConfigError
from ._text import clip

__all__ = ["DEFAULT_SERIAL_PATTERNS", "DevicePolicy", "PortRefused", "device_policy", "set_device_policy"]

#: Serial devices a plugin may open unless the container file says otherwise.
DEFAULT_SERIAL_PATTERNS: Final = ("/dev/tty*", "/dev/serial/*", "/dev/ldlidar")

_DEFAULT_REPLAY_MAX: Final = 64 * 1024 * 1024
#: pyserial URL schemes that open network connections.
_NETWORK_SCHEMES: Final = frozenset({"socket", "rfc2217"})


class PortRefused(ConfigError):
    """A port or file the device policy does not allow; the message says why and what would.

    :param port: what was asked for, as given (the message shows it clipped).
    """

    def __init__(self, message: str, *, port: str) -> None:
        # A peer's parameter: a 1 MB port must not make a 1 MB log line.
        super().__init__(message, source=f"port {clip(port, quote=True)}")
        self.port = port


@dataclass(frozen=True)
class DevicePolicy:
    """What a port parameter may name.

    :param serial: glob patterns of serial device paths; a path matches if
        it, or the file it links to, matches one.
    :param replay_dirs: directories whose regular files may be replayed
        (``file://`` ports); none by default.
    :param replay_max_bytes: the largest replay file.
    :param network: whether ``socket://`` and ``rfc2217://`` ports may connect.
    """

    serial: tuple[str, ...] = DEFAULT_SERIAL_PATTERNS
    replay_dirs: tuple[Path, ...] = ()
    replay_max_bytes: int = _DEFAULT_REPLAY_MAX
    network: bool = False
    #: Where the policy came from, for messages (a container file, "the default").
    origin: str = field(default="the default device policy", compare=False)

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

    def check_port(self, port: str) -> str:
        """Check a serial device path or pyserial URL; return it unchanged.

        Only looks (``stat``), never opens or reads: a named pipe or a
        device is refused before anything could block on it.

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
        self._check_serial(port)
        return port

    def _check_serial(self, path: str) -> None:
        if not os.path.isabs(path):
            raise PortRefused("a serial device must be an absolute path (or 'auto')", port=path)
        # Normalised first: '/dev/tty/../null' must not pass as '/dev/tty*'.
        normal, real = os.path.normpath(path), os.path.realpath(path)
        if not any(fnmatch.fnmatchcase(candidate, pattern) for pattern in self.serial for candidate in {normal, real}):
            raise PortRefused(
                f"not a serial device {self.origin} allows ({', '.join(self.serial) or 'none'}; "
                "container.devices.serial in the container file)",
                port=path,
            )
        try:
            mode = os.stat(real).st_mode
        except OSError as exc:
            raise PortRefused(f"cannot open: {exc.strerror or exc}", port=path) from None
        if not stat.S_ISCHR(mode):
            raise PortRefused("not a character device", port=path)

    def check_replay(self, path: str) -> Path:
        """Check a capture file to replay; return its resolved path.

        :raises PortRefused: not a regular file under :attr:`replay_dirs`, or too big.
        """
        real = Path(os.path.realpath(path))
        if not any(real.is_relative_to(directory) for directory in self.replay_dirs):
            where = ", ".join(str(d) for d in self.replay_dirs) or "none"
            raise PortRefused(
                f"replays are allowed only of files under the directories {self.origin} names "
                f"(container.devices.replay_dirs: {where})",
                port=path,
            )
        try:
            info = os.stat(real)
        except OSError as exc:
            raise PortRefused(f"cannot read capture: {exc.strerror or exc}", port=path) from None
        if not stat.S_ISREG(info.st_mode):
            raise PortRefused("a replay must be a regular file (not a pipe or device)", port=path)
        if info.st_size > self.replay_max_bytes:
            raise PortRefused(
                f"the capture is {info.st_size} bytes, over the {self.replay_max_bytes} allowed "
                "(container.devices.replay_max_bytes)",
                port=path,
            )
        return real


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

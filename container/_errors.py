"""The project's one exception hierarchy.

::

    ContainerError                 anything this package raises on purpose
    ├── ExecutorError              the executor refused an impossible move
    ├── ConfigError                a configuration value (file, setting, parameter) is wrong
    ├── PluginError                a plugin distribution could not be used
    ├── LoadError                  a node could not be loaded into the container
    │   └── ReloadError            a node could not be reloaded with new code
    ├── TransitionError            a lifecycle transition could not be carried out
    ├── DeviceError                a device (serial port, capture file) failed
    ├── SecurityError              DDS security was asked for and cannot be had
    └── StateFileError             a container's state file cannot be read, used or written

Each keeps what it is about as attributes (``source``, ``node``, ``device``,
...) and the bare ``reason``, so callers never take the message apart. The
attributes hold values whole; messages echo a value from outside clipped
(:func:`~container.clip`), so that ``str(exc)`` is fit for a log line.
Foreign errors (rclpy, import machinery, serial, YAML) are translated into
these where they enter our code, chained with ``raise ... from exc`` so the
original traceback is kept.
"""

from __future__ import annotations

from ._text import clip

__all__ = [
    "ConfigError",
    "ContainerError",
    "DeviceError",
    "ExecutorError",
    "LoadError",
    "PluginError",
    "ReloadError",
    "SecurityError",
    "StateFileError",
    "TransitionError",
]


class ContainerError(Exception):
    """Base of every error this package raises on purpose.

    :param reason: what went wrong, without the context the subclasses add
        in front of it (file, node, device); the message when there is none.
    """

    def __init__(self, message: str, *, reason: str | None = None) -> None:
        super().__init__(message)
        self.reason = message if reason is None else reason


class ExecutorError(ContainerError):
    """The executor was asked for something its state does not allow."""


class ConfigError(ContainerError):
    """A configuration file or value is invalid.

    :param source: where the bad value came from (a file path, a key path).
    """

    def __init__(self, message: str, *, source: str | None = None) -> None:
        super().__init__(f"{source}: {message}" if source else message, reason=message)
        self.source = source


class PluginError(ContainerError):
    """A plugin distribution or entry point could not be used.

    :param distribution: the distribution that ships the plugin, if known.
    :param entry_point: the entry point's name, if known.
    """

    def __init__(
        self,
        message: str,
        *,
        distribution: str | None = None,
        entry_point: str | None = None,
    ) -> None:
        where = " ".join(
            part
            for part in (
                f"distribution {distribution!r}" if distribution else "",
                f"entry point {entry_point!r}" if entry_point else "",
            )
            if part
        )
        super().__init__(f"{where}: {message}" if where else message, reason=message)
        self.distribution = distribution
        self.entry_point = entry_point


class LoadError(ContainerError):
    """A node could not be loaded; the message is what a LoadNode caller sees."""


class ReloadError(LoadError):
    """A reload failed; the message says why and what runs now.

    :param distribution: the distribution whose code was to be reloaded.
    :param location: ``file:line`` of the new code's failure, if it is known.
    :param old_code_running: whether the nodes run (again) on the old code.
    """

    def __init__(self, message: str, *, distribution: str, location: str = "", old_code_running: bool) -> None:
        super().__init__(message)
        self.distribution = distribution
        self.location = location
        self.old_code_running = old_code_running


class TransitionError(ContainerError):
    """A lifecycle transition could not be carried out.

    :param node: the full name of the node.
    :param transition: the transition's label.
    """

    def __init__(self, message: str, *, node: str, transition: str) -> None:
        super().__init__(f"{node}: transition {transition!r}: {message}", reason=message)
        self.node = node
        self.transition = transition


class DeviceError(ContainerError):
    """A device failed: the port could not open, vanished, or sent nothing valid.

    :param device: the port or URL of the device.
    """

    def __init__(self, message: str, *, device: str) -> None:
        # The device may be a peer's parameter: the message shows its start and its length.
        super().__init__(f"{clip(device)}: {message}", reason=message)
        self.device = device


class SecurityError(ContainerError):
    """DDS security was asked for (``ROS_SECURITY_ENABLE=true``) and cannot be had.

    Raised before rcl starts, where rcl or Fast DDS would refuse to (a
    missing keystore or enclave under ``ROS_SECURITY_STRATEGY=Enforce``, a
    Fast DDS without its security plugins): the message is the one line a
    command prints before it exits 1.

    :param enclave: the enclave rcl would look up.
    """

    def __init__(self, message: str, *, enclave: str) -> None:
        super().__init__(message)
        self.enclave = enclave


class StateFileError(ContainerError):
    """A container's state file (``state_file``) cannot be read, used or written.

    :param path: the state file.
    """

    def __init__(self, message: str, *, path: str) -> None:
        super().__init__(f"state file {clip(path, quote=True)}: {message}", reason=message)
        self.path = path

"""What DDS security the environment asks for, and what rcl and Fast DDS will make of it.

rcl decides from the environment when it starts, by rules that fail
quietly: only ``ROS_SECURITY_ENABLE=true`` (exactly) enables security; only
``ROS_SECURITY_STRATEGY=Enforce`` (exactly) enforces it, anything else is
Permissive; under Permissive, a keystore or enclave that is not there means
running without security, and not a word said; under Enforce it means
``failed to initialize rcl`` with no reason, or one that names a directory.
Fast DDS then refuses any enclave at all when it was built without its
security plugins (the PyPI wheels' is), whatever the strategy.

:func:`check_security` applies the same rules before ``rclpy.init``, so
that every command can say in one line what will happen and why: a
:class:`~container.SecurityError` when security was asked for and cannot be
had (the command exits 1 without starting rcl), a warning when the process
will run without the security its environment seems to ask for, nothing
when security is off or on as asked.

The rules, from rcl's ``security.c`` and ``init.c`` and rmw_fastrtps'
``participant.cpp`` (Jazzy), are mirrored here, not guessed:

* the enclave is ``ROS_SECURITY_ENCLAVE_OVERRIDE`` when it is not empty,
  else the last ``--enclave``/``-e`` of the ROS arguments, else ``/``;
* its directory is ``<ROS_SECURITY_KEYSTORE>/enclaves`` followed by the
  enclave name without its first character; rcl checks only that this
  directory exists, and hands it to the middleware;
* Fast DDS built with security needs six files in it (each of the first four
  may be a PKCS#11 ``.p11`` file instead of the ``.pem``): all present,
  secured; some missing, an error under Enforce and no security under
  Permissive; Fast DDS built without refuses the directory outright.
"""

from __future__ import annotations

import contextlib
import ctypes
import functools
import os
import re
import sys
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

from ._errors import SecurityError
from ._text import clip

__all__ = [
    "ENCLAVE_FILES",
    "NO_SECURITY_PLUGINS",
    "SecurityCheck",
    "check_security",
    "clear_rcl_error",
    "enclave_directory",
    "enclave_from_arguments",
    "fast_dds_has_security",
    "missing_enclave_files",
]

#: The one line for a Fast DDS without security plugins that is handed an enclave.
NO_SECURITY_PLUGINS = (
    "ROS_SECURITY_ENABLE is true, but this Fast DDS is built without its security plugins "
    "(the PyPI wheels' Fast DDS is): use a ROS 2 whose Fast DDS was built with -DSECURITY=ON, "
    "or unset ROS_SECURITY_ENABLE"
)

#: The files Fast DDS reads from an enclave's directory: each entry's first
#: name, or one of the others (PKCS#11 URIs in a file) where there are more.
ENCLAVE_FILES: tuple[tuple[str, ...], ...] = (
    ("identity_ca.cert.pem", "identity_ca.cert.p11"),
    ("cert.pem", "cert.p11"),
    ("key.pem", "key.p11"),
    ("permissions_ca.cert.pem", "permissions_ca.cert.p11"),
    ("governance.p7s",),
    ("permissions.p7s",),
)

#: Values of ROS_SECURITY_ENABLE that mean "off" in any spelling: nothing to say.
_OFF = frozenset({"", "false", "0", "no", "off"})

#: The rmw implementations whose rules (and library) are Fast DDS's; unset is Jazzy's default.
_FAST_DDS_RMWS = frozenset({"", "rmw_fastrtps_cpp", "rmw_fastrtps_dynamic_cpp"})

#: Only rmw_fastrtps built without security holds this text (its refusal).
_NO_SECURITY_MARKER = b"doesn't have the security libraries"
_RMW_LIBRARY = "librmw_fastrtps_shared_cpp.so"

#: rcl's flags for the enclave, and those of its flags that take a value.
_ENCLAVE_FLAGS = frozenset({"-e", "--enclave"})
_VALUE_FLAGS = frozenset(
    {"-r", "--remap", "-p", "--param", "--params-file", "--log-level", "--log-config-file", "--log-file-name"}
)
#: An enclave name rcl_init accepts (rcl_validate_enclave_name: a namespace's rules).
_VALID_ENCLAVE = re.compile(r"/|(/[A-Za-z_][A-Za-z0-9_]*)+")
_ROS_ARGS = "--ros-args"
_END_OF_ROS_ARGS = "--"

#: Longest environment value quoted in a line.
_QUOTE_LIMIT = 80


@dataclass(frozen=True)
class SecurityCheck:
    """What a process will run with, as decided before rcl starts.

    :ivar secured: rcl will hand the middleware an enclave whose files are
        there (Fast DDS with security: the participant is secured).
    :ivar warning: the one line to log when the process runs without the
        security its environment seems to ask for; ``None`` otherwise.
    :ivar stale_rcl_error: rcl's enclave lookup fails quietly under
        Permissive but leaves its failure set as the thread's rcutils error,
        which the next error rmw sets (an ordinary one, while it creates the
        first node) prints as a ten-line "error state is being overwritten"
        block. The caller clears it after ``rclpy.init``.
    """

    secured: bool = False
    warning: str | None = None
    stale_rcl_error: bool = False


def check_security(
    ros_args: Sequence[str] = (),
    *,
    environ: Mapping[str, str] | None = None,
    fast_dds_security: bool | None = None,
) -> SecurityCheck:
    """Decide, as rcl and Fast DDS will, what the environment's security settings come to.

    :param ros_args: the command line's ROS arguments (``--ros-args``
        sections), for ``--enclave``.
    :param environ: the environment rcl will read (default: this process's).
    :param fast_dds_security: whether the Fast DDS in use has its security
        plugins (default: :func:`fast_dds_has_security`; ``None`` there
        means unknown, and the files decide).
    :raises SecurityError: security was asked for (``ROS_SECURITY_ENABLE=true``)
        and rcl or Fast DDS will refuse to start: the message is the one line.
    """
    env = os.environ if environ is None else environ
    named = enclave_from_arguments(ros_args)
    if named is not None and not _VALID_ENCLAVE.fullmatch(named):
        # rcl_init refuses the name whatever the security: its error is the line.
        return SecurityCheck()
    enable = env.get("ROS_SECURITY_ENABLE", "")
    if enable != "true":
        if enable.strip().lower() in _OFF:
            return SecurityCheck()
        return SecurityCheck(
            warning=(
                f"ROS_SECURITY_ENABLE={_quote(enable)} is not 'true', the only value rcl reads as enabled: "
                "running WITHOUT DDS security (set ROS_SECURITY_ENABLE=true to enable it, or unset it)"
            )
        )
    strategy = env.get("ROS_SECURITY_STRATEGY", "")
    enforce = strategy == "Enforce"
    override = env.get("ROS_SECURITY_ENCLAVE_OVERRIDE", "")
    enclave = override or named or "/"
    which = f"enclave {enclave!r}" + (" (ROS_SECURITY_ENCLAVE_OVERRIDE)" if override else "")
    keystore = env.get("ROS_SECURITY_KEYSTORE", "")

    # What rcl will not find, and what makes it.
    missing: tuple[str, str] | None = None
    if not keystore:
        missing = ("ROS_SECURITY_KEYSTORE is not set", "point it at a keystore: `ros2 security create_keystore DIR`")
    elif not os.path.isdir(keystore):
        missing = (
            f"the keystore {keystore!r} (ROS_SECURITY_KEYSTORE) does not exist",
            f"`ros2 security create_keystore {keystore}` makes one",
        )
    else:
        directory = enclave_directory(keystore, enclave)
        if not os.path.isdir(directory):
            missing = (
                f"the keystore {keystore!r} has no directory {directory!r} for {which}",
                f"`ros2 security create_enclave {keystore} {enclave}` makes it",
            )
    if missing is not None:
        # Enforce fails rcl_init; Permissive runs without security, silently.
        what, remedy = missing
        if enforce:
            raise SecurityError(
                f"ROS_SECURITY_STRATEGY is Enforce, but {what}: DDS security cannot start; {remedy}",
                enclave=enclave,
            )
        return SecurityCheck(
            warning=f"ROS_SECURITY_ENABLE is true, but {what}: {_permissive(strategy, by='rcl')}",
            stale_rcl_error=bool(keystore),
        )

    # rcl hands the enclave's directory to the middleware, which decides alone.
    if env.get("RMW_IMPLEMENTATION", "") not in _FAST_DDS_RMWS:
        return SecurityCheck(secured=True)
    if fast_dds_security is None:
        fast_dds_security = fast_dds_has_security()
    if fast_dds_security is False:
        raise SecurityError(NO_SECURITY_PLUGINS, enclave=enclave)
    absent = missing_enclave_files(directory)
    if not absent:
        return SecurityCheck(secured=True)
    lacks = f"the directory {directory!r} of {which} lacks {', '.join(absent)}"
    if enforce:
        raise SecurityError(
            f"ROS_SECURITY_STRATEGY is Enforce, but {lacks}: DDS security cannot start; "
            "`ros2 security create_enclave` and `create_permission` make them",
            enclave=enclave,
        )
    return SecurityCheck(warning=f"ROS_SECURITY_ENABLE is true, but {lacks}: {_permissive(strategy, by='Fast DDS')}")


def _permissive(strategy: str, *, by: str) -> str:
    """Why running unsecured is what rcl (or Fast DDS) does: the strategy, as the user spelled it."""
    if strategy == "Permissive":
        why = "under ROS_SECURITY_STRATEGY=Permissive"
    elif not strategy:
        why = "when ROS_SECURITY_STRATEGY is unset (Permissive)"
    else:
        why = f"under ROS_SECURITY_STRATEGY={_quote(strategy)}, which it reads as Permissive (only 'Enforce' enforces)"
    return f"running WITHOUT DDS security, as {by} does {why}; ROS_SECURITY_STRATEGY=Enforce refuses to start instead"


def _quote(value: str) -> str:
    return repr(clip(value, limit=_QUOTE_LIMIT))


def enclave_from_arguments(ros_args: Sequence[str]) -> str | None:
    """The enclave the ROS arguments name (rcl takes the last ``--enclave``/``-e``), if any.

    Only inside ``--ros-args`` sections, and a flag's value is never read as
    a flag: ``-r -e:=x`` is a remap rule.
    """
    enclave: str | None = None
    inside = False
    args = list(ros_args)
    index = 0
    while index < len(args):
        arg = args[index]
        if arg == _ROS_ARGS:
            inside = True
        elif inside and arg == _END_OF_ROS_ARGS:
            inside = False
        elif inside and index + 1 < len(args) and (arg in _ENCLAVE_FLAGS or arg in _VALUE_FLAGS):
            if arg in _ENCLAVE_FLAGS:
                enclave = args[index + 1]
            index += 1
        index += 1
    return enclave


def enclave_directory(keystore: str, enclave: str) -> str:
    """The directory rcl looks the enclave up in (its ``exact_match_lookup``).

    rcl drops the name's first character, whatever it is (rcl checks that
    ``--enclave`` names start with ``/``, not the override's).
    """
    enclaves = os.path.join(keystore, "enclaves")
    if enclave == "/":
        return enclaves
    return os.path.join(enclaves, enclave[1:])


def missing_enclave_files(directory: str) -> list[str]:
    """The files Fast DDS needs that ``directory`` lacks (named by their ``.pem``/``.p7s`` names)."""
    root = Path(directory)
    return [names[0] for names in ENCLAVE_FILES if not any(_usable(root / name) for name in names)]


def _usable(path: Path) -> bool:
    """Whether Fast DDS would take ``path``: a regular file; a ``.p11`` one holding a ``pkcs11:`` URI."""
    if path.suffix != ".p11":
        return path.is_file()
    try:
        with path.open(encoding="utf-8", errors="replace") as file:
            return file.read(4096).lstrip().startswith("pkcs11:")
    except OSError:
        return False


@functools.cache
def fast_dds_has_security() -> bool | None:
    """Whether the Fast DDS rmw this process would load was built with security; ``None``: unknown.

    rmw_fastrtps compiles its refusal ("This Fast DDS version doesn't have
    the security libraries") only into a build without security, so its
    library holding that text is the answer, known without starting rcl.
    The library is looked for where the dynamic loader will find it: the
    ``LD_LIBRARY_PATH`` the ROS wheels' bootstrapper sets, then each ROS
    prefix.
    """
    prefixes = [p for p in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p]
    directories = [d for d in os.environ.get("LD_LIBRARY_PATH", "").split(os.pathsep) if d]
    directories += [os.path.join(prefix, "lib") for prefix in [*prefixes, sys.prefix]]
    for directory in directories:
        library = os.path.join(directory, _RMW_LIBRARY)
        try:
            data = Path(library).read_bytes()
        except OSError:
            continue
        return _NO_SECURITY_MARKER not in data
    return None


def clear_rcl_error() -> None:
    """Forget the error rcl left set after a quiet, Permissive enclave lookup failure.

    rcl_init succeeds without security then, but keeps "SECURITY ERROR:
    directory ... does not exist" as the thread's rcutils error state; the
    next error anything sets on that thread (rmw sets and clears one while
    creating the first node) prints a ten-line warning about the overwritten
    state. rclpy offers no way to reset it, so this calls rcutils' own
    ``rcutils_reset_error`` on the thread that ran ``rclpy.init``; the library
    is rclpy's, loaded already. Without it (not found) the block is printed,
    nothing worse.
    """
    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL("librcutils.so").rcutils_reset_error()

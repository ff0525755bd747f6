"""Process-level set-up shared by every command: DDS profile, rclpy, logging.

Kept in one place so that the container, the command-line clients and the
tests start ROS the same way.
"""

from __future__ import annotations

import faulthandler
import functools
import importlib.metadata
import logging
import os
import signal
from pathlib import Path

__all__ = [
    "PROFILE_VARIABLES",
    "configure_logging",
    "configure_warnings",
    "dds_profile",
    "dump_stacks_on_sigusr1",
    "fast_dds_major",
    "profile_variable",
    "use_fast_discovery",
]

#: The project's Fast DDS profile (quick discovery announcements, frequent
#: writer heartbeats), by Fast DDS major version: 3.x renamed XML elements
#: (``heartbeatPeriod`` is ``heartbeat_period``), and a file with one unknown
#: element is not applied at all.
_DDS_PROFILES = {2: "fastdds2_profile.xml", 3: "fastdds_profile.xml"}

#: Where Fast DDS looks for an XML profile: 3.x (Kilted) reads the first, and
#: the second too but with a deprecation warning on every process start;
#: 2.x (Jazzy's 2.14) reads only the second.
PROFILE_VARIABLES = ("FASTDDS_DEFAULT_PROFILES_FILE", "FASTRTPS_DEFAULT_PROFILES_FILE")

#: Distributions whose Fast DDS is 2.x, for installs without the wheels' metadata.
_FAST_DDS_2 = frozenset({"humble", "iron", "jazzy"})


def use_fast_discovery() -> None:
    """Point Fast DDS at the project's profile unless the user chose one.

    A profile named in either variable is the user's and wins: nothing is
    set then. Otherwise the project's goes in the variable this Fast DDS
    reads. Must run before the first rclpy context is initialised: Fast DDS
    reads the variable when it creates the participant.
    """
    if any(os.environ.get(name) for name in PROFILE_VARIABLES):
        return
    os.environ[profile_variable()] = str(dds_profile())


def dds_profile(*, major: int | None = None) -> Path:
    """The project's profile in the XML the installed Fast DDS reads (or Fast DDS ``major``'s)."""
    major = fast_dds_major() if major is None else major
    return Path(__file__).with_name(_DDS_PROFILES[2 if major < 3 else 3])


def profile_variable() -> str:
    """The profile variable the installed Fast DDS reads without a warning."""
    return PROFILE_VARIABLES[1] if fast_dds_major() < 3 else PROFILE_VARIABLES[0]


@functools.cache
def fast_dds_major() -> int:
    """The major version of the Fast DDS rclpy runs on (from the ROS wheels'
    distribution metadata; else from ``ROS_DISTRO``; else 3, the current one)."""
    for distribution in ("ros-fastdds", "ros-fastrtps"):
        try:
            return int(importlib.metadata.version(distribution).split(".")[0])
        except (importlib.metadata.PackageNotFoundError, ValueError):
            continue
    return 2 if os.environ.get("ROS_DISTRO") in _FAST_DDS_2 else 3


def configure_logging(*, verbose: bool = False) -> None:
    """Send Python-level logs (plugin loading, dispatch failures, the watchdog) through ROS logging.

    A server's lines (``container run``, ``container manager``) are ROS log
    lines like its nodes' (:mod:`container._roslog`): time stamp, severity,
    logger name, the log file and ``/rosout``.
    """
    from ._roslog import install

    install(level=logging.INFO, verbose=verbose)


def configure_warnings() -> None:
    """Send a client command's warnings and errors through ROS logging, if nothing configured logging.

    A client command (``container list``, ``container lifecycle get``, ...)
    logs only warnings and errors; its results are its output, on stdout.
    Where logging is configured already (``container run``, pytest) this
    does nothing.
    """
    from ._roslog import install

    install(level=logging.WARNING)


def dump_stacks_on_sigusr1() -> bool:
    """Have SIGUSR1 write every thread's Python stack to standard error, the process going on.

    For a container that stops answering, or does not end after SIGINT:
    ``kill -USR1 <pid>`` shows where each thread is, without a debugger
    (faulthandler writes from the signal handler itself, so it works while
    a thread holds the GIL or the loop is stuck). Left alone when SIGUSR1
    already has a handler (an embedding application's).

    :return: whether SIGUSR1 now dumps the stacks.
    """
    if signal.getsignal(signal.SIGUSR1) not in (signal.SIG_DFL, None):
        return False
    faulthandler.register(signal.SIGUSR1, all_threads=True)
    return True

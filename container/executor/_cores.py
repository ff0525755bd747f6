"""How many CPUs this process may use: its affinity, bounded by its cgroup's CPU quota.

``os.cpu_count()`` is the machine's. A robot's container is often limited
to less: ``taskset`` and cgroup cpusets (``docker --cpuset-cpus``) narrow
the process's affinity (``os.sched_getaffinity``), and a cgroup CPU quota
(``docker --cpus=1``: cgroup v2's ``cpu.max``, v1's ``cpu.cfs_quota_us``
over ``cpu.cfs_period_us``) lets it run on every CPU but for no more CPU
time than the quota. Either way, a thread that spins while waiting for
another (see ``fastpath/handoff.c``) takes the CPU time the other needs
once the process has one CPU's worth.

The quota is looked up in every cgroup from the process's own (as
``/proc/self/cgroup`` names it, under the hierarchy's mount point from
``/proc/self/mountinfo``) up to the mount's root: a parent's limit holds
for its children too. A file that is missing or unreadable means no limit
from it.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Iterator
from pathlib import Path

__all__ = ["cpu_quota", "usable_cpus"]

#: Reads one cgroup directory's quota, in CPUs (``None``: no limit there).
_Reader = Callable[[Path], float | None]

#: Where cgroup hierarchies are mounted when ``/proc/self/mountinfo`` cannot tell.
_V2_MOUNT = "/sys/fs/cgroup"
_V1_MOUNTS = ("/sys/fs/cgroup/cpu,cpuacct", "/sys/fs/cgroup/cpu")


def usable_cpus(*, root: Path | str = "/") -> int:
    """The CPUs this process may use: its affinity, at most its CPU quota rounded up, at least 1.

    :param root: where ``/proc`` and ``/sys`` are looked for (tests pass a
        directory of fake cgroup files); the affinity is always this
        process's own.
    """
    count = len(os.sched_getaffinity(0))
    quota = cpu_quota(root=root)
    if quota is not None:
        count = min(count, math.ceil(quota))
    return max(1, count)


def cpu_quota(*, root: Path | str = "/") -> float | None:
    """The cgroup CPU quota of this process in CPUs (``1.5``: one and a half), ``None`` without one.

    The smallest quota of the process's cgroup and its ancestors, in the v2
    hierarchy and in a v1 ``cpu`` one alike.
    """
    base = Path(root)
    memberships = _memberships(base)
    limits = [
        quota
        for directory, read in _cgroup_directories(base, memberships)
        if (quota := read(directory)) is not None
    ]
    return min(limits, default=None)


def _memberships(base: Path) -> dict[str, str]:
    """The process's cgroup path by hierarchy: ``""`` for v2, ``"cpu"`` for a v1 one with the cpu controller."""
    found: dict[str, str] = {}
    for line in _lines(base / "proc/self/cgroup"):
        parts = line.split(":", 2)
        if len(parts) != 3:
            continue
        _, controllers, path = parts
        if controllers == "":
            found[""] = path
        elif "cpu" in controllers.split(","):
            found["cpu"] = path
    return found


def _cgroup_directories(base: Path, memberships: dict[str, str]) -> Iterator[tuple[Path, _Reader]]:
    """Each cgroup directory whose quota applies, from the process's own up, with its reader."""
    mounts = _mounts(base)
    for hierarchy, reader in (("", _read_v2), ("cpu", _read_v1)):
        path = memberships.get(hierarchy)
        if path is None:
            continue
        defaults = (_V2_MOUNT,) if hierarchy == "" else _V1_MOUNTS
        candidates = mounts.get(hierarchy) or [(mount, "/") for mount in defaults]
        top = next(
            (
                (base / point.lstrip("/"), mount_root)
                for point, mount_root in candidates
                if (base / point.lstrip("/")).is_dir()
            ),
            None,
        )
        if top is None:
            continue
        mount, mount_root = top
        # The path is relative to the cgroup namespace's root; the mount shows
        # the hierarchy from mount_root down (inside a container, its own
        # cgroup is usually the mount's root). Not found there: the mount's.
        directory = mount / os.path.relpath(path, mount_root) if _under(path, mount_root) else mount
        if not directory.is_dir():
            directory = mount
        yield directory, reader
        while directory != mount:
            directory = directory.parent
            yield directory, reader


def _mounts(base: Path) -> dict[str, list[tuple[str, str]]]:
    """Mount points (and the hierarchy's path at each) of cgroup v2 (``""``) and of v1's ``cpu`` controller."""
    found: dict[str, list[tuple[str, str]]] = {}
    for line in _lines(base / "proc/self/mountinfo"):
        # id parent major:minor root mount-point options [optional...] - type source super-options
        before, separator, after = line.partition(" - ")
        fields, tail = before.split(), after.split()
        if not separator or len(fields) < 5 or not tail:
            continue
        mount_root, mount_point = _unescape(fields[3]), _unescape(fields[4])
        if tail[0] == "cgroup2":
            found.setdefault("", []).append((mount_point, mount_root))
        elif tail[0] == "cgroup" and len(tail) >= 3 and "cpu" in tail[2].split(","):
            found.setdefault("cpu", []).append((mount_point, mount_root))
    return found


def _read_v2(directory: Path) -> float | None:
    """``cpu.max``: ``"max 100000"`` (no limit) or ``"150000 100000"`` (quota and period, us)."""
    fields = _text(directory / "cpu.max").split()
    if len(fields) != 2 or fields[0] == "max":
        return None
    return _ratio(fields[0], fields[1])


def _read_v1(directory: Path) -> float | None:
    """``cpu.cfs_quota_us`` (``-1``: no limit) over ``cpu.cfs_period_us``."""
    return _ratio(_text(directory / "cpu.cfs_quota_us"), _text(directory / "cpu.cfs_period_us"))


def _ratio(quota: str, period: str) -> float | None:
    try:
        q, p = int(quota), int(period)
    except ValueError:
        return None
    return q / p if q > 0 and p > 0 else None


def _under(path: str, parent: str) -> bool:
    return parent == "/" or path == parent or path.startswith(parent.rstrip("/") + "/")


def _unescape(field: str) -> str:
    """mountinfo escapes spaces, tabs, newlines and backslashes as octal (``\\040``)."""
    return field.replace("\\040", " ").replace("\\011", "\t").replace("\\012", "\n").replace("\\134", "\\")


def _text(path: Path) -> str:
    try:
        return path.read_text(encoding="ascii").strip()
    except (OSError, UnicodeDecodeError):
        return ""


def _lines(path: Path) -> list[str]:
    return _text(path).splitlines()


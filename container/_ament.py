"""The ament index entries that make plugin distributions ROS packages.

launch_ros, ros2cli (``ros2 run``, ``ros2 pkg``, ``ros2 component types``) and
ament_index_python find packages, executables and component types through
the ament resource index of every prefix on ``AMENT_PREFIX_PATH``:

* ``<prefix>/share/ament_index/resource_index/packages/<package>``: an empty
  marker, which makes ``<package>`` a ROS package installed in ``<prefix>``;
* ``<prefix>/lib/<package>/<executable>``: what ``ros2 run <package>
  <executable>`` and launch_ros's ``Node(package=..., executable=...)`` start;
* ``<prefix>/share/ament_index/resource_index/rclcpp_components/<package>``:
  one ``<type>;<library>`` line per component type, which ``ros2 component
  types`` lists (the part before ``;``). Here the library part names the
  Python class (``module:qualname``); nothing loads it from there.

:func:`write_index` writes these for every package of registered node types,
and for this project's own package the container executables, each into the
prefix its distribution is installed in (a package's prefix is where ROS
tools look for all of it: ``get_package_prefix``). What it wrote is recorded
in a resource type of its own (:data:`RECORD_TYPE`), so that a later run
removes the entries of a distribution that went away, and never touches a
package some other installation registered; a marker colcon's build of the
distribution installed in the same prefix is the package's own, kept.
"""

from __future__ import annotations

import importlib.metadata
import os
import shlex
import sys
import tempfile
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path

from ._registry import NodeType, ros_package_name

__all__ = [
    "EXECUTABLES",
    "PROJECT_PACKAGE",
    "RECORD_TYPE",
    "IndexReport",
    "installed_prefix",
    "resource_index",
    "write_index",
]

#: This project's own ROS package: the container executables live in it.
PROJECT_PACKAGE = ros_package_name("lifecycle-container")

#: The executables of :data:`PROJECT_PACKAGE`, and the ``container`` command
#: each one is. rclcpp_components' three container names are the same
#: container here: every node already has its own lanes (isolation) on one
#: executor, so a launch file needs to change only the package.
EXECUTABLES: Mapping[str, str] = {
    "component_container": "run",
    "component_container_mt": "run",
    "component_container_isolated": "run",
    "lifecycle_manager": "manager",
}

#: Resource type recording what :func:`write_index` registered, one entry per package.
RECORD_TYPE = "lifecycle_container_plugins"
_PACKAGES = "packages"
_COMPONENTS = "rclcpp_components"

#: An executable: a sh script that is also Python, as the ``container`` command is
#: (``container/interfaces/container.in``): sh starts Python on this same file
#: with SIGINT and SIGTERM blocked where env can, held until the command's entry
#: point takes them (:mod:`container._entry`).
_SCRIPT = """#!/bin/sh
'''':
# Written by `container index` (lifecycle-container): `container {command}`, run
# by ros2 run and launch_ros as {package}'s {executable}. Python on this same
# file, started with SIGINT and SIGTERM blocked where env can (coreutils 8.31
# or later), held until the command's entry point takes them.
if env --block-signal=INT --version >/dev/null 2>&1; then
    exec env --block-signal=INT,TERM {python} "$0" "$@"
fi
exec {python} "$0" "$@"
'''
import sys

from container.__main__ import main

sys.argv[1:1] = ["{command}"]
sys.exit(main())
"""


def resource_index(prefix: Path) -> Path:
    """The resource index directory of ``prefix``."""
    return prefix / "share" / "ament_index" / "resource_index"


@dataclass
class IndexReport:
    """What :func:`write_index` did.

    :ivar registered: each package registered, with its component types.
    :ivar executables: each package's executables.
    :ivar removed: packages whose entries were removed (their distribution is gone).
    :ivar skipped: packages left alone, with the reason.
    :ivar changed: files written or removed; none when the index was up to date.
    :ivar with_wheel: packages whose entries their distribution's wheel installed
        (``container.build_backend``): left to pip.
    """

    registered: dict[str, list[str]] = field(default_factory=dict)
    executables: dict[str, list[str]] = field(default_factory=dict)
    removed: list[str] = field(default_factory=list)
    skipped: list[tuple[str, str]] = field(default_factory=list)
    changed: list[Path] = field(default_factory=list)
    with_wheel: list[str] = field(default_factory=list)


@dataclass(frozen=True)
class _Record:
    """One package's entry in :data:`RECORD_TYPE`: what was written for it.

    :ivar marker: whether the package marker was written here (not when the
        package's own build installed it): only then is it removed with the rest.
    """

    distribution: str
    marker: bool
    executables: tuple[str, ...]

    def text(self) -> str:
        return (
            f"distribution {self.distribution}\n"
            f"marker {'yes' if self.marker else 'no'}\n"
            f"executables {' '.join(self.executables)}\n"
        )

    @classmethod
    def parse(cls, text: str) -> _Record:
        fields = dict(line.partition(" ")[::2] for line in text.splitlines() if line.strip())
        return cls(
            distribution=fields.get("distribution", ""),
            marker=fields.get("marker") == "yes",
            executables=tuple(fields.get("executables", "").split()),
        )


def write_index(
    prefix: Path,
    types: Iterable[NodeType],
    *,
    python: str = sys.executable,
    project: str | None = "lifecycle-container",
    prune: bool = True,
    strict: bool = False,
) -> IndexReport:
    """Register every package of ``types`` in the ament index of ``prefix``.

    A distribution's entries go into the prefix it is installed in (its
    metadata under ``<prefix>/lib/pythonX.Y/site-packages``): one installed
    in another prefix is skipped, so that no prefix shadows the package of
    another (``get_package_prefix``, ``ros2 run``). One installed in no
    prefix (on ``PYTHONPATH``, ``pip install --target``) goes into ``prefix``.

    Idempotent: files are written only when their content changes, each
    atomically (a concurrent reader sees the old or the new one).

    :param python: the interpreter the executables run with (this environment's).
    :param project: the distribution of :data:`PROJECT_PACKAGE`, which is
        registered with its executables even if it has no node types;
        ``None`` leaves that package out (and its entries alone).
    :param prune: remove the entries this function wrote earlier for packages
        not in ``types`` (their distribution is gone) or installed in another
        prefix; off when ``types`` is only some of the installed plugins' on purpose.
    :param strict: write nothing when any package is skipped (each was asked
        for by name); the report says why.
    """
    report = IndexReport()
    index = resource_index(prefix)
    here = prefix.resolve()
    wanted: dict[str, tuple[str, list[NodeType]]] = {}
    if project is not None:
        wanted[PROJECT_PACKAGE] = (project, [])
    for node_type in types:
        wanted.setdefault(node_type.package, (node_type.distribution, []))[1].append(node_type)
    records = _records(index)

    # Decide everything first: a refusal under ``strict`` leaves the prefix untouched.
    plans: list[tuple[str, str, list[NodeType], bool]] = []
    elsewhere: set[str] = set()
    for package in sorted(wanted):
        dist, node_types = wanted[package]
        record = records.get(package)
        marker = index / _PACKAGES / package
        home = installed_prefix(dist)
        if home is not None and home != here:
            elsewhere.add(package)
            report.skipped.append(
                (package, f"{dist} is installed in {home}, not in {prefix} (container index --prefix {home})")
            )
        elif marker.exists() and _installed_by(dist, marker):
            # The distribution's wheel carries its entries, and pip removes
            # them with it: they are pip's (an earlier run's record goes).
            report.with_wheel.append(package)
        elif record is None and marker.exists() and home is None:
            # Some other installation's package (a ROS wheel of the same name).
            report.skipped.append((package, f"a ROS package named {package!r} is already installed in {prefix}"))
        else:
            # A marker already there, with the distribution installed in this
            # prefix, is the package's own (colcon's ament_python and
            # ament_cmake builds write it): kept, and never removed.
            own_marker = not marker.exists() or (record is not None and record.marker)
            plans.append((package, dist, node_types, own_marker))
    if strict and report.skipped:
        return report

    for package, dist, node_types, own_marker in plans:
        record = records.get(package)
        lines = sorted(f"{t.full_name};{t.node_class.__module__}:{t.node_class.__qualname__}" for t in node_types)
        if own_marker:
            _write(report, index / _PACKAGES / package, "")
        components = index / _COMPONENTS / package
        if lines:
            _write(report, components, "".join(f"{line}\n" for line in lines))
        else:
            _remove(report, components)
        executables = sorted(EXECUTABLES) if package == PROJECT_PACKAGE else []
        for name in executables:
            script = _SCRIPT.format(
                python=shlex.quote(python), command=EXECUTABLES[name], package=package, executable=name
            )
            _write(report, prefix / "lib" / package / name, script, executable=True)
        if record is not None:
            for name in set(record.executables) - set(executables):
                _remove(report, prefix / "lib" / package / name)
        _write(report, index / RECORD_TYPE / package, _Record(dist, own_marker, tuple(executables)).text())
        report.registered[package] = sorted(t.full_name for t in node_types)
        report.executables[package] = executables
    for package in report.with_wheel:
        if package in records:
            _remove(report, index / RECORD_TYPE / package)

    for package in sorted(set(records) - (set(wanted) - elsewhere) if prune else ()):
        record = records[package]
        for name in record.executables:
            _remove(report, prefix / "lib" / package / name)
        _remove_dir_if_empty(prefix / "lib" / package)
        _remove(report, index / _COMPONENTS / package)
        if record.marker:
            _remove(report, index / _PACKAGES / package)
        _remove(report, index / RECORD_TYPE / package)
        report.removed.append(package)
    return report


def installed_prefix(distribution: str) -> Path | None:
    """The prefix ``distribution`` is installed in, if it is installed in one.

    That is ``<prefix>`` of its metadata's ``<prefix>/lib/pythonX.Y/site-packages``
    (or ``dist-packages``): a virtualenv, a colcon install prefix, ``/usr``.
    ``None`` when it is not installed, or installed in a directory of its own
    (``pip install --target``, a directory on ``PYTHONPATH``).
    """
    try:
        found = importlib.metadata.distribution(distribution)
    except importlib.metadata.PackageNotFoundError:
        return None
    site = Path(str(found.locate_file(""))).resolve()
    if site.name in ("site-packages", "dist-packages") and site.parent.name.startswith("python") \
            and site.parent.parent.name in ("lib", "lib64"):
        return site.parent.parent.parent
    return None


def _installed_by(distribution: str, marker: Path) -> bool:
    """Whether pip installed ``marker`` as a file of ``distribution``."""
    try:
        files = importlib.metadata.distribution(distribution).files or []
    except importlib.metadata.PackageNotFoundError:
        return False
    target = marker.resolve()
    return any(f.name == marker.name and Path(str(f.locate())).resolve() == target for f in files)


def _records(index: Path) -> dict[str, _Record]:
    directory = index / RECORD_TYPE
    if not directory.is_dir():
        return {}
    return {
        path.name: _Record.parse(path.read_text(encoding="utf-8"))
        for path in directory.iterdir()
        if path.is_file() and not path.name.startswith(".")
    }


def _write(report: IndexReport, path: Path, content: str, *, executable: bool = False) -> None:
    mode = 0o755 if executable else 0o644
    try:
        if path.read_text(encoding="utf-8") == content and (path.stat().st_mode & 0o777) == mode:
            return
    except (FileNotFoundError, UnicodeDecodeError):
        pass
    path.parent.mkdir(parents=True, exist_ok=True)
    # Hidden while written: the index skips names starting with a dot.
    fd, temporary = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.")
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as file:
            file.write(content)
        os.chmod(temporary, mode)
        os.replace(temporary, path)
    except BaseException:
        Path(temporary).unlink(missing_ok=True)
        raise
    report.changed.append(path)


def _remove(report: IndexReport, path: Path) -> None:
    if path.is_file():
        path.unlink()
        report.changed.append(path)


def _remove_dir_if_empty(path: Path) -> None:
    if path.is_dir() and not any(path.iterdir()):
        path.rmdir()

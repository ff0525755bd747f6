"""``container index [--prefix DIR]``: register the installed plugins in the ament index.

Makes every installed plugin distribution a ROS package of this environment,
as ROS tools see packages: ``ros2 pkg list`` lists them, ``ros2 component
types`` lists their node types, and ``ros2 run lifecycle_container
component_container`` (or launch_ros's ``ComposableNodeContainer`` with that
package and executable) starts a container. ``.ci/setup`` runs it after every
install; run it again after installing or removing a plugin with pip.

Each distribution's entries go into the prefix it is installed in, never
into another one (where they would shadow the package's own prefix): one
installed elsewhere is named on stderr with its prefix. With
``--distribution``, every named one is registered or nothing is written
(exit status 1), so a colcon install step can run it for its own package::

    container index --prefix install/my_robot --distribution my_robot
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from .._compat import SubParsers

__all__ = ["add_parser"]


def add_parser(subparsers: SubParsers) -> None:
    parser = subparsers.add_parser(
        "index",
        help="register the installed plugins in the ament index (ros2 pkg, ros2 run, launch_ros)",
        description=(
            "Register every installed plugin distribution as a ROS package in the ament index "
            "of a prefix (this environment by default), with its node types and, for "
            "lifecycle_container, the container executables. A distribution installed in "
            "another prefix is left to that prefix."
        ),
    )
    parser.add_argument(
        "--prefix", type=Path, default=Path(sys.prefix),
        help="the install prefix to register in (default: this environment, %(default)s)",
    )
    parser.add_argument(
        "--distribution", action="append", metavar="NAME",
        help=(
            "register only this distribution's package (repeatable; lifecycle-container's only if named): "
            "all of them or, with a reason, nothing; entries of others are kept"
        ),
    )
    parser.add_argument("-q", "--quiet", action="store_true", help="print only problems")
    parser.set_defaults(handler=_run, finish_without_output=True)


def _run(args: argparse.Namespace) -> int:
    from .._ament import PROJECT_PACKAGE, write_index
    from .._registry import PluginRegistry, ros_package_name
    from .._runtime import configure_logging

    # The registry logs each plugin it skips (once), with the reason.
    configure_logging()
    registry = PluginRegistry()
    prefix: Path = args.prefix.absolute()
    types = list(registry.types.values())
    project: str | None = "lifecycle-container"
    if args.distribution:
        wanted = {ros_package_name(name) for name in args.distribution}
        if PROJECT_PACKAGE not in wanted:
            project = None
        missing = wanted - {ros_package_name(t.distribution) for t in types} - {PROJECT_PACKAGE}
        if missing:
            print(f"container index: no node types from {', '.join(sorted(missing))}", file=sys.stderr)
            return 1
        types = [t for t in types if ros_package_name(t.distribution) in wanted]
    try:
        # Named distributions: all of them, or nothing written.
        named = bool(args.distribution)
        report = write_index(prefix, types, project=project, prune=not named, strict=named)
    except OSError as exc:
        print(f"container index: cannot write the index in {prefix}: {exc}", file=sys.stderr)
        return 1
    for package, reason in report.skipped:
        print(f"container index: {package} not registered: {reason}", file=sys.stderr)
    if args.distribution and report.skipped:
        print(f"container index: nothing written in {prefix}", file=sys.stderr)
        return 1
    if args.quiet:
        return 0
    state = f"{len(report.changed)} file(s) changed" if report.changed else "up to date"
    print(f"ament index of {prefix}: {state}")
    for package, type_names in report.registered.items():
        executables = report.executables.get(package) or []
        print(f"  {package}: {len(type_names)} node type(s)" + (f"; {', '.join(executables)}" if executables else ""))
    for package in report.with_wheel:
        print(f"  {package}: installed with its wheel")
    for package in report.removed:
        print(f"  {package}: removed (no longer installed in this prefix)")
    return 0

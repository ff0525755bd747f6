"""Start-up hook of the sanitizer run: the sanitized build is ``container.executor._fastpath``.

``.ci/sanitize`` puts this directory on ``PYTHONPATH``, so every Python
process of its run imports this module at start-up (``site`` does): the
test process and every child process a test starts (a container, a client
script), which inherit the environment. Where ``CONTAINER_SANITIZED_FASTPATH``
names a file, a meta-path finder placed first makes that file the module
``container.executor._fastpath``, ahead of the editable install's finder
and of the package directory. Elsewhere it does nothing.
"""

from __future__ import annotations

import importlib.abc
import importlib.machinery
import importlib.util
import os
import sys
from collections.abc import Sequence
from importlib.machinery import ModuleSpec
from types import ModuleType

__all__ = ["MODULE", "VARIABLE", "SanitizedFinder", "install"]

#: The module the sanitized build stands in for.
MODULE = "container.executor._fastpath"
#: The environment variable naming the sanitized build (a ``.so`` file).
VARIABLE = "CONTAINER_SANITIZED_FASTPATH"


class SanitizedFinder(importlib.abc.MetaPathFinder):
    """Find :data:`MODULE` at one file, an extension module; nothing else."""

    def __init__(self, path: str) -> None:
        self.path = path

    def find_spec(
        self, fullname: str, path: Sequence[str] | None, target: ModuleType | None = None
    ) -> ModuleSpec | None:
        if fullname != MODULE:
            return None
        loader = importlib.machinery.ExtensionFileLoader(fullname, self.path)
        return importlib.util.spec_from_file_location(fullname, self.path, loader=loader)


def install() -> None:
    """Put the finder first on ``sys.meta_path`` when :data:`VARIABLE` names a file."""
    path = os.environ.get(VARIABLE, "")
    if not path:
        return
    if not os.path.isfile(path):
        # A warning from site, and the process goes on with the module it
        # finds otherwise: the test process's check (sanitized_fastpath) fails.
        raise FileNotFoundError(f"{VARIABLE}={path}: no such file")
    if not any(isinstance(finder, SanitizedFinder) for finder in sys.meta_path):
        sys.meta_path.insert(0, SanitizedFinder(os.path.abspath(path)))


install()

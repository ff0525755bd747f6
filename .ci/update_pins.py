"""Update the pinned check tools (pyproject.toml's ``test`` extra) to their latest releases, if the checks pass.

Run through ``bash .ci/update-pins`` (CONTRIBUTING.md, "The checks"). Why pins:
a new release of ruff, mypy, pytest or mkdocs must not turn a green CI red
without a change of ours (mypy 2.4 rejected ``ndarray.max()`` against numpy
2.5's stubs overnight). Updating them is a change like any other: this
script makes it, and shows it.

What it does:

1. reads the pins (every entry of the ``test`` extra must be ``name==version``);
2. in a throwaway virtualenv that sees the project's virtualenv underneath
   (a ``.pth`` file: rclpy, the project, the plugins stay as installed),
   installs the latest release of every pinned tool, with no pin;
3. if any version moved, runs the checks with those versions: ruff, mypy
   (strict, as ``.ci/test`` runs it), the documentation site (``mkdocs build
   --strict``) and, with ``--fast``, the fast lane of the tests;
4. only if all pass, rewrites the pins in pyproject.toml and prints the diff;
   otherwise prints which check failed and leaves the file alone.

Offline (the package index cannot be reached) it says so in one line, and
exits 2 with the pins untouched.

``--set NAME==VERSION ... [--pyproject FILE]`` rewrites pins to the given
versions with no network and no checks (the rewriting the update uses, and
what its test exercises on a copy of the file).
"""

from __future__ import annotations

import argparse
import difflib
import json
import os
import re
import subprocess
import sys
import sysconfig
import tempfile
import tomllib
from collections.abc import Mapping, Sequence
from pathlib import Path

__all__ = ["CHECK_TOOLS", "main", "read_pins", "rewrite_pins"]

REPO = Path(__file__).resolve().parents[1]

#: The check tools .ci/test runs, each pinned exactly in the ``test`` extra.
CHECK_TOOLS = ("pytest", "pytest-asyncio", "pytest-timeout", "mypy", "ruff", "types-PyYAML", "mkdocs")

_PIN = re.compile(r"^([A-Za-z0-9][A-Za-z0-9._-]*)==([A-Za-z0-9.+!_-]+)$")


class PinError(Exception):
    """The ``test`` extra is not what this script can update (a tool unpinned, missing or unknown)."""


def _normal(name: str) -> str:
    """A distribution name as PEP 503 compares them."""
    return re.sub(r"[-_.]+", "-", name).lower()


def read_pins(text: str) -> dict[str, str]:
    """The pins of pyproject.toml's ``test`` extra, by name as written.

    :raises PinError: an entry that is not ``name==version``, or the set of
        tools is not :data:`CHECK_TOOLS`.
    """
    extra = tomllib.loads(text)["project"]["optional-dependencies"]["test"]
    pins: dict[str, str] = {}
    for entry in extra:
        match = _PIN.match(entry)
        if match is None:
            raise PinError(f"test extra: {entry!r} is not pinned exactly (name==version)")
        pins[match[1]] = match[2]
    if sorted(map(_normal, pins)) != sorted(map(_normal, CHECK_TOOLS)):
        raise PinError(f"test extra: expected exactly {', '.join(CHECK_TOOLS)}; found {', '.join(pins)}")
    return pins


def rewrite_pins(text: str, versions: Mapping[str, str]) -> str:
    """``text`` (pyproject.toml) with each named tool pinned to its new version; nothing else changed.

    :raises PinError: a name that is not pinned in the ``test`` extra.
    """
    pinned = {_normal(name): name for name in read_pins(text)}
    for name, version in versions.items():
        written = pinned.get(_normal(name))
        if written is None:
            raise PinError(f"{name} is not a pinned check tool ({', '.join(CHECK_TOOLS)})")
        text, count = re.subn(rf'"{re.escape(written)}==[^"]+"', f'"{written}=={version}"', text)
        if count != 1:
            raise PinError(f"{written}: expected one pin in the file, found {count}")
    read_pins(text)  # still well-formed
    return text


def _diff(before: str, after: str, path: Path) -> str:
    return "".join(difflib.unified_diff(
        before.splitlines(keepends=True), after.splitlines(keepends=True), f"a/{path.name}", f"b/{path.name}"
    ))


def _say(message: str) -> None:
    print(f"update-pins: {message}", flush=True)


def _venv_python(directory: Path) -> Path:
    return directory / "bin" / "python"


def _throwaway(directory: Path) -> Path:
    """A fresh virtualenv in ``directory``, for the latest tools; its interpreter."""
    subprocess.run([sys.executable, "-m", "venv", str(directory)], check=True)
    return _venv_python(directory)


def _see_project(python: Path, project_venv: Path) -> None:
    """Let ``python`` see the project's virtualenv below its own packages (after the tools are installed).

    Afterwards, so that pip installs every tool and its dependencies afresh
    instead of finding the pinned ones installed there.
    """
    below = sysconfig.get_paths(vars={"base": str(project_venv), "platbase": str(project_venv)})["purelib"]
    # addsitedir, not a bare path: the project's editable install is a .pth file there too.
    Path(_purelib(python), "zz_project_venv.pth").write_text(
        f"import site; site.addsitedir({below!r})\n", encoding="utf-8"
    )


def _installed(python: Path, names: Sequence[str]) -> dict[str, str]:
    listing = subprocess.run(
        [str(python), "-m", "pip", "list", "--path", _purelib(python), "--format", "json"],
        check=True, capture_output=True, text=True,
    ).stdout
    found = {_normal(item["name"]): item["version"] for item in json.loads(listing)}
    return {name: found[_normal(name)] for name in names if _normal(name) in found}


def _purelib(python: Path) -> str:
    return subprocess.run(
        [str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
        check=True, capture_output=True, text=True,
    ).stdout.strip()


def _checks(python: Path, scratch: Path, *, fast: bool) -> list[tuple[str, list[str]]]:
    """The checks, as .ci/test runs them, with the throwaway virtualenv's tools."""
    py = str(python)
    version = f"{sys.version_info.major}.{sys.version_info.minor}"
    generic = subprocess.run(
        [py, "-c", "import sys, typing, rclpy.publisher as p; sys.exit(typing.Generic not in p.Publisher.__mro__)"],
        capture_output=True,
    ).returncode == 0
    mypy = [py, "-m", "mypy", "--python-version", version, "--cache-dir", str(scratch / "mypy_cache")]
    if not generic:
        mypy += ["--disable-error-code", "type-arg"]
    checks = [
        ("ruff", [py, "-m", "ruff", "check", "--quiet", "."]),
        ("mypy", mypy),
        ("docs", [py, "-m", "mkdocs", "build", "--strict", "--quiet", "--site-dir", str(scratch / "site")]),
    ]
    if fast:
        checks.append(("fast lane", [py, "-m", "pytest", "-m", "not slow", "-q", "-p", "no:cacheprovider"]))
    return checks


def update(pyproject: Path, project_venv: Path, *, fast: bool) -> int:
    """The whole update: 0 pins current or updated, 1 a check failed, 2 no index or no virtualenv."""
    text = pyproject.read_text(encoding="utf-8")
    pins = read_pins(text)
    if not _venv_python(project_venv).exists():
        _say(f"no virtualenv at {project_venv}: run 'bash .ci/setup' first")
        return 2
    with tempfile.TemporaryDirectory(prefix="update-pins-") as scratch_dir:
        scratch = Path(scratch_dir)
        python = _throwaway(scratch / "venv")
        _say(f"installing the latest {', '.join(pins)} into a throwaway virtualenv")
        install = subprocess.run(
            [str(python), "-m", "pip", "install", "--upgrade", "--disable-pip-version-check",
             "--timeout", "15", "--retries", "1", *pins],
            capture_output=True, text=True,
        )
        if install.returncode != 0:
            tail = " ".join(install.stderr.strip().splitlines()[-1:])
            _say(f"cannot install the latest check tools (is the package index reachable?): {tail}; pins unchanged")
            return 2
        latest = _installed(python, list(pins))
        _see_project(python, project_venv)
        moved = {name: version for name, version in latest.items() if version != pins[name]}
        if not moved:
            _say("every pin is the latest release: nothing to change")
            return 0
        for name, version in moved.items():
            _say(f"{name} {pins[name]} -> {version}")
        env = {**os.environ, "AMENT_PREFIX_PATH": str(project_venv)}
        for label, command in _checks(python, scratch, fast=fast):
            _say(f"{label}: running")
            if subprocess.run(command, cwd=REPO, env=env).returncode != 0:
                _say(f"{label} fails with the new versions: pins unchanged (fix the code, or keep the pins)")
                return 1
        after = rewrite_pins(text, moved)
    pyproject.write_text(after, encoding="utf-8")
    print(_diff(text, after, pyproject), end="")
    _say(f"{pyproject.name} updated; run 'bash .ci/setup' to install the new pins, then commit")
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="update-pins", description=__doc__.split("\n\n")[0])
    parser.add_argument("--pyproject", type=Path, default=REPO / "pyproject.toml", help="the file to update")
    parser.add_argument("--venv", type=Path, default=REPO / os.environ.get("VENV", ".venv"),
                        help="the project's virtualenv (default: .venv, or VENV)")
    parser.add_argument("--fast", action="store_true", help="run the fast lane of the tests too (minutes)")
    parser.add_argument("--set", nargs="+", metavar="NAME==VERSION",
                        help="rewrite these pins, with no network and no checks; print the diff")
    args = parser.parse_args(argv)
    try:
        if args.set:
            versions = {}
            for item in args.set:
                name, sep, version = item.partition("==")
                if not sep or not name or not version:
                    parser.error(f"expected NAME==VERSION, not {item!r}")
                versions[name] = version
            before = args.pyproject.read_text(encoding="utf-8")
            after = rewrite_pins(before, versions)
            args.pyproject.write_text(after, encoding="utf-8")
            print(_diff(before, after, args.pyproject), end="")
            return 0
        return update(args.pyproject, args.venv.absolute(), fast=args.fast)
    except PinError as exc:
        _say(str(exc))
        return 1


if __name__ == "__main__":
    sys.exit(main())

"""The security decision, case by case, without starting ROS: rcl's rules and Fast DDS's, mirrored.

The rows a Fast DDS *with* its security plugins would take (secured; an
enclave missing files) cannot run on the PyPI wheels: they are decided here
with ``fast_dds_security=True``. ``tests/cli/test_security.py`` runs the
table through real commands.
"""

from __future__ import annotations

import importlib.metadata
from pathlib import Path

import pytest

from container import SecurityError
from container._security import (
    NO_SECURITY_PLUGINS,
    check_security,
    enclave_directory,
    enclave_from_arguments,
    fast_dds_has_security,
    missing_enclave_files,
)

FILES = ("identity_ca.cert.pem", "cert.pem", "key.pem", "permissions_ca.cert.pem", "governance.p7s", "permissions.p7s")


@pytest.fixture
def keystore(tmp_path: Path) -> Path:
    """A keystore whose root enclave ``/`` has every file, and whose ``/bare`` has none."""
    enclaves = tmp_path / "keystore" / "enclaves"
    (enclaves / "bare").mkdir(parents=True)
    for name in FILES:
        (enclaves / name).write_text("placeholder\n")
    return tmp_path / "keystore"


def secure(keystore: Path, **more: str) -> dict[str, str]:
    return {"ROS_SECURITY_ENABLE": "true", "ROS_SECURITY_KEYSTORE": str(keystore), **more}


@pytest.mark.parametrize("value", ["", "false", "False", "0", "no", "OFF", " false "])
def test_security_off_in_any_spelling_says_nothing(value: str) -> None:
    assert check_security(environ={"ROS_SECURITY_ENABLE": value}) == check_security(environ={})
    assert check_security(environ={}).warning is None


@pytest.mark.parametrize("value", ["True", "TRUE", "1", "yes", "on", " true", "true "])
def test_a_spelling_rcl_ignores_is_a_warning_naming_the_one_it_reads(value: str) -> None:
    check = check_security(environ={"ROS_SECURITY_ENABLE": value, "ROS_SECURITY_STRATEGY": "Enforce"})

    assert not check.secured
    assert check.warning is not None
    assert check.warning.startswith(f"ROS_SECURITY_ENABLE={value!r} is not 'true'")


def test_enforce_without_keystore_is_refused_before_rcl_says_error_not_set() -> None:
    with pytest.raises(SecurityError) as info:
        check_security(environ={"ROS_SECURITY_ENABLE": "true", "ROS_SECURITY_STRATEGY": "Enforce"})
    assert str(info.value).startswith("ROS_SECURITY_STRATEGY is Enforce, but ROS_SECURITY_KEYSTORE is not set")
    assert info.value.enclave == "/"


@pytest.mark.parametrize("strategy", ["", "Permissive", "enforce", "ENFORCE", " Enforce"])
def test_anything_but_enforce_is_permissive_and_runs_unsecured_with_a_warning(strategy: str) -> None:
    check = check_security(environ={"ROS_SECURITY_ENABLE": "true", "ROS_SECURITY_STRATEGY": strategy})

    assert check.warning is not None and "running WITHOUT DDS security, as rcl does" in check.warning
    # No keystore set: rcl's lookup fails without leaving an error behind.
    assert not check.stale_rcl_error
    if strategy not in ("", "Permissive"):
        assert f"ROS_SECURITY_STRATEGY={strategy!r}, which it reads as Permissive" in check.warning


def test_a_missing_enclave_leaves_rcls_error_to_clear(keystore: Path) -> None:
    check = check_security(["--ros-args", "--enclave", "/nobody"], environ=secure(keystore))

    assert check.stale_rcl_error
    assert check.warning is not None
    assert f"has no directory '{keystore}/enclaves/nobody' for enclave '/nobody'" in check.warning


def test_the_override_wins_over_the_argument_and_is_named(keystore: Path) -> None:
    env = secure(keystore, ROS_SECURITY_STRATEGY="Enforce", ROS_SECURITY_ENCLAVE_OVERRIDE="/nobody")

    with pytest.raises(SecurityError, match=r"for enclave '/nobody' \(ROS_SECURITY_ENCLAVE_OVERRIDE\)"):
        check_security(["--ros-args", "--enclave", "/bare"], environ=env, fast_dds_security=True)


def test_the_wheels_fast_dds_refuses_any_enclave_whatever_the_strategy(keystore: Path) -> None:
    for strategy in ("Enforce", "Permissive"):
        for args in ([], ["--ros-args", "-e", "/bare"]):
            with pytest.raises(SecurityError) as info:
                check_security(args, environ=secure(keystore, ROS_SECURITY_STRATEGY=strategy), fast_dds_security=False)
            assert str(info.value) == NO_SECURITY_PLUGINS


def test_with_security_plugins_an_enclave_with_its_files_is_secured(keystore: Path) -> None:
    check = check_security(environ=secure(keystore, ROS_SECURITY_STRATEGY="Enforce"), fast_dds_security=True)

    assert check.secured and check.warning is None


def test_with_security_plugins_missing_files_are_named(keystore: Path) -> None:
    args = ["--ros-args", "--enclave", "/bare"]
    with pytest.raises(SecurityError, match=r"lacks identity_ca\.cert\.pem, cert\.pem, key\.pem, permissions_ca"):
        check_security(args, environ=secure(keystore, ROS_SECURITY_STRATEGY="Enforce"), fast_dds_security=True)

    check = check_security(args, environ=secure(keystore), fast_dds_security=True)
    assert check.warning is not None
    assert "lacks identity_ca.cert.pem" in check.warning and "as Fast DDS does" in check.warning


def test_another_middleware_gets_the_enclave_and_decides_itself(keystore: Path) -> None:
    env = secure(keystore, ROS_SECURITY_STRATEGY="Enforce", RMW_IMPLEMENTATION="rmw_cyclonedds_cpp")

    assert check_security(["--ros-args", "-e", "/bare"], environ=env, fast_dds_security=False).secured


def test_an_enclave_name_rcl_refuses_is_left_to_rcl() -> None:
    env = {"ROS_SECURITY_ENABLE": "true", "ROS_SECURITY_STRATEGY": "Enforce"}

    for name in ("no_slash", "/a/", "/1a", "/a-b", "/a//b"):
        assert check_security(["--ros-args", "--enclave", name], environ=env).warning is None


def test_the_last_enclave_argument_wins_inside_ros_args_only() -> None:
    assert enclave_from_arguments([]) is None
    assert enclave_from_arguments(["-e", "/x"]) is None
    assert enclave_from_arguments(["--ros-args", "-e", "/a", "--enclave", "/b"]) == "/b"
    assert enclave_from_arguments(["--ros-args", "-e", "/a", "--", "-e", "/b"]) == "/a"
    # A flag's value is not a flag.
    assert enclave_from_arguments(["--ros-args", "-r", "-e", "-p", "x:=1"]) is None


def test_enclave_directories_are_rcls() -> None:
    assert enclave_directory("/k", "/") == "/k/enclaves"
    assert enclave_directory("/k", "/a/b") == "/k/enclaves/a/b"
    # rcl drops the first character of an override, slash or not.
    assert enclave_directory("/k", "xab") == "/k/enclaves/ab"


def test_pkcs11_uris_stand_in_for_pem_files(tmp_path: Path) -> None:
    for name in FILES:
        if name.endswith(".p7s"):
            (tmp_path / name).write_text("placeholder\n")
    (tmp_path / "identity_ca.cert.p11").write_text("pkcs11:object=ca\n")
    (tmp_path / "cert.p11").write_text("pkcs11:object=cert\n")
    (tmp_path / "key.p11").write_text("not a uri\n")

    assert missing_enclave_files(str(tmp_path)) == ["key.pem", "permissions_ca.cert.pem"]


def test_the_wheels_fast_dds_is_known_to_lack_security() -> None:
    try:
        importlib.metadata.version("ros-fastrtps")
    except importlib.metadata.PackageNotFoundError:
        pytest.skip("not the PyPI wheels' Fast DDS")
    assert fast_dds_has_security() is False

"""The CPUs the process may use (``_cores``): affinity, bounded by the cgroup CPU quota."""

from __future__ import annotations

import math
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from container.executor._cores import cpu_quota, usable_cpus
from tests.container_support import REPO

AFFINITY = len(os.sched_getaffinity(0))


def fake(root: Path, files: dict[str, str]) -> Path:
    """A directory standing in for ``/``: ``files`` by their absolute path."""
    for name, text in files.items():
        path = root / name.lstrip("/")
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text, encoding="ascii")
    return root


V2_MOUNTINFO = "31 23 0:28 / /sys/fs/cgroup rw,nosuid,nodev,noexec,relatime shared:9 - cgroup2 cgroup2 rw\n"


def test_a_v2_quota_of_one_and_a_half_cpus_is_two(tmp_path: Path) -> None:
    root = fake(
        tmp_path,
        {
            "/proc/self/cgroup": "0::/robot.slice/app.scope\n",
            "/proc/self/mountinfo": V2_MOUNTINFO,
            "/sys/fs/cgroup/robot.slice/app.scope/cpu.max": "150000 100000\n",
            "/sys/fs/cgroup/robot.slice/cpu.max": "max 100000\n",
            "/sys/fs/cgroup/cpu.max": "max 100000\n",
        },
    )
    assert cpu_quota(root=root) == 1.5
    assert usable_cpus(root=root) == min(AFFINITY, 2)


def test_a_parents_quota_holds_for_its_children(tmp_path: Path) -> None:
    root = fake(
        tmp_path,
        {
            "/proc/self/cgroup": "0::/robot.slice/app.scope\n",
            "/proc/self/mountinfo": V2_MOUNTINFO,
            "/sys/fs/cgroup/robot.slice/app.scope/cpu.max": "max 100000\n",
            "/sys/fs/cgroup/robot.slice/cpu.max": "50000 100000\n",
        },
    )
    assert cpu_quota(root=root) == 0.5
    assert usable_cpus(root=root) == 1  # rounded up, at least one


def test_docker_cpus_1_seen_from_inside_its_cgroup_namespace(tmp_path: Path) -> None:
    """``docker --cpus=1`` on cgroup v2: the container's cgroup is the mount's root."""
    root = fake(
        tmp_path,
        {
            "/proc/self/cgroup": "0::/\n",
            "/proc/self/mountinfo": V2_MOUNTINFO,
            "/sys/fs/cgroup/cpu.max": "100000 100000\n",
        },
    )
    assert cpu_quota(root=root) == 1.0
    assert usable_cpus(root=root) == 1


def test_v1_quota_with_the_host_cgroup_path_mounted_at_its_root(tmp_path: Path) -> None:
    """cgroup v1 without a cgroup namespace: ``/proc/self/cgroup`` names the
    host's path, which the container's mount shows as its root."""
    root = fake(
        tmp_path,
        {
            "/proc/self/cgroup": "12:pids:/docker/abc\n4:cpu,cpuacct:/docker/abc\n1:name=systemd:/docker/abc\n",
            "/proc/self/mountinfo": (
                "40 31 0:37 /docker/abc /sys/fs/cgroup/cpu,cpuacct ro,nosuid - cgroup cgroup rw,cpu,cpuacct\n"
                "41 31 0:38 /docker/abc /sys/fs/cgroup/pids ro,nosuid - cgroup cgroup rw,pids\n"
            ),
            "/sys/fs/cgroup/cpu,cpuacct/cpu.cfs_quota_us": "250000\n",
            "/sys/fs/cgroup/cpu,cpuacct/cpu.cfs_period_us": "100000\n",
        },
    )
    assert cpu_quota(root=root) == 2.5
    assert usable_cpus(root=root) == min(AFFINITY, 3)


def test_v1_without_a_quota_and_without_mountinfo(tmp_path: Path) -> None:
    """``-1`` is no limit; the usual mount point is used when mountinfo is missing."""
    root = fake(
        tmp_path,
        {
            "/proc/self/cgroup": "3:cpu:/robot\n",
            "/sys/fs/cgroup/cpu/robot/cpu.cfs_quota_us": "-1\n",
            "/sys/fs/cgroup/cpu/robot/cpu.cfs_period_us": "100000\n",
            "/sys/fs/cgroup/cpu/cpu.cfs_quota_us": "-1\n",
            "/sys/fs/cgroup/cpu/cpu.cfs_period_us": "100000\n",
        },
    )
    assert cpu_quota(root=root) is None
    assert usable_cpus(root=root) == AFFINITY
    (root / "sys/fs/cgroup/cpu/cpu.cfs_quota_us").write_text("100000\n", encoding="ascii")
    assert cpu_quota(root=root) == 1.0  # the root's limit, found from the process's cgroup up


def test_v1_and_v2_together_take_the_smaller(tmp_path: Path) -> None:
    root = fake(
        tmp_path,
        {
            "/proc/self/cgroup": "2:cpu:/\n0::/\n",
            "/proc/self/mountinfo": (
                "32 31 0:29 / /sys/fs/cgroup/cpu rw,relatime - cgroup cgroup rw,cpu\n"
                "41 31 0:38 / /sys/fs/cgroup/unified rw,relatime - cgroup2 cgroup2 rw\n"
            ),
            "/sys/fs/cgroup/cpu/cpu.cfs_quota_us": "300000\n",
            "/sys/fs/cgroup/cpu/cpu.cfs_period_us": "100000\n",
            "/sys/fs/cgroup/unified/cpu.max": "120000 100000\n",
        },
    )
    assert cpu_quota(root=root) == 1.2


@pytest.mark.parametrize(
    "files",
    [
        {},
        {"/proc/self/cgroup": "0::/gone\n", "/proc/self/mountinfo": V2_MOUNTINFO},
        {"/proc/self/cgroup": "not a cgroup line\n", "/sys/fs/cgroup/cpu.max": "100000 100000\n"},
        {"/proc/self/cgroup": "0::/\n", "/sys/fs/cgroup/cpu.max": "lots\n"},
        {"/proc/self/cgroup": "0::/\n", "/sys/fs/cgroup/cpu.max": "100000 0\n"},
        {"/proc/self/cgroup": "0::/\n", "/proc/self/mountinfo": "garbage\n", "/sys/fs/cgroup/cpu.max": "max\n"},
    ],
    ids=["nothing", "cgroup-gone", "bad-cgroup-line", "bad-cpu-max", "zero-period", "bad-mountinfo"],
)
def test_missing_or_unreadable_files_mean_no_limit(tmp_path: Path, files: dict[str, str]) -> None:
    root = fake(tmp_path, files)
    assert cpu_quota(root=root) is None
    assert usable_cpus(root=root) == AFFINITY


def test_a_cgroup_gone_from_the_mount_falls_back_to_the_mounts_own_limit(tmp_path: Path) -> None:
    root = fake(
        tmp_path,
        {
            "/proc/self/cgroup": "0::/elsewhere\n",
            "/proc/self/mountinfo": V2_MOUNTINFO,
            "/sys/fs/cgroup/cpu.max": "100000 100000\n",
        },
    )
    assert cpu_quota(root=root) == 1.0


def test_this_process_is_counted_as_its_affinity_and_quota_allow() -> None:
    quota = cpu_quota()
    expected = AFFINITY if quota is None else min(AFFINITY, math.ceil(quota))
    assert usable_cpus() == max(1, expected)


@pytest.mark.skipif(shutil.which("taskset") is None, reason="taskset (util-linux) is not installed")
def test_a_process_under_taskset_one_cpu_counts_one() -> None:
    cpu = min(os.sched_getaffinity(0))  # taskset -c 0, unless this process may not use CPU 0
    result = subprocess.run(
        ["taskset", "-c", str(cpu), sys.executable, "-c",
         "from container.executor._cores import usable_cpus; print(usable_cpus())"],
        capture_output=True, text=True, timeout=60, check=False, cwd=REPO,
    )  # fmt: skip
    assert (result.returncode, result.stdout) == (0, "1\n"), result.stderr[-2000:]

"""Process-level set-up shared by every command: DDS profile, rclpy, logging.

Kept in one place so that the container, the command-line clients and the
tests start ROS the same way.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

__all__ = ["DDS_PROFILE", "configure_logging", "use_fast_discovery"]

#: Fast DDS participant profile with quick discovery announcements.
DDS_PROFILE = Path(__file__).with_name("fastdds_profile.xml")

_PROFILE_VARIABLE = "FASTRTPS_DEFAULT_PROFILES_FILE"


def use_fast_discovery() -> None:
    """Point Fast DDS at the project's profile unless the user chose one.

    Must run before the first rclpy context is initialised: Fast DDS reads
    the variable when it creates the participant.
    """
    os.environ.setdefault(_PROFILE_VARIABLE, str(DDS_PROFILE))


def configure_logging(*, verbose: bool = False) -> None:
    """Send Python-level logs (plugin loading, dispatch failures) to stderr."""
    logging.basicConfig(
        level=logging.DEBUG if verbose else logging.INFO,
        format="[%(levelname)s] [%(name)s]: %(message)s",
    )

"""Where the package's data (URDF, config, scenarios) lives.

Works from the source tree, from a pip install into a venv (data under
``$VIRTUAL_ENV/share/humfall_ros``) and from a colcon install (ament index).
"""
from __future__ import annotations

import functools
import os
import pathlib
import sys

PACKAGE = "humfall_ros"
ROBOT_URDF = "humfall_humanoid.urdf"


@functools.lru_cache(maxsize=1)
def share_dir() -> pathlib.Path:
    """The directory that holds ``urdf/`` and ``config/``.

    The source tree wins when this module is imported from it, so edits are seen
    without reinstalling; otherwise the installed share directory.
    """
    src_root = pathlib.Path(__file__).resolve().parents[1]
    if (src_root / "package.xml").is_file() and (src_root / "urdf").is_dir():
        return src_root
    candidates = [pathlib.Path(sys.prefix) / "share" / PACKAGE]
    try:  # colcon / full ROS install
        from ament_index_python.packages import get_package_share_directory

        candidates.append(pathlib.Path(get_package_share_directory(PACKAGE)))
    except Exception:  # noqa: BLE001 - not on the index: fall through to the other candidates
        pass
    for prefix in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep):
        if prefix:
            candidates.append(pathlib.Path(prefix) / "share" / PACKAGE)
    for c in candidates:
        if (c / "urdf" / ROBOT_URDF).is_file():
            return c
    raise FileNotFoundError(f"cannot find the {PACKAGE} share directory (looked in {candidates})")


def urdf_path() -> pathlib.Path:
    return share_dir() / "urdf" / ROBOT_URDF


def config_path(name: str) -> pathlib.Path:
    return share_dir() / "config" / name


def scenario_path(name: str) -> pathlib.Path:
    p = pathlib.Path(name)
    if p.suffix in (".yaml", ".yml") and p.is_file():
        return p
    return share_dir() / "config" / "scenarios" / f"{name}.yaml"


def interface_share_dir(package: str) -> pathlib.Path | None:
    """Share directory of an interface package (for .msg texts), or None."""
    candidates = [pathlib.Path(sys.prefix) / "share" / package]
    for prefix in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep):
        if prefix:
            candidates.append(pathlib.Path(prefix) / "share" / package)
    for c in candidates:
        if c.is_dir():
            return c
    return None

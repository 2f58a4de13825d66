"""Where the files that ship with cegc_ros are: the network weights, the parameter files and
the Fast DDS profile for publishers of huge clouds.

There is one copy of each. An installed package (``pip install .``, ``colcon build``) has them
under ``share/cegc_ros/`` of its prefix, found through the ament index; a source checkout has
them in the repository (``cegc_ros/weights/``, ``params/``), next to the package.

    shipped_weights(ENGINE_WEIGHTS)          # Path of the weights the engine loads
    shipped_params("register_node.yaml")      # Path of the node's parameter file
    shipped_fastdds_profile()                 # params/fastdds_large_clouds.xml
    with fastdds_profile():                   # FASTRTPS_DEFAULT_PROFILES_FILE while a
        node = rclpy.create_node(...)         # process's first node is created

Standard library only (``ament_index_python`` is imported when it is needed), so tools that
never load torch can use it.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

PACKAGE = "cegc_ros"
#: The weights the engine loads by default (cegc_ros.engine.default_weights).
ENGINE_WEIGHTS = "cegc_views.pt"
#: The learned verification's weights (cegc_ros.verification; engine.verify_score 'learned').
VERIFICATION_WEIGHTS = "verification.json"
WEIGHT_NAMES = (ENGINE_WEIGHTS, VERIFICATION_WEIGHTS)
#: Fast DDS profile for processes that publish multi-megabyte clouds (heartbeat every 0.1 s).
FASTDDS_PROFILE = "fastdds_large_clouds.xml"
#: The variable Fast DDS 2.x (ROS 2 Jazzy) reads its profiles file from.
FASTDDS_PROFILE_ENV = "FASTRTPS_DEFAULT_PROFILES_FILE"

_PACKAGE_DIR = Path(__file__).resolve().parent
_CHECKOUT = _PACKAGE_DIR.parent          # the repository root when running from a checkout


class ShippedFileError(FileNotFoundError):
    """A file that should ship with the package is in none of the places it is looked for."""


def share_dir() -> Path | None:
    """``share/cegc_ros`` of the prefix the ament index names, or None when not installed."""
    try:
        from ament_index_python.packages import (
            PackageNotFoundError,
            get_package_share_directory,
        )
    except ModuleNotFoundError:   # a bare checkout without the ROS Python packages
        return None
    try:
        return Path(get_package_share_directory(PACKAGE))
    except (PackageNotFoundError, OSError):   # OSError: AMENT_PREFIX_PATH unset or empty
        return None


def _find(kind: str, name: str, in_checkout: Path, in_share: str) -> Path:
    if Path(name).name != name or name in ("", ".", ".."):
        raise ValueError(f"{kind} name must be a file name, got {name!r}")
    # The checkout's own copy first: code run from a checkout uses that checkout's files even
    # when an older install is on AMENT_PREFIX_PATH. An install has no copy next to the package.
    looked = [in_checkout / name]
    if looked[0].is_file():
        return looked[0]
    share = share_dir()
    if share is not None:
        looked.append(share / in_share / name)
        if looked[-1].is_file():
            return looked[-1]
    where = " and ".join(str(p) for p in looked)
    extra = "" if share is not None else f" (package {PACKAGE} is not in the ament index)"
    raise ShippedFileError(f"shipped {kind} {name} not found: looked at {where}{extra}")


def shipped_weights(name: str) -> Path:
    """The shipped weights file ``name`` (e.g. ``ENGINE_WEIGHTS``); ShippedFileError if absent."""
    return _find("weights", name, _PACKAGE_DIR / "weights", "weights")


def shipped_params(name: str = "register_node.yaml") -> Path:
    """The shipped parameter file ``name``; ShippedFileError if absent."""
    return _find("parameter file", name, _CHECKOUT / "params", "params")


def shipped_fastdds_profile() -> Path:
    """The shipped Fast DDS profile ``FASTDDS_PROFILE``; ShippedFileError if absent."""
    return _find("Fast DDS profile", FASTDDS_PROFILE, _CHECKOUT / "params", "params")


@contextmanager
def fastdds_profile(choice: str = "default") -> Iterator[str | None]:
    """``FASTRTPS_DEFAULT_PROFILES_FILE`` set for the block; yields the profiles file in effect
    (None: Fast DDS's defaults).

    Fast DDS reads the variable once per process, when the process's first ROS node (DDS
    participant) is created: create that node inside the block. ``choice``: ``"default"``: the
    user's setting when the variable is set (non-empty), or nothing when
    ``DEFAULT_FASTRTPS_PROFILES.xml`` is in the working directory (Fast DDS loads that file by
    itself), else the shipped profile; ``"none"``: no profiles file; anything else: the path of
    a profiles file (FileNotFoundError if it is not a file). The variable is restored after.
    """
    old = os.environ.get(FASTDDS_PROFILE_ENV)
    in_cwd = Path("DEFAULT_FASTRTPS_PROFILES.xml")
    if choice == "none":
        value = None
    elif choice != "default":
        if not Path(choice).is_file():
            raise FileNotFoundError(f"Fast DDS profile {choice} is not a file")
        value = str(Path(choice).resolve())
    elif old:
        value = old
    elif in_cwd.is_file():
        value = None
    else:
        value = str(shipped_fastdds_profile())
    if value is None:
        os.environ.pop(FASTDDS_PROFILE_ENV, None)
    else:
        os.environ[FASTDDS_PROFILE_ENV] = value
    try:
        yield value or (str(in_cwd.resolve()) if in_cwd.is_file() else None)
    finally:
        if old is None:
            os.environ.pop(FASTDDS_PROFILE_ENV, None)
        else:
            os.environ[FASTDDS_PROFILE_ENV] = old

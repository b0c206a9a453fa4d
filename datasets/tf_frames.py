"""A bag's tf (REP-105): where the laser sits on the robot, and odometry published only as tf.

A robot's frames form a tree: ``odom`` -> ``base_link`` (the wheel odometry, moving) -> ... ->
the laser's ``header.frame_id`` (fixed mounts, usually on ``/tf_static``). :class:`FrameTree`
holds the fixed transforms and composes the laser's pose in the base frame; :func:`planar_mount`
projects it onto the scan plane: its (x, y, yaw) in the base frame, whether the laser is mounted
upside down (its z axis pointing down: the scan turns clockwise in the base frame, so its beams
are mirrored) and how far it is tilted from level. Messages are ``tf2_msgs/TFMessage`` (ROS 1's
``tf/tfMessage`` alike). Frame names are compared without a leading ``/`` (ROS 1's tf_prefix
style). Units: metres, radians (``tilt_deg`` in degrees).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

TF_TYPES = ("tf2_msgs/msg/TFMessage", "tf/msg/tfMessage")
BASE_NAMES = ("base_link", "base_footprint")  # REP-105's robot base frames, in order of preference
MAX_DEPTH = 64  # frames walked up a chain before it is taken for a cycle


def frame_name(name: str) -> str:
    """``name`` as tf compares it: no surrounding blanks, no leading ``/``."""
    return str(name).strip().lstrip("/")


def is_odom_frame(name: str) -> bool:
    """True for an odometry frame (``odom``, ``odom_combined``, ``robot/odom``, ...)."""
    return "odom" in frame_name(name).rsplit("/", 1)[-1].lower()


def transform_matrix(tr: Any) -> np.ndarray | None:
    """4x4 homogeneous matrix of a ``geometry_msgs/Transform``; None when it is not finite or its
    quaternion has no length."""
    p, q = tr.translation, tr.rotation
    v = np.array([q.x, q.y, q.z, q.w], dtype=np.float64)
    t = np.array([p.x, p.y, p.z], dtype=np.float64)
    n = float(np.linalg.norm(v))
    if not (np.isfinite(v).all() and np.isfinite(t).all()) or n < 1e-9:
        return None
    x, y, z, w = v / n
    m = np.eye(4)
    m[:3, :3] = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ]
    m[:3, 3] = t
    return m


@dataclass(frozen=True, slots=True)
class Mount:
    """The laser's pose in the base frame, on the scan plane (metres, radians)."""

    x: float = 0.0
    y: float = 0.0
    yaw: float = 0.0
    mirrored: bool = False  # mounted upside down: beam angle a lies at -a in the mount's frame
    tilt_deg: float = 0.0  # the laser's z axis off the base's vertical (upside down: from straight down)

    @property
    def offset(self) -> tuple[float, float, float]:
        """(x, y, yaw) as :attr:`Scan.sensor_offset`."""
        return (self.x, self.y, self.yaw)


def planar_mount(m: np.ndarray) -> Mount:
    """The mount of a laser whose pose in the base frame is the 4x4 matrix ``m``.

    The laser's x axis sets the yaw; its z axis pointing down means the scan is mirrored: a beam at
    angle a (counter-clockwise about the laser's z) lies at -a about the base's z.
    """
    zz = float(m[2, 2])
    tilt = math.degrees(math.acos(min(1.0, abs(zz))))
    yaw = math.atan2(float(m[1, 0]), float(m[0, 0]))
    return Mount(float(m[0, 3]), float(m[1, 3]), yaw, zz < 0.0, tilt)


class FrameTree:
    """Fixed transforms between frames: each frame has one parent (the first one given wins)."""

    def __init__(self) -> None:
        self._parent: dict[str, tuple[str, np.ndarray]] = {}

    def __len__(self) -> int:
        return len(self._parent)

    def add(self, parent: str, child: str, m: np.ndarray) -> bool:
        """Add ``child``'s pose ``m`` in ``parent``; False when ``child`` already has a parent."""
        parent, child = frame_name(parent), frame_name(child)
        if child in self._parent or parent == child:
            return False
        self._parent[child] = (parent, m)
        return True

    def add_message(self, msg: Any, skip: Any = None) -> int:
        """Add the transforms of one TFMessage (``skip(parent, child)`` True: left out); how many."""
        added = 0
        for tr in getattr(msg, "transforms", ()):
            parent, child = frame_name(tr.header.frame_id), frame_name(tr.child_frame_id)
            if skip is not None and skip(parent, child):
                continue
            m = transform_matrix(tr.transform)
            if m is not None:
                added += self.add(parent, child, m)
        return added

    def _ancestors(self, frame: str) -> dict[str, np.ndarray]:
        """Each ancestor of ``frame`` (itself included) -> ``frame``'s pose in it."""
        out = {frame: np.eye(4)}
        m, f = np.eye(4), frame
        for _ in range(MAX_DEPTH):
            if f not in self._parent:
                break
            f, step = self._parent[f]
            if f in out:  # a cycle: stop where it closes
                break
            m = step @ m
            out[f] = m
        return out

    def chain(self, frame: str) -> list[str]:
        """``frame`` and its ancestors, nearest first."""
        return list(self._ancestors(frame_name(frame)))

    def pose(self, base: str, frame: str) -> np.ndarray | None:
        """4x4 pose of ``frame`` in ``base``, or None when the two are not connected."""
        base, frame = frame_name(base), frame_name(frame)
        up = self._ancestors(frame)
        m_base = np.eye(4)
        f = base
        for _ in range(MAX_DEPTH + 1):
            if f in up:
                return np.linalg.inv(m_base) @ up[f]
            if f not in self._parent:
                return None
            f, step = self._parent[f]
            m_base = step @ m_base
        return None

    def base_of(self, frame: str) -> str | None:
        """The robot base frame above ``frame`` (``base_link``, else ``base_footprint``), or None."""
        chain = self.chain(frame)
        for name in BASE_NAMES:
            for f in chain:
                if f.rsplit("/", 1)[-1] == name:
                    return f
        return None

"""ROS bags (ROS 1 ``.bag`` files, ROS 2 bag directories) -> :class:`Traversal`, via the
``rosbags`` package (pure Python, no ROS install needed; the optional extra ``[ros]``).

Reads ``sensor_msgs/msg/LaserScan`` (one traversal step per scan) and, when present,
``nav_msgs/msg/Odometry`` (paired to each scan by time). Output conventions match
:func:`pyro_slam.io.read_carmen`: ranges ``[T, B]`` in metres with invalid readings (non-finite,
``<= range_min``, ``>= max_range``) masked and set to ``max_range``; ``controls`` ``[T-1, 3]``
odometry increments (``control_model = "odometry_delta"``); ``poses`` None (a bag holds no
reference trajectory); timestamps from the scans' header stamps (bag receive time when zero).
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np

from pyro_slam.data import Traversal
from pyro_slam.extras import require
from pyro_slam.geometry import wrap_angle
from pyro_slam.io.common import ParseError, build_traversal, poses_at, sentinel_max_range

try:  # the [ros] extra
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore
except ImportError:
    AnyReader = Stores = get_typestore = None

LASER_SCAN = "sensor_msgs/msg/LaserScan"
ODOMETRY = "nav_msgs/msg/Odometry"


def _stamp(msg, bag_time_ns: int) -> float:
    t = msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec
    return float(t) if t > 0 else bag_time_ns * 1e-9


def _yaw(q) -> float:
    return math.atan2(2.0 * (q.w * q.z + q.x * q.y), 1.0 - 2.0 * (q.y * q.y + q.z * q.z))


def _connections(reader, path: Path, topic: str | None, msgtype: str, required: bool):
    """The connections of ``topic`` (checked to carry ``msgtype``), or of the single topic of
    that type when ``topic`` is None; ``[]`` when optional and absent."""
    conns = [c for c in reader.connections if (c.topic == topic if topic else c.msgtype == msgtype)]
    topics = sorted({c.topic for c in conns})
    if topic and not conns:
        raise ParseError(path, None, f"no topic {topic!r} in the bag")
    if topic and any(c.msgtype != msgtype for c in conns):
        raise ParseError(path, None, f"topic {topic!r} is {conns[0].msgtype}, not {msgtype}")
    if len(topics) > 1:
        raise ParseError(path, None, f"several {msgtype} topics {topics}; choose one")
    if required and not conns:
        raise ParseError(path, None, f"no {msgtype} topic in the bag")
    return conns


def _read_messages(reader, path: Path, scans, odoms):
    """The scans' ranges ``[T] x [B]`` and stamps, the first scan message, and the odometry
    poses ``[N] x [3]`` and stamps, in bag order."""
    ranges, times, first = [], [], None
    odom_pose, odom_time = [], []
    for conn, bag_ns, raw in reader.messages(connections=scans + odoms):
        msg = reader.deserialize(raw, conn.msgtype)
        if conn.msgtype == ODOMETRY:
            p = msg.pose.pose
            odom_pose.append([p.position.x, p.position.y, _yaw(p.orientation)])
            odom_time.append(_stamp(msg, bag_ns))
            continue
        if first is None:
            first = msg
        config = (len(msg.ranges), msg.angle_min, msg.angle_increment)
        if config != (len(first.ranges), first.angle_min, first.angle_increment):
            raise ParseError(
                path, None, f"scan {len(ranges)} on {conn.topic}: beams (n, angle_min, "
                f"increment) = {config} differ from the first scan's"
            )  # fmt: skip
        ranges.append(np.asarray(msg.ranges, dtype=np.float64))
        times.append(_stamp(msg, bag_ns))
    return ranges, times, first, odom_pose, odom_time


def _sensor(first, ranges: np.ndarray, max_range: float | None) -> tuple[dict, float]:
    """The sensor's metadata and its maximum range (argument, ``range_max`` or sentinel)."""
    sensor = {
        "type": LASER_SCAN,
        "frame_id": first.header.frame_id,
        "num_beams_raw": int(ranges.shape[1]),
        "range_min": float(first.range_min),
        "angle_min": float(first.angle_min),
        "angle_increment": float(first.angle_increment),
    }
    if max_range is not None:
        sensor["max_range_source"] = "argument"
    elif math.isfinite(first.range_max) and first.range_max > 0:
        max_range, sensor["max_range_source"] = float(first.range_max), "LaserScan.range_max"
    else:
        max_range, sensor["max_range_source"] = sentinel_max_range(ranges)
    return sensor, max_range


def read_rosbag(
    path: str | os.PathLike,
    scan_topic: str | None = None,
    odom_topic: str | None = None,
    *,
    beam_stride: int = 1,
    max_range: float | None = None,
    pairing: str = "nearest",
) -> Traversal:
    """Read a ROS 1 ``.bag`` or ROS 2 bag directory into a :class:`Traversal`.

    Args:
        scan_topic / odom_topic: topics to use; default: the bag's only LaserScan / Odometry
            topic (no odometry topic -> zero controls, said in ``metadata``).
        beam_stride: keep every ``beam_stride``-th beam.
        max_range: override the first scan's ``range_max``.
        pairing: ``"nearest"`` (default) or ``"interp"``: odometry record matched to a scan.
    Raises:
        ParseError: unreadable bag, missing / ambiguous topics, inconsistent scans, no scans.
    """
    require(AnyReader, "reading ROS bags", "rosbags", "ros")
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such bag")
    try:
        reader = AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE))
        reader.open()
    except Exception as e:  # rosbags raises several unrelated reader error types
        raise ParseError(path, None, f"cannot open bag ({type(e).__name__}: {e})") from e
    try:
        scans = _connections(reader, path, scan_topic, LASER_SCAN, required=True)
        odoms = _connections(reader, path, odom_topic, ODOMETRY, required=False)
        ranges, times, first, odom_pose, odom_time = _read_messages(reader, path, scans, odoms)
    finally:
        reader.close()
    if not ranges:
        raise ParseError(path, None, f"no messages on {scans[0].topic}")
    ranges = np.stack(ranges)  # [T, B]
    times = np.asarray(times)  # [T]
    sensor, max_range = _sensor(first, ranges, max_range)
    meta = {"source": "rosbag", "file": str(path), "scan_topic": scans[0].topic, "sensor": sensor}
    if odom_pose:
        odom, gap = poses_at(times, np.asarray(odom_time), np.asarray(odom_pose), pairing)
        meta.update(
            odom_topic=odoms[0].topic,
            odometry_source=f"{odoms[0].topic} ({pairing} in time to each scan)",
            odometry_max_time_gap=float(gap.max()),
        )
    else:
        odom = np.zeros((len(times), 3))
        meta.update(odom_topic=None, odometry_source="none (no Odometry topic): zero controls")
    meta["counts"] = {"scans": len(times), "odometry": len(odom_pose)}
    angles = wrap_angle(first.angle_min + first.angle_increment * np.arange(ranges.shape[1]))
    return build_traversal(ranges, angles, max_range, odom, odom, times, None, meta,
                           beam_stride=beam_stride, min_range=float(first.range_min))  # fmt: skip

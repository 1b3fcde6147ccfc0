"""ROS bags (ROS 1 ``.bag`` files, ROS 2 bag directories) -> :class:`Traversal`, via the
``rosbags`` package (pure Python, no ROS install needed; the optional extra ``[ros]``).

Reads ``sensor_msgs/msg/LaserScan`` (one traversal step per scan) and, when present,
``nav_msgs/msg/Odometry`` (paired to each scan by time), else the odometry in ``/tf``
(``odom -> base_link``). The laser's mounting offset on the robot (``base_link -> laser`` in
``/tf_static``) is applied: the controls move the laser's frame, whose origin and heading the
scans are measured from. Output conventions match
:func:`pyro_slam.io.read_carmen`: ranges ``[T, B]`` in metres with invalid readings (non-finite,
``<= range_min``, ``>= max_range``) masked and set to ``max_range``; ``controls`` ``[T-1, 3]``
odometry increments (``control_model = "odometry_delta"``); ``poses`` None (a bag holds no
reference trajectory); timestamps from the scans' header stamps (bag receive time when zero).
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pyro_slam.data import Traversal
from pyro_slam.extras import require
from pyro_slam.geometry import wrap_angle
from pyro_slam.io.common import (
    ParseError,
    build_traversal,
    compose,
    poses_at,
    sentinel_max_range,
)

try:  # the [ros] extra
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore
except ImportError:
    AnyReader = Stores = get_typestore = None

LASER_SCAN = "sensor_msgs/msg/LaserScan"
ODOMETRY = "nav_msgs/msg/Odometry"
TF = "tf2_msgs/msg/TFMessage"
TF_STATIC_TOPIC = "/tf_static"
ODOM_FRAME = "odom"  # the parent frame of odometry in /tf (REP 105)


@dataclass
class _Bag:
    """What :func:`read_rosbag` takes from a bag, in bag order."""

    ranges: list = field(default_factory=list)  # T x [B]
    times: list = field(default_factory=list)  # T
    first: object = None  # the first LaserScan message
    odom_pose: list = field(default_factory=list)  # K x [3]
    odom_time: list = field(default_factory=list)  # K
    odom_child: str = ""  # the Odometry messages' child frame
    static: dict = field(default_factory=dict)  # /tf_static: child -> (parent, [3])
    dynamic: dict = field(default_factory=dict)  # /tf: (parent, child) -> ([time], [[3]])


def _stamp(msg, bag_time_ns: int) -> float:
    t = msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec
    return float(t) if t > 0 else bag_time_ns * 1e-9


def _yaw(q) -> float:
    return math.atan2(2.0 * (q.w * q.z + q.x * q.y), 1.0 - 2.0 * (q.y * q.y + q.z * q.z))


def _frame(name: str) -> str:
    """A frame id without ROS 1's leading slash."""
    return str(name).lstrip("/")


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
        option = "scan" if msgtype == LASER_SCAN else "odom"
        raise ParseError(
            path, None, f"several {msgtype} topics {topics}; choose one with --{option}-topic"
        )
    if required and not conns:
        raise ParseError(path, None, f"no {msgtype} topic in the bag")
    return conns


def _add_scan(bag: _Bag, path: Path, topic: str, msg, bag_ns: int) -> None:
    if bag.first is None:
        bag.first = msg
    first = bag.first
    config = (len(msg.ranges), msg.angle_min, msg.angle_increment)
    if config != (len(first.ranges), first.angle_min, first.angle_increment):
        raise ParseError(
            path,
            None,
            f"scan {len(bag.ranges)} on {topic}: beams (n, angle_min, "
            f"increment) = {config} differ from the first scan's",
        )
    bag.ranges.append(np.asarray(msg.ranges, dtype=np.float64))
    bag.times.append(_stamp(msg, bag_ns))


def _add_transforms(bag: _Bag, msg, static: bool) -> None:
    """The 2-D parts ``(x, y, yaw)`` of a TFMessage's transforms."""
    for tf in msg.transforms:
        t, q = tf.transform.translation, tf.transform.rotation
        parent, child = _frame(tf.header.frame_id), _frame(tf.child_frame_id)
        pose = [t.x, t.y, _yaw(q)]
        if static:
            bag.static[child] = (parent, np.asarray(pose))
        else:
            times, poses = bag.dynamic.setdefault((parent, child), ([], []))
            times.append(tf.header.stamp.sec + 1e-9 * tf.header.stamp.nanosec)
            poses.append(pose)


def _read_messages(reader, path: Path, conns) -> _Bag:
    """Scans, odometry and transforms of the connections ``conns``, in bag order."""
    bag = _Bag()
    for conn, bag_ns, raw in reader.messages(connections=conns):
        msg = reader.deserialize(raw, conn.msgtype)
        if conn.msgtype == ODOMETRY:
            p = msg.pose.pose
            bag.odom_pose.append([p.position.x, p.position.y, _yaw(p.orientation)])
            bag.odom_time.append(_stamp(msg, bag_ns))
            bag.odom_child = _frame(msg.child_frame_id)
        elif conn.msgtype == TF:
            _add_transforms(bag, msg, conn.topic == TF_STATIC_TOPIC)
        else:
            _add_scan(bag, path, conn.topic, msg, bag_ns)
    return bag


def _mount_chain(static: dict, laser: str) -> list[tuple[str, np.ndarray]]:
    """``[(frame, pose of the laser in that frame [3])]``, from the laser's own frame up the
    ``/tf_static`` tree (e.g. ``laser`` -> ``base_link`` -> ``base_footprint``)."""
    chain, pose, frame = [(laser, np.zeros(3))], np.zeros(3), laser
    while frame in static and static[frame][0] not in {f for f, _ in chain}:
        frame, offset = static[frame]
        pose = compose(offset, pose)
        chain.append((frame, pose))
    return chain


def _odometry(bag: _Bag, times: np.ndarray, pairing: str, odom_topic: str | None):
    """The laser's odometry poses ``[T, 3]`` at the scan ``times [T]`` (the base frame's, from
    the Odometry topic or from ``/tf`` ``odom -> base``, composed with the laser's mounting
    offset on the base from ``/tf_static``) and the metadata saying where they came from."""
    chain = dict(_mount_chain(bag.static, _frame(bag.first.header.frame_id)))
    if bag.odom_pose:
        stamps, poses, base = np.asarray(bag.odom_time), np.asarray(bag.odom_pose), bag.odom_child
        source = f"{odom_topic} ({pairing} in time to each scan)"
    else:
        found = [k for k in bag.dynamic if k[1] in chain]
        found.sort(key=lambda k: k[0] != ODOM_FRAME)  # odom -> base first (REP 105)
        if not found:
            meta = {
                "odometry_source": "none (no Odometry topic, no odometry in /tf): zero controls"
            }
            return np.zeros((len(times), 3)), meta
        (parent, base), (stamps, poses) = found[0], bag.dynamic[found[0]]
        stamps, poses = np.asarray(stamps), np.asarray(poses)
        source = f"/tf {parent} -> {base} ({pairing} in time to each scan)"
    odom, gap = poses_at(times, stamps, poses, pairing)
    offset = chain.get(base)
    meta = {
        "odometry_source": source,
        "odometry_max_time_gap": float(gap.max()),
        "base_frame": base,
        "laser_offset": None if offset is None else offset.tolist(),
    }
    if offset is None:  # the laser is not on the base frame in /tf_static: taken as at its origin
        return odom, meta
    return compose(odom, np.broadcast_to(offset, odom.shape)), meta


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
            topic. Without an Odometry topic, odometry comes from ``/tf`` (``odom -> base``,
            the base being the frame ``/tf_static`` mounts the laser on); without either, the
            controls are zero (said in ``metadata``).
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
        tfs = [c for c in reader.connections if c.msgtype == TF]
        bag = _read_messages(reader, path, scans + odoms + tfs)
    finally:
        reader.close()
    if not bag.ranges:
        raise ParseError(path, None, f"no messages on {scans[0].topic}")
    ranges = np.stack(bag.ranges)  # [T, B]
    times = np.asarray(bag.times)  # [T]
    first = bag.first
    sensor, max_range = _sensor(first, ranges, max_range)
    meta = {"source": "rosbag", "file": str(path), "scan_topic": scans[0].topic, "sensor": sensor}
    odom, odom_meta = _odometry(bag, times, pairing, odoms[0].topic if odoms else None)
    meta.update(odom_topic=odoms[0].topic if odoms else None, **odom_meta)
    meta["counts"] = {"scans": len(times), "odometry": len(bag.odom_pose)}
    angles = wrap_angle(first.angle_min + first.angle_increment * np.arange(ranges.shape[1]))
    return build_traversal(
        ranges,
        angles,
        max_range,
        odom,
        odom,
        times,
        None,
        meta,
        beam_stride=beam_stride,
        min_range=float(first.range_min),
    )

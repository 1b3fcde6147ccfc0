"""ROS bags (ROS 1 ``.bag`` files, ROS 2 bag directories) -> :class:`Traversal`, via the
``rosbags`` package (pure Python, no ROS install needed; the optional extra ``[ros]``).

Reads ``sensor_msgs/msg/LaserScan`` (one traversal step per scan) and, when present,
``nav_msgs/msg/Odometry`` (paired to each scan by time), else the odometry in ``/tf``
(``odom -> base_link``). Transforms come from ``/tf_static`` and ``/tf`` (``tf2_msgs/TFMessage``
or ROS 1's older ``tf/tfMessage``). Which transform is the odometry is read from the tree of
frames, not from how constant a transform is: ``odom -> base`` where the bag has an ``odom``
frame (REP 105), else the topmost moving transform above the laser; the transforms between the
base and the laser are its mount, fixed up to ``MOUNT_TOL`` of jitter when republished on ``/tf``
(ROS 1's ``static_transform_publisher``), and refused where they change. The laser's mounting
offset on the robot (``base_link -> laser``) is applied: the controls move the laser's frame,
whose origin and heading the scans are measured from. Scans whose stamps do not go forward are
refused (skipped, counted and listed with ``lenient``); empty frame ids are refused naming the
topic. Where the
bag holds no odometry, or does not say where the laser sits on the odometry's frame, reading
stops naming what is missing, unless the caller chooses (``odometry=False``,
``laser_offset``). Output conventions match
:func:`pyro_slam.io.read_carmen`: ranges ``[T, B]`` in metres with invalid readings (non-finite,
``<= range_min``, ``>= max_range``) masked and set to ``max_range``; ``controls`` ``[T-1, 3]``
odometry increments (``control_model = "odometry_delta"``); ``poses`` None (a bag holds no
reference trajectory); timestamps from the scans' header stamps (bag receive time when zero).
"""

from __future__ import annotations

import logging
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

log = logging.getLogger(__name__)

LASER_SCAN = "sensor_msgs/msg/LaserScan"
ODOMETRY = "nav_msgs/msg/Odometry"
TF_TYPES = ("tf2_msgs/msg/TFMessage", "tf/msg/tfMessage")  # ROS 2 / ROS 1, and ROS 1's older one
TF_STATIC_TOPIC = "/tf_static"
ODOM_FRAME = "odom"  # the parent frame of odometry in /tf (REP 105)
CONSTANT_TOL = 1e-6  # metres / radians: a --laser-offset this close to the bag's mount agrees
# metres / radians: a mount on /tf that moves less than this over the bag is fixed (jitter)
MOUNT_TOL = 1e-3
MAX_REASONS = 20  # skipped scans listed in the metadata (all are counted)


@dataclass
class _Bag:
    """What :func:`read_rosbag` takes from a bag, in bag order."""

    ranges: list = field(default_factory=list)  # T x [B]
    times: list = field(default_factory=list)  # T
    first: object = None  # the first LaserScan message
    odom_pose: list = field(default_factory=list)  # K x [3]
    odom_time: list = field(default_factory=list)  # K
    odom_child: str = ""  # the Odometry messages' child frame
    odom_parent: str = ""  # the Odometry messages' header frame
    static: dict = field(default_factory=dict)  # mounts: child -> (parent, [3], topic)
    dynamic: dict = field(default_factory=dict)  # /tf: (parent, child) -> ([time], [[3]])


def _stamp(msg, bag_time_ns: int) -> float:
    t = msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec
    return float(t) if t > 0 else bag_time_ns * 1e-9


def _yaw(q) -> float:
    return math.atan2(2.0 * (q.w * q.z + q.x * q.y), 1.0 - 2.0 * (q.y * q.y + q.z * q.z))


def _frame(name: str) -> str:
    """A frame id without ROS 1's leading slash."""
    return str(name).lstrip("/")


def _in_time_order(path: Path, bag: _Bag, topic: str, lenient: bool) -> dict:
    """Keep the scans whose stamps go forward: a stamp at or before the previous scan's is a
    :class:`ParseError` naming the scan, or with ``lenient`` the scan is skipped (odometry is
    paired by time, so a scan out of order would get another's); the metadata of what was
    skipped (``skipped_scans``, ``skip_reasons``)."""
    keep, reasons, latest = [], [], -math.inf
    for k, t in enumerate(bag.times):
        if t > latest:
            keep.append(k)
            latest = t
            continue
        why = "repeats" if t == latest else "is before"
        reason = (
            f"scan {k} on {topic}: its stamp {t:.9g} s {why} the previous scan's {latest:.9g} s"
        )
        if not lenient:
            raise ParseError(path, None, f"{reason}; --lenient skips such scans")
        reasons.append(reason)
    if not reasons:
        return {}
    bag.ranges = [bag.ranges[k] for k in keep]
    bag.times = [bag.times[k] for k in keep]
    return {"skipped_scans": len(reasons), "skip_reasons": reasons[:MAX_REASONS]}


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


def _add_transforms(bag: _Bag, path: Path, topic: str, msg, static: bool) -> None:
    """The 2-D parts ``(x, y, yaw)`` of a TFMessage's transforms; a :class:`ParseError`
    naming the topic for a transform with an empty frame id."""
    for tf in msg.transforms:
        t, q = tf.transform.translation, tf.transform.rotation
        parent, child = _frame(tf.header.frame_id), _frame(tf.child_frame_id)
        if not parent or not child:
            raise ParseError(
                path,
                None,
                f"{topic}: a transform with an empty frame id (parent {parent!r}, child "
                f"{child!r}): the tree of frames cannot be built",
            )
        pose = [t.x, t.y, _yaw(q)]
        if static:
            bag.static[child] = (parent, np.asarray(pose), TF_STATIC_TOPIC)
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
            bag.odom_parent = _frame(msg.header.frame_id)
        elif conn.msgtype in TF_TYPES:
            static = conn.topic.lstrip("/") == TF_STATIC_TOPIC[1:]
            _add_transforms(bag, path, conn.topic, msg, static)
        else:
            _add_scan(bag, path, conn.topic, msg, bag_ns)
    return bag


def _spread(poses: np.ndarray) -> float:
    """How far poses ``[K, 3]`` move from the first (metres or radians, the larger)."""
    p = np.asarray(poses)
    d = np.concatenate([p[:, :2] - p[0, :2], wrap_angle(p[:, 2:] - p[0, 2])], 1)
    return float(np.abs(d).max())


def _parents(bag: _Bag) -> dict[str, tuple[str, np.ndarray, str]]:
    """The tree of frames: ``child -> (parent, poses [K, 3], topic)`` over ``/tf_static`` and
    ``/tf`` (a child in both: ``/tf_static``'s)."""
    tree = {c: (p, pose[None], topic) for c, (p, pose, topic) in bag.static.items()}
    for (parent, child), (_, poses) in bag.dynamic.items():
        tree.setdefault(child, (parent, np.asarray(poses), "/tf"))
    return tree


def _ancestry(tree: dict, laser: str) -> list[str]:
    """The frames from the laser's up to the tree's root (``laser``, ``base_link``, ``odom``)."""
    chain = [laser]
    while chain[-1] in tree and tree[chain[-1]][0] not in chain:
        chain.append(tree[chain[-1]][0])
    return chain


def _odometry_edge(bag: _Bag, ancestry: list[str]) -> tuple[str, str] | None:
    """The ``/tf`` transform that is the odometry, by the tree's structure (REP 105): the one
    leaving ``odom`` (the one above the laser where several do); without an ``odom`` frame,
    the topmost transform above the laser that moves. None where there is none."""
    leaving = [k for k in bag.dynamic if k[0] == ODOM_FRAME]
    if leaving:
        return min(leaving, key=lambda k: k[1] not in ancestry)
    up = [(ancestry[i + 1], ancestry[i]) for i in range(len(ancestry) - 1)]
    moving = [k for k in up if k in bag.dynamic and _spread(bag.dynamic[k][1]) > MOUNT_TOL]
    return moving[-1] if moving else None


def _mount_chain(path: Path, tree: dict, laser: str, base: str):
    """``{frame: (pose of the laser in that frame [3], topics)}`` from the laser's frame up to
    ``base`` (the odometry's frame; the root where it is not above the laser). A mount on
    ``/tf`` is fixed where it moves less than :data:`MOUNT_TOL` over the bag (its median);
    one that moves more, below ``base``, is a :class:`ParseError` naming ``--laser-offset``."""
    chain, pose, frame, topics = {laser: (np.zeros(3), "")}, np.zeros(3), laser, []
    while frame != base and frame in tree and tree[frame][0] not in chain:
        parent, poses, topic = tree[frame]
        if _spread(poses) > MOUNT_TOL:
            if base in _ancestry(tree, parent):
                raise ParseError(
                    path,
                    None,
                    f"the laser's mount {parent} -> {frame} on {topic} changes by "
                    f"{_spread(poses):.3g} over the bag (more than {MOUNT_TOL:g}): a moving "
                    f"mount is not supported; {OFFSET_HINT}",
                )
            break
        pose = compose(np.median(poses, axis=0), pose)
        topics.append(topic)
        frame = parent
        chain[frame] = (pose, " + ".join(dict.fromkeys(topics)))
    return chain


NO_ODOMETRY_HINT = "pass --no-odometry (odometry=False) to run on the scans alone, zero controls"
OFFSET_HINT = "give the laser's pose on it with --laser-offset X Y YAW (laser_offset=)"


def _odometry_records(bag: _Bag, ancestry: list[str], odom_topic: str | None):
    """``(stamps [K], poses [K, 3], parent frame, base frame, source)`` of the odometry: the
    Odometry topic's, else the ``/tf`` transform :func:`_odometry_edge` finds; None where the
    bag has neither."""
    if bag.odom_pose:
        stamps, poses = np.asarray(bag.odom_time), np.asarray(bag.odom_pose)
        return stamps, poses, bag.odom_parent, bag.odom_child, odom_topic
    edge = _odometry_edge(bag, ancestry)
    if edge is None:
        return None
    (parent, base), (stamps, poses) = edge, bag.dynamic[edge]
    return np.asarray(stamps), np.asarray(poses), parent, base, f"/tf {parent} -> {base}"


def _mount(path: Path, chain: dict, base: str, laser: str, odom_source, laser_offset):
    """The laser's pose on the odometry's ``base`` frame ``[3]`` and where it came from:
    ``laser_offset`` where given (a warning where the bag's mounts say otherwise), else the
    chain of mounts; a :class:`ParseError` naming what is missing where the bag does not say."""
    if laser_offset is not None:
        offset = np.asarray(laser_offset, dtype=np.float64)
        if offset.shape != (3,) or not np.isfinite(offset).all():
            raise ValueError(
                f"laser_offset must be 3 finite numbers (x, y, yaw), got {laser_offset}"
            )
        if base in chain and not np.allclose(chain[base][0], offset, atol=CONSTANT_TOL):
            log.warning(
                "%s: --laser-offset %s replaces the laser's mount %s on %r from %s",
                path,
                offset.tolist(),
                [round(v, 6) for v in chain[base][0].tolist()],
                base,
                chain[base][1] or "the frames (the same)",
            )
        return offset, "argument (--laser-offset)"
    if base in chain:
        pose, topics = chain[base]
        return pose, (topics or "none: the laser's frame is the odometry's")
    if not base:
        raise ParseError(
            path,
            None,
            f"the odometry on {odom_source} has an empty child_frame_id, so the frame the laser "
            f"{laser!r} is mounted on is unknown; {OFFSET_HINT}",
        )
    raise ParseError(
        path,
        None,
        f"no transform from the odometry's frame {base!r} to the laser's frame {laser!r} in "
        f"/tf_static or /tf: the laser's mounting offset is unknown; {OFFSET_HINT}",
    )


def _odometry(
    path: Path,
    bag: _Bag,
    times: np.ndarray,
    pairing: str,
    odom_topic: str | None,
    odometry: bool = True,
    laser_offset=None,
):
    """The laser's odometry poses ``[T, 3]`` at the scan ``times [T]`` (the base frame's, from
    the Odometry topic or from ``/tf`` ``odom -> base``, composed with the laser's mounting
    offset on the base) and the metadata saying where they came from and which frames."""
    laser = _frame(bag.first.header.frame_id)
    if not odometry:
        meta = {
            "odometry_source": "none (odometry=False, --no-odometry): zero controls",
            "laser_offset": None,
            "laser_offset_source": "not used without odometry",
            "frames": {"laser": laser},
        }
        return np.zeros((len(times), 3)), meta
    tree = _parents(bag)
    found = _odometry_records(bag, _ancestry(tree, laser), odom_topic)
    if found is None:
        raise ParseError(
            path,
            None,
            f"no odometry: no {ODOMETRY} topic, and no transform in /tf that moves the laser's "
            f"frame {laser!r} or leaves {ODOM_FRAME!r} (constant /tf transforms are mounts); "
            + NO_ODOMETRY_HINT,
        )
    stamps, poses, parent, base, source = found
    try:
        chain = _mount_chain(path, tree, laser, base)
    except ParseError:  # a moving mount: refused unless replaced
        if laser_offset is None:
            raise
        chain = {}
    offset, offset_source = _mount(path, chain, base, laser, source, laser_offset)
    odom, gap = poses_at(times, stamps, poses, pairing)
    meta = {
        "odometry_source": f"{source} ({pairing} in time to each scan)",
        "odometry_max_time_gap": float(gap.max()),
        "base_frame": base,
        "laser_offset": offset.tolist(),
        "laser_offset_source": offset_source,
        "frames": {"laser": laser, "base": base, "odometry": parent},
    }
    return compose(odom, np.broadcast_to(offset, odom.shape)), meta


def _log_choices(path: Path, meta: dict) -> None:
    """Say where the odometry and the laser's mount came from."""
    if meta["laser_offset"] is None:
        log.info("%s: %s", path, meta["odometry_source"])
        return
    log.info(
        "%s: odometry %s; laser %r at %s on %r (%s)",
        path,
        meta["odometry_source"],
        meta["frames"]["laser"],
        [round(v, 6) for v in meta["laser_offset"]],
        meta["frames"]["base"],
        meta["laser_offset_source"],
    )


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


def _read_bag(path: Path, scan_topic: str | None, odom_topic: str | None, odometry: bool):
    """The bag's scans, odometry and transforms (:class:`_Bag`), and the scan and odometry
    topics read (the latter None where there is none or ``odometry`` is False)."""
    try:
        reader = AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE))
        reader.open()
    except Exception as e:  # rosbags raises several unrelated reader error types
        raise ParseError(path, None, f"cannot open bag ({type(e).__name__}: {e})") from e
    try:
        scans = _connections(reader, path, scan_topic, LASER_SCAN, required=True)
        odoms = _connections(reader, path, odom_topic, ODOMETRY, False) if odometry else []
        tfs = [c for c in reader.connections if c.msgtype in TF_TYPES]
        bag = _read_messages(reader, path, scans + odoms + tfs)
    finally:
        reader.close()
    if not bag.ranges:
        raise ParseError(path, None, f"no messages on {scans[0].topic}")
    return bag, scans[0].topic, odoms[0].topic if odoms else None


def read_rosbag(
    path: str | os.PathLike,
    scan_topic: str | None = None,
    odom_topic: str | None = None,
    *,
    beam_stride: int = 1,
    max_range: float | None = None,
    pairing: str = "nearest",
    odometry: bool = True,
    laser_offset=None,
    lenient: bool = False,
) -> Traversal:
    """Read a ROS 1 ``.bag`` or ROS 2 bag directory into a :class:`Traversal`.

    Args:
        scan_topic / odom_topic: topics to use; default: the bag's only LaserScan / Odometry
            topic. Without an Odometry topic, odometry comes from ``/tf`` (``odom -> base``,
            the mounts below ``base`` putting the laser on it); without either, a
            :class:`ParseError` says so.
        beam_stride: keep every ``beam_stride``-th beam.
        max_range: override the first scan's ``range_max``.
        pairing: ``"nearest"`` (default) or ``"interp"``: odometry record matched to a scan.
        odometry: False: ignore any odometry, zero controls (SLAM on the scans alone).
        laser_offset: ``(x, y, yaw)``, the laser's pose on the odometry's frame, instead of
            the bag's transforms (needed where the bag has none, e.g. an Odometry topic with
            an empty ``child_frame_id`` and no ``/tf_static``).
        lenient: skip scans whose stamps do not go forward (counted and listed in the
            metadata's ``skipped_scans`` / ``skip_reasons``) instead of refusing the bag.
    ``metadata`` records ``odometry_source``, ``laser_offset`` (and its source) and the
    ``frames`` used (``laser``, ``base``, ``odometry``).

    Raises:
        ParseError: unreadable bag, missing / ambiguous topics, inconsistent scans, no scans,
            no odometry (without ``odometry=False``), no mount of the laser on the odometry's
            frame (without ``laser_offset``).
    """
    require(AnyReader, "reading ROS bags", "rosbags", "ros")
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such bag")
    bag, scan_topic, odom_topic = _read_bag(path, scan_topic, odom_topic, odometry)
    if not _frame(bag.first.header.frame_id) and laser_offset is None and odometry:
        raise ParseError(
            path,
            None,
            f"{scan_topic}: the scans' header has an empty frame_id, so where the laser is "
            f"mounted is unknown; {OFFSET_HINT}",
        )
    skipped = _in_time_order(path, bag, scan_topic, lenient)
    ranges = np.stack(bag.ranges)  # [T, B]
    times = np.asarray(bag.times)  # [T]
    first = bag.first
    sensor, max_range = _sensor(first, ranges, max_range)
    meta = {"source": "rosbag", "file": str(path), "scan_topic": scan_topic, "sensor": sensor}
    odom, odom_meta = _odometry(path, bag, times, pairing, odom_topic, odometry, laser_offset)
    meta.update(odom_topic=odom_topic if odometry else None, **odom_meta)
    _log_choices(path, meta)
    meta["counts"] = {"scans": len(times), "odometry": len(bag.odom_pose)}
    meta.update(skipped)
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

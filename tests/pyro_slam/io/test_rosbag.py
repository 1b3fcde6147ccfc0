"""ROS bags written here with ``rosbags`` (ROS 2 directory and ROS 1 file), read back."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from pyro_slam import cli
from pyro_slam.io import ParseError, read_any, read_rosbag
from pyro_slam.io.common import compose, relative

B, T, RANGE_MAX = 7, 5, 8.0
ANGLE_MIN, ANGLE_INC = -1.5, 0.5
SCAN_TIMES = 100.0 + 0.2 * np.arange(T)


def true_pose(t):
    return np.array([0.3 * t, 0.1 * t * t, 0.4 * t - 2.0])


def scan_ranges(k):
    r = np.linspace(0.5, 6.0, B) + k
    r[1], r[3], r[5] = np.nan, np.inf, RANGE_MAX  # invalid: masked
    r[6] = 0.01  # below range_min
    return r.astype(np.float32)


def messages(store, ros1: bool, laser="base_link", odom_child="base_link", stamps=SCAN_TIMES):
    """(topic, msgtype, t_ns, message) in time order: scans at SCAN_TIMES in the frame
    ``laser`` (their header stamps ``stamps``), odometry of the frame ``odom_child`` at 20 Hz."""
    T_ = store.types
    Header, Time = T_["std_msgs/msg/Header"], T_["builtin_interfaces/msg/Time"]

    def header(t, frame):
        stamp = Time(sec=int(t), nanosec=int(round((t % 1) * 1e9)))
        return Header(seq=0, stamp=stamp, frame_id=frame) if ros1 else Header(stamp, frame)

    out = []
    for k, (t, stamp) in enumerate(zip(SCAN_TIMES, stamps)):
        scan = T_["sensor_msgs/msg/LaserScan"](
            header=header(stamp, laser),
            angle_min=ANGLE_MIN,
            angle_max=ANGLE_MIN + ANGLE_INC * 6,
            angle_increment=ANGLE_INC,
            time_increment=0.0,
            scan_time=0.1,
            range_min=0.05,
            range_max=RANGE_MAX,
            ranges=scan_ranges(k),
            intensities=np.zeros(0, np.float32),
        )
        out.append(("/scan", "sensor_msgs/msg/LaserScan", t, scan))
    gm = "geometry_msgs/msg/"
    for t in np.arange(99.9, 101.2, 0.05):
        x, y, th = true_pose(t)
        pose = T_[gm + "Pose"](
            position=T_[gm + "Point"](x=x, y=y, z=0.0),
            orientation=T_[gm + "Quaternion"](x=0.0, y=0.0, z=math.sin(th / 2), w=math.cos(th / 2)),
        )
        cov = np.zeros(36)
        twist = T_[gm + "TwistWithCovariance"](
            twist=T_[gm + "Twist"](
                linear=T_[gm + "Vector3"](x=0.0, y=0.0, z=0.0),
                angular=T_[gm + "Vector3"](x=0.0, y=0.0, z=0.0),
            ),
            covariance=cov,
        )
        odom = T_["nav_msgs/msg/Odometry"](
            header=header(t, "odom"),
            child_frame_id=odom_child,
            pose=T_[gm + "PoseWithCovariance"](pose=pose, covariance=cov),
            twist=twist,
        )
        out.append(("/odom", "nav_msgs/msg/Odometry", t, odom))
    return sorted(out, key=lambda m: m[2])


def write_ros2(path, extra_scan_topic=False, with_odom=True, **frames):
    store = get_typestore(Stores.ROS2_HUMBLE)
    with Writer2(path, version=9) as w:
        conns = {}
        for topic, msgtype, t, msg in messages(store, ros1=False, **frames):
            if topic == "/odom" and not with_odom:
                continue
            topics = [topic, "/scan2"] if extra_scan_topic and topic == "/scan" else [topic]
            for tp in topics:
                if tp not in conns:
                    conns[tp] = w.add_connection(tp, msgtype, typestore=store)
                w.write(conns[tp], int(t * 1e9), store.serialize_cdr(msg, msgtype))
    return path


def write_ros1(path):
    store = get_typestore(Stores.ROS1_NOETIC)
    with Writer1(path) as w:
        conns = {}
        for topic, msgtype, t, msg in messages(store, ros1=True):
            if topic not in conns:
                conns[topic] = w.add_connection(topic, msgtype, typestore=store)
            w.write(conns[topic], int(t * 1e9), store.serialize_ros1(msg, msgtype))
    return path


def check(tr):
    raw = np.stack([scan_ranges(k) for k in range(T)]).astype(np.float64)
    assert tr.observations.shape == (T, B) and tr.max_range == RANGE_MAX
    np.testing.assert_allclose(tr.beam_angles, ANGLE_MIN + ANGLE_INC * np.arange(B))
    valid = np.isfinite(raw) & (raw > 0.05) & (raw < RANGE_MAX)
    np.testing.assert_array_equal(tr.obs_mask, valid)
    np.testing.assert_array_equal(tr.observations, np.where(valid, raw, RANGE_MAX))
    np.testing.assert_allclose(tr.timestamps, SCAN_TIMES, atol=1e-6)
    odom = np.stack([true_pose(t) for t in SCAN_TIMES])  # odometry stamped at every scan time
    np.testing.assert_allclose(tr.controls, relative(odom[:-1], odom[1:]), atol=1e-6)
    assert tr.metadata["control_model"] == "odometry_delta" and tr.poses is None
    assert tr.metadata["odometry_max_time_gap"] < 1e-6


def test_ros2_bag_round_trip(tmp_path):
    path = write_ros2(tmp_path / "bag2")
    check(read_rosbag(path))
    check(read_any(path))
    assert read_rosbag(path, beam_stride=3).observations.shape == (T, 3)


def test_ros1_bag_round_trip(tmp_path):
    path = write_ros1(tmp_path / "run.bag")
    check(read_any(path, pairing="interp"))


def test_topic_selection_and_errors(tmp_path):
    path = write_ros2(tmp_path / "two", extra_scan_topic=True)
    with pytest.raises(ParseError, match="several sensor_msgs/msg/LaserScan topics"):
        read_rosbag(path)
    check(read_rosbag(path, scan_topic="/scan2"))
    with pytest.raises(ParseError, match="no topic '/nope'"):
        read_rosbag(path, scan_topic="/nope")
    with pytest.raises(ParseError, match="is nav_msgs/msg/Odometry, not sensor_msgs"):
        read_rosbag(path, scan_topic="/odom")


def test_unreadable_bag(tmp_path):
    bad = tmp_path / "junk.bag"
    bad.write_bytes(b"not a bag at all")
    with pytest.raises(ParseError, match="junk.bag: cannot open bag"):
        read_rosbag(bad)


# ------------------------------------------------------------------- TF and the CLI's topics
MOUNT = [("base_link", "laser_mount", (0.1, 0.0, 0.0)), ("laser_mount", "laser", (0.1, -0.1, 0.3))]
LASER_ON_BASE = np.array([0.2, -0.1, 0.3])  # the two static transforms composed


def transform(store, parent, child, t, pose):
    """A ``geometry_msgs/msg/TransformStamped`` of the 2-D ``pose`` at time ``t``."""
    T_, gm = store.types, "geometry_msgs/msg/"
    stamp = T_["builtin_interfaces/msg/Time"](sec=int(t), nanosec=int(round((t % 1) * 1e9)))
    x, y, th = pose
    return T_[gm + "TransformStamped"](
        header=T_["std_msgs/msg/Header"](stamp, parent),
        child_frame_id=child,
        transform=T_[gm + "Transform"](
            translation=T_[gm + "Vector3"](x=x, y=y, z=0.0),
            rotation=T_[gm + "Quaternion"](x=0.0, y=0.0, z=math.sin(th / 2), w=math.cos(th / 2)),
        ),
    )


def write_tf_bag(path, with_odom: bool):
    """Scans in the frame ``laser``, mounted on ``base_link`` by two ``/tf_static`` transforms;
    ``/tf`` holds ``odom -> base_link`` (the true pose, 20 Hz) and a ``map -> odom`` that is
    not odometry; with ``with_odom`` an Odometry topic too."""
    store = get_typestore(Stores.ROS2_HUMBLE)
    tf_type = "tf2_msgs/msg/TFMessage"
    TFMessage = store.types[tf_type]
    with Writer2(path, version=9) as w:
        conns = {}

        def put(topic, msgtype, t, msg):
            if topic not in conns:
                conns[topic] = w.add_connection(topic, msgtype, typestore=store)
            w.write(conns[topic], int(t * 1e9), store.serialize_cdr(msg, msgtype))

        static = [transform(store, p, c, 99.0, pose) for p, c, pose in MOUNT]
        put("/tf_static", tf_type, 99.0, TFMessage(transforms=static))
        for topic, msgtype, t, msg in messages(store, ros1=False, laser="laser"):
            if topic == "/odom":
                tfs = [
                    transform(store, "odom", "base_link", t, true_pose(t)),
                    transform(store, "map", "odom", t, (5.0, 5.0, 1.0)),
                ]
                put("/tf", tf_type, t, TFMessage(transforms=tfs))
                if not with_odom:
                    continue
            put(topic, msgtype, t, msg)
    return path


@pytest.mark.parametrize("with_odom", [False, True])
def test_odometry_from_tf_and_the_laser_mounting_offset(tmp_path, with_odom):
    """Without an Odometry topic the odometry is ``/tf``'s ``odom -> base_link``; either way
    the laser's mounting offset on ``base_link`` from ``/tf_static`` (a chain of two) is
    applied: the controls move the laser's frame."""
    tr = read_rosbag(write_tf_bag(tmp_path / "bag", with_odom))
    base = np.stack([true_pose(t) for t in SCAN_TIMES])
    laser = compose(base, np.broadcast_to(LASER_ON_BASE, base.shape))
    np.testing.assert_allclose(tr.controls, relative(laser[:-1], laser[1:]), atol=1e-6)
    np.testing.assert_allclose(tr.metadata["laser_offset"], LASER_ON_BASE, atol=1e-9)
    assert tr.metadata["base_frame"] == "base_link"
    source = "/odom" if with_odom else "/tf odom -> base_link"
    assert tr.metadata["odometry_source"].startswith(source)


TINY = '{"filter": {"particles": 16}}'  # (the real-log preset takes no SVI steps)


def test_a_bag_with_two_scan_topics_runs_with_scan_topic(tmp_path, capsys):
    """From the command line: two LaserScan topics are refused naming ``--scan-topic``, which
    picks one; an Odometry topic that is not in the bag is named."""
    path = write_ros2(tmp_path / "two", extra_scan_topic=True)
    args = ["slam", str(path), "--config", TINY]
    assert cli.main([*args, "--out", str(tmp_path / "a")]) == 2
    assert "--scan-topic" in capsys.readouterr().err
    scan2 = ["--scan-topic", "/scan2"]
    assert cli.main([*args, "--out", str(tmp_path / "b"), *scan2, "--odom-topic", "/nope"]) == 2
    assert "/nope" in capsys.readouterr().err
    assert cli.main([*args, "--out", str(tmp_path / "c"), *scan2]) == 0
    report = json.loads((tmp_path / "c" / "metrics.json").read_text())
    assert report["steps"] == T and report["preset"] == "real"
    # five scans: no two of them are far enough apart in time to score each other
    consistency = report["scan_consistency"]["slam"]
    assert consistency["mean"] is None and "too short" in consistency["reason"]
    assert "NaN" not in (tmp_path / "c" / "metrics.json").read_text()


# ----------------------------------------------------- TF as ROS 1 and ROS 2 users publish it
MOUNT_ON_TF = (0.2, -0.1, 0.3)  # base_link -> laser, republished on /tf with every message
OLD_TF = "tf/msg/tfMessage"  # ROS 1's message type before tf2


def tf_message(store, tf_type, ros1, transforms):
    """A TF message of ``transforms`` ``[(parent, child, t, pose)]``."""
    T_, gm = store.types, "geometry_msgs/msg/"
    out = []
    for parent, child, t, (x, y, th) in transforms:
        stamp = T_["builtin_interfaces/msg/Time"](sec=int(t), nanosec=int(round((t % 1) * 1e9)))
        head = T_["std_msgs/msg/Header"]
        out.append(
            T_[gm + "TransformStamped"](
                header=head(0, stamp, parent) if ros1 else head(stamp, parent),
                child_frame_id=child,
                transform=T_[gm + "Transform"](
                    translation=T_[gm + "Vector3"](x=x, y=y, z=0.0),
                    rotation=T_[gm + "Quaternion"](
                        x=0.0, y=0.0, z=math.sin(th / 2), w=math.cos(th / 2)
                    ),
                ),
            )
        )
    return T_[tf_type](transforms=out)


def write_tf_only_bag(
    path, ros1=False, tf_type="tf2_msgs/msg/TFMessage", odom=True, mount=True, drift=None
):
    """Scans in ``laser``; no Odometry topic and no ``/tf_static``: ``/tf`` alone holds, at 20
    Hz, the moving ``odom -> base_link`` (``odom``) and the constant ``base_link -> laser``
    (``mount``), as ROS 1's ``static_transform_publisher`` republishes it; ``drift(k)``: what
    is added to the mount's k-th message (jitter, a change)."""
    store = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    if tf_type == OLD_TF:
        store.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms", OLD_TF))
    serialize = store.serialize_ros1 if ros1 else store.serialize_cdr
    with Writer1(path) if ros1 else Writer2(path, version=9) as w:
        conns = {}

        def put(topic, msgtype, t, msg):
            if topic not in conns:
                conns[topic] = w.add_connection(topic, msgtype, typestore=store)
            w.write(conns[topic], int(t * 1e9), serialize(msg, msgtype))

        for k, (topic, msgtype, t, msg) in enumerate(messages(store, ros1=ros1, laser="laser")):
            if topic != "/odom":
                put(topic, msgtype, t, msg)
                continue
            pose = np.asarray(MOUNT_ON_TF) + (0 if drift is None else drift(k))
            tfs = [("odom", "base_link", t, true_pose(t))] if odom else []
            tfs += [("base_link", "laser", t, tuple(pose))] if mount else []
            put("/tf", tf_type, t, tf_message(store, tf_type, ros1, tfs))
    return path


def laser_controls(offset):
    base = np.stack([true_pose(t) for t in SCAN_TIMES])
    laser = compose(base, np.broadcast_to(np.asarray(offset), base.shape))
    return relative(laser[:-1], laser[1:])


def test_bag_mount_on_tf_is_not_odometry(tmp_path):
    """A constant ``base_link -> laser`` on ``/tf`` is the laser's mount, applied on the
    odometry ``odom -> base_link``; alone on ``/tf`` it is no odometry, and reading stops
    saying so instead of taking the mount for a robot standing still."""
    tr = read_rosbag(write_tf_only_bag(tmp_path / "bag"))
    np.testing.assert_allclose(tr.controls, laser_controls(MOUNT_ON_TF), atol=1e-6)
    meta = tr.metadata
    np.testing.assert_allclose(meta["laser_offset"], MOUNT_ON_TF, atol=1e-9)
    assert meta["laser_offset_source"] == "/tf"
    assert meta["odometry_source"].startswith("/tf odom -> base_link")
    assert meta["frames"] == {"laser": "laser", "base": "base_link", "odometry": "odom"}
    with pytest.raises(ParseError, match="no odometry.*'laser'.*--no-odometry"):
        read_rosbag(write_tf_only_bag(tmp_path / "mount_only", odom=False))


def test_bag_old_tf_message_type(tmp_path):
    """A ROS 1 bag whose ``/tf`` is the older ``tf/tfMessage`` (no ``/tf_static``, the mount
    republished on ``/tf``) gives the same odometry and mount as ``tf2_msgs/TFMessage``."""
    tr = read_rosbag(write_tf_only_bag(tmp_path / "old.bag", ros1=True, tf_type=OLD_TF))
    np.testing.assert_allclose(tr.controls, laser_controls(MOUNT_ON_TF), atol=1e-6)
    np.testing.assert_allclose(tr.metadata["laser_offset"], MOUNT_ON_TF, atol=1e-9)
    assert tr.metadata["odometry_source"].startswith("/tf odom -> base_link")


def test_bag_without_offset_or_odometry_is_reported(tmp_path, capsys):
    """No odometry at all, or an Odometry topic with an empty ``child_frame_id`` and no
    ``/tf_static`` (the laser's mount unknown): reading stops naming what is missing and the
    option that decides it; with the choice made (``odometry=False`` / ``--no-odometry``,
    ``laser_offset`` / ``--laser-offset``) it runs and ``metrics.json`` records it."""
    scans_only = write_ros2(tmp_path / "scans_only", with_odom=False)
    with pytest.raises(ParseError, match="scans_only: no odometry.*--no-odometry"):
        read_rosbag(scans_only)
    tr = read_rosbag(scans_only, odometry=False)
    assert (tr.controls == 0).all() and tr.metadata["odometry_source"].startswith("none")
    unnamed = write_ros2(tmp_path / "unnamed", laser="laser", odom_child="")
    with pytest.raises(ParseError, match="empty child_frame_id.*'laser'.*--laser-offset"):
        read_rosbag(unnamed)
    tr = read_rosbag(unnamed, laser_offset=MOUNT_ON_TF)
    np.testing.assert_allclose(tr.controls, laser_controls(MOUNT_ON_TF), atol=1e-6)
    assert tr.metadata["laser_offset_source"].startswith("argument")
    named = write_ros2(tmp_path / "named", laser="laser")
    with pytest.raises(ParseError, match="no transform from .*'base_link' to .*'laser'"):
        read_rosbag(named)

    args = ["slam", str(unnamed), "--config", TINY, "--out"]
    assert cli.main([*args, str(tmp_path / "a")]) == 2
    assert "--laser-offset" in capsys.readouterr().err
    offset = ["--laser-offset", *map(str, MOUNT_ON_TF)]
    assert cli.main([*args, str(tmp_path / "b"), *offset]) == 0
    report = json.loads((tmp_path / "b" / "metrics.json").read_text())
    np.testing.assert_allclose(report["laser_offset"], MOUNT_ON_TF)
    assert report["odometry_source"].startswith("/odom")
    assert report["frames"] == {"laser": "laser", "base": "", "odometry": "odom"}
    assert (
        cli.main(
            [
                "slam",
                str(scans_only),
                "--config",
                TINY,
                "--no-odometry",
                "--out",
                str(tmp_path / "c"),
            ]
        )
        == 0
    )
    report = json.loads((tmp_path / "c" / "metrics.json").read_text())
    assert report["odometry_source"].startswith("none") and report["laser_offset"] is None


def test_quiet_and_verbose_drive_the_library_logging(tmp_path, capsys):
    """The library's log messages reach stderr through ``logging``: its warnings by default
    (here: ``--laser-offset`` replacing the bag's own mount), its INFO messages too with
    ``--verbose`` (the odometry's source, the map export), errors only with ``--quiet``."""
    bag = write_tf_bag(tmp_path / "bag", with_odom=True)
    run = ["slam", str(bag), "--config", TINY, "--laser-offset", "0", "0", "0", "--out"]
    assert cli.main([*run, str(tmp_path / "a")]) == 0
    err = capsys.readouterr().err
    assert "pyro-slam slam: WARNING:" in err and "replaces the laser's mount" in err
    assert "INFO" not in err
    assert cli.main(["--verbose", *run, str(tmp_path / "b")]) == 0
    err = capsys.readouterr().err
    assert "WARNING:" in err and "pyro-slam slam: INFO: map.pgm:" in err
    assert f"INFO: {bag}: odometry /odom" in err
    assert cli.main(["--quiet", *run, str(tmp_path / "c")]) == 0
    err = capsys.readouterr().err
    assert "WARNING" not in err and "INFO" not in err


def test_mount_with_jitter_is_not_odometry(tmp_path):
    """A ``base_link -> laser`` mount republished on ``/tf`` with 1e-5 jitter is still the
    mount, and ``odom -> base_link`` the odometry (the tree's structure decides, not how
    constant a transform is); a mount that changes once during the bag is refused naming
    ``--laser-offset``, and runs with it."""
    jitter = read_rosbag(write_tf_only_bag(tmp_path / "jitter", drift=lambda k: 1e-5 * (-1) ** k))
    np.testing.assert_allclose(jitter.controls, laser_controls(MOUNT_ON_TF), atol=1e-4)
    assert jitter.metadata["odometry_source"].startswith("/tf odom -> base_link")
    np.testing.assert_allclose(jitter.metadata["laser_offset"], MOUNT_ON_TF, atol=2e-5)
    assert jitter.metadata["frames"] == {"laser": "laser", "base": "base_link", "odometry": "odom"}
    changed = write_tf_only_bag(tmp_path / "changed", drift=lambda k: [0.05 * (k > 20), 0, 0])
    with pytest.raises(ParseError, match="mount base_link -> laser on /tf changes.*--laser-offset"):
        read_rosbag(changed)
    tr = read_rosbag(changed, laser_offset=MOUNT_ON_TF)
    np.testing.assert_allclose(tr.controls, laser_controls(MOUNT_ON_TF), atol=1e-6)


def test_backwards_stamps_refused_or_listed(tmp_path, capsys):
    """A scan whose header stamp is before the previous scan's (or repeats it) is refused,
    naming the scan and ``--lenient``; with it, the scan is skipped, counted and listed, and
    the others keep their own odometry."""
    store, path = get_typestore(Stores.ROS2_HUMBLE), tmp_path / "backwards"
    stamps = SCAN_TIMES.copy()
    stamps[2], stamps[3] = SCAN_TIMES[1], SCAN_TIMES[0]  # one repeat, one step back
    with Writer2(path, version=9) as w:
        conns = {}
        for topic, msgtype, t, msg in messages(store, ros1=False, stamps=stamps):
            if topic not in conns:
                conns[topic] = w.add_connection(topic, msgtype, typestore=store)
            w.write(conns[topic], int(t * 1e9), store.serialize_cdr(msg, msgtype))
    with pytest.raises(ParseError, match="scan 2 on /scan: its stamp .* repeats.*--lenient"):
        read_rosbag(path)
    tr = read_rosbag(path, lenient=True)
    kept = SCAN_TIMES[[0, 1, 4]]
    np.testing.assert_allclose(tr.timestamps, kept, atol=1e-6)
    odom = np.stack([true_pose(t) for t in kept])
    np.testing.assert_allclose(tr.controls, relative(odom[:-1], odom[1:]), atol=1e-6)
    assert tr.metadata["skipped_scans"] == 2
    assert [r.split(":")[0] for r in tr.metadata["skip_reasons"]] == [
        "scan 2 on /scan",
        "scan 3 on /scan",
    ]
    out = tmp_path / "run"
    args = ["slam", str(path), "--config", TINY, "--out", str(out), "--lenient"]
    assert cli.main(args) == 0
    assert "--lenient skipped 2 scan(s)" in capsys.readouterr().err
    assert json.loads((out / "metrics.json").read_text())["skipped_scans"] == 2

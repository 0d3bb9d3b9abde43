"""TransformBuffer lookups against an analytic scene (moving map -> base_link, static base_link -> lidar),
its error messages, bounds and skip counters; boxes moved between frames (pure Python, no rclpy)."""
from __future__ import annotations

import math
import random
from types import SimpleNamespace as NS

import numpy as np
import pytest

from gd_completion.box_messages import BoxSet
from gd_completion.errors import GDCompletionError
from gd_completion.geometry import Box3D
from gd_completion.rotations import rotation_quaternion
from gd_completion.transforms import (
    TransformBuffer,
    TransformError,
    boxes_in_frame,
    boxes_to_frame,
    transform_boxes,
)

NS_PER_S = 1_000_000_000
T0 = 1_700_000_000 * NS_PER_S   # a realistic epoch stamp: the first map -> base_link sample
RATE_HZ = 10
N_SAMPLES = 21                  # 2 s of odometry
YAW0, YAW_RATE = 2.9, 0.8       # heading crosses +pi during the samples
P0, VEL = np.array([5.0, -3.0, 0.2]), np.array([8.0, 1.5, 0.05])
LIDAR_T, LIDAR_YAW = np.array([1.2, 0.1, 1.8]), 0.1
TILT_T, TILT_YAW, TILT_PITCH = np.array([-0.5, 0.3, 1.6]), -0.3, 0.04


def rz(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def ry(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rigid(rot: np.ndarray, trans: np.ndarray) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = rot, trans
    return out


def map_base(stamp: int) -> np.ndarray:
    """Analytic map <- base_link: translation and yaw linear in time."""
    t = (stamp - T0) / NS_PER_S
    return rigid(rz(YAW0 + YAW_RATE * t), P0 + VEL * t)


BASE_LIDAR = rigid(rz(LIDAR_YAW), LIDAR_T)
BASE_TILTED = rigid(rz(TILT_YAW) @ ry(TILT_PITCH), TILT_T)


def tf(parent: str, child: str, stamp: int, trans, quat) -> NS:
    """A duck-typed geometry_msgs/TransformStamped."""
    return NS(header=NS(stamp=NS(sec=stamp // NS_PER_S, nanosec=stamp % NS_PER_S), frame_id=parent),
              child_frame_id=child,
              transform=NS(translation=NS(x=trans[0], y=trans[1], z=trans[2]),
                           rotation=NS(x=quat[0], y=quat[1], z=quat[2], w=quat[3])))


def tf_of(parent: str, child: str, stamp: int, m: np.ndarray) -> NS:
    return tf(parent, child, stamp, m[:3, 3].tolist(), rotation_quaternion(m[:3, :3]))


def odom_stamp(k: int) -> int:
    return T0 + k * NS_PER_S // RATE_HZ


def scene(**kwargs) -> TransformBuffer:
    buf = TransformBuffer(**kwargs)
    static = NS(transforms=[tf_of("base_link", "lidar", 0, BASE_LIDAR), tf_of("base_link", "tilted", 0, BASE_TILTED)])
    assert buf.add_message(static, static=True) == 2
    for k in range(N_SAMPLES):
        s = odom_stamp(k)
        assert buf.add_message(NS(transforms=[tf_of("map", "base_link", s, map_base(s))]), static=False) == 1
    return buf


BETWEEN = [T0, T0 + 1, T0 + 37_000_000, T0 + 50_000_000, odom_stamp(7) + 12_345_678, odom_stamp(N_SAMPLES - 1)]


@pytest.mark.parametrize("stamp", BETWEEN)
@pytest.mark.parametrize("frame,mount", [("lidar", BASE_LIDAR), ("tilted", BASE_TILTED)])
def test_lookup_matches_the_analytic_scene(stamp, frame, mount):
    buf = scene()
    expected = map_base(stamp) @ mount
    np.testing.assert_allclose(buf.lookup("map", frame, stamp), expected, rtol=0, atol=1e-9)
    np.testing.assert_allclose(buf.lookup("base_link", frame, stamp), mount, rtol=0, atol=1e-12)
    np.testing.assert_allclose(buf.lookup("map", "base_link", stamp), map_base(stamp), rtol=0, atol=1e-9)


@pytest.mark.parametrize("stamp", BETWEEN)
def test_chain_both_ways_are_inverses(stamp):
    buf = scene()
    up, down = buf.lookup("map", "lidar", stamp), buf.lookup("lidar", "map", stamp)
    np.testing.assert_allclose(up @ down, np.eye(4), rtol=0, atol=1e-12)
    np.testing.assert_allclose(down, np.linalg.inv(map_base(stamp) @ BASE_LIDAR), rtol=0, atol=1e-9)
    # sibling frames: through their common parent base_link, not map
    np.testing.assert_allclose(buf.lookup("tilted", "lidar", stamp), np.linalg.inv(BASE_TILTED) @ BASE_LIDAR,
                               rtol=0, atol=1e-12)


def test_identity_for_the_same_frame_even_unknown():
    buf = TransformBuffer()
    np.testing.assert_array_equal(buf.lookup("lidar", "lidar", T0), np.eye(4))
    np.testing.assert_array_equal(buf.lookup("lidar", "/lidar", T0), np.eye(4))


def test_slerp_between_samples_far_apart_in_heading():
    buf = TransformBuffer()
    a, b = 0.2, 0.2 + 2.5   # 2.5 rad between two samples: the true spherical interpolation, not nlerp
    buf.add_message(NS(transforms=[tf_of("odom", "base", T0, rigid(rz(a), np.zeros(3))),
                                   tf_of("odom", "base", T0 + NS_PER_S, rigid(rz(b), np.array([4.0, 0, 0])))]),
                    static=False)
    for f in (0.1, 0.25, 0.5, 0.9):
        m = buf.lookup("odom", "base", T0 + round(f * NS_PER_S))
        np.testing.assert_allclose(m, rigid(rz(a + f * (b - a)), np.array([4.0 * f, 0, 0])), rtol=0, atol=1e-9)


def box_yaw_in(frame_rot: np.ndarray, yaw: float) -> float:
    """Analytic heading of a box of `yaw` after rotation `frame_rot`: its x-axis projected on the new xy plane."""
    h = frame_rot @ np.array([math.cos(yaw), math.sin(yaw), 0.0])
    return math.atan2(h[1], h[0])


def angle_diff(a: float, b: float) -> float:
    return abs((a - b + math.pi) % (2 * math.pi) - math.pi)


@pytest.mark.parametrize("yaw", [0.0, 1.0, -2.5, math.pi - 1e-3, -math.pi + 1e-3])
def test_a_box_in_map_lands_where_the_scene_puts_it_in_lidar(yaw):
    buf = scene()
    stamp = odom_stamp(4) + 61_000_000
    box = Box3D(center=(30.0, -4.0, 0.9), size=(4.5, 1.9, 1.6), yaw=yaw, label="truck", instance_id=17)
    (moved,) = boxes_to_frame([box], "map", "lidar", stamp, buf)
    lidar_map = np.linalg.inv(map_base(stamp) @ BASE_LIDAR)
    expected_center = lidar_map[:3, :3] @ np.array(box.center) + lidar_map[:3, 3]
    assert np.linalg.norm(np.array(moved.center) - expected_center) < 1e-6
    t = (stamp - T0) / NS_PER_S
    assert angle_diff(moved.yaw, yaw - (YAW0 + YAW_RATE * t) - LIDAR_YAW) < 1e-9  # flat mount: yaws subtract
    assert -math.pi <= moved.yaw <= math.pi
    assert (moved.size, moved.label, moved.instance_id) == (box.size, "truck", 17)


def test_a_box_in_map_seen_from_a_pitched_lidar():
    buf = scene()
    stamp = odom_stamp(12) + 3_000_000
    box = Box3D(center=(-12.0, 20.0, 1.0), size=(4.0, 1.8, 1.5), yaw=0.7)
    (moved,) = boxes_to_frame([box], "map", "tilted", stamp, buf)
    tilted_map = np.linalg.inv(map_base(stamp) @ BASE_TILTED)
    expected_center = tilted_map[:3, :3] @ np.array(box.center) + tilted_map[:3, 3]
    assert np.linalg.norm(np.array(moved.center) - expected_center) < 1e-6
    assert angle_diff(moved.yaw, box_yaw_in(tilted_map[:3, :3], 0.7)) < 1e-9
    t = (stamp - T0) / NS_PER_S
    assert angle_diff(moved.yaw, 0.7 - (YAW0 + YAW_RATE * t) - TILT_YAW) < 2e-3  # a 0.04 rad pitch barely turns it


def test_unknown_frame_names_it():
    buf = scene()
    with pytest.raises(TransformError, match=r"'ghost' -> 'map'.*frame 'ghost' is unknown \(known: 'base_link'"):
        buf.lookup("map", "ghost", T0)
    with pytest.raises(TransformError, match="frame 'nowhere' is unknown"):
        buf.lookup("nowhere", "lidar", T0)
    with pytest.raises(TransformError, match="empty frame id"):
        buf.lookup("", "lidar", T0)
    assert issubclass(TransformError, GDCompletionError)


def test_disconnected_trees_name_both_roots():
    buf = scene()
    buf.add_message(NS(transforms=[tf("world", "radar", 0, (1, 2, 3), (0, 0, 0, 1))]), static=True)
    with pytest.raises(TransformError, match=r"'radar' -> 'lidar'.*not connected.*'radar' is in the tree of "
                                             r"'world', 'lidar' in the tree of 'map'"):
        buf.lookup("lidar", "radar", T0)


def test_stamps_outside_the_samples_beyond_the_tolerance_raise_with_the_range():
    buf = scene(extrapolation_s=0.05)
    last = odom_stamp(N_SAMPLES - 1)
    with pytest.raises(TransformError, match=r"'lidar' -> 'map' at .*edge 'map' -> 'base_link'.*into the future: "
                                             r"its samples cover \[1700000000.000, 1700000002.000\] s, the stamp "
                                             r"is 0.060 s after the newest \(tolerance 0.05 s\)"):
        buf.lookup("map", "lidar", last + 60_000_000)
    with pytest.raises(TransformError, match=r"into the past.*0.200 s before the oldest"):
        buf.lookup("lidar", "map", T0 - 200_000_000)
    # within the tolerance: the nearest sample, held
    np.testing.assert_allclose(buf.lookup("map", "base_link", last + 50_000_000), map_base(last), atol=1e-12)
    np.testing.assert_allclose(buf.lookup("map", "base_link", T0 - 40_000_000), map_base(T0), atol=1e-12)
    strict = scene(extrapolation_s=0.0)
    with pytest.raises(TransformError, match="future"):
        strict.lookup("map", "lidar", last + 1)
    # static edges have no time range
    np.testing.assert_allclose(strict.lookup("base_link", "lidar", 0), BASE_LIDAR, atol=1e-12)


def test_pruning_keeps_memory_bounded():
    buf = TransformBuffer(cache_s=10.0)
    for k in range(10_000):   # 100 s at 100 Hz
        s = T0 + k * 10_000_000
        assert buf.add_message(NS(transforms=[tf("odom", "base", s, (k * 0.01, 0, 0), (0, 0, 0, 1))]),
                               static=False) == 1
    assert buf.sample_count("base") == 1001   # the newest and every sample up to 10 s before it
    newest = T0 + 9_999 * 10_000_000
    assert buf.lookup("odom", "base", newest - 10 * NS_PER_S)[0, 3] == pytest.approx(89.99, abs=1e-9)
    with pytest.raises(TransformError, match="past"):
        buf.lookup("odom", "base", newest - 11 * NS_PER_S)
    # a late sample from before the cache is not taken
    assert buf.add_message(NS(transforms=[tf("odom", "base", T0, (0, 0, 0), (0, 0, 0, 1))]), static=False) == 0
    assert buf.counters.too_old == 1 and buf.sample_count() == 1001

    capped = TransformBuffer(cache_s=1000.0, max_samples_per_frame=500)
    for k in range(10_000):
        capped.add_message(NS(transforms=[tf("odom", "base", T0 + k, (0, 0, 0), (0, 0, 0, 1))]), static=False)
    assert capped.sample_count() == 500


def test_malformed_transforms_are_counted_never_raised():
    buf = TransformBuffer(max_frames=3)
    good = tf("map", "odom", T0, (1, 2, 3), (0, 0, 0, 2))   # not unit: normalised
    bad = [
        tf("map", "a", T0, (math.nan, 0, 0), (0, 0, 0, 1)),
        tf("map", "b", T0, (0, 0, 0), (0, 0, math.inf, 1)),
        tf("map", "c", T0, (0, 0, 0), (0, 0, 0, 0)),
        tf("", "d", T0, (0, 0, 0), (0, 0, 0, 1)),
        tf("map", "", T0, (0, 0, 0), (0, 0, 0, 1)),
        tf("map", "map", T0, (0, 0, 0), (0, 0, 0, 1)),
        tf("map", "e", T0, ("x", 0, 0), (0, 0, 0, 1)),
        NS(header=NS(frame_id="map"), child_frame_id="f"),               # no transform
        NS(header=NS(frame_id="map", stamp=None), child_frame_id="g",     # dynamic without a readable stamp
           transform=good.transform),
    ]
    assert buf.add_message(NS(transforms=[good, *bad]), static=False) == 1
    assert buf.counters.malformed == len(bad) and buf.counters.taken == 1
    assert "stamp" in buf.last_problem
    assert buf.add_message(None, static=False) == 0 and buf.add_message(NS(transforms=3), static=True) == 0
    assert buf.counters.malformed == len(bad) + 2
    np.testing.assert_allclose(buf.lookup("map", "odom", T0), rigid(np.eye(3), np.array([1.0, 2, 3])), atol=1e-12)
    # a loop: map would become a child of its own descendant
    assert buf.add_message(NS(transforms=[tf("odom", "map", T0, (0, 0, 0), (0, 0, 0, 1))]), static=True) == 0
    assert buf.counters.loop == 1 and "loop" in buf.last_problem
    # max_frames: odom is one child frame; two more fit, the fourth does not
    msg = NS(transforms=[tf("odom", f"f{i}", 0, (0, 0, 0), (0, 0, 0, 1)) for i in range(3)])
    assert buf.add_message(msg, static=True) == 2
    assert buf.counters.too_many_frames == 1 and "f2" in buf.last_problem
    assert buf.counters.as_dict() == {"taken": 3, "malformed": len(bad) + 2, "loop": 1, "too_old": 0,
                                      "too_many_frames": 1, "reparented": 0, "kind_changed": 0}


def test_static_updates_replace_and_reparent():
    buf = TransformBuffer()
    buf.add_message(NS(transforms=[tf("base_link", "lidar", 0, (1, 0, 0), (0, 0, 0, 1))]), static=True)
    buf.add_message(NS(transforms=[tf("base_link", "lidar", 0, (2, 0, 0), (0, 0, 0, 1))]), static=True)
    assert buf.lookup("base_link", "lidar", 123)[0, 3] == 2.0 and buf.sample_count() == 1
    # a new parent replaces the old edge: base_link is no longer known
    buf.add_message(NS(transforms=[tf("/chassis", "/lidar", 0, (0, 3, 0), (0, 0, 0, 1))]), static=True)
    assert buf.counters.reparented == 1
    assert buf.lookup("chassis", "lidar", 0)[1, 3] == 3.0
    assert buf.frames() == {"chassis", "lidar"}
    with pytest.raises(TransformError, match="'base_link' is unknown"):
        buf.lookup("base_link", "lidar", 0)
    # a dynamic message for a static frame: the latest kind wins
    buf.add_message(NS(transforms=[tf("chassis", "lidar", T0, (0, 4, 0), (0, 0, 0, 1))]), static=False)
    assert buf.counters.kind_changed == 1
    assert buf.lookup("chassis", "lidar", T0)[1, 3] == 4.0
    with pytest.raises(TransformError, match="future"):
        buf.lookup("chassis", "lidar", T0 + NS_PER_S)
    buf.clear()
    assert buf.frames() == set() and buf.counters.taken == 4


def test_out_of_order_samples_are_sorted():
    stamps = [odom_stamp(k) for k in range(N_SAMPLES)]
    random.Random(3).shuffle(stamps)
    buf = TransformBuffer()
    buf.add_message(NS(transforms=[tf_of("base_link", "lidar", 0, BASE_LIDAR)]), static=True)
    # a wrong sample first, then the right one with the same stamp replaces it
    buf.add_message(NS(transforms=[tf("map", "base_link", stamps[0], (9, 9, 9), (0, 0, 0, 1))]), static=False)
    buf.add_message(NS(transforms=[tf_of("map", "base_link", s, map_base(s)) for s in stamps]), static=False)
    assert buf.sample_count("base_link") == N_SAMPLES
    for stamp in BETWEEN:
        np.testing.assert_allclose(buf.lookup("map", "lidar", stamp), map_base(stamp) @ BASE_LIDAR, atol=1e-9)


def test_messages_deserialised_by_rosbags():
    from rosbags.typesys import Stores, get_typestore
    ts = get_typestore(Stores.ROS2_JAZZY)
    t = ts.types
    TFMessage, TransformStamped = t["tf2_msgs/msg/TFMessage"], t["geometry_msgs/msg/TransformStamped"]
    Header, Time = t["std_msgs/msg/Header"], t["builtin_interfaces/msg/Time"]
    Transform, Vector3, Quaternion = (t["geometry_msgs/msg/Transform"], t["geometry_msgs/msg/Vector3"],
                                      t["geometry_msgs/msg/Quaternion"])

    def stamped(parent: str, child: str, stamp: int, m: np.ndarray):
        q = rotation_quaternion(m[:3, :3])
        return TransformStamped(
            header=Header(stamp=Time(sec=stamp // NS_PER_S, nanosec=stamp % NS_PER_S), frame_id=parent),
            child_frame_id=child,
            transform=Transform(translation=Vector3(*m[:3, 3].tolist()), rotation=Quaternion(*q)))

    def round_trip(msg):
        raw = ts.serialize_cdr(msg, TFMessage.__msgtype__)
        return ts.deserialize_cdr(raw, TFMessage.__msgtype__)

    buf = TransformBuffer()
    static = round_trip(TFMessage(transforms=[stamped("base_link", "lidar", 0, BASE_LIDAR)]))
    assert buf.add_message(static, static=True) == 1
    dynamic = round_trip(TFMessage(transforms=[stamped("map", "base_link", odom_stamp(k), map_base(odom_stamp(k)))
                                               for k in range(N_SAMPLES)]))
    assert buf.add_message(dynamic, static=False) == N_SAMPLES
    stamp = odom_stamp(9) + 42_000_000
    np.testing.assert_allclose(buf.lookup("map", "lidar", stamp), map_base(stamp) @ BASE_LIDAR, atol=1e-9)


def test_transform_boxes_moves_centres_and_headings():
    boxes = [Box3D((1.0, 0.0, 0.0), (4, 2, 1.5), 0.0, "car", 1), Box3D((0.0, 2.0, 1.0), (5, 2, 2), 1.0, "van", 2)]
    moved = transform_boxes(boxes, rigid(rz(math.pi / 2), np.array([10.0, 0.0, -1.0])))
    assert moved[0].center == pytest.approx((10.0, 1.0, -1.0), abs=1e-12)
    assert moved[1].center == pytest.approx((8.0, 0.0, 0.0), abs=1e-12)
    assert [b.yaw for b in moved] == pytest.approx([math.pi / 2, 1.0 + math.pi / 2], abs=1e-12)
    assert [(b.size, b.label, b.instance_id) for b in moved] == [((4, 2, 1.5), "car", 1), ((5, 2, 2), "van", 2)]
    assert transform_boxes([], np.eye(4)) == []
    with pytest.raises(TransformError, match="finite 4x4"):
        transform_boxes(boxes, np.eye(3))
    with pytest.raises(TransformError, match="finite 4x4"):
        transform_boxes(boxes, np.full((4, 4), np.nan))


class CountingBuffer(TransformBuffer):
    """The real buffer, counting its lookups."""

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.lookups: list[tuple[str, str]] = []

    def lookup(self, target_frame, source_frame, stamp_ns, wait_s=0.0):
        self.lookups.append((target_frame, source_frame))
        return super().lookup(target_frame, source_frame, stamp_ns, wait_s)


def test_boxes_in_frame_transforms_per_frame_and_counts_the_rest():
    stamp = odom_stamp(5) + 20_000_000
    boxes = tuple(Box3D((float(i), 2.0 * i, 0.5), (4.0, 1.8, 1.5), 0.1 * i, "car", i) for i in range(6))
    frames = ("lidar", "map", "radar", "map", "lidar", "map")
    box_set = BoxSet(stamp, boxes, frames)

    assert boxes_in_frame(box_set, "lidar", stamp, None) == box_set.split_by_frame("lidar")
    assert boxes_in_frame(box_set, "lidar", stamp, None) == ([boxes[0], boxes[4]], 4)

    buf = CountingBuffer()
    for msg in (NS(transforms=[tf_of("base_link", "lidar", 0, BASE_LIDAR)]),):
        buf.add_message(msg, static=True)
    for k in range(N_SAMPLES):
        buf.add_message(NS(transforms=[tf_of("map", "base_link", odom_stamp(k), map_base(odom_stamp(k)))]),
                        static=False)
    problems: list[str] = []
    kept, missing = boxes_in_frame(box_set, "lidar", stamp, buf, problems)
    assert missing == 1 and len(problems) == 1 and "'radar' -> 'lidar'" in problems[0]
    assert sorted(buf.lookups) == [("lidar", "map"), ("lidar", "radar")]   # once per frame, not per box
    assert [b.instance_id for b in kept] == [0, 1, 3, 4, 5]                # input order
    assert kept[0] is boxes[0] and kept[3] is boxes[4]                      # already in the frame: untouched
    lidar_map = np.linalg.inv(map_base(stamp) @ BASE_LIDAR)
    for b in (kept[1], kept[2], kept[4]):
        src = boxes[b.instance_id]
        assert np.linalg.norm(np.array(b.center) - (lidar_map[:3, :3] @ src.center + lidar_map[:3, 3])) < 1e-6
        assert angle_diff(b.yaw, box_yaw_in(lidar_map[:3, :3], src.yaw)) < 1e-9

    # a stamp the buffer cannot reach: every box in another frame counted
    far = boxes_in_frame(box_set, "lidar", stamp + 60 * NS_PER_S, buf)
    assert far == ([boxes[0], boxes[4]], 4)
    assert boxes_in_frame(BoxSet(None, (), ()), "lidar", stamp, buf) == ([], 0)


def test_bad_parameters_raise():
    for kwargs in ({"cache_s": -1.0}, {"cache_s": math.nan}, {"extrapolation_s": math.inf}, {"max_frames": 0},
                   {"max_samples_per_frame": 0}):
        with pytest.raises(ValueError):
            TransformBuffer(**kwargs)
    with pytest.raises(TransformError, match="not integer nanoseconds"):
        scene().lookup("map", "lidar", "soon")


def test_a_lookup_waits_for_a_transform_still_to_come():
    """A stamp past the newest sample (the transform lags the cloud, as tf often does): with a wait, the lookup takes
    the sample that arrives meanwhile and interpolates, instead of holding the older one; a stamp older than the
    samples is no reason to wait (waiting cannot mend it) and fails as without one."""
    import threading

    from gd_completion.transforms import TransformNotYet

    buf = scene(extrapolation_s=0.05)
    last = odom_stamp(N_SAMPLES - 1)
    stamp = last + 40_000_000                       # within the tolerance: without a wait, the held sample
    np.testing.assert_allclose(buf.lookup("map", "base_link", stamp), map_base(last), atol=1e-12)
    arrived = threading.Event()

    def late_odometry() -> None:
        arrived.wait(5.0)
        nxt = odom_stamp(N_SAMPLES)
        buf.add_message(NS(transforms=[tf_of("map", "base_link", nxt, map_base(nxt))]), static=False)

    feeder = threading.Thread(target=late_odometry)
    feeder.start()
    arrived.set()
    waited = buf.lookup("map", "base_link", stamp, wait_s=30.0)
    feeder.join()
    np.testing.assert_allclose(waited, map_base(stamp), atol=1e-9)   # interpolated with the late sample
    with pytest.raises(TransformNotYet):             # nothing comes: after the wait, beyond the tolerance
        buf.lookup("map", "base_link", odom_stamp(N_SAMPLES) + 60_000_000, wait_s=0.05)
    with pytest.raises(TransformError) as past:
        buf.lookup("map", "base_link", T0 - 200_000_000, wait_s=30.0)
    assert not isinstance(past.value, TransformNotYet) and "into the past" in str(past.value)

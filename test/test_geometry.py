"""Box geometry: validation, cropping against a per-point reference, normalisation."""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from gd_completion.errors import BoxError
from gd_completion.geometry import (
    Box3D,
    box_corners,
    box_problem,
    boxes_to_array,
    crop_boxes,
    denormalize,
    finite_mask,
    normalize,
)


def reference_inside(point, box: Box3D, margin: float) -> bool:
    """Per-point reference: express the point in the box frame with plain math and compare half sizes."""
    x, y, z = (float(v) - c for v, c in zip(point, box.center))
    if not all(math.isfinite(v) for v in (x, y, z)):
        return False
    # Rotate by -yaw.
    lx = math.cos(box.yaw) * x + math.sin(box.yaw) * y
    ly = -math.sin(box.yaw) * x + math.cos(box.yaw) * y
    hl, hw, hh = (s / 2 + margin for s in box.size)
    return abs(lx) <= hl and abs(ly) <= hw and abs(z) <= hh


def reference_crop(points: np.ndarray, boxes: list[Box3D], margin: float) -> list[np.ndarray]:
    return [np.array([i for i, p in enumerate(points) if reference_inside(p, b, margin)], dtype=np.intp)
            for b in boxes]


def random_scene(seed: int, n_points: int = 4000, n_boxes: int = 8):
    rng = np.random.default_rng(seed)
    boxes = [Box3D(center=tuple(rng.uniform([-15, -15, -1], [15, 15, 1])),
                   size=tuple(rng.uniform([2.0, 1.0, 1.0], [6.0, 2.5, 2.5])),
                   yaw=float(rng.uniform(-2 * np.pi, 2 * np.pi)), instance_id=i) for i in range(n_boxes)]
    # Background points plus dense points around every box, some boxes overlapping.
    pts = [rng.uniform([-20, -20, -2], [20, 20, 2], size=(n_points // 2, 3))]
    for b in boxes:
        pts.append(np.asarray(b.center) + rng.normal(scale=[b.size[0] / 2, b.size[0] / 2, b.size[2] / 2],
                                                     size=(n_points // (2 * n_boxes), 3)))
    points = np.concatenate(pts).astype(np.float32)
    points[rng.choice(len(points), 10, replace=False)] = np.nan
    return points, boxes


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("margin", [0.0, 0.3, -0.2])
def test_crop_matches_per_point_reference(seed: int, margin: float) -> None:
    points, boxes = random_scene(seed)
    if seed == 0:
        boxes.append(dataclasses.replace(boxes[0], yaw=boxes[0].yaw + 0.3, instance_id=99))  # overlapping box
    got = crop_boxes(points, boxes, margin)
    want = reference_crop(points, boxes, margin)
    assert len(got) == len(boxes)
    for g, w in zip(got, want):
        assert g.dtype == np.intp
        np.testing.assert_array_equal(g, w)
    assert sum(len(g) for g in got) > 100  # the scene really puts points in the boxes


def test_points_exactly_on_faces_are_inside() -> None:
    box = Box3D(center=(1.0, 2.0, 3.0), size=(4.0, 2.0, 1.0), yaw=0.0)
    on_faces = np.array([[3, 2, 3], [-1, 2, 3], [1, 3, 3], [1, 1, 3], [1, 2, 3.5], [1, 2, 2.5], [3, 3, 3.5]],
                        dtype=np.float32)
    just_out = on_faces.copy()
    just_out[0, 0] = np.nextafter(np.float32(3), np.float32(4))
    just_out[1, 0] = np.nextafter(np.float32(-1), np.float32(-2))
    just_out[2, 1] = np.nextafter(np.float32(3), np.float32(4))
    just_out[3, 1] = np.nextafter(np.float32(1), np.float32(0))
    just_out[4, 2] = np.nextafter(np.float32(3.5), np.float32(4))
    just_out[5, 2] = np.nextafter(np.float32(2.5), np.float32(2))
    just_out[6, :] = [3.0001, 3, 3.5]
    (idx,) = crop_boxes(np.concatenate([on_faces, just_out]), [box])
    np.testing.assert_array_equal(idx, np.arange(7))
    # With a margin the faces move out by exactly that much.
    grown = on_faces + np.array([0.5, 0.5, 0.5], dtype=np.float32) * np.sign(on_faces - np.float32([1, 2, 3]))
    (idx,) = crop_boxes(grown, [box], margin=0.5)
    np.testing.assert_array_equal(idx, np.arange(7))
    (idx,) = crop_boxes(grown, [box], margin=0.25)
    assert idx.size == 0


def test_rotated_box_uses_heading_for_length() -> None:
    box = Box3D(center=(10.0, 0.0, 0.0), size=(4.0, 2.0, 2.0), yaw=math.pi / 2)  # length along +y
    pts = np.array([[10, 1.9, 0], [10, -1.9, 0], [10.9, 0, 0], [11.5, 0, 0], [10, 2.2, 0], [10, 0, 1.1]],
                   dtype=np.float32)
    (idx,) = crop_boxes(pts, [box])
    np.testing.assert_array_equal(idx, [0, 1, 2])
    box45 = Box3D(center=(0.0, 0.0, 0.0), size=(4.0, 1.0, 2.0), yaw=math.pi / 4)
    pts = np.array([[1.3, 1.3, 0], [1.3, -1.3, 0], [0.3, -0.3, 0], [-1.4, -1.4, 0.9]], dtype=np.float32)
    (idx,) = crop_boxes(pts, [box45])
    np.testing.assert_array_equal(idx, [0, 2, 3])


def test_crop_edge_cases() -> None:
    points, boxes = random_scene(1, n_points=200)
    assert crop_boxes(points, []) == []
    empty = crop_boxes(np.empty((0, 3), np.float32), boxes)
    assert len(empty) == len(boxes) and all(e.size == 0 for e in empty)
    far = Box3D(center=(1e4, -1e4, 0), size=(1, 1, 1))
    tiny = Box3D(center=(0.0, 0.0, 0.0), size=(1e-3, 1e-3, 1e-3))
    pts = np.array([[1e4, -1e4, 0], [0, 0, 0], [1e4 + 0.6, -1e4, 0], [np.nan, 0, 0], [np.inf, -np.inf, 0]],
                   dtype=np.float32)
    res = crop_boxes(pts, [far, tiny])
    np.testing.assert_array_equal(res[0], [0])
    np.testing.assert_array_equal(res[1], [1])
    # A negative margin that swallows the box leaves it empty.
    assert crop_boxes(pts, [tiny], margin=-0.01)[0].size == 0
    # float64 input works the same.
    np.testing.assert_array_equal(crop_boxes(pts.astype(np.float64), [far])[0], [0])


def test_crop_many_boxes_spread_wide_matches_reference() -> None:
    """Boxes hundreds of metres apart force a coarse prefilter grid; results must not change."""
    rng = np.random.default_rng(7)
    boxes = [Box3D(center=(float(x), float(y), 0.0), size=(4.5, 1.9, 1.6), yaw=float(rng.uniform(0, 7)))
             for x, y in rng.uniform(-3000, 3000, size=(12, 2))]
    pts = np.concatenate([np.asarray(b.center) + rng.uniform(-3, 3, size=(150, 3)) for b in boxes]).astype(np.float32)
    for g, w in zip(crop_boxes(pts, boxes, 0.1), reference_crop(pts, boxes, 0.1)):
        np.testing.assert_array_equal(g, w)


def test_crop_rejects_bad_input() -> None:
    pts = np.zeros((3, 3), np.float32)
    with pytest.raises(BoxError, match=r"box 1 \(car, instance 5\) is unusable: non-positive size"):
        crop_boxes(pts, [Box3D((0, 0, 0), (1, 1, 1)), Box3D((0, 0, 0), (1, 0, 1), instance_id=5)])
    with pytest.raises(BoxError, match="margin must be finite"):
        crop_boxes(pts, [Box3D((0, 0, 0), (1, 1, 1))], margin=float("nan"))
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        crop_boxes(np.zeros((3, 2)), [Box3D((0, 0, 0), (1, 1, 1))])


# --- boxes ---------------------------------------------------------------------------------------

@pytest.mark.parametrize("kwargs, reason", [
    (dict(center=(0, 0, float("nan")), size=(4, 2, 1.5)), "non-finite centre"),
    (dict(center=(0, float("inf"), 0), size=(4, 2, 1.5)), "non-finite centre"),
    (dict(center=(0, 0, 0), size=(4, float("nan"), 1.5)), "non-finite size"),
    (dict(center=(0, 0, 0), size=(4, 2, 1.5), yaw=float("inf")), "non-finite yaw"),
    (dict(center=(0, 0, 0), size=(0, 2, 1.5)), "non-positive size"),
    (dict(center=(0, 0, 0), size=(4, 2, -1.5)), "non-positive size"),
    (dict(center=(0, 0, 0), size=(4, 2, 1.5), yaw=12.0), None),
])
def test_box_problem(kwargs: dict, reason: str | None) -> None:
    problem = box_problem(Box3D(**kwargs))
    if reason is None:
        assert problem is None
    else:
        assert problem is not None and problem.startswith(reason)


def test_box3d_coerces_and_is_frozen() -> None:
    b = Box3D(center=np.array([1, 2, 3]), size=[4, 2, 1.5], yaw=np.float32(0.5), label="truck", instance_id=np.int64(3))
    assert b.center == (1.0, 2.0, 3.0) and isinstance(b.center[0], float)
    assert b.size == (4.0, 2.0, 1.5) and b.yaw == 0.5 and b.instance_id == 3 and b.label == "truck"
    assert hash(b) == hash(Box3D((1, 2, 3), (4, 2, 1.5), 0.5, "truck", 3))
    with pytest.raises(dataclasses.FrozenInstanceError):
        b.yaw = 1.0  # type: ignore[misc]
    with pytest.raises(BoxError, match="center must be three numbers"):
        Box3D(center=(1, 2), size=(1, 1, 1))


def test_boxes_to_array() -> None:
    arr = boxes_to_array([Box3D((1, 2, 3), (4, 5, 6), 0.7), Box3D((-1, 0, 0), (1, 1, 1), -3.0)])
    assert arr.dtype == np.float64
    np.testing.assert_array_equal(arr, [[1, 2, 3, 4, 5, 6, 0.7], [-1, 0, 0, 1, 1, 1, -3.0]])
    assert boxes_to_array([]).shape == (0, 7)


def test_box_corners() -> None:
    box = Box3D(center=(10.0, 5.0, 1.0), size=(4.0, 2.0, 1.0), yaw=math.pi / 2)
    corners = box_corners(box)
    assert corners.shape == (8, 3)
    # Front-left bottom: local (+2, +1, -0.5) rotated by 90 deg -> (-1, +2, -0.5).
    np.testing.assert_allclose(corners[0], [9.0, 7.0, 0.5], atol=1e-12)
    np.testing.assert_allclose(corners[6], [11.0, 3.0, 1.5], atol=1e-12)
    np.testing.assert_allclose(corners.mean(axis=0), box.center, atol=1e-12)
    # Every corner is on the box surface: normalised |x| = 0.5.
    np.testing.assert_allclose(np.abs(normalize(corners, box)[:, 0]), 0.5, atol=1e-6)
    np.testing.assert_array_equal(crop_boxes(corners, [box], margin=1e-6)[0], np.arange(8))
    assert crop_boxes(np.asarray(box.center) + 1.01 * (corners - box.center), [box], margin=1e-6)[0].size == 0


# --- normalisation -------------------------------------------------------------------------------

def test_normalize_known_values() -> None:
    yaw = 0.6
    box = Box3D(center=(12.0, -4.0, 0.5), size=(4.5, 1.8, 1.6), yaw=yaw)
    heading, left = np.array([math.cos(yaw), math.sin(yaw), 0]), np.array([-math.sin(yaw), math.cos(yaw), 0])
    c = np.array(box.center)
    pts = np.stack([c + 2.25 * heading,              # front centre
                    c - 2.25 * heading,              # rear centre
                    c + 0.9 * left,                  # left side centre
                    c + np.array([0, 0, 0.8]),       # roof centre
                    c])
    out = normalize(pts, box)
    assert out.dtype == np.float32 and out.shape == (5, 3)
    np.testing.assert_allclose(out, [[0.5, 0, 0], [-0.5, 0, 0], [0, 0.2, 0], [0, 0, 0.8 / 4.5], [0, 0, 0]],
                               atol=1e-6)


@pytest.mark.parametrize("seed", range(5))
def test_denormalize_is_exact_inverse(seed: int) -> None:
    rng = np.random.default_rng(seed)
    box = Box3D(center=tuple(rng.uniform(-60, 60, 3)), size=tuple(rng.uniform(1, 8, 3)), yaw=float(rng.uniform(-7, 7)))
    pts = (np.asarray(box.center) + rng.normal(scale=3, size=(500, 3))).astype(np.float32)
    back = denormalize(normalize(pts, box), box)
    assert back.dtype == np.float32
    scale = np.abs(pts).max()
    np.testing.assert_allclose(back, pts, rtol=0, atol=4 * np.finfo(np.float32).eps * scale)
    unit = rng.uniform(-0.6, 0.6, size=(100, 3)).astype(np.float32)
    np.testing.assert_allclose(normalize(denormalize(unit, box), box), unit, rtol=0,
                               atol=4 * np.finfo(np.float32).eps * scale / box.size[0])


def test_normalize_refuses_bad_box_and_keeps_empty() -> None:
    with pytest.raises(BoxError, match="non-positive size"):
        normalize(np.zeros((2, 3)), Box3D((0, 0, 0), (0, 1, 1)))
    with pytest.raises(BoxError, match="non-finite yaw"):
        denormalize(np.zeros((2, 3)), Box3D((0, 0, 0), (1, 1, 1), yaw=float("nan")))
    assert normalize(np.empty((0, 3)), Box3D((0, 0, 0), (1, 1, 1))).shape == (0, 3)


def test_finite_mask() -> None:
    pts = np.array([[0, 0, 0], [np.nan, 0, 0], [0, np.inf, 0], [0, 0, -np.inf], [1e30, -1e30, 5]], np.float32)
    np.testing.assert_array_equal(finite_mask(pts), [True, False, False, False, True])
    assert finite_mask(np.empty((0, 3))).shape == (0,)

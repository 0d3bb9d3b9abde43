"""Built-in demo drive: a simulated lidar moving down a street of parked and moving procedural vehicles."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gd_completion.geometry import Box3D
from gd_completion.synth.beams import BeamPattern
from gd_completion.synth.lidar import scan_meshes
from gd_completion.synth.meshio import Mesh, box_mesh, merge_meshes
from gd_completion.synth.vehicles import BASE_KINDS, generate_vehicle, vehicle_label

__all__ = ["SyntheticFrame", "synthetic_drive", "SENSOR_HEIGHT", "FRAME_PERIOD_NS"]

SENSOR_HEIGHT = 1.8          # metres above the ground; the sensor frame has the ground at z = -SENSOR_HEIGHT
FRAME_PERIOD_NS = 100_000_000  # 10 Hz
EGO_SPEED = 10.0             # m/s along +x
START_STAMP_NS = 1_700_000_000_000_000_000

_KIND_WEIGHTS = np.array([0.25, 0.15, 0.2, 0.1, 0.12, 0.1, 0.08])  # order of BASE_KINDS
# Lanes (y of the lane centre, metres; the ego drives in lane 0 towards +x, right-hand traffic).
_PARK_RIGHT, _ONCOMING, _PARK_LEFT = -3.3, 3.5, 6.8


@dataclass
class SyntheticFrame:
    """One lidar revolution in the sensor frame: points (N,3) float32, intensity (N,) float32 in [0,1],
    vehicle boxes (sensor frame, stable instance ids) and the stamp in nanoseconds."""

    points: np.ndarray
    intensity: np.ndarray
    boxes: list[Box3D]
    stamp_ns: int


@dataclass
class _Actor:
    mesh: Mesh
    kind: str
    x0: float
    y: float
    yaw: float
    speed: float      # along the heading, m/s
    reflectivity: float

    def x(self, t: float) -> float:
        return self.x0 + np.cos(self.yaw) * self.speed * t


def _overlaps(a: _Actor, b: _Actor, times: np.ndarray) -> bool:
    la, wa = a.mesh.extent[:2]
    lb, wb = b.mesh.extent[:2]
    if abs(a.y - b.y) > (wa + wb) / 2 + 0.3:
        return False
    dx = np.abs(np.array([a.x(t) - b.x(t) for t in times]))
    return bool(np.any(dx < (la + lb) / 2 + 1.0))


def _place_actor(rng: np.random.Generator, times: np.ndarray) -> _Actor:
    kind = BASE_KINDS[int(rng.choice(len(BASE_KINDS), p=_KIND_WEIGHTS / _KIND_WEIGHTS.sum()))]
    mesh = generate_vehicle(rng, kind)
    refl = float(rng.uniform(0.25, 0.9))
    role = rng.choice(["park_right", "park_left", "ahead", "oncoming"], p=[0.4, 0.25, 0.15, 0.2])
    if role == "ahead":
        return _Actor(mesh, kind, float(rng.uniform(10, 35)), float(rng.normal(0, 0.15)),
                      float(rng.normal(0, 0.02)), float(rng.uniform(EGO_SPEED - 0.5, EGO_SPEED + 3)), refl)
    if role == "oncoming":
        return _Actor(mesh, kind, float(rng.uniform(15, 45)), _ONCOMING + float(rng.normal(0, 0.15)),
                      float(np.pi + rng.normal(0, 0.02)), float(rng.uniform(7, 13)), refl)
    y = _PARK_RIGHT if role == "park_right" else _PARK_LEFT
    y += (1 if role == "park_left" else -1) * (mesh.extent[1] / 2 - 0.9) + float(rng.normal(0, 0.1))
    yaw = (0.0 if rng.random() < 0.75 else np.pi) + float(rng.normal(0, 0.04))
    return _Actor(mesh, kind, float(rng.uniform(-15, 40)), y, yaw, 0.0, refl)


def _buildings(rng: np.random.Generator, x_from: float, x_to: float) -> Mesh:
    """Facades along both kerbs with gaps (static clutter that occludes and is occluded)."""
    parts = []
    for side in (-1.0, 1.0):
        x = x_from
        while x < x_to:
            length = rng.uniform(8, 25)
            if rng.random() < 0.8:
                size = np.array([length, rng.uniform(6, 12), rng.uniform(4, 15)])
                y = (_PARK_RIGHT - 5.0 if side < 0 else _PARK_LEFT + 5.0) + side * size[1] / 2
                parts.append(box_mesh(size, (x + length / 2, y, size[2] / 2)))  # standing on z = 0
            x += length + rng.uniform(1, 8)
    return merge_meshes(parts)


def synthetic_drive(seed: int = 0, n_frames: int = 10, n_vehicles: int = 6,
                    pattern: str | BeamPattern = "hdl64e") -> list[SyntheticFrame]:
    """A short deterministic drive at 10 Hz: the sensor, 1.8 m above the road, moves at 10 m/s past parked,
    leading and oncoming vehicles 5-40 m away; frames hold points and boxes in the sensor frame."""
    if isinstance(pattern, str):
        pattern = BeamPattern.named(pattern)
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x5CE7E]))
    times = np.arange(n_frames) * FRAME_PERIOD_NS * 1e-9
    actors: list[_Actor] = []
    for _ in range(200 * max(n_vehicles, 1)):
        if len(actors) >= n_vehicles:
            break
        a = _place_actor(rng, times)
        dist0 = np.hypot(a.x(0.0), a.y)
        if 5.0 <= dist0 <= 40.0 and not any(_overlaps(a, b, times) for b in actors):
            actors.append(a)
    span = EGO_SPEED * times[-1] if n_frames else 0.0
    static = _buildings(rng, -60.0, span + 80.0)
    frames = []
    for k, t in enumerate(times):
        ego = np.array([EGO_SPEED * t, 0.0, SENSOR_HEIGHT])
        meshes, boxes = [], []
        for i, a in enumerate(actors):
            ext = a.mesh.extent
            centre = np.array([a.x(t), a.y, ext[2] / 2]) - ego
            meshes.append(a.mesh.transformed(a.yaw, centre))
            yaw = float((a.yaw + np.pi) % (2 * np.pi) - np.pi)
            boxes.append(Box3D(center=tuple(float(c) for c in centre), size=tuple(float(s) for s in ext),
                               yaw=yaw, label=vehicle_label(a.kind), instance_id=i + 1))
        meshes.append(Mesh(static.vertices - ego, static.faces))
        scan = scan_meshes(meshes, np.zeros(3), pattern, np.random.default_rng([int(seed), k, 0x5CA7]),
                           ground_z=-SENSOR_HEIGHT, max_range=120.0,
                           reflectivity=np.array([a.reflectivity for a in actors] + [0.4]))
        frames.append(SyntheticFrame(scan.points, scan.intensity, boxes, START_STAMP_NS + k * FRAME_PERIOD_NS))
    return frames

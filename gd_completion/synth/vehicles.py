"""Procedural vehicle meshes: lofted body profile, greenhouse, wheel arches, wheels and mirrors."""
from __future__ import annotations

import numpy as np

from gd_completion.synth.meshio import Mesh, box_mesh, load_mesh, load_mesh_folder, merge_meshes, sample_surface

__all__ = [
    "BASE_KINDS", "VEHICLE_KINDS", "KIND_SIZE_RANGES", "WIDE_SIZE_SPREAD", "size_range", "Mesh", "generate_vehicle",
    "vehicle_label", "perturb_mesh",
    "fit_to_size", "load_mesh", "load_mesh_folder", "sample_surface",
]

#: The kinds of generator version 1 (drawn by `synth.dataset` and the demo drive unless told otherwise).
BASE_KINDS = ("sedan", "hatchback", "suv", "pickup", "van", "box_truck", "bus")
#: Every procedural kind: BASE_KINDS and the composite kinds built from boxes, wheels and lofted bodies.
VEHICLE_KINDS = BASE_KINDS + ("construction", "semi_trailer", "pickup_load", "trailer")
#: Default of `generate_vehicle`'s `size_spread` in wide presets: every size range widened by 15 % each way.
WIDE_SIZE_SPREAD = 0.15

#: (length, width, height) ranges in metres, bounding box including wheels and mirrors.
KIND_SIZE_RANGES: dict[str, tuple[tuple[float, float], tuple[float, float], tuple[float, float]]] = {
    "sedan": ((4.3, 4.9), (1.75, 1.9), (1.4, 1.5)),
    "hatchback": ((3.7, 4.35), (1.65, 1.82), (1.42, 1.55)),
    "suv": ((4.4, 5.0), (1.8, 2.0), (1.62, 1.85)),
    "pickup": ((5.2, 5.9), (1.85, 2.05), (1.75, 1.95)),
    "van": ((4.8, 6.0), (1.9, 2.1), (1.9, 2.6)),
    "box_truck": ((6.0, 9.0), (2.3, 2.5), (2.8, 3.5)),
    "bus": ((10.0, 12.5), (2.45, 2.55), (2.9, 3.3)),
    "construction": ((5.0, 9.0), (2.3, 2.8), (2.8, 3.6)),
    "semi_trailer": ((12.0, 17.0), (2.45, 2.6), (3.0, 4.1)),
    "pickup_load": ((5.2, 5.9), (1.85, 2.05), (1.75, 2.9)),
    "trailer": ((3.0, 8.0), (1.8, 2.55), (0.9, 3.2)),
}

_LABELS = {"sedan": "car", "hatchback": "car", "suv": "car", "pickup": "car", "van": "van",
           "box_truck": "truck", "bus": "truck", "construction": "truck", "semi_trailer": "truck", "pickup_load": "car",
           "trailer": "truck"}

# Side profile per kind: top outline as (fraction of length from the rear, fraction of height),
# body bottom (fraction of height), wheel radius (fraction of height), axle positions (fraction of length),
# belt line (fraction of height, greenhouse starts above it), greenhouse tumblehome, cross-section squareness,
# index of the top-outline point where the windscreen starts (mirror position).
_PROFILES: dict[str, dict] = {
    "sedan": dict(top=[(0.0, 0.46), (0.01, 0.64), (0.05, 0.69), (0.22, 0.71), (0.36, 1.0), (0.58, 1.0),
                       (0.75, 0.70), (0.96, 0.62), (1.0, 0.48)],
                  bottom=0.12, wheel=0.22, axles=(0.2, 0.79), belt=0.66, tumble=0.22, square=5.0, mirror=6),
    "hatchback": dict(top=[(0.0, 0.45), (0.01, 0.80), (0.06, 0.97), (0.16, 1.0), (0.6, 1.0),
                           (0.76, 0.68), (0.96, 0.6), (1.0, 0.46)],
                      bottom=0.11, wheel=0.21, axles=(0.17, 0.82), belt=0.62, tumble=0.2, square=5.0, mirror=5),
    "suv": dict(top=[(0.0, 0.45), (0.01, 0.86), (0.05, 0.98), (0.1, 1.0), (0.64, 1.0), (0.77, 0.69),
                     (0.96, 0.63), (1.0, 0.48)],
                bottom=0.14, wheel=0.23, axles=(0.17, 0.81), belt=0.63, tumble=0.16, square=6.0, mirror=5),
    "pickup": dict(top=[(0.0, 0.40), (0.01, 0.58), (0.41, 0.58), (0.43, 0.99), (0.46, 1.0), (0.63, 1.0),
                        (0.74, 0.68), (0.96, 0.63), (1.0, 0.48)],
                   bottom=0.15, wheel=0.21, axles=(0.16, 0.8), belt=0.6, tumble=0.14, square=6.0, mirror=6),
    "van": dict(top=[(0.0, 0.3), (0.01, 0.96), (0.03, 1.0), (0.7, 1.0), (0.86, 0.58), (0.97, 0.48),
                     (1.0, 0.38)],
                bottom=0.1, wheel=0.16, axles=(0.18, 0.83), belt=0.5, tumble=0.08, square=7.0, mirror=4),
    "box_truck": dict(top=[(0.0, 0.3), (0.005, 1.0), (0.7, 1.0), (0.715, 0.8), (0.86, 0.8), (0.94, 0.5),
                           (1.0, 0.42)],
                      bottom=0.22, wheel=0.15, axles=(0.2, 0.86), belt=0.45, tumble=0.04, square=12.0, mirror=4),
    "bus": dict(top=[(0.0, 0.3), (0.005, 0.97), (0.02, 1.0), (0.985, 1.0), (1.0, 0.95), (1.0, 0.3)],
                bottom=0.1, wheel=0.15, axles=(0.22, 0.84), belt=0.35, tumble=0.03, square=12.0, mirror=3),
}


def vehicle_label(kind: str) -> str:
    """Detection label of a procedural kind: "car", "van" or "truck"."""
    try:
        return _LABELS[kind]
    except KeyError as exc:
        raise ValueError(f"unknown vehicle kind {kind!r}; expected one of {VEHICLE_KINDS}") from exc


def _tube_faces(n_st: int, n_loop: int) -> np.ndarray:
    """Triangles joining consecutive closed loops of `n_loop` vertices over `n_st` stations."""
    i, j = np.meshgrid(np.arange(n_st - 1), np.arange(n_loop), indexing="ij")
    a = i * n_loop + j
    b = (i + 1) * n_loop + j
    c = (i + 1) * n_loop + (j + 1) % n_loop
    d = i * n_loop + (j + 1) % n_loop
    return np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])


def _cap_faces(start: int, n_loop: int, centre: int, flip: bool) -> np.ndarray:
    j = np.arange(n_loop)
    f = np.stack([np.full(n_loop, centre), start + j, start + (j + 1) % n_loop], axis=1)
    return f[:, [0, 2, 1]] if flip else f


def _loft(stations: np.ndarray, loops: np.ndarray) -> Mesh:
    """Closed tube through `loops` (S, C, 3) with flat end caps."""
    s, c, _ = loops.shape
    verts = loops.reshape(-1, 3)
    centres = np.stack([loops[0].mean(axis=0), loops[-1].mean(axis=0)])
    faces = np.concatenate([_tube_faces(s, c), _cap_faces(0, c, s * c, True),
                            _cap_faces((s - 1) * c, c, s * c + 1, False)])
    return Mesh(np.concatenate([verts, centres]), faces)


def _wheel(center: np.ndarray, radius: float, width: float, n_seg: int = 18) -> Mesh:
    """Cylinder with its axis along y."""
    a = np.linspace(0.0, 2 * np.pi, n_seg, endpoint=False)
    ring = np.stack([radius * np.cos(a), np.zeros(n_seg), radius * np.sin(a)], axis=1)
    loops = np.stack([ring + [0.0, -width / 2, 0.0], ring + [0.0, width / 2, 0.0]]) + center
    return _loft(np.array([0.0, 1.0]), loops)


def _body(profile: dict, top: np.ndarray, length: float, width: float, height: float,
          wheel_r: float, axles: np.ndarray, rng: np.random.Generator) -> tuple[Mesh, float]:
    """Lofted body: the side profile extruded across the width with rounded, tapered sections."""
    n_uniform = int(np.clip(length * 10, 40, 110))
    f_st = np.unique(np.concatenate([np.linspace(0.0, 1.0, n_uniform), top[:, 0]]))
    x = (f_st - 0.5) * length
    z_top = np.interp(f_st, top[:, 0], top[:, 1]) * height
    # Body bottom: ground clearance, lifted at the overhangs and cut by the wheel arches.
    clearance = profile["bottom"] * height
    overhang = np.clip(np.minimum(f_st, 1 - f_st) / 0.06, 0, 1)
    z_bot = clearance + (1 - overhang) * 0.25 * (z_top - clearance).clip(0) * 0.6
    arch_r = wheel_r * rng.uniform(1.08, 1.2)
    for xa in axles:
        dx = x - xa
        inside = np.abs(dx) < arch_r
        z_bot = np.where(inside, np.maximum(z_bot, wheel_r + np.sqrt(np.clip(arch_r**2 - dx**2, 0, None))), z_bot)
    z_bot = np.minimum(z_bot, z_top - 0.05 * height)
    # Plan view: ends rounded inwards.
    end = np.clip((0.07 - np.minimum(f_st, 1 - f_st)) / 0.07, 0, 1)
    half_w = width / 2 * (1 - rng.uniform(0.06, 0.14) * end**2)
    # Rounded-rectangle cross-section (superellipse), greenhouse narrowed above the belt line.
    n_loop = 28
    th = np.linspace(0.0, 2 * np.pi, n_loop, endpoint=False)
    p = profile["square"] * rng.uniform(0.85, 1.15)
    cy = np.sign(np.cos(th)) * np.abs(np.cos(th)) ** (2 / p)
    cz = np.sign(np.sin(th)) * np.abs(np.sin(th)) ** (2 / p)
    zc, hh = (z_top + z_bot) / 2, (z_top - z_bot) / 2
    zz = zc[:, None] + hh[:, None] * cz[None, :]
    belt = profile["belt"] * height * rng.uniform(0.97, 1.03)
    tumble = profile["tumble"] * rng.uniform(0.8, 1.2)
    g = np.clip((zz - belt) / max(height - belt, 1e-6), 0, 1)
    yy = half_w[:, None] * cy[None, :] * (1 - tumble * g)
    loops = np.stack([np.broadcast_to(x[:, None], zz.shape), yy, zz], axis=-1)
    return _loft(x, loops), belt


def size_range(kind: str, size_spread: float = 0.0) -> np.ndarray:
    """(3, 2) [min, max] of (length, width, height) of `kind`, each range widened by `size_spread` (a
    fraction: 0.15 gives [0.85 min, 1.15 max])."""
    if kind not in KIND_SIZE_RANGES:
        raise ValueError(f"unknown vehicle kind {kind!r}; expected one of {VEHICLE_KINDS}")
    if not 0.0 <= size_spread < 1.0:
        raise ValueError(f"size_spread must be in [0, 1), got {size_spread}")
    r = np.array(KIND_SIZE_RANGES[kind], dtype=np.float64)
    if size_spread:
        r = r * np.array([1.0 - size_spread, 1.0 + size_spread])
    return r


def generate_vehicle(rng: np.random.Generator, kind: str | None = None, *, size_spread: float = 0.0) -> Mesh:
    """Random vehicle mesh (metres, x forward, y left, z up) centred on its bounding box.

    `kind` None draws one of VEHICLE_KINDS. `size_spread` widens the kind's size ranges (see `size_range`):
    the length, width and height are drawn independently, so a wide spread gives unusual widths and heights
    for a length. With 0 the draws are those of generator version 1.
    """
    if kind is None:
        kind = VEHICLE_KINDS[int(rng.integers(len(VEHICLE_KINDS)))]
    if kind in _COMPOSITES:
        return _COMPOSITES[kind](rng, size_range(kind, size_spread))
    if kind not in _PROFILES:
        raise ValueError(f"unknown vehicle kind {kind!r}; expected one of {VEHICLE_KINDS}")
    prof = _PROFILES[kind]
    (l0, l1), (w0, w1), (h0, h1) = size_range(kind, size_spread)
    length, width, height = rng.uniform(l0, l1), rng.uniform(w0, w1), rng.uniform(h0, h1)
    # Jitter the profile key points (keeping the ends and the ordering).
    top = np.array(prof["top"], dtype=np.float64)
    inner = (top[:, 0] > 0) & (top[:, 0] < 1)
    top[inner, 0] += rng.uniform(-0.012, 0.012, inner.sum())
    top[:, 0] = np.maximum.accumulate(top[:, 0])
    top[:, 1] = np.clip(top[:, 1] + np.where(top[:, 1] < 0.999, rng.uniform(-0.03, 0.03, len(top)), 0), 0.25, 1.0)
    wheel_r = prof["wheel"] * height * rng.uniform(0.92, 1.08)
    wheel_r = min(wheel_r, 0.55)
    axles = (np.array(prof["axles"]) + rng.uniform(-0.015, 0.015, 2) - 0.5) * length
    mirror_out = 0.06 * width if kind not in ("bus", "box_truck") else 0.05 * width
    body_w = width - 2 * mirror_out
    body, belt = _body(prof, top, length, body_w, height, wheel_r, axles, rng)
    parts = [body]
    tyre_w = np.clip(0.12 * body_w, 0.18, 0.3)
    wy = body_w / 2 - tyre_w / 2 - 0.02
    rear_axles = [axles[0]] if kind != "bus" or rng.random() < 0.7 else [axles[0], axles[0] - 2.2 * wheel_r]
    for xa in rear_axles + [axles[1]]:
        for side in (-1.0, 1.0):
            parts.append(_wheel(np.array([xa, side * wy, wheel_r]), wheel_r, tyre_w))
    # Mirrors at the base of the windscreen.
    fm = top[prof["mirror"], 0]
    mx = (fm - 0.5) * length + 0.04 * length * (kind in ("bus", "van", "box_truck"))
    mz = belt + rng.uniform(0.05, 0.15)
    msize = np.array([0.12, mirror_out + 0.06, 0.13]) * (1.6 if kind in ("bus", "box_truck") else 1.0)
    for side in (-1.0, 1.0):
        parts.append(box_mesh(msize, np.array([min(mx, length / 2 - 0.1), side * (width / 2 - msize[1] / 2), mz])))
    mesh = merge_meshes(parts)
    mesh = _deform(mesh, rng, 0.02)
    return fit_to_size(mesh, np.array([length, width, height]))


def _deform(mesh: Mesh, rng: np.random.Generator, amount: float) -> Mesh:
    """Mild smooth deformation: bend, plan-view trapezoid and lean, each up to `amount` of the size."""
    return bend_taper_lean(mesh, rng.uniform(-amount, amount, 3))


def bend_taper_lean(mesh: Mesh, amounts: np.ndarray | tuple[float, float, float]) -> Mesh:
    """`mesh` bent (its ends raised by amounts[0] of its height), tapered in plan view (its width grown by amounts[1]
    at the front, shrunk at the back) and leant (its top moved forward by amounts[2] / 2 of its length)."""
    v = mesh.vertices.copy()
    ext = np.maximum(mesh.extent, 1e-9)
    lo = mesh.bounds[0]
    u = (v - lo) / ext - 0.5  # in [-0.5, 0.5]
    a = np.asarray(amounts, dtype=np.float64)
    v[:, 2] += a[0] * ext[2] * (4 * u[:, 0] ** 2)
    v[:, 1] *= 1 + a[1] * 2 * u[:, 0]
    v[:, 0] += a[2] * ext[0] * 0.5 * (u[:, 2] + 0.5)
    return Mesh(v, mesh.faces)


def fit_to_size(mesh: Mesh, size: np.ndarray) -> Mesh:
    """Copy scaled per axis to the bounding-box `size` (x, y, z) and centred on the bounding box."""
    m = mesh.centered()
    return Mesh(m.vertices * (np.asarray(size, dtype=np.float64) / np.maximum(m.extent, 1e-9)), m.faces)


def perturb_mesh(mesh: Mesh, rng: np.random.Generator, *, scale: tuple[float, float] = (0.9, 1.1),
                 deform: float = 0.02) -> Mesh:
    """Random anisotropic scale (per axis in `scale`) and mild deformation; result centred on its bbox."""
    m = _deform(mesh, rng, deform)
    return fit_to_size(m, mesh.extent * rng.uniform(scale[0], scale[1], 3))


# --- composite kinds: boxes, wheels and beams, built standing on z = 0 with x forward, then fitted to size ----


def _beam(p0: np.ndarray | tuple, p1: np.ndarray | tuple, width: float, thickness: float) -> Mesh:
    """Box of `width` (y) and `thickness` from `p0` to `p1` (points (x, y, z), same y): a sloped arm or strut."""
    p0, p1 = np.asarray(p0, dtype=np.float64), np.asarray(p1, dtype=np.float64)
    d = p1 - p0
    length = float(np.hypot(d[0], d[2]))
    m = box_mesh((max(length, 1e-3), width, thickness))
    a = np.arctan2(d[2], d[0])
    c, s = np.cos(a), np.sin(a)
    v = m.vertices @ np.array([[c, 0.0, -s], [0.0, 1.0, 0.0], [s, 0.0, c]]).T + (p0 + p1) / 2
    return Mesh(v, m.faces)


def _block(x0: float, x1: float, y0: float, y1: float, z0: float, z1: float) -> Mesh:
    """Axis-aligned box between the given bounds."""
    return box_mesh((x1 - x0, y1 - y0, z1 - z0), ((x0 + x1) / 2, (y0 + y1) / 2, (z0 + z1) / 2))


def _axle(x: float, radius: float, track: float, tyre: float) -> list[Mesh]:
    """A pair of wheels at `x` whose outer faces are `track` apart."""
    wy = track / 2 - tyre / 2
    return [_wheel(np.array([x, side * wy, radius]), radius, tyre) for side in (-1.0, 1.0)]


def _draw_size(rng: np.random.Generator, ranges: np.ndarray) -> np.ndarray:
    return rng.uniform(ranges[:, 0], ranges[:, 1])


def _construction(rng: np.random.Generator, ranges: np.ndarray) -> Mesh:
    """Wheel loader, excavator or roller: a heavy low chassis over most of the length (top at 50-65 % of the
    height), a cab block at one end reaching the top and a bucket, boom or drum reaching the other end."""
    length, width, height = _draw_size(rng, ranges)
    sub = int(rng.integers(3))
    deck = height * rng.uniform(0.5, 0.65)  # top of the heavy lower part
    hw = width / 2
    parts: list[Mesh] = []
    if sub == 0:  # wheel loader: big wheels, bucket on lift arms at the front, cab over the rear axle
        r = min(deck * rng.uniform(0.42, 0.5), 0.8)
        tyre = width * rng.uniform(0.2, 0.25)
        x_rear, x_front = -length * rng.uniform(0.22, 0.3), length * rng.uniform(0.08, 0.15)
        parts += _axle(x_rear, r, width * 0.96, tyre) + _axle(x_front, r, width * 0.96, tyre)
        body_w = width * 0.96 - 2 * tyre - 0.05
        parts.append(_block(-length / 2, x_front + r * 0.6, -body_w / 2, body_w / 2, r * 0.5, deck))
        parts.append(_block(-length / 2, x_rear + r * 1.2, -hw * 0.9, hw * 0.9, deck * 0.7, deck))  # engine hood
        cx = x_rear + rng.uniform(0.6, 1.0) * r
        parts.append(_block(cx - 0.8, cx + 0.8, -hw * 0.55, hw * 0.55, deck, height))  # cab
        bx = length / 2
        b_len, b_h = rng.uniform(0.9, 1.3), rng.uniform(0.9, 1.3)
        b_z = rng.uniform(0.0, 0.5) * deck  # bucket lowered or carried
        parts.append(_block(bx - b_len, bx, -hw, hw, b_z, b_z + b_h))  # bucket
        for side in (-1.0, 1.0):
            parts.append(_beam((x_front, side * hw * 0.45, deck * 0.95), (bx - b_len * 0.7, side * hw * 0.45,
                                                                           b_z + b_h * 0.6), 0.25, 0.3))
    elif sub == 1:  # excavator: tracks, upper house, cab at the front left, boom and stick to a bucket
        track_h = deck * rng.uniform(0.35, 0.45)
        t_len = length * rng.uniform(0.5, 0.6)
        t0 = -length / 2 + length * rng.uniform(0.0, 0.08)
        tw = width * 0.22
        for side in (-1.0, 1.0):
            parts.append(_block(t0, t0 + t_len, side * hw - (tw if side > 0 else 0),
                                side * hw + (0 if side > 0 else tw), 0.0, track_h))
        parts.append(_block(t0 + 0.3, t0 + t_len - 0.3, -hw + tw, hw - tw, track_h * 0.5, track_h))
        h0 = t0 - rng.uniform(0.0, 0.3)
        h1 = t0 + t_len * rng.uniform(0.85, 1.0)
        parts.append(_block(h0, h1, -hw * 0.95, hw * 0.95, track_h + 0.1, deck))  # house with counterweight
        parts.append(_block(h1 - 1.6, h1, 0.1 * hw, hw * 0.95, deck, height))  # cab
        pivot = np.array([h1 - 0.3, -0.2 * hw, deck * 0.9])
        elbow = np.array([h1 + (length / 2 - h1) * rng.uniform(0.45, 0.7), -0.2 * hw, height * rng.uniform(0.8, 0.98)])
        tip = np.array([length / 2 - 0.5, -0.2 * hw, rng.uniform(0.1, 0.6) * deck])
        parts += [_beam(pivot, elbow, 0.5, 0.55), _beam(elbow, tip, 0.4, 0.4)]
        parts.append(_block(length / 2 - 1.0, length / 2, -0.2 * hw - 0.55, -0.2 * hw + 0.55, tip[2] - 0.5,
                            tip[2] + 0.4))  # bucket
    else:  # roller: front drum, rear wheels, ROPS cab at the rear
        r = deck * rng.uniform(0.5, 0.6) * 0.9
        drum_x = length / 2 - r
        parts.append(_wheel(np.array([drum_x, 0.0, r]), r, width, n_seg=20))
        parts.append(_block(drum_x - r * 0.3, drum_x + r * 1.0, -hw, hw, r * 1.2, r * 1.6))  # drum frame
        rr = r * rng.uniform(0.7, 0.9)
        x_rear = -length / 2 + rr * 1.3
        parts += _axle(x_rear, rr, width * 0.95, width * 0.25)
        parts.append(_block(-length / 2, drum_x - r * 1.05, -hw * 0.7, hw * 0.7, rr * 0.5, deck))  # chassis
        cx0, cx1 = -length / 2 + 0.2, -length / 2 + 0.2 + rng.uniform(1.5, 2.0)
        parts.append(_block(cx0, cx1, -hw * 0.75, hw * 0.75, height - 0.12, height))  # roof
        for x in (cx0 + 0.05, cx1 - 0.05):
            for side in (-1.0, 1.0):
                parts.append(_block(x - 0.05, x + 0.05, side * hw * 0.7 - 0.05, side * hw * 0.7 + 0.05, deck,
                                    height))  # roll-over posts
        parts.append(_block(cx0 + 0.3, cx1 - 0.3, -0.3, 0.3, deck, deck + 0.6))  # seat and controls
    if rng.random() < 0.5:  # mirror image: cab and tool at the other end
        parts = [Mesh(m.vertices * np.array([-1.0, 1.0, 1.0]), m.faces[:, ::-1]) for m in parts]
    return fit_to_size(_deform(merge_meshes(parts), rng, 0.01), np.array([length, width, height]))


def _tractor(rng: np.random.Generator, x_front: float, width: float, height: float) -> tuple[list[Mesh], float]:
    """Truck tractor whose front is at `x_front`: cab (cab-over or with a bonnet), chassis, two or three axles.
    Returns the parts and the x of the fifth wheel."""
    cab_len = rng.uniform(1.9, 2.4)
    bonnet = rng.uniform(1.2, 1.9) if rng.random() < 0.35 else 0.0
    r = rng.uniform(0.48, 0.55)
    cab_h = height * rng.uniform(0.85, 1.0)
    x_cab1 = x_front - bonnet
    parts = [_block(x_cab1 - cab_len, x_cab1, -width / 2, width / 2, 2 * r * 0.9, cab_h)]
    if bonnet:
        parts.append(_block(x_cab1, x_front, -width * 0.42, width * 0.42, 2 * r * 0.8, 2 * r + 0.9))
    wheelbase = rng.uniform(3.3, 4.2)
    x_fa = x_front - bonnet * 0.6 - 1.2
    x_ra = x_fa - wheelbase
    frame_end = x_ra - rng.uniform(0.6, 1.0)
    parts.append(_block(frame_end, x_front - 0.1, -0.5, 0.5, r * 0.8, r * 2.1))
    parts += _axle(x_fa, r, width * 0.98, 0.32)
    for k in range(int(rng.integers(1, 3))):
        parts += _axle(x_ra - k * 1.35, r, width * 0.98, 0.55)
    parts.append(_block(x_cab1 - 0.1, x_cab1 + 0.05, -width / 2 - 0.02, width / 2 + 0.02, 1.5, 2.3))  # mirrors
    return parts, x_ra - 0.3


def _semi_trailer(rng: np.random.Generator, ranges: np.ndarray) -> Mesh:
    """Articulated lorry: tractor and a box, curtain or flatbed semi-trailer on a tandem or tridem at the rear."""
    length, width, height = _draw_size(rng, ranges)
    flatbed = rng.random() < 0.35
    parts, fifth = _tractor(rng, length / 2, width, height * (1.0 if flatbed else rng.uniform(0.82, 0.97)))
    gap = rng.uniform(0.5, 1.2)
    cab_back = min(float(m.vertices[:, 0].min()) for m in parts[:1])
    t_front = cab_back - gap
    t_rear = -length / 2
    deck = rng.uniform(1.2, 1.45)
    r = rng.uniform(0.45, 0.52)
    for k in range(int(rng.integers(2, 4))):
        parts += _axle(t_rear + 1.4 + k * 1.35, r, width * 0.98, 0.55)
    parts.append(_block(t_rear + 0.9, fifth + 1.0, -0.45, 0.45, deck - 0.35, deck))  # trailer frame
    if flatbed:
        parts.append(_block(t_rear, t_front, -width / 2, width / 2, deck, deck + 0.2))
        x = t_rear + rng.uniform(0.0, 1.0)
        while x < t_front - 1.5:  # loads on the deck: crates, coils, machinery
            ln = rng.uniform(1.0, 4.0)
            x1 = min(x + ln, t_front - 0.3)
            if rng.random() < 0.75:
                w = width * rng.uniform(0.5, 1.0)
                parts.append(_block(x, x1, -w / 2, w / 2, deck + 0.2, deck + 0.2 + rng.uniform(0.4, 2.4)))
            x = x1 + rng.uniform(0.2, 1.5)
    else:
        parts.append(_block(t_rear, t_front, -width / 2, width / 2, deck, height))
    mesh = merge_meshes(parts)
    height = float(np.clip(mesh.extent[2], ranges[2, 0], ranges[2, 1]))
    return fit_to_size(_deform(mesh, rng, 0.01), np.array([length, width, height]))


def _pickup_load(rng: np.random.Generator, ranges: np.ndarray) -> Mesh:
    """Pickup whose bed carries crates and boxes of random sizes, sometimes higher than the cab."""
    spread = max(0.0, 1.0 - ranges[0, 0] / KIND_SIZE_RANGES["pickup_load"][0][0])  # the widening asked for
    truck = generate_vehicle(rng, "pickup", size_spread=spread)
    size = truck.extent
    length, width, height = size
    lo = -height / 2
    floor = lo + 0.58 * height  # top of the bed sides in the pickup profile
    x0, x1 = -length / 2 + 0.03 * length, -length / 2 + 0.40 * length
    top_max = min(ranges[2, 1], height * rng.uniform(1.05, 1.55)) + lo
    parts = [truck]
    x = x0
    for _ in range(int(rng.integers(1, 4))):
        if x > x1 - 0.3:
            break
        ln = min(rng.uniform(0.4, 1.6), x1 - x)
        w = width * rng.uniform(0.35, 0.85)
        y = rng.uniform(-1, 1) * (width * 0.85 - w) / 2
        top = rng.uniform(floor + 0.25, top_max)
        parts.append(_block(x, x + ln, y - w / 2, y + w / 2, floor - 0.05, top))
        x += ln + rng.uniform(0.0, 0.3)
    return merge_meshes(parts).centered()


def _trailer(rng: np.random.Generator, ranges: np.ndarray) -> Mesh:
    """Car or box trailer without a cab: deck on one or two axles, low sides or a box, A-frame drawbar in front."""
    length, width, height = _draw_size(rng, ranges)
    r = rng.uniform(0.28, 0.4)
    deck = r * 2 + rng.uniform(0.05, 0.2)
    bar = rng.uniform(1.0, 1.6)
    body0, body1 = -length / 2, length / 2 - bar
    parts: list[Mesh] = [_block(body0, body1, -width / 2, width / 2, deck - 0.15, deck)]
    xa = body0 + (body1 - body0) * rng.uniform(0.4, 0.55)
    for k in range(1 + int(rng.random() < 0.5)):
        parts += _axle(xa - k * 0.9, r, width, 0.2)
    if height > deck + 1.0 and rng.random() < 0.6:  # box trailer
        parts.append(_block(body0, body1, -width / 2, width / 2, deck, height))
    else:  # open trailer: side boards and sometimes a load
        wall = rng.uniform(0.1, 0.45)
        for side in (-1.0, 1.0):
            parts.append(_block(body0, body1, side * width / 2 - 0.03, side * width / 2 + 0.03, deck, deck + wall))
        load_top = height if height > deck + wall + 0.1 else deck + wall
        lw = width * rng.uniform(0.6, 0.9)
        parts.append(_block(body0 + 0.2, body1 - 0.2, -lw / 2, lw / 2, deck, load_top))
    parts += [_beam((body1, side * width * 0.35, deck - 0.1), (length / 2, 0.0, deck - 0.15), 0.08, 0.1)
              for side in (-1.0, 1.0)]  # A-frame
    mesh = merge_meshes(parts)
    return fit_to_size(mesh, np.array([length, width, np.clip(mesh.extent[2], ranges[2, 0], ranges[2, 1])]))


_COMPOSITES = {"construction": _construction, "semi_trailer": _semi_trailer, "pickup_load": _pickup_load,
               "trailer": _trailer}

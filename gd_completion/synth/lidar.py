"""Lidar simulation: vectorised ray casting of a beam pattern (rotating or forward-facing) against triangle meshes."""
from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from gd_completion.synth.beams import BeamPattern
from gd_completion.synth.meshio import Mesh

__all__ = ["ScanResult", "simulate_scan", "scan_meshes", "intersect_arcs"]


@functools.lru_cache(maxsize=16)
def _ray_tables(pattern: BeamPattern) -> tuple:
    """Per-beam sin/cos elevation, per (beam, firing) cos/sin azimuth, and beam groups of similar offset.

    Each group is (beams sorted by elevation, their tan(elevation), min offset, max offset); grouping by
    azimuth offset keeps the firing window of a triangle tight for patterns with staggered channels.
    """
    e = np.radians(np.asarray(pattern.elevations_deg))
    off = np.radians(np.asarray(pattern.azimuth_offsets_deg))
    n_az = pattern.n_azimuth
    res = 2 * np.pi / n_az
    az = np.arange(n_az)[None, :] * res + off[:, None]
    key = np.floor(off / res).astype(np.int64)
    groups = []
    for g in np.unique(key):
        beams = np.flatnonzero(key == g)
        beams = beams[np.argsort(e[beams], kind="stable")]
        groups.append((beams, np.tan(e[beams]), off[beams].min(), off[beams].max()))
    return np.sin(e), np.cos(e), np.cos(az), np.sin(az), groups, res


@dataclass
class ScanResult:
    """Simulated returns: points (N,3) float32, intensity in [0,1], object index (-1 ground), ring (beam)."""

    points: np.ndarray
    intensity: np.ndarray
    object_index: np.ndarray
    ring: np.ndarray


def _wrap(a: np.ndarray) -> np.ndarray:
    return (a + np.pi) % (2 * np.pi) - np.pi


def _triangle_windows(p: np.ndarray) -> tuple[np.ndarray, ...]:
    """Conservative angular window of every triangle (p: (F,3,3), sensor at 0).

    Returns azimuth start and arc (rad; arc >= pi means all azimuths) and the tan(elevation) bounds.
    Azimuth is monotonic along an edge, so the vertex arc is exact; elevation is bounded with the vertical
    extent over the nearest / farthest horizontal distance of the triangle.
    """
    x, y, z = p[..., 0], p[..., 1], p[..., 2]
    ang = np.sort(np.arctan2(y, x) % (2 * np.pi), axis=1)
    gaps = np.stack([ang[:, 1] - ang[:, 0], ang[:, 2] - ang[:, 1], 2 * np.pi - (ang[:, 2] - ang[:, 0])], axis=1)
    k = np.argmax(gaps, axis=1)
    rows = np.arange(len(k))
    arc = 2 * np.pi - gaps[rows, k]
    a_start = ang[rows, (k + 1) % 3]
    full = arc >= np.pi - 1e-6
    rho_max = np.hypot(x, y).max(axis=1)
    a2, b2 = p[:, :, :2], np.roll(p[:, :, :2], -1, axis=1)
    d = b2 - a2
    s = np.clip(-(a2 * d).sum(-1) / np.maximum((d * d).sum(-1), 1e-18), 0, 1)
    rho_min = np.where(full, 0.0, np.linalg.norm(a2 + s[..., None] * d, axis=-1).min(axis=1))
    zmin, zmax = z.min(axis=1), z.max(axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        t_hi = np.where(zmax > 0, zmax / rho_min, zmax / rho_max)
        t_lo = np.where(zmin > 0, zmin / rho_max, zmin / rho_min)
    t_hi = np.where(np.isnan(t_hi), np.inf, t_hi)
    t_lo = np.where(np.isnan(t_lo), -np.inf, t_lo)
    return a_start, np.where(full, 2 * np.pi, arc), t_lo, t_hi


def intersect_arcs(a: tuple[float, float], b: tuple[float, float]) -> tuple[float, float] | None:
    """Overlap of two azimuth arcs (deg, [lo, hi] counter-clockwise; hi - lo >= 360 is the full circle), as
    [lo, hi] in `a`'s turn; None when they do not overlap. Two overlaps (arcs over 360 deg together)
    give the longer one."""
    wa, wb = a[1] - a[0], b[1] - b[0]
    if wa >= 360.0:
        return (float(b[0]), float(b[1])) if wb < 360.0 else (float(a[0]), float(a[1]))
    if wb >= 360.0:
        return float(a[0]), float(a[1])
    start = (b[0] - a[0]) % 360.0
    pieces = []
    for s0 in (start, start - 360.0):
        lo, hi = max(0.0, s0), min(wa, s0 + wb)
        if hi > lo:
            pieces.append((lo, hi))
    if not pieces:
        return None
    lo, hi = max(pieces, key=lambda p: p[1] - p[0])
    return float(a[0] + lo), float(a[0] + hi)


def _mix_pixels(grid: np.ndarray, beam: np.ndarray, j: np.ndarray, r: np.ndarray, pattern: BeamPattern,
                rng: np.random.Generator, prob: float, jump: float) -> np.ndarray:
    """Ranges `r` of returns (beam, firing j) with mixed pixels at depth discontinuities of the range `grid`
    (n_beams, n_az; inf without return): see `scan_meshes`."""
    n_beams, n_az = grid.shape
    res = 360.0 / n_az
    elev = np.asarray(pattern.elevations_deg)
    off = np.asarray(pattern.azimuth_offsets_deg)
    order = np.argsort(elev, kind="stable")
    rank = np.empty(n_beams, np.int64)
    rank[order] = np.arange(n_beams)
    r0 = grid[beam, j]
    neigh = [grid[beam, (j - 1) % n_az], grid[beam, (j + 1) % n_az]]
    for step in (-1, 1):
        other = order[np.clip(rank[beam] + step, 0, n_beams - 1)]
        jo = (j + np.rint((off[beam] - off[other]) / res).astype(np.int64)) % n_az
        neigh.append(np.where(other != beam, grid[other, jo], r0))
    nb = np.stack(neigh)
    gap = np.abs(nb - r0)
    edge = np.isfinite(nb) & (gap > np.maximum(jump, 0.05 * r0))
    # the neighbour across the largest discontinuity
    k = np.argmax(np.where(edge, gap, -1.0), axis=0)
    has = edge.any(axis=0)
    pick = has & (rng.random(len(r)) < prob)
    other_r = nb[k, np.arange(len(r))]
    u = rng.random(len(r))
    out = r.copy()
    out[pick] = (r0 + u * (other_r - r0))[pick] + (r - r0)[pick]  # keep the return's range noise
    return out


def _object_visible(mesh: Mesh, sensor: np.ndarray, az_range: tuple[float, float] | None, max_range: float) -> bool:
    """Bounding-box test of an object against the range limit and the azimuth window."""
    b = mesh.bounds - sensor
    nearest = np.clip(0.0, b[0], b[1])
    if np.linalg.norm(nearest) > max_range:
        return False
    if az_range is None or (b[0, 0] <= 0 <= b[1, 0] and b[0, 1] <= 0 <= b[1, 1]):
        return True
    corners = np.array([[b[i, 0], b[j, 1]] for i in (0, 1) for j in (0, 1)])
    a = np.arctan2(corners[:, 1], corners[:, 0])
    c = np.arctan2(corners[:, 1].mean(), corners[:, 0].mean())
    rel = _wrap(a - c)
    lo, hi = np.radians(az_range)
    mid, half = (lo + hi) / 2, (hi - lo) / 2
    o_lo, o_hi = c + rel.min(), c + rel.max()
    o_mid, o_half = (o_lo + o_hi) / 2, (o_hi - o_lo) / 2
    return bool(abs(_wrap(np.array(o_mid - mid))) <= half + o_half + 0.02)


def scan_meshes(meshes: list[Mesh], sensor_position: np.ndarray | tuple[float, float, float], pattern: BeamPattern,
                rng: np.random.Generator, *, azimuth_range: tuple[float, float] | None = None,
                range_noise_std: float = 0.02, dropout: float = 0.05, max_range: float = 120.0,
                ground_z: float | None = None, reflectivity: np.ndarray | None = None,
                ground_reflectivity: float = 0.25, max_pairs: int = 1_500_000,
                ground_plane: tuple[np.ndarray | tuple[float, float, float], float] | None = None,
                sensor_heading_deg: float = 0.0, mixed_pixel_prob: float = 0.0,
                mixed_pixel_jump: float = 0.3) -> ScanResult:
    """Cast every firing of one revolution against `meshes` (world frame, sensor axes = world axes).

    Each triangle is rasterised into the (beam, firing) grid through a conservative angular window, the
    candidate (ray, triangle) pairs get an exact Moller-Trumbore test, and the nearest hit per ray wins, so
    self-occlusion and occlusion between objects are exact. `azimuth_range` (deg, [lo, hi] counter-clockwise
    from +x) keeps only firings in that window. A pattern with a horizontal field of view under 360 deg (a
    forward-facing solid-state sensor) fires only within `sensor_heading_deg` +- fov/2 (intersected with
    `azimuth_range`). The ground is the plane z = `ground_z`, or `ground_plane` = (normal n, offset c): the
    points p with n . p = c (a tilted ground), when given.

    Mixed pixels: with `mixed_pixel_prob` > 0, a return whose neighbour in the grid (the next firing of its
    beam either side, or the beam above or below at the same azimuth) lies more than
    max(`mixed_pixel_jump`, 5 % of the range) farther or nearer is, with that probability, moved to a range
    drawn uniformly between the two: the beam straddles a depth discontinuity and the receiver averages
    the foreground and background echoes (the "veil" along silhouettes). Neighbours without a return
    (open sky) give no mixed pixel.
    """
    sensor = np.asarray(sensor_position, dtype=np.float64).reshape(3)
    if pattern.fov_deg < 360.0:
        fov = (sensor_heading_deg - pattern.fov_deg / 2, sensor_heading_deg + pattern.fov_deg / 2)
        azimuth_range = fov if azimuth_range is None else intersect_arcs(azimuth_range, fov)
        if azimuth_range is None:
            return ScanResult(np.zeros((0, 3), np.float32), np.zeros(0, np.float32), np.zeros(0, np.int32),
                              np.zeros(0, np.int16))
    sin_e, cos_e, cos_az, sin_az, groups, res = _ray_tables(pattern)
    n_beams, n_az = len(sin_e), cos_az.shape[1]
    n_rays = n_beams * n_az
    refl = np.full(len(meshes), 0.6) if reflectivity is None else np.asarray(reflectivity, dtype=np.float64)
    keep = [i for i, m in enumerate(meshes) if len(m.faces) and _object_visible(m, sensor, azimuth_range, max_range)]
    hit_ray, hit_t, hit_tri = [], [], []
    tri_obj = np.zeros(0, np.int64)
    normals = np.zeros((0, 3))
    if keep:
        tris = np.concatenate([meshes[i].triangles() for i in keep]) - sensor
        tri_obj = np.concatenate([np.full(len(meshes[i].faces), i) for i in keep])
        v0, e1, e2 = tris[:, 0], tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0]
        # Moller-Trumbore with the ray origin at 0, reduced to three dot products per (ray, triangle) pair.
        a_vec = np.cross(e2, e1)          # det = d . a
        b_vec = np.cross(e2, -v0)         # u * det = d . b
        c_vec = np.cross(-v0, e1)         # v * det = d . c
        t_num = (e2 * c_vec).sum(-1)      # t * det
        normals = -a_vec / np.maximum(np.linalg.norm(a_vec, axis=1, keepdims=True), 1e-18)
        a_start, arc, t_lo, t_hi = _triangle_windows(tris)
        full = arc >= 2 * np.pi
        for g_beams, g_tan, off_min, off_max in groups:
            lo = np.searchsorted(g_tan, t_lo - 1e-9, side="left")
            nb = np.clip(np.searchsorted(g_tan, t_hi + 1e-9, side="right") - lo, 0, None)
            j_lo = np.where(full, 0, np.ceil((a_start - off_max) / res - 1e-9).astype(np.int64))
            j_hi = np.floor((a_start + arc - off_min) / res + 1e-9).astype(np.int64)
            nj = np.where(full, n_az, np.clip(j_hi - j_lo + 1, 0, n_az))
            cnt = nb * nj
            nz = np.flatnonzero(cnt)
            if len(nz) == 0:
                continue
            csum = np.cumsum(cnt[nz])
            cuts = np.searchsorted(csum, np.arange(1, int(csum[-1]) // max_pairs + 1) * max_pairs, side="right")
            edges = np.unique(np.concatenate([[0], cuts, [len(nz)]]))
            for start, stop in zip(edges[:-1], edges[1:]):
                sel = nz[start:stop]
                c = cnt[sel]
                tri = np.repeat(sel, c)
                k = np.arange(c.sum()) - np.repeat(np.cumsum(c) - c, c)
                njt = nj[tri]
                beam = g_beams[lo[tri] + k // njt]
                j = (j_lo[tri] + k % njt) % n_az
                ce = cos_e[beam]
                dx, dy, dz = ce * cos_az[beam, j], ce * sin_az[beam, j], sin_e[beam]
                det = dx * a_vec[tri, 0] + dy * a_vec[tri, 1] + dz * a_vec[tri, 2]
                with np.errstate(divide="ignore", invalid="ignore"):
                    inv = 1.0 / det
                    u = (dx * b_vec[tri, 0] + dy * b_vec[tri, 1] + dz * b_vec[tri, 2]) * inv
                    v = (dx * c_vec[tri, 0] + dy * c_vec[tri, 1] + dz * c_vec[tri, 2]) * inv
                    t = t_num[tri] * inv
                    ok = (np.abs(det) > 1e-12) & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 1e-6) & (t <= max_range)
                hit_ray.append(beam[ok] * n_az + j[ok])
                hit_t.append(t[ok])
                hit_tri.append(tri[ok])
    best = np.full(n_rays, np.inf)
    best_src = np.full(n_rays, -1, np.int64)  # triangle index, -2 ground
    if hit_ray:
        ray, tt, tri = np.concatenate(hit_ray), np.concatenate(hit_t), np.concatenate(hit_tri)
        np.minimum.at(best, ray, tt)
        win = tt == best[ray]
        best_src[ray[win]] = tri[win]
    # Firings that can fall in the azimuth window (all of them without one): the ground and the returns
    # are only looked at there (dense patterns have far more firings than a vehicle's window).
    cols = np.arange(n_az)
    if azimuth_range is not None:
        lo_a, hi_a = np.radians(azimuth_range)
        offs = np.radians(np.asarray(pattern.azimuth_offsets_deg))
        c0 = int(np.floor((lo_a - offs.max()) / res)) - 2
        c1 = int(np.ceil((hi_a - offs.min()) / res)) + 2
        if c1 - c0 + 1 < n_az:
            cols = np.unique(np.arange(c0, c1 + 1) % n_az)
    cand = np.arange(n_beams)[:, None] * n_az + cols[None, :]
    if ground_plane is None and ground_z is not None:   # the level ground: normal +z (the same hits, bit for bit)
        ground_plane = ((0.0, 0.0, 1.0), float(ground_z))
    if ground_plane is not None:
        n = np.asarray(ground_plane[0], dtype=np.float64).reshape(3)
        n = n / np.linalg.norm(n)
        height = float(n @ sensor - ground_plane[1])
        if height > 0:
            nd = (n[0] * cos_az[:, cols] + n[1] * sin_az[:, cols]) * cos_e[:, None] + n[2] * sin_e[:, None]
            with np.errstate(divide="ignore"):
                tg_c = np.where(nd < -1e-9, -height / nd, np.inf)
            tg_c[tg_c > max_range] = np.inf
            g = tg_c < best[cand]
            best[cand[g]] = tg_c[g]
            best_src[cand[g]] = -2
    cand = cand.reshape(-1)
    rays = cand[np.isfinite(best[cand])]  # ascending: cols are sorted
    beam, j = rays // n_az, rays % n_az
    if azimuth_range is not None:
        lo_a, hi_a = np.radians(azimuth_range)
        az = np.arctan2(sin_az[beam, j], cos_az[beam, j])
        inside = ((az - lo_a) % (2 * np.pi) <= hi_a - lo_a + 1e-12) if hi_a - lo_a < 2 * np.pi \
            else np.ones(len(rays), bool)
        rays, beam, j = rays[inside], beam[inside], j[inside]
    if dropout > 0:
        kept = rng.random(len(rays)) >= dropout
        rays, beam, j = rays[kept], beam[kept], j[kept]
    d = np.stack([cos_e[beam] * cos_az[beam, j], cos_e[beam] * sin_az[beam, j], sin_e[beam]], axis=1)
    r = best[rays]
    if range_noise_std > 0:
        r = r + rng.normal(0.0, range_noise_std, len(r))
    if mixed_pixel_prob > 0 and len(rays):
        r = _mix_pixels(best.reshape(n_beams, n_az), beam, j, r, pattern, rng, mixed_pixel_prob, mixed_pixel_jump)
    src = best_src[rays]
    on_obj = src >= 0
    obj = np.full(len(rays), -1, np.int32)
    obj[on_obj] = tri_obj[src[on_obj]]
    cos_inc = np.where(on_obj, np.abs((d * normals[np.maximum(src, 0)]).sum(1)) if len(normals) else 0.0,
                       np.abs(d[:, 2]))
    base = np.where(on_obj, refl[np.maximum(obj, 0)] if len(refl) else 0.0, ground_reflectivity)
    intensity = np.clip(base * (0.3 + 0.7 * cos_inc), 0, 1).astype(np.float32)
    points = (sensor + d * r[:, None]).astype(np.float32)
    return ScanResult(points, intensity, obj, beam.astype(np.int16))


def simulate_scan(meshes: list[Mesh], sensor_position: np.ndarray | tuple[float, float, float],
                  pattern: BeamPattern | str, rng: np.random.Generator, *,
                  azimuth_range: tuple[float, float] | None = None, range_noise_std: float = 0.02,
                  dropout: float = 0.05, max_range: float = 120.0, ground_z: float | None = None,
                  sensor_heading_deg: float = 0.0, mixed_pixel_prob: float = 0.0) -> np.ndarray:
    """(N,3) float32 world-frame returns of one revolution of `pattern` at `sensor_position` (see `scan_meshes`)."""
    if isinstance(pattern, str):
        pattern = BeamPattern.named(pattern)
    return scan_meshes(meshes, sensor_position, pattern, rng, azimuth_range=azimuth_range,
                       range_noise_std=range_noise_std, dropout=dropout, max_range=max_range,
                       ground_z=ground_z, sensor_heading_deg=sensor_heading_deg,
                       mixed_pixel_prob=mixed_pixel_prob).points

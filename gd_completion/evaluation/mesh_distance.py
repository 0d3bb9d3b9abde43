"""Exact Euclidean distance from points to a triangle mesh (numba): a uniform grid over the triangles' boxes,
searched in shells of cells around each point until the unsearched cells are farther than the closest triangle.

Each candidate triangle is measured with the closest-point-on-triangle test of Ericson (Real-Time Collision
Detection, 5.1.5, ClosestPtPointTriangle); a degenerate triangle (a segment or a point) by its three edges.
The grid only prunes which triangles are measured: the result is the minimum over every triangle.
"""
from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import numba
import numpy as np

from gd_completion.cell_grid import bucket_by_cell

__all__ = ["NEAR_SURFACE", "FAR_FROM_SURFACE", "MeshGrid", "mesh_grid", "grid_distance", "distance_to_mesh",
           "distances_to_meshes", "surface_shares"]

NEAR_SURFACE = 0.02        # on the surface: within 2 % of the vehicle length (normalised frame)
FAR_FROM_SURFACE = 0.03    # far from it: beyond 3 %
_CELLS_PER_TRIANGLE = 0.5  # grid cells per triangle over the bounding box (0.25-1: within 10 % on the vehicles)
_MAX_CELLS_PER_AXIS = 256


class MeshGrid(NamedTuple):
    """A mesh's triangles (F, 3, 3) float64 and their boxes (F, 6) (min xyz, max xyz), bucketed on a grid of
    `dims` (3,) int64 cells of `width` (3,) from `lo` (3,); `hi` (3,) is the triangles' maximum corner. The
    triangles whose box overlaps cell c are members[start[c]:start[c + 1]] (cells row-major, x slowest)."""

    triangles: np.ndarray
    boxes: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    width: np.ndarray
    dims: np.ndarray
    start: np.ndarray
    members: np.ndarray


@numba.njit(cache=True, nogil=True)
def _segment_sq(px: float, py: float, pz: float, ax: float, ay: float, az: float,
                bx: float, by: float, bz: float) -> float:
    """Squared distance from p to the segment ab (a point when a == b)."""
    ex, ey, ez = bx - ax, by - ay, bz - az
    ee = ex * ex + ey * ey + ez * ez
    t = 0.0
    if ee > 0.0:
        t = min(max(((px - ax) * ex + (py - ay) * ey + (pz - az) * ez) / ee, 0.0), 1.0)
    dx, dy, dz = ax + t * ex - px, ay + t * ey - py, az + t * ez - pz
    return dx * dx + dy * dy + dz * dz


@numba.njit(cache=True, nogil=True)
def _triangle_sq(px: float, py: float, pz: float, tri: np.ndarray) -> float:
    """Squared distance from p to the triangle tri (3, 3) (Ericson's ClosestPtPointTriangle)."""
    ax, ay, az = tri[0, 0], tri[0, 1], tri[0, 2]
    bx, by, bz = tri[1, 0], tri[1, 1], tri[1, 2]
    cx, cy, cz = tri[2, 0], tri[2, 1], tri[2, 2]
    abx, aby, abz = bx - ax, by - ay, bz - az
    acx, acy, acz = cx - ax, cy - ay, cz - az
    nx, ny, nz = aby * acz - abz * acy, abz * acx - abx * acz, abx * acy - aby * acx
    scale = max(abx * abx + aby * aby + abz * abz, acx * acx + acy * acy + acz * acz)
    if nx * nx + ny * ny + nz * nz <= 1e-24 * scale * scale:  # degenerate: a segment or a point
        return min(_segment_sq(px, py, pz, ax, ay, az, bx, by, bz),
                   min(_segment_sq(px, py, pz, bx, by, bz, cx, cy, cz),
                       _segment_sq(px, py, pz, cx, cy, cz, ax, ay, az)))
    apx, apy, apz = px - ax, py - ay, pz - az
    d1 = abx * apx + aby * apy + abz * apz
    d2 = acx * apx + acy * apy + acz * apz
    if d1 <= 0.0 and d2 <= 0.0:  # vertex region a
        qx, qy, qz = ax, ay, az
    else:
        bpx, bpy, bpz = px - bx, py - by, pz - bz
        d3 = abx * bpx + aby * bpy + abz * bpz
        d4 = acx * bpx + acy * bpy + acz * bpz
        vc = d1 * d4 - d3 * d2
        cpx, cpy, cpz = px - cx, py - cy, pz - cz
        d5 = abx * cpx + aby * cpy + abz * cpz
        d6 = acx * cpx + acy * cpy + acz * cpz
        vb = d5 * d2 - d1 * d6
        va = d3 * d6 - d5 * d4
        if d3 >= 0.0 and d4 <= d3:  # vertex region b
            qx, qy, qz = bx, by, bz
        elif vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:  # edge region ab
            v = d1 / (d1 - d3)
            qx, qy, qz = ax + v * abx, ay + v * aby, az + v * abz
        elif d6 >= 0.0 and d5 <= d6:  # vertex region c
            qx, qy, qz = cx, cy, cz
        elif vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:  # edge region ac
            w = d2 / (d2 - d6)
            qx, qy, qz = ax + w * acx, ay + w * acy, az + w * acz
        elif va <= 0.0 and d4 - d3 >= 0.0 and d5 - d6 >= 0.0:  # edge region bc
            w = (d4 - d3) / ((d4 - d3) + (d5 - d6))
            qx, qy, qz = bx + w * (cx - bx), by + w * (cy - by), bz + w * (cz - bz)
        else:  # the face
            denom = 1.0 / (va + vb + vc)
            v, w = vb * denom, vc * denom
            qx, qy, qz = ax + abx * v + acx * w, ay + aby * v + acy * w, az + abz * v + acz * w
    dx, dy, dz = qx - px, qy - py, qz - pz
    return dx * dx + dy * dy + dz * dz


@numba.njit(cache=True, nogil=True)
def _box_sq(px: float, py: float, pz: float, x0: float, y0: float, z0: float,
            x1: float, y1: float, z1: float) -> float:
    """Squared distance from p to the box [x0, x1] x [y0, y1] x [z0, z1]."""
    dx = max(x0 - px, 0.0, px - x1)
    dy = max(y0 - py, 0.0, py - y1)
    dz = max(z0 - pz, 0.0, pz - z1)
    return dx * dx + dy * dy + dz * dz


@numba.njit(cache=True, nogil=True)
def _cell_range(v: float, lo: float, width: float, dim: int) -> int:
    t = (v - lo) / width
    if t <= 0.0:
        return 0
    if t >= dim - 1:
        return dim - 1
    return int(t)


@numba.njit(cache=True, nogil=True)
def _bucket_triangles(boxes: np.ndarray, lo: np.ndarray, width: np.ndarray, dims: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray]:
    """(start, members): every triangle listed in each cell its box overlaps."""
    f = boxes.shape[0]
    span = np.empty((f, 6), np.int64)
    total = 0
    for t in range(f):
        n = 1
        for a in range(3):
            span[t, a] = _cell_range(boxes[t, a], lo[a], width[a], dims[a])
            span[t, 3 + a] = _cell_range(boxes[t, 3 + a], lo[a], width[a], dims[a])
            n *= span[t, 3 + a] - span[t, a] + 1
        total += n
    cell = np.empty(total, np.int64)
    owner = np.empty(total, np.int64)
    k = 0
    for t in range(f):
        for x in range(span[t, 0], span[t, 3] + 1):
            for y in range(span[t, 1], span[t, 4] + 1):
                for z in range(span[t, 2], span[t, 5] + 1):
                    cell[k] = (x * dims[1] + y) * dims[2] + z
                    owner[k] = t
                    k += 1
    start, order = bucket_by_cell(cell, dims[0] * dims[1] * dims[2])
    return start, owner[order]


@numba.njit(cache=True, nogil=True)
def _gap(v: float, v0: float, v1: float) -> float:
    g = max(v0 - v, 0.0, v - v1)
    return g * g


@numba.njit(cache=True, nogil=True)
def _unsearched_sq(p: np.ndarray, blo: np.ndarray, bhi: np.ndarray, lo: np.ndarray, hi: np.ndarray,
                   width: np.ndarray, dims: np.ndarray) -> float:
    """Squared distance from p (3,) to the grid's box outside the searched cells [blo, bhi] (inf: none left)."""
    best = np.inf
    for a in range(3):
        rest = 0.0
        for b in range(3):
            if b != a:
                rest += _gap(p[b], lo[b], hi[b])
        if blo[a] > 0:   # the slab below the searched cells
            best = min(best, rest + _gap(p[a], lo[a], min(lo[a] + blo[a] * width[a], hi[a])))
        if bhi[a] < dims[a] - 1:   # the slab above them
            best = min(best, rest + _gap(p[a], lo[a] + (bhi[a] + 1) * width[a], hi[a]))
    return best


@numba.njit(cache=True, nogil=True)
def _grid_distance(points: np.ndarray, triangles: np.ndarray, boxes: np.ndarray, lo: np.ndarray, hi: np.ndarray,
                   width: np.ndarray, dims: np.ndarray, start: np.ndarray, members: np.ndarray,
                   out: np.ndarray) -> None:
    c0 = np.empty(3, np.int64)
    blo = np.empty(3, np.int64)
    bhi = np.empty(3, np.int64)
    reach = max(dims[0], max(dims[1], dims[2]))
    for i in range(points.shape[0]):
        px, py, pz = points[i, 0], points[i, 1], points[i, 2]
        if not (np.isfinite(px) and np.isfinite(py) and np.isfinite(pz)):
            out[i] = np.nan
            continue
        for a in range(3):
            c0[a] = _cell_range(points[i, a], lo[a], width[a], dims[a])
        best = np.inf
        for ring in range(reach + 1):
            for a in range(3):
                blo[a] = max(c0[a] - ring, 0)
                bhi[a] = min(c0[a] + ring, dims[a] - 1)
            for x in range(blo[0], bhi[0] + 1):
                for y in range(blo[1], bhi[1] + 1):
                    inner = abs(x - c0[0]) < ring and abs(y - c0[1]) < ring
                    z = blo[2]
                    while z <= bhi[2]:
                        if inner and abs(z - c0[2]) < ring:
                            z = c0[2] + ring  # skip the shell's interior (searched before)
                            continue
                        cx0, cy0, cz0 = lo[0] + x * width[0], lo[1] + y * width[1], lo[2] + z * width[2]
                        if _box_sq(px, py, pz, cx0, cy0, cz0, cx0 + width[0], cy0 + width[1],
                                   cz0 + width[2]) < best:
                            c = (x * dims[1] + y) * dims[2] + z
                            for k in range(start[c], start[c + 1]):
                                t = members[k]
                                if _box_sq(px, py, pz, boxes[t, 0], boxes[t, 1], boxes[t, 2], boxes[t, 3],
                                           boxes[t, 4], boxes[t, 5]) < best:
                                    best = min(best, _triangle_sq(px, py, pz, triangles[t]))
                        z += 1
            if best <= _unsearched_sq(points[i], blo, bhi, lo, hi, width, dims):
                break
        out[i] = np.sqrt(best)


def mesh_grid(vertices: np.ndarray, faces: np.ndarray) -> MeshGrid:
    """The search grid of the mesh (`vertices` (V, 3), `faces` (F, 3) vertex indices); reuse it for many clouds."""
    vertices = np.asarray(vertices, np.float64).reshape(-1, 3)
    faces = np.asarray(faces).reshape(-1, 3)
    if not np.issubdtype(faces.dtype, np.integer):
        raise ValueError(f"mesh faces must be integer vertex indices, got {faces.dtype}")
    if len(faces) and (faces.min() < 0 or faces.max() >= len(vertices)):
        raise ValueError(f"mesh faces index vertices outside [0, {len(vertices)})")
    triangles = np.ascontiguousarray(vertices[faces])
    if not np.isfinite(triangles).all():
        raise ValueError("mesh vertices are not finite")
    boxes = np.concatenate([triangles.min(1), triangles.max(1)], axis=1) if len(faces) else np.zeros((0, 6))
    lo = boxes[:, :3].min(0) if len(faces) else np.zeros(3)
    hi = boxes[:, 3:].max(0) if len(faces) else np.zeros(3)
    extent = hi - lo
    floor = max(float(extent.max()), 1e-12) * 1e-2  # a flat mesh gets a flat grid
    h = (np.prod(np.maximum(extent, floor)) / (_CELLS_PER_TRIANGLE * max(len(faces), 1))) ** (1.0 / 3.0)
    dims = np.clip(np.ceil(extent / h), 1, _MAX_CELLS_PER_AXIS).astype(np.int64)
    width = np.where(extent > 0, extent / dims, 1.0)
    start, members = _bucket_triangles(boxes, lo, width, dims)
    return MeshGrid(triangles, boxes, lo, hi, width, dims, start, members)


def grid_distance(grid: MeshGrid, points: np.ndarray) -> np.ndarray:
    """(N,) float64 exact distance of each point (N, 3) to the mesh of `grid` (NaN for a non-finite point,
    inf for a mesh without faces)."""
    points = np.ascontiguousarray(np.asarray(points, np.float64).reshape(-1, 3))
    out = np.empty(len(points), np.float64)
    if len(grid.triangles) == 0:
        out[:] = np.where(np.isfinite(points).all(1), np.inf, np.nan)
        return out
    _grid_distance(points, grid.triangles, grid.boxes, grid.lo, grid.hi, grid.width, grid.dims, grid.start,
                   grid.members, out)
    return out


def distance_to_mesh(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(N,) float64 exact Euclidean distance of each point (N, 3) to the triangle mesh (`vertices` (V, 3),
    `faces` (F, 3))."""
    return grid_distance(mesh_grid(vertices, faces), points)


def distances_to_meshes(clouds: Sequence[np.ndarray], vertices: Sequence[np.ndarray],
                        faces: Sequence[np.ndarray]) -> list[np.ndarray]:
    """Per cloud set (S, N_k, 3) the (S, N_k) distances of sample s's points to mesh s (`vertices[s]`,
    `faces[s]`); each mesh's grid is built once for all the sets."""
    if len(vertices) != len(faces):
        raise ValueError(f"{len(vertices)} vertex arrays for {len(faces)} face arrays")
    arrays = [np.asarray(c, np.float64) for c in clouds]
    for c in arrays:
        if c.ndim != 3 or c.shape[-1] != 3 or len(c) != len(vertices):
            raise ValueError(f"clouds must be ({len(vertices)}, N, 3) arrays (one per mesh), got {c.shape}")
    out = [np.empty(c.shape[:2], np.float64) for c in arrays]
    for s, (v, f) in enumerate(zip(vertices, faces)):
        grid = mesh_grid(v, f)
        for c, d in zip(arrays, out):
            d[s] = grid_distance(grid, c[s])
    return out


def surface_shares(distances: np.ndarray, near: float = NEAR_SURFACE, far: float = FAR_FROM_SURFACE
                   ) -> tuple[float, float]:
    """(share of the distances within `near`, share beyond `far`) of all the points (NaN when there are none)."""
    d = np.asarray(distances, np.float64).ravel()
    if d.size == 0:
        return float("nan"), float("nan")
    return float(np.mean(d <= near)), float(np.mean(d > far))

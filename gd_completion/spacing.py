"""Even spacing: the network's output points moved along their own surface until their spacing is even.

A decoder trained with Chamfer terms places its N_o points unevenly: clumps where many points agree, gaps between
them, and a shell a few centimetres thick. Both cost coverage at a fixed point count (a gap is a part of the vehicle
no point stands for). After the network, each point is pushed away from its nearest neighbours within the plane
fitted to its neighbourhood (a tangential repulsion, as PU-Net's repulsion term but at inference, with no
learning), for a few iterations, and then moved part of the way onto that plane, which thins the shell. The points
stay on the surface the network estimated: the spacing evens out and the shape stays (the pushes move a point by
at most 5 x 0.3 of the median spacing along its plane; where a shell has an edge, its edge points move outwards by
about that). Deterministic and
batch independent; compiled (numba): about 2.8 ms for 2,048 points on one core with the network's kNN graph (the
neighbour search 1.6 ms, the planes and pushes 1.2 ms). Measured in docs/MODEL.md ("Even spacing",
`benchmarks/spacing_variants.py`); `SpacingSettings()` are the shipped values.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np

from gd_completion.kernels import knn

PLANE_NEIGHBOURS = 16   # the neighbourhood of a point's plane (normal and centre), the point itself added
_GRID_CELL = 0.072      # normalised units: the grid of the neighbour search (as the network's kNN graph)


@dataclass(frozen=True)
class SpacingSettings:
    """`iterations` of the tangential push away from the `neighbours` nearest points, each pass moving a point by at
    most `step` times the cloud's median nearest-neighbour distance (the weighted mean direction away from them);
    then `flatten` (0..1) of the distance to its neighbourhood's plane removed. `iterations=0` and `flatten=0` leave
    the points as they are."""

    iterations: int = 5
    neighbours: int = 8
    step: float = 0.3
    flatten: float = 0.3

    def __post_init__(self) -> None:
        if self.iterations < 0 or not 1 <= self.neighbours <= PLANE_NEIGHBOURS:
            raise ValueError(f"spacing: need iterations >= 0 and 1 <= neighbours <= {PLANE_NEIGHBOURS}")
        if not (0.0 <= self.step <= 1.0 and 0.0 <= self.flatten <= 1.0):
            raise ValueError("spacing: step and flatten must lie in [0, 1]")


SHIPPED_SPACING = SpacingSettings()   # the pipeline's (`VehicleCompleter(even_spacing=True)`) and the evaluation's


def even_spacing(points: np.ndarray, settings: SpacingSettings = SHIPPED_SPACING,
                 graph: np.ndarray | None = None) -> np.ndarray:
    """`points` (N, 3) or (B, N, 3), finite, evenly spaced along their own surface (see the module); the same shape,
    float32. Each point's `PLANE_NEIGHBOURS` nearest are searched among all points, or, given a neighbour `graph`
    (N, k) or (B, N, k) over them (such as the network's kNN graph over P_g, `GGDOutput.neighbours`, whose rows P_o
    keeps), among its neighbours and theirs (1.6 ms instead of 2.4 ms for 2,048 points; 96 % of the exact 16
    nearest). Clouds of fewer than 3 points are returned as they are."""
    clouds = np.asarray(points, np.float32)
    single = clouds.ndim == 2
    if single:
        clouds = clouds[None]
    if clouds.ndim != 3 or clouds.shape[2] != 3:
        raise ValueError(f"even_spacing: points must be (N, 3) or (B, N, 3), got {np.shape(points)}")
    if not np.isfinite(clouds).all():
        raise ValueError("even_spacing: non-finite points")
    clouds = np.ascontiguousarray(clouds)
    b, n = clouds.shape[:2]
    if graph is not None:
        graph = np.asarray(graph, np.int64)
        graph = graph[None] if single else graph
        if graph.ndim != 3 or graph.shape[:2] != (b, n) or graph.shape[2] < 1:
            raise ValueError(f"even_spacing: graph must be (N, k) per cloud of N points, got {graph.shape}")
        if ((graph < 0) | (graph >= n)).any():
            raise ValueError("even_spacing: graph indices outside the cloud")
    if n < 3 or (settings.iterations == 0 and settings.flatten == 0.0):
        out = clouds.copy()
    else:
        out = np.empty_like(clouds)
        k = min(PLANE_NEIGHBOURS, n - 1)
        for c in range(b):
            if graph is None:
                nbr = knn(clouds[c:c + 1], clouds[c:c + 1], k, margin=_GRID_CELL, block=64, windowed=False,
                          exclude_self=True, cell=_GRID_CELL)[1][0]
            else:
                nbr = _two_hop_nearest(clouds[c], np.ascontiguousarray(graph[c]), k)
            out[c] = _spread_cloud(clouds[c], nbr, settings.iterations, min(settings.neighbours, nbr.shape[1]),
                                   settings.step, settings.flatten)
    return out[0] if single else out


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _two_hop_nearest(points: np.ndarray, graph: np.ndarray, k: int) -> np.ndarray:
    """(N, k) int64: each point's k nearest among its `graph` neighbours and theirs (itself excluded), ascending;
    where fewer than k are found, the point itself fills the rest (its plane counts it again, the pushes skip it)."""
    n, g = graph.shape
    out = np.empty((n, k), np.int64)
    seen = np.full(n, -1, np.int64)
    cand = np.empty(g + g * g, np.int64)
    best_d = np.empty(k, np.float32)
    best_i = np.empty(k, np.int64)
    for i in range(n):
        seen[i] = i
        m = 0
        for s in range(g):   # the neighbours, then each one's neighbours, each candidate once
            for t in range(-1, g):
                j = graph[i, s] if t < 0 else graph[graph[i, s], t]
                if seen[j] != i:
                    seen[j] = i
                    cand[m] = j
                    m += 1
        # the k nearest candidates: fill, then replace the farthest kept while a candidate is nearer
        count = min(m, k)
        far = 0
        for s in range(m):
            j = cand[s]
            dx, dy, dz = points[i, 0] - points[j, 0], points[i, 1] - points[j, 1], points[i, 2] - points[j, 2]
            d = dx * dx + dy * dy + dz * dz
            if s < count:
                best_d[s] = d
                best_i[s] = j
                if d > best_d[far]:
                    far = s
            elif d < best_d[far]:
                best_d[far] = d
                best_i[far] = j
                for t in range(k):
                    if best_d[t] > best_d[far]:
                        far = t
        for s in range(1, count):   # ascending (insertion sort of the k kept)
            d, j = best_d[s], best_i[s]
            pos = s
            while pos > 0 and best_d[pos - 1] > d:
                best_d[pos] = best_d[pos - 1]
                best_i[pos] = best_i[pos - 1]
                pos -= 1
            best_d[pos] = d
            best_i[pos] = j
        for s in range(k):
            out[i, s] = best_i[s] if s < count else i
    return out


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _centre(points: np.ndarray, nbr: np.ndarray, i: int, centre: np.ndarray) -> None:
    """The centre of point i's neighbourhood (itself and its `nbr` row)."""
    k = nbr.shape[1]
    cx, cy, cz = float(points[i, 0]), float(points[i, 1]), float(points[i, 2])
    for s in range(k):
        j = nbr[i, s]
        cx += points[j, 0]
        cy += points[j, 1]
        cz += points[j, 2]
    centre[0], centre[1], centre[2] = cx / (k + 1), cy / (k + 1), cz / (k + 1)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _plane(points: np.ndarray, nbr: np.ndarray, i: int, centre: np.ndarray, normal: np.ndarray) -> None:
    """The centre of point i's neighbourhood (itself and its `nbr` row) and the unit normal of its least-squares
    plane (the covariance's smallest eigenvector, closed form); a zero normal where no plane is defined (the
    neighbourhood is a line or a point)."""
    k = nbr.shape[1]
    _centre(points, nbr, i, centre)
    cx, cy, cz = centre[0], centre[1], centre[2]
    a00 = a01 = a02 = a11 = a12 = a22 = 0.0
    for s in range(-1, k):
        j = i if s < 0 else nbr[i, s]
        x, y, z = points[j, 0] - cx, points[j, 1] - cy, points[j, 2] - cz
        a00 += x * x
        a01 += x * y
        a02 += x * z
        a11 += y * y
        a12 += y * z
        a22 += z * z
    normal[:] = 0.0
    q = (a00 + a11 + a22) / 3.0
    off = a01 * a01 + a02 * a02 + a12 * a12
    spread2 = (a00 - q) ** 2 + (a11 - q) ** 2 + (a22 - q) ** 2 + 2.0 * off
    if spread2 <= 1e-30:
        return   # isotropic or empty: no plane
    p = math.sqrt(spread2 / 6.0)
    b00, b11, b22 = (a00 - q) / p, (a11 - q) / p, (a22 - q) / p
    b01, b02, b12 = a01 / p, a02 / p, a12 / p
    r = 0.5 * (b00 * (b11 * b22 - b12 * b12) - b01 * (b01 * b22 - b12 * b02) + b02 * (b01 * b12 - b11 * b02))
    r = min(1.0, max(-1.0, r))
    smallest = q + 2.0 * p * math.cos(math.acos(r) / 3.0 + 2.0 * math.pi / 3.0)
    # rows of A - smallest I; their largest cross product is the eigenvector
    r0 = (a00 - smallest, a01, a02)
    r1 = (a01, a11 - smallest, a12)
    r2 = (a02, a12, a22 - smallest)
    best = 0.0
    for u, v in ((r0, r1), (r0, r2), (r1, r2)):
        nx, ny, nz = u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0]
        size = nx * nx + ny * ny + nz * nz
        if size > best:
            best = size
            normal[0], normal[1], normal[2] = nx, ny, nz
    if best <= 1e-12 * (spread2 * spread2):
        normal[:] = 0.0   # the smallest eigenvalue is repeated: a line-like neighbourhood has no plane
        return
    # one sign for one plane (its largest component positive): repeated points get the same tangent, and part
    normal /= math.sqrt(best)
    big = 0
    for c in range(1, 3):
        if abs(normal[c]) > abs(normal[big]):
            big = c
    if normal[big] < 0.0:
        normal *= -1.0


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _spacing(points: np.ndarray, nbr: np.ndarray) -> float:
    """The cloud's median distance from a point to its nearest distinct neighbour among `nbr` (0 when there is
    none)."""
    nearest = np.zeros(points.shape[0])
    count = 0
    for i in range(points.shape[0]):
        best = np.inf
        for s in range(nbr.shape[1]):
            j = nbr[i, s]
            d = (points[i, 0] - points[j, 0]) ** 2 + (points[i, 1] - points[j, 1]) ** 2 + \
                (points[i, 2] - points[j, 2]) ** 2
            if 0.0 < d < best:
                best = d
        if best < np.inf:
            nearest[count] = math.sqrt(best)
            count += 1
    return float(np.median(nearest[:count])) if count else 0.0


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _spread_cloud(points: np.ndarray, nbr: np.ndarray, iterations: int, neighbours: int,
                  step: float, flatten: float) -> np.ndarray:
    """Planes of the points' neighbourhoods, `iterations` tangential pushes, then `flatten` of the distance to the
    plane (its normal kept, its centre moved with the points) removed; float64 inside."""
    n = points.shape[0]
    cur = points.astype(np.float64)
    normals = np.zeros((n, 3))
    centre = np.zeros(3)
    for i in range(n):
        _plane(cur, nbr, i, centre, normals[i])
    h = _spacing(cur, nbr)
    nxt = cur.copy()
    if h > 0.0:
        inv_h2 = 1.0 / (h * h)
        for _ in range(iterations):
            for i in range(n):
                fx = fy = fz = 0.0
                wsum = 0.0
                nx, ny, nz = normals[i, 0], normals[i, 1], normals[i, 2]
                for s in range(neighbours):
                    j = nbr[i, s]
                    if j == i:   # a row padded with the point itself (no neighbour found)
                        continue
                    dx, dy, dz = cur[i, 0] - cur[j, 0], cur[i, 1] - cur[j, 1], cur[i, 2] - cur[j, 2]
                    d2 = dx * dx + dy * dy + dz * dz
                    if d2 > 0.0:
                        inv = 1.0 / math.sqrt(d2)
                        dx, dy, dz = dx * inv, dy * inv, dz * inv
                    else:   # a repeated point: the pair separates along a fixed tangent, in opposite directions
                        tx, ty, tz = (0.0, nz, -ny) if abs(nx) < 0.9 else (-nz, 0.0, nx)
                        size = math.sqrt(tx * tx + ty * ty + tz * tz)
                        sign = 1.0 if i > j else -1.0
                        if size > 0.0:
                            dx, dy, dz = sign * tx / size, sign * ty / size, sign * tz / size
                        else:
                            dx, dy, dz = sign, 0.0, 0.0
                    w = math.exp(-d2 * inv_h2)
                    fx += w * dx
                    fy += w * dy
                    fz += w * dz
                    wsum += w
                if wsum > 0.0:
                    fx, fy, fz = fx / wsum, fy / wsum, fz / wsum
                along = fx * nx + fy * ny + fz * nz   # keep the push in the point's plane
                nxt[i, 0] = cur[i, 0] + step * h * (fx - along * nx)
                nxt[i, 1] = cur[i, 1] + step * h * (fy - along * ny)
                nxt[i, 2] = cur[i, 2] + step * h * (fz - along * nz)
            cur[:] = nxt
    if flatten > 0.0:
        for i in range(n):
            _centre(cur, nbr, i, centre)
            off = (nxt[i, 0] - centre[0]) * normals[i, 0] + (nxt[i, 1] - centre[1]) * normals[i, 1] + \
                (nxt[i, 2] - centre[2]) * normals[i, 2]
            nxt[i, 0] -= flatten * off * normals[i, 0]
            nxt[i, 1] -= flatten * off * normals[i, 1]
            nxt[i, 2] -= flatten * off * normals[i, 2]
    return nxt.astype(np.float32)

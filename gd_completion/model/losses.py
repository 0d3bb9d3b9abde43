"""GGD-Net losses: Chamfer (squared L2), smooth-L1 on control points, umbrella-Laplacian shape loss, and the
optional surface term (unsquared distance of each output point to the nearest ground-truth point, or to that point's
tangent plane) and repulsion term (output points closer than `REPULSION_RADIUS` to their graph neighbours pushed
apart)."""
from __future__ import annotations

import torch
from torch import Tensor

from .ops import flat_index, gather_points, knn_graph, nearest_index, neighbour_mean

# Chamfer and Laplacian terms are reported in units of 1e-3 (normalised frame), as in the paper.
CD_SCALE = 1000.0
# The surface term is reported in units of 1e-2 (per cent of the vehicle's length).
SURFACE_SCALE = 100.0
NEAR_REFERENCE = 0.03   # `drive_loss`'s precision term: output points farther from the partial reference feel no pull
# The repulsion term's radius (normalised frame): about the spacing of N_o = 2,048 points spread evenly over a car's
# surface (about 2 square lengths: 1e-3 each, 0.03 apart).
REPULSION_RADIUS = 0.03
# Neighbours of each ground-truth point whose least-squares plane gives its normal (`target_normals`): with 4,096
# points on a car (about 0.02 lengths apart) a patch about 0.1 lengths across.
NORMAL_NEIGHBOURS = 16


def nearest_indices(a: Tensor, b: Tensor, chunk_entries: int = 1 << 22) -> tuple[Tensor, Tensor]:
    """(nearest b of every a (B, Na), nearest a of every b (B, Nb)), no gradient (`ops.nearest_index`)."""
    return nearest_index(a, b, chunk_entries), nearest_index(b, a, chunk_entries)


def chamfer_l2_directional(a: Tensor, b: Tensor) -> tuple[Tensor, Tensor]:
    """(mean_a min_b |a-b|^2, mean_b min_a |a-b|^2), each (B,), for a (B, Na, 3) and b (B, Nb, 3).

    The nearest neighbours are searched without autograd; the distances to them are recomputed
    exactly, so value and gradient equal those of the min over the full matrix (up to ties), at a
    fraction of the memory and time of differentiating through the (B, Na, Nb) matrix.
    """
    ia, ib = nearest_indices(a, b)
    return _squared_to(a, b, ia).mean(1), _squared_to(b, a, ib).mean(1)


def _squared_to(a: Tensor, b: Tensor, nearest: Tensor) -> Tensor:
    """(B, Na): squared distance of every point of `a` to its `nearest` point of `b` (indices (B, Na))."""
    return (a - gather_points(b, nearest)).pow(2).sum(-1)


def _unsquared_mean(squared: Tensor, cap: float | None = None) -> Tensor:
    """(B,): mean over the points of the distances whose squares are `squared` (B, N), each capped at `cap` if given."""
    distance = (squared + 1e-12).sqrt()
    return (distance if cap is None else distance.clamp(max=cap)).mean(1)


def surface_distance(points: Tensor, gt: Tensor) -> Tensor:
    """Mean over `points` (B, N, 3) of the Euclidean (unsquared) distance to the nearest point of `gt`, (B,).

    Its gradient has the same size at 1 mm as at 10 cm, so unlike the squared Chamfer term it keeps pulling
    points that are already close onto the surface: a crisp shell instead of a cloud around it."""
    return _unsquared_mean(_squared_to(points, gt, nearest_index(points, gt)))


def target_normals(targets: Tensor, k: int = NORMAL_NEIGHBOURS, batch: int = 64) -> Tensor:
    """(S, N, 3) unit normals (no gradient, unoriented) of ground-truth samples `targets` (S, N, 3): the least-squares
    plane of each point and its `k` nearest, `batch` samples at a time."""
    normals = torch.empty_like(targets)
    for s in range(0, targets.shape[0], batch):
        chunk = targets[s:s + batch]
        offsets = chunk.unsqueeze(2) - gather_points(chunk, knn_graph(chunk, k))
        normals[s:s + batch] = _plane_normals(offsets)
    return normals


def plane_distance(points: Tensor, gt: Tensor, normals: Tensor, nearest: Tensor | None = None) -> Tensor:
    """Mean over `points` (B, N, 3) of the distance to the tangent plane (`normals` (B, M, 3)) of the nearest point
    of `gt` (B, M, 3), (B,): `surface_distance` without the part along the surface. The nearest sample of a surface
    sampled every 0.02 lengths lies about 0.01 lengths away from a point on the surface, so for a point nearer the
    surface than that the point-to-point term's pull is mostly sideways, towards the sample, and its part along the
    normal shrinks with the distance; the plane's distance pulls along the normal with the same force down to the
    surface. It does not pull along the surface: a point beyond a sheet's edge, in its plane, costs nothing here and
    is held by the Chamfer term alone. `nearest`: the indices (B, N) of the nearest `gt` point if already found."""
    nearest = nearest_index(points, gt) if nearest is None else nearest
    along = ((points - gather_points(gt, nearest)) * gather_points(normals, nearest)).sum(-1)
    return _unsquared_mean(along.pow(2))


def chamfer_and_surface(points: Tensor, gt: Tensor, normals: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """(`chamfer_l2(points, gt)`, `surface_distance(points, gt)`), each (B,), from one nearest-neighbour search; with
    `normals` of `gt`, the second is `plane_distance(points, gt, normals)`."""
    ia, ib = nearest_indices(points, gt)
    to_gt = _squared_to(points, gt, ia)
    to_surface = _unsquared_mean(to_gt) if normals is None else plane_distance(points, gt, normals, ia)
    return to_gt.mean(1) + _squared_to(gt, points, ib).mean(1), to_surface


def chamfer_l2(a: Tensor, b: Tensor) -> Tensor:
    """Chamfer distance (B,): squared L2, each direction averaged over its points, the two summed."""
    ab, ba = chamfer_l2_directional(a, b)
    return ab + ba


def smooth_l1(pred: Tensor, target: Tensor, sigma: float = 2.0) -> Tensor:
    """Fast R-CNN smooth-L1 (beta = 1/sigma^2), summed over xyz, averaged over points and batch."""
    beta = 1.0 / (sigma * sigma)
    diff = (pred - target).abs()
    loss = torch.where(diff < beta, 0.5 * diff * diff / beta, diff - 0.5 * beta)
    return loss.sum(-1).mean()


def laplacian_coordinates(points: Tensor, knn: Tensor) -> Tensor:
    """Umbrella Laplacian coordinates delta_i = p_i - mean_{j in kNN(i)} p_j, (B, N, 3)."""
    b, n, k = knn.shape
    return points - neighbour_mean(points, flat_index(knn, n), k)


def laplacian_loss(deformed: Tensor, reference: Tensor, knn: Tensor) -> Tensor:
    """L_shape = mean_i |delta_i(P_o) - delta_i(P_g)|^2 on the kNN graph of P_g (scale-dependent umbrella)."""
    diff = laplacian_coordinates(deformed, knn) - laplacian_coordinates(reference, knn)
    return diff.pow(2).sum(-1).mean()


def repulsion(points: Tensor, knn: Tensor, radius: float = REPULSION_RADIUS, tangential: bool = False) -> Tensor:
    """(B,): mean over every point of `points` (B, N, 3) and its `knn` (B, N, k) neighbours of max(0, radius - d)^2,
    d their distance: zero for evenly spread points at least `radius` apart, growing as they clump (PU-Net's
    repulsion term, with a truncated quadratic instead of its Gaussian-weighted distance). `tangential`: d measured
    within the point's plane (the least-squares plane of it and its neighbours, held fixed), so the term spreads
    points along the surface and not off it."""
    offsets = points.unsqueeze(2) - gather_points(points, knn)
    if tangential:
        normal = _plane_normals(offsets).unsqueeze(2)
        offsets = offsets - (offsets * normal).sum(-1, keepdim=True) * normal
    gaps = (offsets.pow(2).sum(-1) + 1e-12).sqrt()
    return torch.relu(radius - gaps).pow(2).mean((1, 2))


def _plane_normals(offsets: Tensor) -> Tensor:
    """(B, N, 3) unit normals (no gradient) of the least-squares planes of every point and its neighbours, from the
    `offsets` (B, N, k, 3) of the point from each neighbour (the point itself at offset 0)."""
    with torch.no_grad():
        group = torch.cat([torch.zeros_like(offsets[:, :, :1]), offsets], 2)
        centred = group - group.mean(2, keepdim=True)
        covariance = centred.transpose(2, 3) @ centred
        return torch.linalg.eigh(covariance.double())[1][..., 0].to(offsets.dtype)


def deformation_terms(output) -> tuple[Tensor, Tensor]:
    """(smoothL1(P_c', P_c), 1000 L_shape(P_o, P_g)): how far the control points moved and how much the deformation
    changed the local shape, the regularisers of `ggd_loss` and `drive_loss`."""
    control = smooth_l1(output.control_deformed, output.control)
    return control, laplacian_loss(output.completion, output.generated, output.neighbours) * CD_SCALE


def ggd_loss(output, gt: Tensor, lam: float, alpha: float = 1000.0, beta: float = 0.5, gamma: float = 0.0,
             rho: float = 0.0, tangential: bool = False, normals: Tensor | None = None) -> dict[str, Tensor]:
    """L = 1000 (CD(P_s, GT) + lam CD(P_o, GT)) + alpha smoothL1(P_c', P_c) + beta 1000 L_shape
    [+ gamma 100 surface(P_o, GT) when gamma > 0, with lam > 0: `surface_distance`, or `plane_distance` given the
    ground truth's `normals` (`target_normals`); a deviation from the paper]
    [+ rho 1000 repulsion(P_o) on the kNN graph of P_g when rho > 0: `repulsion`, within each point's plane when
    `tangential`; a deviation from the paper].

    Returns the terms (batch means, unweighted except for their unit factors) and `total`.
    """
    cd_coarse = chamfer_l2(output.coarse, gt).mean() * CD_SCALE
    surface = gamma > 0 and lam > 0
    cd, to_surface = chamfer_and_surface(output.completion, gt, normals) if surface else \
        (chamfer_l2(output.completion, gt), None)
    cd_fine = cd.mean() * CD_SCALE
    control, shape = deformation_terms(output)
    total = cd_coarse + lam * cd_fine + alpha * control + beta * shape
    terms = {"cd_coarse": cd_coarse, "cd_fine": cd_fine, "control": control, "shape": shape}
    if to_surface is not None:
        terms["surface"] = to_surface.mean() * SURFACE_SCALE
        total = total + gamma * terms["surface"]
    if rho > 0:
        terms["repulsion"] = repulsion(output.completion, output.neighbours, tangential=tangential).mean() * CD_SCALE
        total = total + rho * terms["repulsion"]
    return {"total": total, **terms}


def coverage(reference: Tensor, points: Tensor) -> Tensor:
    """(B,): mean over `reference` (B, R, 3) of the squared distance to the nearest of `points` (B, N, 3); the
    Chamfer distance's reference -> points half."""
    return _squared_to(reference, points, nearest_index(reference, points)).mean(1)


def near_reference_distance(points: Tensor, reference: Tensor, cap: float) -> Tensor:
    """(B,): mean over `points` (B, N, 3) of the unsquared distance to the nearest point of `reference`, capped at
    `cap`: a point within `cap` of a partial reference is pulled onto it, one farther away (where the reference may
    simply not have been seen) costs a constant and feels no pull."""
    return _unsquared_mean(_squared_to(points, reference, nearest_index(points, reference)), cap)


def drive_loss(output, reference: Tensor, lam: float, alpha: float = 1000.0, beta: float = 0.5,
               precision: float = 0.0, cap: float = NEAR_REFERENCE) -> dict[str, Tensor]:
    """`ggd_loss` for a partial reference (a real drive's multi-frame aggregate, `drive_frames.drive_pairs`): what
    is missing from it may still be vehicle, so only its coverage counts, L = 1000 (coverage(P_s) + lam
    coverage(P_o)) + alpha smoothL1(P_c', P_c) + beta 1000 L_shape [+ precision 100 near_reference_distance(P_o,
    reference, cap) when precision > 0: the points near the reference kept on it] (a deviation from the paper).

    Returns the terms (batch means, unweighted except for their unit factors) and `total`."""
    coverage_coarse = coverage(reference, output.coarse).mean() * CD_SCALE
    coverage_fine = coverage(reference, output.completion).mean() * CD_SCALE
    control, shape = deformation_terms(output)
    total = coverage_coarse + lam * coverage_fine + alpha * control + beta * shape
    terms = {"coverage_coarse": coverage_coarse, "coverage_fine": coverage_fine, "control": control, "shape": shape}
    if precision > 0:
        terms["near_reference"] = near_reference_distance(output.completion, reference, cap).mean() * SURFACE_SCALE
        total = total + precision * terms["near_reference"]
    return {"total": total, **terms}

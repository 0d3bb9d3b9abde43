"""Exact point-to-mesh distance (evaluation.mesh_distance) and the true meshes of the synthetic pairs."""
from __future__ import annotations

import numpy as np
import pytest

from gd_completion.evaluation.mesh_distance import (
    distance_to_mesh,
    distances_to_meshes,
    mesh_grid,
    surface_shares,
)

SQUARE_V = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 1.0, 0.0], [0.0, 1.0, 0.0]])
SQUARE_F = np.array([[0, 1, 2], [0, 2, 3]])


def _brute(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Distance to every triangle in numpy: the plane's foot when it falls inside, else the nearest edge."""
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    ab, ac = b - a, c - a
    n = np.cross(ab, ac)
    nn = (n * n).sum(1)
    flat = nn > 1e-20
    out = np.empty(len(points))
    for i, p in enumerate(points):
        t = ((p - a) * n).sum(1) / np.where(flat, nn, 1.0)
        q = p - t[:, None] * n - a
        d00, d01, d11 = (ab * ab).sum(1), (ab * ac).sum(1), (ac * ac).sum(1)
        d20, d21 = (q * ab).sum(1), (q * ac).sum(1)
        den = np.where(flat, d00 * d11 - d01 * d01, 1.0)
        v, w = (d11 * d20 - d01 * d21) / den, (d00 * d21 - d01 * d20) / den
        inside = flat & (v >= 0) & (w >= 0) & (v + w <= 1)
        best = np.where(inside, np.abs(t) * np.sqrt(nn), np.inf)
        for s0, s1 in ((a, b), (b, c), (c, a)):
            e = s1 - s0
            ee = (e * e).sum(1)
            u = np.clip(((p - s0) * e).sum(1) / np.where(ee > 0, ee, 1.0), 0.0, 1.0)
            best = np.minimum(best, np.linalg.norm(s0 + u[:, None] * e - p, axis=1))
        out[i] = best.min()
    return out


def test_unit_square_hand_computed():
    points = np.array([[0.3, 0.6, 0.25], [0.7, 0.2, -0.7], [0.5, 0.5, 0.0],   # above / below / on the face
                       [0.5, -0.4, 0.3], [1.6, 0.5, 0.0],                       # beyond an edge
                       [1.3, 1.4, 0.0], [-0.3, -0.4, 1.2]])                     # beyond a corner
    expected = [0.25, 0.7, 0.0, 0.5, 0.6, 0.5, 1.3]
    np.testing.assert_allclose(distance_to_mesh(points, SQUARE_V, SQUARE_F), expected, atol=1e-12)


def test_degenerate_triangles():
    segment = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [2.0, 0.0, 0.0]])  # collinear: the segment 0-2
    points = np.array([[1.5, 0.3, 0.4], [3.0, 0.0, 0.0], [-0.6, 0.8, 0.0]])
    np.testing.assert_allclose(distance_to_mesh(points, segment, np.array([[0, 1, 2]])), [0.5, 1.0, 1.0],
                               atol=1e-12)
    point = np.array([[1.0, 2.0, 3.0]] * 3)   # all three corners on one spot
    assert distance_to_mesh(np.array([[1.0, 2.0, 5.0]]), point, np.array([[0, 1, 2]]))[0] == pytest.approx(2.0)
    # a sliver next to a proper triangle changes nothing where the proper triangle is nearer
    mesh_v = np.vstack([SQUARE_V, [[5.0, 5.0, 5.0], [6.0, 5.0, 5.0]]])
    mesh_f = np.vstack([SQUARE_F, [[4, 5, 5]]])
    assert distance_to_mesh(np.array([[0.3, 0.6, 0.25]]), mesh_v, mesh_f)[0] == pytest.approx(0.25)


def test_matches_brute_force_on_a_random_mesh():
    rng = np.random.default_rng(3)
    vertices = rng.normal(size=(80, 3)) * [1.0, 0.5, 0.3]
    faces = rng.integers(0, 80, (150, 3))
    faces[:5, 2] = faces[:5, 1]   # a few degenerate ones
    points = np.vstack([rng.normal(size=(300, 3)), rng.normal(size=(30, 3)) * 10.0])  # inside and far outside
    np.testing.assert_allclose(distance_to_mesh(points, vertices, faces), _brute(points, vertices, faces),
                               rtol=1e-12, atol=1e-12)


def test_never_above_a_dense_surface_sample():
    from scipy.spatial import cKDTree

    from gd_completion.synth.meshio import sample_surface
    from gd_completion.synth.vehicles import generate_vehicle

    rng = np.random.default_rng(5)
    mesh = generate_vehicle(rng, "pickup")
    sample = sample_surface(mesh, 40_000, rng)
    points = rng.uniform(mesh.bounds[0] - 0.5, mesh.bounds[1] + 0.5, (2000, 3))
    exact = distance_to_mesh(points, mesh.vertices, mesh.faces)
    nearest_sample = cKDTree(sample).query(points)[0]
    assert np.all(exact <= nearest_sample + 1e-12)
    assert np.median(nearest_sample - exact) < 0.05   # a dense sample is close to the surface, not on it
    assert distance_to_mesh(sample[:500], mesh.vertices, mesh.faces).max() < 1e-9   # drawn on the triangles


def test_batch_shares_and_bad_input():
    rng = np.random.default_rng(1)
    clouds = rng.uniform(-0.5, 1.5, (2, 50, 3))
    meshes_v = [SQUARE_V, SQUARE_V * 2.0]
    (batch,) = distances_to_meshes([clouds], meshes_v, [SQUARE_F, SQUARE_F])
    for s in range(2):
        np.testing.assert_array_equal(batch[s], distance_to_mesh(clouds[s], meshes_v[s], SQUARE_F))
    assert surface_shares(np.array([0.0, 0.01, 0.02, 0.025, 0.03, 0.05])) == (0.5, pytest.approx(1 / 6))
    assert np.isnan(distance_to_mesh(np.array([[np.nan, 0.0, 0.0]]), SQUARE_V, SQUARE_F)[0])
    assert distance_to_mesh(np.zeros((1, 3)), SQUARE_V, np.zeros((0, 3), int))[0] == np.inf
    with pytest.raises(ValueError, match="outside"):
        mesh_grid(SQUARE_V, np.array([[0, 1, 4]]))
    with pytest.raises(ValueError, match="one per mesh"):
        distances_to_meshes([clouds[:1]], meshes_v, [SQUARE_F, SQUARE_F])


# --- the synthetic pairs' true meshes ----------------------------------------------------------------

@pytest.mark.parametrize("options", ["v1", "v2"])
def test_surface_mesh_leaves_the_pair_unchanged(options, shared_data):
    from gd_completion.synth.dataset import V1_SAMPLING, V2_SAMPLING, make_sample, sample_rng
    from gd_completion.synth.meshio import load_mesh_folder

    opts = V1_SAMPLING if options == "v1" else V2_SAMPLING   # v2: noisy boxes, tilted sensors
    meshes = load_mesh_folder(shared_data / "vehicle-meshes", only=("basic_taxi",))
    for i, source in enumerate((None, meshes, None)):
        plain = make_sample(sample_rng(11, i), source, surface_resample=True, options=opts)
        with_mesh = make_sample(sample_rng(11, i), source, surface_resample=True, options=opts, surface_mesh=True)
        np.testing.assert_array_equal(plain[0], with_mesh[0])
        np.testing.assert_array_equal(plain[1], with_mesh[1])
        meta = with_mesh[2]
        assert set(meta) - set(plain[2]) == {"mesh_vertices", "mesh_faces"}
        for key, value in plain[2].items():
            np.testing.assert_array_equal(value, meta[key])
        vertices, faces = meta["mesh_vertices"], meta["mesh_faces"]
        assert vertices.dtype == np.float32 and faces.dtype == np.int32 and faces.max() < len(vertices)
        # the mesh is in the pair's frame: both surface samples lie on it (float32 normalisation)
        assert distance_to_mesh(plain[1], vertices, faces).max() < 1e-5
        assert distance_to_mesh(meta["surface_resample"], vertices, faces).max() < 1e-5


def test_build_dataset_meshes_as_lists(tmp_path):
    from gd_completion.synth.dataset import build_dataset, save_dataset

    plain = build_dataset(3, 21)
    data = build_dataset(3, 21, surface_mesh=True)
    for key, value in plain.items():
        if key != "metadata":
            np.testing.assert_array_equal(value, data[key])
    assert len(data["mesh_vertices"]) == len(data["mesh_faces"]) == 3
    for v, f, gt in zip(data["mesh_vertices"], data["mesh_faces"], data["complete"]):
        assert v.shape[1] == 3 and f.shape[1] == 3 and distance_to_mesh(gt, v, f).max() < 1e-5
    with pytest.raises(ValueError, match="per-sample meshes"):
        save_dataset(tmp_path / "meshes.npz", data)

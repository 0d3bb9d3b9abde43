"""Tests of the synthetic data generator: vehicles, mesh files, lidar simulation, demo drive, datasets."""
from __future__ import annotations

import json
import struct

import numpy as np
import pytest

from gd_completion.errors import DataFormatError
from gd_completion.synth.beams import BeamPattern
from gd_completion.synth.lidar import scan_meshes, simulate_scan
from gd_completion.synth.meshio import (
    Mesh,
    box_mesh,
    load_mesh,
    load_mesh_folder,
    mesh_folder_digest,
    sample_surface,
)
from gd_completion.synth.vehicles import BASE_KINDS, KIND_SIZE_RANGES, generate_vehicle, vehicle_label

# --- helpers --------------------------------------------------------------------------------------------


def triangle_set(faces: np.ndarray) -> list[tuple[int, ...]]:
    """Faces as a sorted list, each rotated to start at its smallest index (winding kept): triangulation order
    and starting vertex do not matter, orientation does."""
    faces = np.asarray(faces)
    return sorted(tuple(np.roll(f, -int(np.argmin(f))).tolist()) for f in faces)


def point_triangle_distance(points: np.ndarray, tris: np.ndarray) -> np.ndarray:
    """Distance of each point (N,3) to the nearest triangle of tris (F,3,3) (exact, brute force)."""
    best = np.full(len(points), np.inf)
    a, b, c = tris[:, 0], tris[:, 1], tris[:, 2]
    n = np.cross(b - a, c - a)
    nn = np.maximum((n * n).sum(-1), 1e-30)
    for s in range(0, len(points), 256):
        p = points[s:s + 256, None, :].astype(np.float64)
        # projection onto the plane, inside test by barycentric signs
        d_plane = ((p - a) * n).sum(-1) / np.sqrt(nn)
        q = p - (((p - a) * n).sum(-1) / nn)[..., None] * n
        inside = ((np.cross(b - a, q - a) * n).sum(-1) >= 0) & ((np.cross(c - b, q - b) * n).sum(-1) >= 0) \
            & ((np.cross(a - c, q - c) * n).sum(-1) >= 0)
        d = np.where(inside, np.abs(d_plane), np.inf)
        for u, v in ((a, b), (b, c), (c, a)):
            e = v - u
            t = np.clip(((p - u) * e).sum(-1) / np.maximum((e * e).sum(-1), 1e-30), 0, 1)
            d = np.minimum(d, np.linalg.norm(p - (u + t[..., None] * e), axis=-1))
        best[s:s + 256] = d.min(axis=1)
    return best


def brute_force_scan(mesh: Mesh, sensor: np.ndarray, pattern: BeamPattern) -> np.ndarray:
    """Every ray against every triangle (reference for the windowed ray caster)."""
    e = np.radians(np.asarray(pattern.elevations_deg))[:, None]
    az = np.arange(pattern.n_azimuth)[None, :] * 2 * np.pi / pattern.n_azimuth \
        + np.radians(np.asarray(pattern.azimuth_offsets_deg))[:, None]
    d = np.stack([np.cos(e) * np.cos(az), np.cos(e) * np.sin(az), np.broadcast_to(np.sin(e), az.shape)], -1)
    d = d.reshape(-1, 3)
    tris = mesh.triangles() - sensor
    v0, e1, e2 = tris[:, 0], tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0]
    best = np.full(len(d), np.inf)
    for s in range(0, len(d), 256):
        r = d[s:s + 256, None, :]
        p = np.cross(r, e2[None])
        det = (e1[None] * p).sum(-1)
        with np.errstate(all="ignore"):
            u = (-v0[None] * p).sum(-1) / det
            q = np.cross(-v0[None], e1[None])
            v = (r * q).sum(-1) / det
            t = (e2[None] * q).sum(-1) / det
        ok = (np.abs(det) > 1e-12) & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 1e-6)
        best[s:s + 256] = np.where(ok, t, np.inf).min(axis=1)
    hit = np.isfinite(best)
    return (sensor + d[hit] * best[hit, None]).astype(np.float32)


def sorted_rows(a: np.ndarray) -> np.ndarray:
    return a[np.lexsort(a.T[::-1])]


# --- vehicles --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("kind", BASE_KINDS)  # the composite kinds: test_synth_v2
def test_vehicle_sizes_in_range_and_centred(kind):
    for seed in range(4):
        mesh = generate_vehicle(np.random.default_rng(seed), kind)
        lo, hi = mesh.bounds
        np.testing.assert_allclose((lo + hi) / 2, 0.0, atol=1e-9)
        for axis, (a, b) in enumerate(KIND_SIZE_RANGES[kind]):
            assert a - 1e-6 <= mesh.extent[axis] <= b + 1e-6, (kind, axis, mesh.extent)
        assert mesh.vertices.dtype == np.float64 and mesh.faces.dtype == np.int64
        assert mesh.faces.min() >= 0 and mesh.faces.max() < len(mesh.vertices)
        assert len(mesh.faces) > 500
    assert vehicle_label(kind) in ("car", "van", "truck")


def test_vehicle_shape_has_cabin_and_wheels():
    mesh = generate_vehicle(np.random.default_rng(3), "sedan")
    length, width, height = mesh.extent
    v = mesh.vertices
    # the roof is narrower than the body (greenhouse) and the lowest vertices are the wheels at the axles
    roof = v[v[:, 2] > height / 2 - 0.02]
    assert np.abs(roof[:, 1]).max() < 0.45 * width
    bottom = v[v[:, 2] < -height / 2 + 0.02]
    assert np.abs(bottom[:, 0]).min() > 0.15 * length  # no body at ground level between/over the axles' ends
    assert len(bottom) >= 4


def test_generator_determinism():
    a = generate_vehicle(np.random.default_rng(7))
    b = generate_vehicle(np.random.default_rng(7))
    c = generate_vehicle(np.random.default_rng(8))
    np.testing.assert_array_equal(a.vertices, b.vertices)
    np.testing.assert_array_equal(a.faces, b.faces)
    assert a.vertices.shape != c.vertices.shape or not np.array_equal(a.vertices, c.vertices)
    with pytest.raises(ValueError, match="unknown vehicle kind"):
        generate_vehicle(np.random.default_rng(0), "tank")


# --- mesh files ------------------------------------------------------------------------------------------


def raw_binary_ply(path) -> tuple[np.ndarray, np.ndarray]:
    """Vertices and faces of a binary PLY of float x, y, z and uchar/int triangles, straight from the bytes."""
    raw = path.read_bytes()
    body = raw.index(b"end_header\n") + len(b"end_header\n")
    header = raw[:body].decode().split("\n")
    assert header[1] == "format binary_little_endian 1.0"
    counts = {t[1]: int(t[2]) for t in (line.split() for line in header) if t and t[0] == "element"}
    vertices = np.frombuffer(raw, "<f4", counts["vertex"] * 3, body).reshape(-1, 3)
    faces = np.frombuffer(raw, [("n", "u1"), ("i", "<i4", (3,))], counts["face"], body + vertices.nbytes)
    assert (faces["n"] == 3).all() and body + vertices.nbytes + faces.nbytes == len(raw)
    return vertices.astype(np.float64), faces["i"].astype(np.int64)


def test_load_shared_ply_meshes(shared_data):
    folder = shared_data / "vehicle-meshes"
    manifest = json.loads((folder / "manifest.json").read_text())
    assert len(manifest["meshes"]) == 18
    for entry in manifest["meshes"]:
        mesh = load_mesh(folder / entry["file"])
        assert len(mesh.faces) > 1000
        np.testing.assert_allclose(mesh.extent, entry["extent_m"], atol=2e-3)
        vertices, faces = raw_binary_ply(folder / entry["file"])  # file order kept: nothing merged or dropped
        np.testing.assert_array_equal(mesh.vertices, vertices)
        np.testing.assert_array_equal(mesh.faces, faces)
    meshes = load_mesh_folder(folder)
    assert len(meshes) == 18
    for m in meshes:
        np.testing.assert_allclose(m.bounds.sum(axis=0), 0.0, atol=1e-6)


def test_load_small_ascii_files(tmp_path):
    quad_ply = ("ply\nformat ascii 1.0\ncomment test\nelement vertex 5\nproperty float x\nproperty float y\n"
                "property float z\nproperty uchar red\nelement face 2\nproperty list uchar int vertex_indices\n"
                "end_header\n0 0 0 1\n1 0 0 1\n1 1 0 1\n0 1 0 1\n0.5 0.5 1 1\n4 0 1 2 3\n3 0 1 4\n")
    (tmp_path / "q.ply").write_text(quad_ply)
    m = load_mesh(tmp_path / "q.ply")
    np.testing.assert_array_equal(m.vertices, [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0.5, 0.5, 1]])
    # the quad 0-1-2-3 becomes two triangles with its winding: 0-1-2 and 0-2-3 (or 2-3-0, the same triangle)
    assert triangle_set(m.faces) == [(0, 1, 2), (0, 1, 4), (0, 2, 3)]
    (tmp_path / "q.obj").write_text("# cube side\nv 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nvn 0 0 1\n"
                                    "f 1/1/1 2/2/1 3/3/1 4/4/1\nf -4 -3 -1\n")
    m = load_mesh(tmp_path / "q.obj")
    assert m.vertices.shape == (4, 3)
    assert triangle_set(m.faces) == [(0, 1, 2), (0, 1, 3), (0, 2, 3)]
    (tmp_path / "q.off").write_text("OFF\n# comment\n4 2 0\n0 0 0\n2 0 0\n2 2 0\n0 2 0\n3 0 1 2\n3 0 2 3\n")
    m = load_mesh(tmp_path / "q.off")
    assert m.faces.shape == (2, 3) and m.extent.tolist() == [2.0, 2.0, 0.0]


def test_load_binary_ply_quads(tmp_path):
    head = (b"ply\nformat binary_little_endian 1.0\nelement vertex 5\nproperty float x\nproperty float y\n"
            b"property float z\nelement face 2\nproperty list uchar int vertex_indices\nend_header\n")
    verts = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [2, 0, 0]], "<f4").tobytes()
    (tmp_path / "b.ply").write_bytes(head + verts + struct.pack("<B4i", 4, 0, 1, 2, 3)
                                     + struct.pack("<B4i", 4, 1, 4, 2, 3))
    m = load_mesh(tmp_path / "b.ply")
    assert triangle_set(m.faces) == [(0, 1, 2), (0, 2, 3), (1, 2, 3), (1, 4, 2)]
    # trimesh's binary PLY reader takes one list length for all faces: mixed polygons are a clear error
    mixed = head.replace(b"vertex 5", b"vertex 4")
    (tmp_path / "mixed.ply").write_bytes(mixed + verts[:48] + struct.pack("<B3i", 3, 0, 1, 2)
                                         + struct.pack("<B4i", 4, 0, 1, 2, 3))
    with pytest.raises(DataFormatError, match=r"mixed\.ply: cannot read PLY mesh"):
        load_mesh(tmp_path / "mixed.ply")


def test_load_glb_and_multi_part_files(tmp_path):
    import trimesh

    # glTF: +y up, +z forward, +x left; a car 4.5 m long (z), 1.8 m wide (x), 1.5 m high (y), and its wheel
    body = trimesh.creation.box(extents=(1.8, 1.5, 4.5))
    wheel = trimesh.creation.box(extents=(0.2, 0.6, 0.6), transform=trimesh.transformations.translation_matrix(
        (1.0, -0.5, 1.4)))
    (tmp_path / "car.glb").write_bytes(trimesh.Scene([body, wheel]).export(file_type="glb"))
    m = load_mesh(tmp_path / "car.glb")
    assert len(m.faces) == 24 and len(m.vertices) == 16
    np.testing.assert_allclose(m.bounds, [[-2.25, -0.9, -0.8], [2.25, 1.1, 0.75]], atol=1e-6)
    for part in m.triangles().reshape(2, 12, 3, 3):  # a rotation, not a mirror: faces still point outwards
        normals = np.cross(part[:, 1] - part[:, 0], part[:, 2] - part[:, 0])
        assert (np.einsum("ij,ij->i", normals, part.mean(axis=1) - part.mean(axis=(0, 1))) > 0).all()
    (tmp_path / "two.obj").write_text("o a\nv 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n"
                                      "o b\nv 0 0 1\nv 1 0 1\nv 0 1 1\nf 4 5 6\n")
    m = load_mesh(tmp_path / "two.obj")
    np.testing.assert_array_equal(m.faces, [[0, 1, 2], [3, 4, 5]])
    assert m.extent.tolist() == [1.0, 1.0, 1.0]


def test_corrupt_mesh_files_raise(tmp_path, shared_data):
    good = (shared_data / "vehicle-meshes" / "basic_taxi.ply").read_bytes()
    (tmp_path / "cut.ply").write_bytes(good[: len(good) // 2])
    (tmp_path / "bad.obj").write_text("v 0 0 x\nf 1 2 3\n")
    (tmp_path / "idx.off").write_text("OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 7\n")
    (tmp_path / "idx.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\n")
    (tmp_path / "nan.obj").write_text("v 0 0 nan\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    (tmp_path / "empty.obj").write_text("# no geometry\n")
    (tmp_path / "noply.ply").write_text("hello\n")
    (tmp_path / "junk.glb").write_bytes(b"glTF" + bytes(40))
    (tmp_path / "mesh.stl").write_text("solid x\n")
    for name in ("cut.ply", "bad.obj", "idx.off", "idx.obj", "nan.obj", "empty.obj", "noply.ply", "junk.glb",
                 "mesh.stl", "missing.ply"):
        with pytest.raises(DataFormatError, match=name.replace(".", r"\.")):
            load_mesh(tmp_path / name)
    (tmp_path / "empty").mkdir()
    with pytest.raises(DataFormatError, match=r"empty: no \.ply/\.obj/\.off/\.glb files"):
        load_mesh_folder(tmp_path / "empty")


def test_mesh_folder_digest_follows_names_and_contents(tmp_path, shared_data):
    source = shared_data / "vehicle-meshes"
    a, b = tmp_path / "a", tmp_path / "b"
    for folder in (a, b):
        folder.mkdir()
        for name in ("basic_taxi.ply", "public_bus.ply"):
            (folder / name).write_bytes((source / name).read_bytes())
    (b / "notes.txt").write_text("not a mesh")
    assert mesh_folder_digest(a) == mesh_folder_digest(b)  # same meshes elsewhere, other files ignored
    (b / "public_bus.ply").rename(b / "public_bus2.ply")
    renamed = mesh_folder_digest(b)
    assert renamed != mesh_folder_digest(a)
    raw = bytearray((b / "basic_taxi.ply").read_bytes())
    raw[-5] ^= 1  # same name, same size, one vertex index changed
    (b / "basic_taxi.ply").write_bytes(bytes(raw))
    assert mesh_folder_digest(b) not in (renamed, mesh_folder_digest(a))


def test_sample_surface_is_area_weighted():
    mesh = box_mesh((2.0, 1.0, 1.0))
    pts = sample_surface(mesh, 20000, np.random.default_rng(0))
    assert point_triangle_distance(pts[:500], mesh.triangles()).max() < 1e-9
    on_x = np.isclose(np.abs(pts[:, 0]), 1.0)
    assert abs(on_x.mean() - 0.2) < 0.015  # x faces: 2 of 10 square metres
    assert abs(np.isclose(np.abs(pts[:, 1]), 0.5).mean() - 0.4) < 0.015


# --- lidar -----------------------------------------------------------------------------------------------


def test_calibration_csv_matches_named_patterns(shared_data):
    folder = shared_data / "hesai-nebula" / "calibration"
    for file, name in (("Pandar40.csv", "pandar40"), ("Pandar40P.csv", "pandar40p"), ("Pandar64.csv", "pandar64")):
        csv_pattern, named = BeamPattern.from_csv(folder / file), BeamPattern.named(name)
        np.testing.assert_allclose(csv_pattern.elevations_deg, named.elevations_deg, atol=1e-9)
        np.testing.assert_allclose(csv_pattern.azimuth_offsets_deg, named.azimuth_offsets_deg, atol=1e-9)
    assert BeamPattern.from_csv(folder / "Pandar40M.csv").n_beams == 40


def test_named_patterns_and_bad_csv(tmp_path):
    hdl = BeamPattern.named("hdl64e")
    assert hdl.n_beams == 64 and max(hdl.elevations_deg) == pytest.approx(2.0)
    assert min(hdl.elevations_deg) == pytest.approx(-24.9)
    assert BeamPattern.named("pandar64").n_beams == 64 and BeamPattern.named("pandar40p").n_beams == 40
    with pytest.raises(ValueError):
        BeamPattern.named("vlp16x")
    (tmp_path / "x.csv").write_text("Channel,Elev,Az\n1,2,3\n")
    with pytest.raises(DataFormatError, match="x.csv"):
        BeamPattern.from_csv(tmp_path / "x.csv")
    (tmp_path / "y.csv").write_text("Laser id,Elevation,Azimuth\n1,abc,3\n")
    with pytest.raises(DataFormatError, match="y.csv"):
        BeamPattern.from_csv(tmp_path / "y.csv")


def test_scan_matches_brute_force_ray_casting():
    from gd_completion.synth.meshio import merge_meshes

    pattern = BeamPattern("coarse", tuple(np.linspace(5, -20, 24)), tuple(np.tile([-1.3, 0.0, 2.1], 8)), 0.8)
    rng = np.random.default_rng(1)
    wheel = generate_vehicle(rng, "hatchback")
    wheel = Mesh(wheel.vertices, wheel.faces[-300:])  # the last parts built: wheels and mirrors
    parts = [box_mesh((4.0, 1.8, 1.2), (0.0, 0.0, 0.9)).transformed(0.4, (9.0, 4.0, 0.0)),
             wheel.transformed(2.0, (-3.0, 2.5, 0.8)),  # close: grazing angles
             box_mesh((2.0, 0.5, 3.0), (0.0, 0.0, 1.5)).transformed(1.0, (-6.0, -7.0, 0.0)),
             Mesh([[-15.0, -15.0, 2.5], [20.0, -10.0, 2.3], [-5.0, 25.0, 2.2]], [[0, 1, 2]])]  # roof over the sensor
    world = merge_meshes(parts)
    sensor = np.array([0.0, 0.0, 1.8])
    fast = scan_meshes([world], sensor, pattern, rng, range_noise_std=0.0, dropout=0.0).points
    ref = brute_force_scan(world, sensor, pattern)
    assert len(fast) == len(ref) > 300
    assert np.sum(fast[:, 2] > 2.1) > 50  # the roof triangle (full-azimuth window) is hit
    np.testing.assert_allclose(sorted_rows(fast), sorted_rows(ref), atol=1e-5)


def test_scan_points_lie_on_mesh_surface():
    rng = np.random.default_rng(2)
    car = generate_vehicle(rng, "suv")
    world = car.transformed(1.1, (14.0, -5.0, car.extent[2] / 2))
    pts = simulate_scan([world], (0.0, 0.0, 1.9), BeamPattern.named("pandar64"), rng,
                        range_noise_std=0.0, dropout=0.0)
    assert pts.dtype == np.float32 and len(pts) > 300
    assert point_triangle_distance(pts[::5], world.triangles()).max() < 1e-4
    noisy = simulate_scan([world], (0.0, 0.0, 1.9), "pandar64", rng, range_noise_std=0.02, dropout=0.3)
    d = point_triangle_distance(noisy[::5], world.triangles())
    assert 0.005 < np.median(d) < 0.03 and len(noisy) < 0.8 * len(pts)


def test_far_side_and_occluded_objects_are_hidden():
    rng = np.random.default_rng(3)
    box = box_mesh((4.0, 2.0, 1.5), (0.0, 0.0, 0.75))
    pts = simulate_scan([box], (15.0, 0.5, 1.0), BeamPattern.named("hdl64e"), rng, range_noise_std=0.0, dropout=0.0)
    assert np.sum(np.isclose(pts[:, 0], 2.0, atol=1e-3)) > 100        # near face seen
    assert np.sum(pts[:, 0] < 1.999) == 0  # top (1.5 m) is above the 1.0 m sensor
    bus = generate_vehicle(rng, "bus")
    world = bus.transformed(0.0, (0.0, 0.0, bus.extent[2] / 2))
    pts = simulate_scan([world], (25.0, 0.0, 1.8), "pandar40p", rng, range_noise_std=0.0, dropout=0.0)
    assert len(pts) > 200 and pts[:, 0].min() > -bus.extent[0] / 2 + 0.3
    # a small box right behind a larger one, on the line of sight, gets no return; moved aside it does
    near = box_mesh((2.0, 4.0, 3.0), (8.0, 0.0, 1.5))
    far = box_mesh((1.0, 1.0, 1.0), (14.0, 0.0, 0.5))
    res = scan_meshes([near, far], (0.0, 0.0, 1.8), BeamPattern.named("hdl64e"), rng, ground_z=0.0)
    assert np.sum(res.object_index == 1) == 0 and np.sum(res.object_index == 0) > 100
    res = scan_meshes([near, box_mesh((1.0, 1.0, 1.0), (14.0, 6.0, 0.5))], (0.0, 0.0, 1.8),
                      BeamPattern.named("hdl64e"), rng, ground_z=0.0)
    assert np.sum(res.object_index == 1) > 10
    # the ground is only hit where no object is in front of it
    ground = res.points[res.object_index == -1]
    assert np.allclose(ground[:, 2], 0.0, atol=0.2)


def test_azimuth_window_and_range_limit():
    rng = np.random.default_rng(4)
    cars = [generate_vehicle(rng, "sedan").transformed(0.0, (12 * np.cos(a), 12 * np.sin(a), 0.72))
            for a in np.radians([0.0, 90.0, 180.0])]
    pts = simulate_scan(cars, (0.0, 0.0, 1.8), "hdl64e", rng, azimuth_range=(-20.0, 20.0), ground_z=0.0)
    az = np.degrees(np.arctan2(pts[:, 1], pts[:, 0]))
    assert len(pts) > 500 and np.all(np.abs(az) <= 20.0 + 1e-3)
    assert np.sum(pts[:, 2] > 0.3) > 200  # the car ahead is in it
    pts = simulate_scan(cars, (0.0, 0.0, 1.8), "hdl64e", rng, azimuth_range=(80.0, 100.0))
    assert np.all(np.abs(np.degrees(np.arctan2(pts[:, 1], pts[:, 0])) - 90.0) <= 10.0 + 1e-3) and len(pts) > 300
    pts = simulate_scan(cars, (0.0, 0.0, 1.8), "hdl64e", rng, ground_z=0.0, max_range=30.0, range_noise_std=0.0)
    assert np.linalg.norm(pts - [0.0, 0.0, 1.8], axis=1).max() <= 30.0 + 1e-3


def test_scan_is_deterministic_and_independent_of_chunking():
    """Same generator state, same scan bit for bit, however many (ray, triangle) pairs go into one chunk."""
    car = generate_vehicle(np.random.default_rng(5), "sedan")
    world = car.transformed(0.7, (13.0, 6.0, car.extent[2] / 2))
    pattern = BeamPattern.named("pandar40p")

    def scan(seed: int, **kw):
        return scan_meshes([world], (0.0, 0.0, 1.8), pattern, np.random.default_rng(seed), ground_z=0.0, **kw)

    first, again, chunked = scan(1), scan(1), scan(1, max_pairs=300)  # 3 chunks -> 26
    assert np.sum(first.object_index == 0) > 300 and np.sum(first.object_index == -1) > 1000
    for other in (again, chunked):
        for field in ("points", "intensity", "object_index", "ring"):
            np.testing.assert_array_equal(getattr(first, field), getattr(other, field))
    other_seed = scan(2)  # another seed: other dropouts and range noise, the same geometry
    assert not np.array_equal(other_seed.points[:100], first.points[:100])
    np.testing.assert_allclose(len(other_seed.points), len(first.points), rtol=0.02)


# --- demo drive ------------------------------------------------------------------------------------------


def test_synthetic_drive():
    from gd_completion.geometry import crop_boxes
    from gd_completion.synth.scene import SENSOR_HEIGHT, synthetic_drive

    frames = synthetic_drive(seed=3, n_frames=3, n_vehicles=5)
    again = synthetic_drive(seed=3, n_frames=3, n_vehicles=5)
    other = synthetic_drive(seed=4, n_frames=1, n_vehicles=5)
    assert len(frames) == 3
    np.testing.assert_array_equal(frames[2].points, again[2].points)
    assert not np.array_equal(frames[0].points[:1000], other[0].points[:1000])
    assert [f.stamp_ns - frames[0].stamp_ns for f in frames] == [0, 100_000_000, 200_000_000]
    ids = [sorted(b.instance_id for b in f.boxes) for f in frames]
    assert ids[0] == ids[1] == ids[2] and len(ids[0]) == 5
    for f in frames:
        assert f.points.dtype == np.float32 and f.intensity.shape == (len(f.points),) and len(f.points) > 50_000
        assert 0.0 <= f.intensity.min() and f.intensity.max() <= 1.0
        assert np.percentile(f.points[:, 2], 5) == pytest.approx(-SENSOR_HEIGHT, abs=0.1)  # ground
        for box, _idx in zip(f.boxes, crop_boxes(f.points, f.boxes, 0.1)):
            assert box.label in ("car", "van", "truck")
            assert box.center[2] - box.size[2] / 2 == pytest.approx(-SENSOR_HEIGHT, abs=1e-6)
            assert 5.0 - 1e-6 <= np.hypot(*box.center[:2]) or f is not frames[0]
        assert sum(len(i) > 20 for i in crop_boxes(f.points, f.boxes, 0.1)) >= 3
    first = {b.instance_id: b for b in frames[0].boxes}
    moved = [frames[1].boxes[k].center[0] - first[frames[1].boxes[k].instance_id].center[0] for k in range(5)]
    assert any(m == pytest.approx(-1.0, abs=1e-6) for m in moved)  # a parked car drifts back as the ego drives


# --- dataset ---------------------------------------------------------------------------------------------


def test_make_sample_normalised_pair():
    from gd_completion.synth.dataset import make_sample, sample_rng

    partial, complete, meta = make_sample(sample_rng(0, 1), "sedan", pattern="hdl64e", n_input=256, n_gt=4096)
    assert partial.shape == (256, 3) and complete.shape == (4096, 3)
    assert partial.dtype == np.float32 and complete.dtype == np.float32
    assert complete[:, 0].max() - complete[:, 0].min() == pytest.approx(1.0, abs=0.02)  # divided by length
    assert np.abs(complete).max() <= 0.5 + 1e-5
    assert np.abs(partial[:, 0]).max() <= 0.5 + 0.1 / meta["size"][0] + 1e-4
    assert meta["n_points"] >= 20 and 5.0 <= meta["distance"] <= 50.0 and meta["label"] == "car"
    again = make_sample(sample_rng(0, 1), "sedan", pattern="hdl64e", n_input=256, n_gt=4096)
    np.testing.assert_array_equal(partial, again[0])
    np.testing.assert_array_equal(complete, again[1])
    # the partial lies on the ground-truth surface (up to noise), so its one-sided Chamfer is small
    d = np.sqrt(((partial[:, None, :] - complete[None, :, :]) ** 2).sum(-1)).min(axis=1) * meta["size"][0]
    assert np.median(d) < 0.06


def test_dataset_round_trip_and_determinism(tmp_path):
    from gd_completion.synth.dataset import GENERATOR_VERSION, build_dataset, load_dataset, save_dataset

    data = build_dataset(4, seed=11, n_input=128, n_gt=256, patterns=("pandar64", "hdl64e"))
    assert data["partial"].shape == (4, 128, 3) and data["complete"].shape == (4, 256, 3)
    assert data["metadata"]["generator_version"] == GENERATOR_VERSION and data["metadata"]["seed"] == 11
    part = build_dataset(2, seed=11, n_input=128, n_gt=256, patterns=("pandar64", "hdl64e"))
    np.testing.assert_array_equal(part["partial"], data["partial"][:2])  # sample i depends on (seed, i) only
    other = build_dataset(2, seed=12, n_input=128, n_gt=256, patterns=("pandar64", "hdl64e"))
    assert not np.array_equal(other["complete"], data["complete"][:2])
    path = save_dataset(tmp_path / "ds.npz", data)
    loaded = load_dataset(path)
    assert loaded["partial"].dtype == np.float32
    np.testing.assert_allclose(loaded["partial"], data["partial"], atol=1e-3)
    np.testing.assert_allclose(loaded["complete"], data["complete"], atol=1e-3)
    for key in ("label", "kind", "pattern", "n_points"):
        np.testing.assert_array_equal(loaded[key], data[key])
    assert loaded["metadata"]["seed"] == 11 and loaded["metadata"]["n_samples"] == 4
    (tmp_path / "bad.npz").write_bytes(path.read_bytes()[:200])
    with pytest.raises(DataFormatError, match="bad.npz"):
        load_dataset(tmp_path / "bad.npz")


def test_dataset_with_mesh_folder(shared_data):
    from gd_completion.synth.dataset import build_dataset

    data = build_dataset(3, seed=2, meshes_dir=shared_data / "vehicle-meshes", mesh_fraction=1.0,
                         n_input=128, n_gt=256)
    assert all(k.startswith("mesh:") for k in data["kind"])
    assert data["metadata"]["mesh_fraction"] == 1.0
    assert np.all(data["n_points"] >= 20)


def test_dataset_workers_match_serial():
    from gd_completion.synth.dataset import build_dataset

    serial = build_dataset(2, seed=5, n_input=64, n_gt=64, workers=1)
    parallel = build_dataset(2, seed=5, n_input=64, n_gt=64, workers=2)
    np.testing.assert_array_equal(serial["partial"], parallel["partial"])
    np.testing.assert_array_equal(serial["complete"], parallel["complete"])

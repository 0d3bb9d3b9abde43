"""Triangle meshes: the `Mesh` container, mesh files (PLY, OBJ, OFF, GLB via trimesh), area-weighted sampling."""
from __future__ import annotations

import hashlib
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gd_completion.errors import DataFormatError

MESH_SUFFIXES = (".ply", ".obj", ".off", ".glb")

# Unit cube corners (index = 4x + 2y + z over {-0.5, 0.5}) and its 12 triangles, counter-clockwise from outside.
_BOX_CORNERS = np.array([[x, y, z] for x in (-0.5, 0.5) for y in (-0.5, 0.5) for z in (-0.5, 0.5)])
_BOX_FACES = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                       [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])


@dataclass
class Mesh:
    """Triangle mesh in metres: `vertices` (V,3) float64, `faces` (F,3) int64 vertex indices."""

    vertices: np.ndarray
    faces: np.ndarray

    def __post_init__(self) -> None:
        self.vertices = np.ascontiguousarray(self.vertices, dtype=np.float64).reshape(-1, 3)
        self.faces = np.ascontiguousarray(self.faces, dtype=np.int64).reshape(-1, 3)

    @property
    def bounds(self) -> np.ndarray:
        """(2,3) array: minimum and maximum corner of the axis-aligned bounding box."""
        return np.stack([self.vertices.min(axis=0), self.vertices.max(axis=0)])

    @property
    def extent(self) -> np.ndarray:
        """(3,) size of the bounding box (x, y, z)."""
        b = self.bounds
        return b[1] - b[0]

    def triangles(self) -> np.ndarray:
        """(F,3,3) vertex coordinates of every face."""
        return self.vertices[self.faces]

    def centered(self) -> Mesh:
        """Copy translated so that the bounding box is centred on the origin."""
        b = self.bounds
        return Mesh(self.vertices - (b[0] + b[1]) / 2.0, self.faces.copy())

    def transformed(self, yaw: float = 0.0, translation: np.ndarray | tuple[float, float, float] = (0.0, 0.0, 0.0),
                    scale: np.ndarray | tuple[float, float, float] | float = 1.0) -> Mesh:
        """Copy scaled per axis, rotated by `yaw` about +z, then translated."""
        c, s = np.cos(yaw), np.sin(yaw)
        rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        v = (self.vertices * np.asarray(scale, dtype=np.float64)) @ rot.T + np.asarray(translation, dtype=np.float64)
        return Mesh(v, self.faces.copy())


def merge_meshes(meshes: list[Mesh]) -> Mesh:
    """One mesh holding all faces of `meshes` (indices offset)."""
    if not meshes:
        return Mesh(np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64))
    offsets = np.cumsum([0] + [len(m.vertices) for m in meshes[:-1]])
    return Mesh(np.concatenate([m.vertices for m in meshes]),
                np.concatenate([m.faces + o for m, o in zip(meshes, offsets)]))


def box_mesh(size: np.ndarray | tuple[float, float, float],
             center: np.ndarray | tuple[float, float, float] = (0.0, 0.0, 0.0)) -> Mesh:
    """Axis-aligned box of `size` (x, y, z) centred on `center`: 8 vertices, 12 outward-facing triangles."""
    return Mesh(_BOX_CORNERS * np.asarray(size, dtype=np.float64) + np.asarray(center, dtype=np.float64),
                _BOX_FACES.copy())


def _check(mesh: Mesh, path: Path) -> Mesh:
    if len(mesh.vertices) == 0 or len(mesh.faces) == 0:
        raise DataFormatError(f"{path}: mesh has no vertices or no faces")
    if not np.isfinite(mesh.vertices).all():
        raise DataFormatError(f"{path}: mesh has non-finite vertex coordinates")
    if mesh.faces.min() < 0 or mesh.faces.max() >= len(mesh.vertices):
        raise DataFormatError(f"{path}: face index out of range (mesh has {len(mesh.vertices)} vertices)")
    return mesh


def load_mesh(path: str | Path) -> Mesh:
    """Read a .ply, .obj, .off or .glb mesh with trimesh: file vertex order kept, polygons triangulated, the
    parts of a multi-object file merged; glTF's axes (+y up, +z forward) turned into x forward, z up."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in MESH_SUFFIXES:
        raise DataFormatError(f"{path}: unsupported mesh format {suffix!r} (expected one of {MESH_SUFFIXES})")
    if not path.is_file():
        raise DataFormatError(f"{path}: mesh file not found")
    import trimesh  # here, not at the top: only mesh files need it (0.2 s to import)

    try:
        loaded = trimesh.load_mesh(path, file_type=suffix[1:], process=False, maintain_order=True,
                                   skip_materials=True)
    except Exception as exc:  # trimesh's readers raise ValueError, IndexError, KeyError, ... on bad files
        raise DataFormatError(f"{path}: cannot read {suffix[1:].upper()} mesh ({type(exc).__name__}: {exc})") from exc
    vertices = np.asarray(loaded.vertices, dtype=np.float64).reshape(-1, 3)
    if suffix == ".glb":
        vertices = vertices[:, [2, 0, 1]]  # glTF (left, up, forward) -> (forward, left, up): a rotation
    return _check(Mesh(vertices, np.asarray(loaded.faces)), path)


def mesh_files(directory: str | Path) -> list[Path]:
    """The mesh files of `directory` (suffix in MESH_SUFFIXES), sorted by name."""
    directory = Path(directory)
    if not directory.is_dir():
        raise DataFormatError(f"{directory}: mesh folder not found")
    files = sorted(p for p in directory.iterdir() if p.suffix.lower() in MESH_SUFFIXES and p.is_file())
    if not files:
        raise DataFormatError(f"{directory}: no {'/'.join(MESH_SUFFIXES)} files in mesh folder")
    return files


#: Meshes of `../shared/data/vehicle-meshes` (file stems) never trained on: the held-out shapes of the evaluation.
HELDOUT_MESHES: tuple[str, ...] = ("basic_simplecarshort", "basic_taxi", "public_schoolbus", "realistic_cop_suv",
                                   "realistic_normalcar2", "realistic_sportscar2")


def load_mesh_folder(directory: str | Path, *, exclude: Sequence[str] = (), only: Sequence[str] | None = None
                     ) -> list[Mesh]:
    """Mesh files of `directory` (sorted by name), each centred on its bounding box; file stems in `exclude`
    are left out, and with `only` just those stems are read."""
    return [load_mesh(p).centered() for p in mesh_files(directory)
            if p.stem not in exclude and (only is None or p.stem in only)]


def mesh_folder_digest(directory: str | Path) -> str:
    """SHA-256 over the names and contents of the mesh files of `directory` (what `load_mesh_folder` reads)."""
    digest = hashlib.sha256()
    for path in mesh_files(directory):
        digest.update(path.name.encode() + b"\0" + str(path.stat().st_size).encode() + b"\0")
        with open(path, "rb") as fh:
            for block in iter(lambda: fh.read(1 << 20), b""):
                digest.update(block)
    return digest.hexdigest()


def face_areas(mesh: Mesh) -> np.ndarray:
    """(F,) triangle areas."""
    t = mesh.triangles()
    return 0.5 * np.linalg.norm(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]), axis=1)


def sample_surface(mesh: Mesh, n: int, rng: np.random.Generator) -> np.ndarray:
    """(n,3) float64 points uniformly distributed over the surface (faces chosen by area)."""
    areas = face_areas(mesh)
    total = areas.sum()
    if not total > 0:
        raise DataFormatError("sample_surface: mesh has zero surface area")
    face = rng.choice(len(areas), size=n, p=areas / total)
    u, v = rng.random(n), rng.random(n)
    flip = u + v > 1.0
    u[flip], v[flip] = 1.0 - u[flip], 1.0 - v[flip]
    t = mesh.triangles()[face]
    return t[:, 0] + u[:, None] * (t[:, 1] - t[:, 0]) + v[:, None] * (t[:, 2] - t[:, 0])


"""Triangle meshes: the `Mesh` container, PLY/OBJ/OFF readers and area-weighted surface sampling."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gd_completion.errors import DataFormatError

MESH_SUFFIXES = (".ply", ".obj", ".off")

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}


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


def _fan_triangulate(counts: np.ndarray, flat: np.ndarray) -> np.ndarray:
    """Triangulate polygons given per-polygon vertex counts and concatenated indices (fan from first vertex)."""
    counts = np.asarray(counts, dtype=np.int64)
    flat = np.asarray(flat, dtype=np.int64)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    ntri = np.clip(counts - 2, 0, None)
    poly = np.repeat(np.arange(len(counts)), ntri)
    k = np.arange(ntri.sum()) - np.repeat(np.cumsum(ntri) - ntri, ntri)
    s = starts[poly]
    return np.stack([flat[s], flat[s + k + 1], flat[s + k + 2]], axis=1)


def _check(mesh: Mesh, path: Path) -> Mesh:
    if len(mesh.vertices) == 0 or len(mesh.faces) == 0:
        raise DataFormatError(f"{path}: mesh has no vertices or no faces")
    if not np.isfinite(mesh.vertices).all():
        raise DataFormatError(f"{path}: mesh has non-finite vertex coordinates")
    if mesh.faces.min() < 0 or mesh.faces.max() >= len(mesh.vertices):
        raise DataFormatError(f"{path}: face index out of range (mesh has {len(mesh.vertices)} vertices)")
    return mesh


def _read_ply(path: Path, raw: bytes) -> Mesh:
    end = raw.find(b"end_header")
    if not raw.startswith(b"ply") or end < 0:
        raise DataFormatError(f"{path}: not a PLY file (missing 'ply' magic or 'end_header')")
    nl = raw.find(b"\n", end)
    body = raw[nl + 1:] if nl >= 0 else b""
    header = raw[:end].decode("ascii", errors="replace").splitlines()
    fmt = None
    elements: list[tuple[str, int, list[tuple]]] = []
    for line in header[1:]:
        tok = line.split()
        if not tok or tok[0] in ("comment", "obj_info"):
            continue
        if tok[0] == "format":
            fmt = tok[1] if len(tok) > 1 else None
        elif tok[0] == "element":
            try:
                elements.append((tok[1], int(tok[2]), []))
            except (IndexError, ValueError) as exc:
                raise DataFormatError(f"{path}: bad PLY element line {line!r}") from exc
        elif tok[0] == "property":
            if not elements:
                raise DataFormatError(f"{path}: PLY property before any element")
            if len(tok) >= 5 and tok[1] == "list":
                if tok[2] not in _PLY_TYPES or tok[3] not in _PLY_TYPES:
                    raise DataFormatError(f"{path}: unsupported PLY list type in {line!r}")
                elements[-1][2].append(("list", tok[4], _PLY_TYPES[tok[2]], _PLY_TYPES[tok[3]]))
            elif len(tok) >= 3 and tok[1] in _PLY_TYPES:
                elements[-1][2].append(("scalar", tok[2], _PLY_TYPES[tok[1]]))
            else:
                raise DataFormatError(f"{path}: unsupported PLY property {line!r}")
    if fmt not in ("ascii", "binary_little_endian"):
        raise DataFormatError(f"{path}: unsupported PLY format {fmt!r} (ascii or binary_little_endian)")
    names = [e[0] for e in elements]
    if "vertex" not in names or "face" not in names:
        raise DataFormatError(f"{path}: PLY needs 'vertex' and 'face' elements, has {names}")
    vertices = faces = None
    if fmt == "ascii":
        lines = body.decode("ascii", errors="replace").splitlines()
        pos = 0
        for name, count, props in elements:
            rows = lines[pos:pos + count]
            pos += count
            if len(rows) < count:
                raise DataFormatError(f"{path}: PLY truncated in element {name!r} ({len(rows)} of {count} rows)")
            if name == "vertex":
                pnames = [p[1] for p in props]
                if any(p[0] == "list" for p in props) or not {"x", "y", "z"} <= set(pnames):
                    raise DataFormatError(f"{path}: PLY vertex element needs scalar x, y, z")
                try:
                    arr = np.array([r.split()[:len(props)] for r in rows], dtype=np.float64)
                except ValueError as exc:
                    raise DataFormatError(f"{path}: garbled PLY vertex data ({exc})") from exc
                if arr.shape != (count, len(props)):
                    raise DataFormatError(f"{path}: garbled PLY vertex rows")
                vertices = arr[:, [pnames.index(a) for a in "xyz"]]
            elif name == "face":
                try:
                    vals = [np.array(r.split(), dtype=np.float64).astype(np.int64) for r in rows]
                except ValueError as exc:
                    raise DataFormatError(f"{path}: garbled PLY face data ({exc})") from exc
                counts = np.array([v[0] if len(v) else -1 for v in vals])
                if np.any(counts < 3) or any(len(v) < c + 1 for v, c in zip(vals, counts)):
                    raise DataFormatError(f"{path}: garbled PLY face rows")
                flat = np.concatenate([v[1:c + 1] for v, c in zip(vals, counts)]) if vals else np.zeros(0, np.int64)
                faces = _fan_triangulate(counts, flat)
        return _check(Mesh(vertices, faces), path)
    pos = 0
    for name, count, props in elements:
        if all(p[0] == "scalar" for p in props):
            dt = np.dtype([(p[1], "<" + p[2]) for p in props])
            need = dt.itemsize * count
            if pos + need > len(body):
                raise DataFormatError(f"{path}: PLY truncated in element {name!r}")
            arr = np.frombuffer(body, dtype=dt, count=count, offset=pos)
            pos += need
            if name == "vertex":
                if not {"x", "y", "z"} <= set(dt.names):
                    raise DataFormatError(f"{path}: PLY vertex element needs x, y, z")
                vertices = np.stack([arr[a].astype(np.float64) for a in "xyz"], axis=1)
            continue
        if name != "face" or len(props) != 1:
            raise DataFormatError(f"{path}: unsupported binary PLY element {name!r} with list properties")
        _, _, ctype, itype = props[0]
        cdt, idt = np.dtype("<" + ctype), np.dtype("<" + itype)
        if count == 0:
            faces = np.zeros((0, 3), np.int64)
            continue
        first = np.frombuffer(body, dtype=cdt, count=1, offset=pos)[0] if pos < len(body) else 0
        rec = cdt.itemsize + int(first) * idt.itemsize
        uniform = None
        if first >= 3 and pos + rec * count <= len(body):
            dt = np.dtype([("n", cdt), ("idx", idt, (int(first),))])
            arr = np.frombuffer(body, dtype=dt, count=count, offset=pos)
            if np.all(arr["n"] == first):
                uniform = arr
        if uniform is not None:
            pos += rec * count
            faces = _fan_triangulate(np.full(count, int(first)), uniform["idx"].reshape(-1))
        else:  # mixed polygon sizes: walk the records (rare for vehicle meshes)
            counts, chunks = [], []
            for _ in range(count):
                if pos + cdt.itemsize > len(body):
                    raise DataFormatError(f"{path}: PLY truncated in face list")
                n = int(np.frombuffer(body, dtype=cdt, count=1, offset=pos)[0])
                pos += cdt.itemsize
                if n < 3 or pos + n * idt.itemsize > len(body):
                    raise DataFormatError(f"{path}: garbled PLY face record ({n} indices)")
                chunks.append(np.frombuffer(body, dtype=idt, count=n, offset=pos))
                pos += n * idt.itemsize
                counts.append(n)
            faces = _fan_triangulate(np.array(counts), np.concatenate(chunks))
    return _check(Mesh(vertices, faces), path)


def _read_obj(path: Path, text: str) -> Mesh:
    verts, counts, flat = [], [], []
    for line in text.splitlines():
        if line.startswith("v "):
            verts.append(line.split()[1:4])
        elif line.startswith("f "):
            idx = [int(t.split("/")[0]) for t in line.split()[1:]]
            counts.append(len(idx))
            flat.extend(idx)
    try:
        v = np.array(verts, dtype=np.float64)
    except ValueError as exc:
        raise DataFormatError(f"{path}: garbled OBJ vertex line ({exc})") from exc
    if v.ndim != 2 or v.shape[1] != 3 or not counts or min(counts) < 3:
        raise DataFormatError(f"{path}: OBJ needs 'v x y z' vertices and faces of 3+ vertices")
    f = np.array(flat, dtype=np.int64)
    f = np.where(f < 0, len(v) + f, f - 1)  # OBJ is 1-based; negative indices count from the end
    return _check(Mesh(v, _fan_triangulate(np.array(counts), f)), path)


def _read_off(path: Path, text: str) -> Mesh:
    lines = [ln.split("#")[0].strip() for ln in text.splitlines()]
    lines = [ln for ln in lines if ln]
    if not lines or not lines[0].startswith("OFF"):
        raise DataFormatError(f"{path}: not an OFF file (missing 'OFF' header)")
    head = lines[0][3:].split() or lines.pop(1).split()
    lines = lines[1:]
    try:
        nv, nf = int(head[0]), int(head[1])
        v = np.array([ln.split()[:3] for ln in lines[:nv]], dtype=np.float64)
        rows = [np.array(ln.split(), dtype=np.int64) for ln in lines[nv:nv + nf]]
    except (ValueError, IndexError) as exc:
        raise DataFormatError(f"{path}: garbled OFF data ({exc})") from exc
    if v.shape != (nv, 3) or len(rows) != nf:
        raise DataFormatError(f"{path}: OFF truncated ({len(v)} of {nv} vertices, {len(rows)} of {nf} faces)")
    counts = np.array([r[0] for r in rows])
    if np.any(counts < 3) or any(len(r) < c + 1 for r, c in zip(rows, counts)):
        raise DataFormatError(f"{path}: garbled OFF face rows")
    flat = np.concatenate([r[1:c + 1] for r, c in zip(rows, counts)])
    return _check(Mesh(v, _fan_triangulate(counts, flat)), path)


def load_mesh(path: str | Path) -> Mesh:
    """Read a .ply (ascii / binary_little_endian), .obj or .off triangle mesh; polygons are fan-triangulated."""
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise DataFormatError(f"{path}: cannot read mesh file ({exc.strerror or exc})") from exc
    suffix = path.suffix.lower()
    if suffix == ".ply":
        return _read_ply(path, raw)
    if suffix in (".obj", ".off"):
        try:
            text = raw.decode("utf-8")
        except UnicodeDecodeError as exc:
            raise DataFormatError(f"{path}: mesh file is not text ({exc})") from exc
        return _read_obj(path, text) if suffix == ".obj" else _read_off(path, text)
    raise DataFormatError(f"{path}: unsupported mesh format {suffix!r} (expected one of {MESH_SUFFIXES})")


def load_mesh_folder(directory: str | Path) -> list[Mesh]:
    """Every mesh file of `directory` (sorted by name), each centred on its bounding box."""
    directory = Path(directory)
    if not directory.is_dir():
        raise DataFormatError(f"{directory}: mesh folder not found")
    files = sorted(p for p in directory.iterdir() if p.suffix.lower() in MESH_SUFFIXES)
    if not files:
        raise DataFormatError(f"{directory}: no {'/'.join(MESH_SUFFIXES)} files in mesh folder")
    return [load_mesh(p).centered() for p in files]


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


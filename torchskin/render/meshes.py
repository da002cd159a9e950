"""Stage 1 of the renderer: scene meshes -> triangles. Primitives (plane, cylinder, sphere, ground), anny bodies
and OBJ/PLY files become ``TriMesh`` (float32 vertices, int32 faces, a material per face, vertex normals), placed
by each ``MeshSpec``'s tilt, yaw and position.

>>> from torchskin.render.scene import MeshSpec
>>> m = build_mesh(MeshSpec("board", "plane", "paint", params={"width": 2.0, "height": 1.0}))
>>> m.vertices.shape, m.faces.shape, m.vertex_normals[0].tolist()
((4, 3), (2, 3), [1.0, 0.0, 0.0])
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import io
import json
import math
import os
import sys
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NoReturn

import numpy as np
import torch

from ..io import write_text
from .scene import MeshSpec, Scene


@dataclass
class TriMesh:
    """Triangles ready for ray casting: vertices (V, 3) float32, faces (F, 3) int32, per-face material names
    (index into ``material_names``), and per-vertex normals (V, 3)."""

    name: str
    vertices: np.ndarray
    faces: np.ndarray
    face_material: np.ndarray
    material_names: list[str]
    vertex_normals: np.ndarray


def face_cross(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(F, 3) float64 cross products of the faces' edges (twice each face's area along its normal)."""
    v = vertices.astype(np.float64)
    return np.cross(v[faces[:, 1]] - v[faces[:, 0]], v[faces[:, 2]] - v[faces[:, 0]])


def vertex_normals(vertices: np.ndarray, faces: np.ndarray, cross: np.ndarray | None = None) -> np.ndarray:
    """Area-weighted vertex normals (unit length; zero-area neighbourhoods get +z). ``cross``: the faces'
    ``face_cross`` if already computed."""
    fn = face_cross(vertices, faces) if cross is None else cross
    corner = faces.T.reshape(-1)  # every face's corners, corner 0 of all faces first (np.add.at's order)
    n = np.stack([np.bincount(corner, weights=np.tile(fn[:, c], 3), minlength=len(vertices)) for c in range(3)],
                 axis=1)
    ln = np.linalg.norm(n, axis=1, keepdims=True)
    n = np.where(ln > 0, n / np.maximum(ln, 1e-300), np.array([0.0, 0.0, 1.0]))
    return n.astype(np.float32)


def check_mesh(name: str, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """``ValueError`` naming mesh ``name`` unless it has finite vertices, in-range faces and a triangle of
    non-zero area; returns the faces' ``face_cross`` (for ``vertex_normals``)."""
    if vertices.ndim != 2 or vertices.shape[1] != 3 or len(vertices) < 3:
        raise ValueError(f"mesh {name!r} has no usable vertices (shape {vertices.shape})")
    if faces.ndim != 2 or faces.shape[1] != 3 or len(faces) == 0:
        raise ValueError(f"mesh {name!r} has no triangles")
    if not np.isfinite(vertices).all():
        raise ValueError(f"mesh {name!r} has non-finite vertex coordinates")
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise ValueError(f"mesh {name!r} has faces indexing missing vertices")
    cross = face_cross(vertices, faces)
    if not (np.linalg.norm(cross, axis=1) > 0).any():
        raise ValueError(f"mesh {name!r} has only degenerate (zero-area) triangles")
    return cross


def grid_plane(width: float, height: float, nu: int = 1, nv: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """A rectangle in the plane x = 0 facing +x: y in [-w/2, w/2], z in [0, h]. Returns vertices, faces."""
    us = np.linspace(-width / 2, width / 2, nu + 1)
    vs = np.linspace(0.0, height, nv + 1)
    U, V = np.meshgrid(us, vs, indexing="ij")
    verts = np.stack([np.zeros_like(U), U, V], axis=-1).reshape(-1, 3)  # plane x = 0, normal +x
    idx = np.arange((nu + 1) * (nv + 1)).reshape(nu + 1, nv + 1)
    a, b, c, d = idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]
    faces = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
    return verts, faces


def cylinder_mesh(radius: float, height: float, segments: int = 256) -> tuple[np.ndarray, np.ndarray]:
    """An open vertical cylinder (axis z, base at z = 0) with outward faces."""
    ang = np.linspace(0, 2 * np.pi, segments, endpoint=False)
    ring = np.stack([radius * np.cos(ang), radius * np.sin(ang)], -1)
    verts = np.concatenate([np.c_[ring, np.zeros(segments)], np.c_[ring, np.full(segments, height)]])
    i = np.arange(segments)
    j = (i + 1) % segments
    faces = np.concatenate([np.stack([i, j, j + segments], -1), np.stack([i, j + segments, i + segments], -1)])
    return verts, faces


def sphere_mesh(radius: float, subdivisions: int = 5) -> tuple[np.ndarray, np.ndarray]:
    """An icosphere centred at the origin (faces outward)."""
    t = (1 + 5**0.5) / 2
    v = np.array([[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t], [0, -1, -t], [0, 1, -t],
                  [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]], dtype=np.float64)
    f = np.array([[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4], [11, 10, 2],
                  [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8], [3, 8, 9], [4, 9, 5],
                  [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]])
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    for _ in range(subdivisions):
        edges = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
        uniq, inv = np.unique(edges, axis=0, return_inverse=True)
        mid = v[uniq[:, 0]] + v[uniq[:, 1]]
        mid /= np.linalg.norm(mid, axis=1, keepdims=True)
        m = inv.reshape(3, -1).T + len(v)
        v = np.concatenate([v, mid])
        a, b, c = f[:, 0], f[:, 1], f[:, 2]
        ab, bc, ca = m[:, 0], m[:, 1], m[:, 2]
        f = np.concatenate([np.stack([a, ab, ca], -1), np.stack([b, bc, ab], -1), np.stack([c, ca, bc], -1),
                            np.stack([ab, bc, ca], -1)])
    return v * radius, f


def cache_dir() -> Path:
    """Folder for cached meshes: ``$TORCHSKIN_CACHE`` or ``~/.cache/torchskin``."""
    return Path(os.environ.get("TORCHSKIN_CACHE", Path.home() / ".cache" / "torchskin"))


#: anny bones whose vertices are exposed skin (head, neck, hands); eyes are not skin
_SKIN_BONES = ("neck01", "neck02", "neck03", "head")
_SKIN_BONE_PREFIXES = ("wrist", "finger", "metacarpal")


def _euler_deg_to_matrix(angles: Sequence[float] | np.ndarray | torch.Tensor) -> torch.Tensor:
    ax, ay, az = (math.radians(float(a)) for a in angles)
    cx, sx, cy, sy, cz, sz = math.cos(ax), math.sin(ax), math.cos(ay), math.sin(ay), math.cos(az), math.sin(az)
    rx = torch.tensor([[1, 0, 0], [0, cx, -sx], [0, sx, cx]], dtype=ANNY_DTYPE)
    ry = torch.tensor([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]], dtype=ANNY_DTYPE)
    rz = torch.tensor([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]], dtype=ANNY_DTYPE)
    return rz @ ry @ rx


def anny_body(phenotype: dict | None = None, pose: dict | None = None,
              cache: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """An anny body: ``(vertices, faces, skin_face_mask)``, feet on z = 0, facing +x, metres.

    ``phenotype``: anny phenotype values in [0, 1] (gender, age, muscle, weight, height, proportions; 0.5
    when missing). ``pose``: bone name -> XYZ Euler angles in degrees (anny's local pose parameters), e.g.
    ``{"head": [0, 0, 20]}`` (for the head: x pitches, z turns); the rest pose otherwise. Built meshes are
    cached in ``cache_dir()/anny`` unless ``cache=False`` (random bodies of a dataset are not reused); the
    first anny model load builds anny's own cache and takes about a minute.
    """
    phenotype = dict(phenotype or {})
    pose = {k: [float(x) for x in v] for k, v in (pose or {}).items()}
    for k, v in phenotype.items():
        if not (0.0 <= float(v) <= 1.0):
            raise ValueError(f"anny phenotype {k!r} must lie in [0, 1], got {v}")
    try:
        _init_warp_quietly()
        import anny  # noqa: F401 - a clear error when it is missing
    except ModuleNotFoundError as e:  # anny, or the warp it brings: the render extra names both (exit 1)
        raise ModuleNotFoundError(f"anny subjects need anny ({e})", name="anny") from e
    key = _anny_key(phenotype, pose)
    if key in _PREBUILT:  # built in a batch (``anny_batch``)
        return _PREBUILT[key]
    path = cache_dir() / "anny" / f"{key}.npz"
    if cache and path.exists():
        with np.load(path) as z:
            return z["vertices"], z["faces"], z["skin"]
    v, f, face_skin = _anny_forward([(phenotype, pose)])[0]
    if not cache:
        return v, f, face_skin
    path.parent.mkdir(parents=True, exist_ok=True)
    from ..io import atomic_path

    with atomic_path(path, suffix=".npz") as tmp:
        with open(tmp, "wb") as fh:
            np.savez(fh, vertices=v, faces=f, skin=face_skin)
    return v, f, face_skin


def _anny_key(phenotype: dict, pose: dict) -> str:
    """The cache key of an anny body (anny version, dtype, phenotype and pose)."""
    import anny

    return hashlib.sha256(json.dumps([getattr(anny, "__version__", "?"), str(ANNY_DTYPE), sorted(phenotype.items()),
                                      sorted(pose.items()), f"batch{ANNY_BATCH_MULTIPLE}"]).encode()).hexdigest()[:16]


#: ``anny_batch`` runs anny on a multiple of this many bodies (the last body repeated): anny's float64 blend-shape
#: products then take the same BLAS path for every body, so a body's float32 vertices do not depend on the batch
#: it was built in (measured: batches of 4, 8 and 16 give the same bits; a lone body differs by one float32 step in
#: ~0.1 % of its coordinates)
ANNY_BATCH_MULTIPLE = 8

_PREBUILT: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}


@contextlib.contextmanager
def anny_batch(bodies: Sequence[tuple[dict | None, dict | None]]) -> Iterator[None]:
    """Build the anny bodies ``[(phenotype, pose), ...]`` in one batched anny call (padded to a multiple of
    ``ANNY_BATCH_MULTIPLE``) and let ``anny_body`` return them inside the ``with`` block: a dataset shard builds
    its pose groups' bodies together, ~4 ms a body instead of ~20 ms one by one. The bodies are those of one
    batch whatever else is in it (``ANNY_BATCH_MULTIPLE``)."""
    norm = [(dict(ph or {}), {k: [float(x) for x in v] for k, v in (po or {}).items()}) for ph, po in bodies]
    keys = []
    if norm:
        _init_warp_quietly()
        keys = [_anny_key(ph, po) for ph, po in norm]
        _PREBUILT.update(zip(keys, _anny_forward(norm), strict=True))
    try:
        yield
    finally:
        for k in keys:
            _PREBUILT.pop(k, None)


def _anny_forward(bodies: list[tuple[dict, dict]]) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """anny on ``bodies`` [(phenotype, pose)] in one batch padded to a multiple of ``ANNY_BATCH_MULTIPLE``:
    ``(vertices, faces, skin_face_mask)`` each, feet on z = 0, facing +x, metres (``anny_body``)."""
    for phenotype, _ in bodies:
        for k, val in phenotype.items():
            if not (0.0 <= float(val) <= 1.0):
                raise ValueError(f"anny phenotype {k!r} must lie in [0, 1], got {val}")
    model = _anny_model()
    labels = list(model.bone_labels)
    for phenotype, pose in bodies:
        unknown = set(phenotype) - set(model.phenotype_labels)
        if unknown:
            raise ValueError(f"unknown anny phenotype(s) {sorted(unknown)}; known: {list(model.phenotype_labels)}")
        for bone in pose:
            if bone not in labels:
                raise ValueError(f"unknown anny bone {bone!r} in pose")
    n = len(bodies)
    padded = bodies + [bodies[-1]] * (-n % ANNY_BATCH_MULTIPLE)
    pose_t = torch.eye(4, dtype=ANNY_DTYPE)[None, None].repeat(len(padded), model.bone_count, 1, 1)
    for i, (_, pose) in enumerate(padded):
        for bone, ang in pose.items():
            pose_t[i, labels.index(bone), :3, :3] = _euler_deg_to_matrix(ang)
    kw = {k: torch.tensor([float(ph.get(k, 0.5)) for ph, _ in padded], dtype=ANNY_DTYPE)
          for k in model.phenotype_labels}
    with torch.no_grad(), contextlib.redirect_stdout(io.StringIO()):  # warp's messages stay off stdout
        out = model(pose_parameters=pose_t, phenotype_kwargs=kw)
    f = model.faces.numpy().astype(np.int64)
    f32 = f.astype(np.int32)
    bi, bw = model.vertex_bone_indices.numpy(), model.vertex_bone_weights.numpy()
    dominant = bi[np.arange(len(bi)), bw.argmax(1)]
    skin_bones = [i for i, name in enumerate(labels) if name in _SKIN_BONES or name.startswith(_SKIN_BONE_PREFIXES)]
    face_skin = np.isin(dominant, skin_bones)[f].sum(1) >= 2
    f32.flags.writeable = face_skin.flags.writeable = False  # shared by every body of the batch
    result = []
    for i in range(n):
        v = out["vertices"][i].double().numpy()
        # anny faces -y with its origin at mid-body: turn to face +x, feet on z = 0
        v = np.stack([-v[:, 1], v[:, 0], v[:, 2]], axis=1)
        v[:, 2] -= v[:, 2].min()
        result.append((v.astype(np.float32), f32, face_skin))
    return result


@functools.lru_cache(maxsize=1)
def _init_warp_quietly() -> None:
    """Initialise warp (anny compiles its kernels with it; once per process) without its banner on stdout (JSON
    output) and, on a machine without CUDA, without the "Warp CUDA warning" its native library prints on stderr
    at start-up. warp's logging settings are restored afterwards: nothing of the caller's warp set-up changes."""
    import warp

    saved_config = {k: getattr(warp.config, k) for k in ("log_level", "quiet") if hasattr(warp.config, k)}
    if hasattr(warp, "LOG_WARNING"):  # warp >= 1.x: the start-up banner is info-level
        warp.config.log_level = max(warp.config.log_level, warp.LOG_WARNING)
    warp.config.quiet = True  # type: ignore[attr-defined]  # older warp only
    try:
        if torch.cuda.is_available():
            warp.init()
            return
        sys.stderr.flush()
        saved, devnull = os.dup(2), os.open(os.devnull, os.O_WRONLY)
        try:
            os.dup2(devnull, 2)
            warp.init()
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            os.close(devnull)
    finally:
        for k, v in saved_config.items():
            setattr(warp.config, k, v)


#: anny runs in float64 and its vertices are rounded to float32: the blend-shape products (136 shape coefficients
#: against 41,154 coordinates) and the skinning then round the same way whatever the BLAS kernel, its thread
#: count or the CPU (in float32 their last bits moved with the thread count, and a moved triangle edge relabels
#: the pixels on a silhouette: datasets were not reproducible across machines)
ANNY_DTYPE = torch.float64


@functools.lru_cache(maxsize=1)
def _anny_model() -> Any:
    import anny

    with contextlib.redirect_stdout(io.StringIO()):
        return anny.Anny().to(dtype=ANNY_DTYPE)


#: plausible extent (largest side of the bounding box, m) of a mesh file: outside it a warning names the file
MESH_EXTENT_M = (0.05, 50.0)


def load_mesh_file(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Vertices and triangles of an OBJ or PLY file (open3d's reader). Units are metres, +z is up and the
    subject should stand on z = 0 facing +x (as anny bodies do; ``MeshSpec`` can yaw and move it): a mesh whose
    extent is implausible for metres (``MESH_EXTENT_M``, e.g. a millimetre-scale scan) gets a warning on
    stderr."""
    p = Path(path)
    if not p.is_file():
        raise ValueError(f"mesh file {str(p)!r} does not exist")
    if p.suffix.lower() not in (".obj", ".ply"):
        raise ValueError(f"mesh file {str(p)!r} must be .obj or .ply")
    import open3d as o3d

    m = o3d.io.read_triangle_mesh(str(p))  # type: ignore[arg-type]  # open3d's stub wants a PathLike; str works
    v = np.asarray(m.vertices, dtype=np.float64)
    f = np.asarray(m.triangles, dtype=np.int64)
    check_mesh(p.name, v, f) if len(v) and len(f) else _raise_empty(p)
    extent = float((v.max(0) - v.min(0)).max())
    if not (MESH_EXTENT_M[0] <= extent <= MESH_EXTENT_M[1]):
        print(f"torchskin: warning: mesh {str(p)!r} spans {extent:.4g} units; torchskin reads metres with +z up "
              f"(a person spans about 1.5-2 m): a millimetre or centimetre file renders as a speck or a giant "
              "(scale it to metres)", file=sys.stderr)
    return v.astype(np.float32), f.astype(np.int32)


def write_obj(path: str | os.PathLike, vertices: np.ndarray, faces: np.ndarray) -> None:
    """Write a triangle mesh as a Wavefront OBJ file (``v x y z`` lines at full precision, then 1-based ``f a b c``
    triangles; atomically), readable by ``load_mesh_file`` and any mesh tool.

    Args:
        path: the .obj file to write.
        vertices: (V, 3) coordinates, metres, +z up.
        faces: (F, 3) vertex indices, 0-based.

    >>> import tempfile, pathlib
    >>> v, f = sphere_mesh(0.3, subdivisions=1)
    >>> path = pathlib.Path(tempfile.mkdtemp()) / "ball.obj"
    >>> write_obj(path, v, f)
    >>> [a.shape for a in load_mesh_file(path)]
    [(42, 3), (80, 3)]
    """
    v, f = np.asarray(vertices, dtype=np.float64), np.asarray(faces)
    if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3:
        raise ValueError(f"write_obj needs vertices (V, 3) and faces (F, 3), got {v.shape} and {f.shape}")
    lines = [f"v {a!r} {b!r} {c!r}" for a, b, c in v.tolist()] + [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in f.tolist()]
    write_text(path, "\n".join(lines) + "\n")


def _raise_empty(p: Path) -> NoReturn:
    raise ValueError(f"mesh file {str(p)!r} holds no triangles (empty or unreadable)")


def build_mesh(spec: MeshSpec) -> TriMesh:
    """The triangles of ``spec``: its primitive, body or file, tilted, yawed and moved into place.

    Args:
        spec: the mesh description (``MeshSpec``).

    Returns:
        ``TriMesh`` with float32 vertices (V, 3), int32 faces (F, 3), per-face material indices into
        ``material_names`` and unit vertex normals (V, 3).
    """
    p = spec.params
    mats = [spec.material]
    fm = None
    normals = None  # analytic vertex normals of primitives (local frame), else area-weighted
    if spec.kind == "anny":
        v, f, skin = anny_body(p.get("phenotype"), p.get("pose"), cache=bool(p.get("cache", True)))
        mats = [str(spec.other_material), spec.material]  # MeshSpec requires other_material for anny
        fm = skin.astype(np.int32)
    elif spec.kind == "file":
        v, f = load_mesh_file(p["path"])
    elif spec.kind == "plane":
        v, f = grid_plane(float(p.get("width", 1.0)), float(p.get("height", 1.0)), int(p.get("nu", 1)),
                           int(p.get("nv", 1)))
    elif spec.kind == "cylinder":
        v, f = cylinder_mesh(float(p.get("radius", 0.1)), float(p.get("height", 1.0)), int(p.get("segments", 256)))
        normals = np.c_[v[:, :2], np.zeros(len(v))]
    elif spec.kind == "sphere":
        v, f = sphere_mesh(float(p.get("radius", 0.5)), int(p.get("subdivisions", 5)))
        normals = v.copy()
    else:  # ground
        s = float(p.get("size", 50.0))
        v = np.array([[-s, -s, 0], [s, -s, 0], [s, s, 0], [-s, s, 0]], dtype=np.float64)
        f = np.array([[0, 1, 2], [0, 2, 3]])
    for k in ("width", "height", "radius", "size"):
        if k in p and not float(p[k]) > 0:
            raise ValueError(f"mesh {spec.name!r}: {k} must be > 0, got {p[k]}")
    c, s = math.cos(math.radians(spec.yaw_deg)), math.sin(math.radians(spec.yaw_deg))
    ct, st = math.cos(math.radians(spec.tilt_deg)), math.sin(math.radians(spec.tilt_deg))

    def turn(x: np.ndarray) -> np.ndarray:
        x = np.stack([ct * x[:, 0] - st * x[:, 2], x[:, 1], st * x[:, 0] + ct * x[:, 2]], 1)  # tilt
        return np.stack([c * x[:, 0] - s * x[:, 1], s * x[:, 0] + c * x[:, 1], x[:, 2]], 1)  # yaw

    v = turn(np.asarray(v, dtype=np.float64)) + np.asarray(spec.position)
    f = np.asarray(f, dtype=np.int32)
    v32 = v.astype(np.float32)
    cross = check_mesh(spec.name, v32, f)  # of the float32 vertices the ray caster gets; reused for the normals
    fm = np.zeros(len(f), dtype=np.int32) if fm is None else fm
    if normals is not None:
        normals = turn(normals)
        normals = (normals / np.linalg.norm(normals, axis=1, keepdims=True)).astype(np.float32)
    else:
        normals = vertex_normals(v32, f, cross)
    return TriMesh(spec.name, v32, f, fm, mats, normals)


def build_meshes(scene: Scene) -> list[TriMesh]:
    """``build_mesh`` of every mesh of ``scene``, in order."""
    return [build_mesh(m) for m in scene.meshes]

"""Scenes as plain data: meshes (anny humans, OBJ/PLY files, primitives), materials, cameras, suns.

Every class here is a dataclass that round-trips through JSON (``Scene.to_json`` / ``Scene.from_json``).
Geometry is described, not stored: ``MeshSpec.build()`` makes the triangles (anny bodies are cached on
disk). World frame: metres, z up; subjects stand on z = 0 facing +x. Directions are given by zenith (from
+z) and azimuth (from +x towards +y) in degrees; a camera or sun at azimuth 0 is in front of the subject.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import hashlib
import io
import json
import math
import os
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from . import tissue
from .bands import DEFAULT_BANDS, Band, as_bands
from .io import write_text
from .optics import check_surface


def _finite(what: str, **values) -> None:
    """``ValueError`` naming the first value that is not a finite number."""
    for k, v in values.items():
        try:
            ok = math.isfinite(float(v))
        except (TypeError, ValueError):
            ok = False
        if not ok:
            raise ValueError(f"{what} {k} must be a finite number, got {v!r}")


# ------------------------------------------------------------------------------------------------ materials
#: Spectralon reference panels, directional-hemispherical reflectance per band (thesis Table 3)
SPECTRALON_DHR = {
    "white": {544.0: 0.989, 633.0: 0.990, 1080.0: 0.992, 1580.0: 0.988},
    "dark": {544.0: 0.075, 633.0: 0.079, 1080.0: 0.104, 1580.0: 0.133},
}


@dataclass
class Material:
    """A surface material.

    - ``kind="lambertian"``: ``reflectance`` is one value or one per band;
    - ``kind="spectralon"``: the Table 3 DHR of ``panel`` ("white" or "dark"), Lambertian, or with
      ``brdf=True`` the Spectralon-like BRDF of ``optics.spectralon_brdf_cos`` (a weak forward lobe growing
      with incidence, Appendix B);
    - ``kind="skin"``: the combined skin BRDF (eq 3.1.1) with skin parameters ``skin`` (a preset name or a
      dict of ``tissue`` parameters) and the section 3.3.3 microfacet parameters per band (``specular``
      False gives the diffuse-only model). ``surface`` is the skin surface model of eq 3.1.1's diffuse term
      (``optics.skin_diffuse``): "thesis" (default; ρ_d is the total diffuse-model reflectance, front surface
      included, as the thesis defines it and as its measured images support) or "conserving" (the
      subsurface part only: energy-conserving).
    """

    kind: str = "lambertian"
    reflectance: float | list[float] | None = None
    panel: str | None = None
    skin: str | dict | None = None
    specular: bool = True
    brdf: bool = False
    surface: str = "thesis"

    def __post_init__(self):
        check_surface(self.surface)
        if self.kind not in ("lambertian", "spectralon", "skin"):
            raise ValueError(f"material kind must be 'lambertian', 'spectralon' or 'skin', got {self.kind!r}")
        if self.kind == "lambertian":
            if self.reflectance is None:
                raise ValueError("a lambertian material needs reflectance (one value or one per band)")
            vals = self.reflectance if isinstance(self.reflectance, list) else [self.reflectance]
            for v in vals:
                if not (0.0 <= float(v) <= 1.0):
                    raise ValueError(f"reflectance must lie in [0, 1], got {v}")
        if self.kind == "spectralon" and self.panel not in SPECTRALON_DHR:
            raise ValueError(f"spectralon panel must be 'white' or 'dark', got {self.panel!r}")
        if self.brdf and self.kind != "spectralon":
            raise ValueError("brdf=True is for spectralon materials")
        if self.kind == "skin":
            self.skin = self.skin if self.skin is not None else "I-II"
            self.skin_params()  # validate now

    def skin_params(self, dtype=torch.float64, device=None) -> tissue.SkinParams:
        if isinstance(self.skin, str):
            return tissue.preset(self.skin, dtype=dtype, device=device)
        return tissue.SkinParams.create(dtype=dtype, device=device, **dict(self.skin))

    def band_reflectance(self, bands: tuple[Band, ...]) -> list[float]:
        """Per-band reflectance of a Lambertian or Spectralon material."""
        if self.kind == "spectralon":
            table = SPECTRALON_DHR[self.panel]
            out = []
            for b in bands:
                near = min(table, key=lambda c: abs(c - b.center_nm))
                if abs(near - b.center_nm) > 30:
                    raise ValueError(f"no Spectralon value near {b.center_nm:g} nm (Table 3 has {list(table)})")
                out.append(table[near])
            return out
        if self.kind == "lambertian":
            if isinstance(self.reflectance, list):
                vals = [float(x) for x in self.reflectance]
                if len(vals) == len(bands):
                    return vals
                if len(vals) == len(DEFAULT_BANDS):  # a spectrum at 544, 633, 1080, 1580 nm: linear in wavelength
                    xp = [b.center_nm for b in DEFAULT_BANDS]
                    return [float(v) for v in np.interp([b.center_nm for b in bands], xp, vals)]
                raise ValueError(f"a lambertian reflectance list needs one value per band ({len(bands)}) or four (at "
                                 f"544, 633, 1080, 1580 nm, interpolated), got {len(vals)}")
            return [float(self.reflectance)] * len(bands)
        raise ValueError("band_reflectance is for lambertian and spectralon materials")


# ------------------------------------------------------------------------------------------------- geometry
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


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted vertex normals (unit length; zero-area neighbourhoods get +z)."""
    v = vertices.astype(np.float64)
    fn = np.cross(v[faces[:, 1]] - v[faces[:, 0]], v[faces[:, 2]] - v[faces[:, 0]])
    n = np.zeros_like(v)
    for k in range(3):
        np.add.at(n, faces[:, k], fn)
    ln = np.linalg.norm(n, axis=1, keepdims=True)
    n = np.where(ln > 0, n / np.maximum(ln, 1e-300), np.array([0.0, 0.0, 1.0]))
    return n.astype(np.float32)


def _check_mesh(name: str, vertices: np.ndarray, faces: np.ndarray) -> None:
    if vertices.ndim != 2 or vertices.shape[1] != 3 or len(vertices) < 3:
        raise ValueError(f"mesh {name!r} has no usable vertices (shape {vertices.shape})")
    if faces.ndim != 2 or faces.shape[1] != 3 or len(faces) == 0:
        raise ValueError(f"mesh {name!r} has no triangles")
    if not np.isfinite(vertices).all():
        raise ValueError(f"mesh {name!r} has non-finite vertex coordinates")
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise ValueError(f"mesh {name!r} has faces indexing missing vertices")
    v = vertices.astype(np.float64)
    area = np.linalg.norm(np.cross(v[faces[:, 1]] - v[faces[:, 0]], v[faces[:, 2]] - v[faces[:, 0]]), axis=1)
    if not (area > 0).any():
        raise ValueError(f"mesh {name!r} has only degenerate (zero-area) triangles")


def _grid_plane(width: float, height: float, nu: int = 1, nv: int = 1):
    """A rectangle in the plane x = 0 facing +x: y in [-w/2, w/2], z in [0, h]. Returns vertices, faces."""
    us = np.linspace(-width / 2, width / 2, nu + 1)
    vs = np.linspace(0.0, height, nv + 1)
    U, V = np.meshgrid(us, vs, indexing="ij")
    verts = np.stack([np.zeros_like(U), U, V], axis=-1).reshape(-1, 3)  # plane x = 0, normal +x
    idx = np.arange((nu + 1) * (nv + 1)).reshape(nu + 1, nv + 1)
    a, b, c, d = idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]
    faces = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
    return verts, faces


def cylinder_mesh(radius: float, height: float, segments: int = 256):
    """An open vertical cylinder (axis z, base at z = 0) with outward faces."""
    ang = np.linspace(0, 2 * np.pi, segments, endpoint=False)
    ring = np.stack([radius * np.cos(ang), radius * np.sin(ang)], -1)
    verts = np.concatenate([np.c_[ring, np.zeros(segments)], np.c_[ring, np.full(segments, height)]])
    i = np.arange(segments)
    j = (i + 1) % segments
    faces = np.concatenate([np.stack([i, j, j + segments], -1), np.stack([i, j + segments, i + segments], -1)])
    return verts, faces


def sphere_mesh(radius: float, subdivisions: int = 5):
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


def _euler_deg_to_matrix(angles) -> torch.Tensor:
    ax, ay, az = (math.radians(float(a)) for a in angles)
    cx, sx, cy, sy, cz, sz = math.cos(ax), math.sin(ax), math.cos(ay), math.sin(ay), math.cos(az), math.sin(az)
    rx = torch.tensor([[1, 0, 0], [0, cx, -sx], [0, sx, cx]], dtype=torch.float32)
    ry = torch.tensor([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]], dtype=torch.float32)
    rz = torch.tensor([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]], dtype=torch.float32)
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
        import anny
    except ImportError as e:  # pragma: no cover - dependency missing
        raise ValueError("the anny package is needed for anny subjects: pip install 'torchskin[render]'") from e
    key = hashlib.sha256(json.dumps([getattr(anny, "__version__", "?"), sorted(phenotype.items()),
                                     sorted(pose.items())]).encode()).hexdigest()[:16]
    path = cache_dir() / "anny" / f"{key}.npz"
    if cache and path.exists():
        with np.load(path) as z:
            return z["vertices"], z["faces"], z["skin"]
    model = _anny_model()
    unknown = set(phenotype) - set(model.phenotype_labels)
    if unknown:
        raise ValueError(f"unknown anny phenotype(s) {sorted(unknown)}; known: {list(model.phenotype_labels)}")
    labels = list(model.bone_labels)
    pose_t = torch.eye(4)[None, None].repeat(1, model.bone_count, 1, 1)
    for bone, ang in pose.items():
        if bone not in labels:
            raise ValueError(f"unknown anny bone {bone!r} in pose")
        pose_t[0, labels.index(bone), :3, :3] = _euler_deg_to_matrix(ang)
    kw = {k: float(phenotype.get(k, 0.5)) for k in model.phenotype_labels}
    with torch.no_grad(), contextlib.redirect_stdout(io.StringIO()):  # warp's messages stay off stdout
        out = model(pose_parameters=pose_t, phenotype_kwargs=kw)
    v = out["vertices"][0].double().numpy()
    f = model.faces.numpy().astype(np.int64)
    bi, bw = model.vertex_bone_indices.numpy(), model.vertex_bone_weights.numpy()
    dominant = bi[np.arange(len(bi)), bw.argmax(1)]
    skin_bones = [i for i, n in enumerate(labels) if n in _SKIN_BONES or n.startswith(_SKIN_BONE_PREFIXES)]
    vskin = np.isin(dominant, skin_bones)
    face_skin = vskin[f].sum(1) >= 2
    # anny faces -y with its origin at mid-body: turn to face +x, feet on z = 0
    v = np.stack([-v[:, 1], v[:, 0], v[:, 2]], axis=1)
    v[:, 2] -= v[:, 2].min()
    v = v.astype(np.float32)
    f = f.astype(np.int32)
    if not cache:
        return v, f, face_skin
    path.parent.mkdir(parents=True, exist_ok=True)
    from .io import atomic_path

    with atomic_path(path, suffix=".npz") as tmp:
        with open(tmp, "wb") as fh:
            np.savez(fh, vertices=v, faces=f, skin=face_skin)
    return v, f, face_skin


@functools.lru_cache(maxsize=1)
def _init_warp_quietly() -> None:
    """Initialise warp (anny compiles its kernels with it) without its banner on stdout (JSON output) and, on a
    machine without CUDA, without the "Warp CUDA warning" its native library prints on stderr at start-up."""
    import warp

    if hasattr(warp, "LOG_WARNING"):  # warp >= 1.x: the start-up banner is info-level
        warp.config.log_level = max(warp.config.log_level, warp.LOG_WARNING)
    warp.config.quiet = True  # older warp
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


@functools.lru_cache(maxsize=1)
def _anny_model():
    import anny

    with contextlib.redirect_stdout(io.StringIO()):
        return anny.Anny().to(dtype=torch.float32)


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

    m = o3d.io.read_triangle_mesh(str(p))
    v = np.asarray(m.vertices, dtype=np.float64)
    f = np.asarray(m.triangles, dtype=np.int64)
    _check_mesh(p.name, v, f) if len(v) and len(f) else _raise_empty(p)
    extent = float((v.max(0) - v.min(0)).max())
    if not (MESH_EXTENT_M[0] <= extent <= MESH_EXTENT_M[1]):
        print(f"torchskin: warning: mesh {str(p)!r} spans {extent:.4g} units; torchskin reads metres with +z up "
              f"(a person spans about 1.5-2 m): a millimetre or centimetre file renders as a speck or a giant "
              "(scale it to metres)", file=sys.stderr)
    return v.astype(np.float32), f.astype(np.int32)


def _raise_empty(p: Path):
    raise ValueError(f"mesh file {str(p)!r} holds no triangles (empty or unreadable)")


@dataclass
class MeshSpec:
    """A mesh described as data.

    ``kind``: "anny" (params: ``phenotype``, ``pose``), "file" (params: ``path``), "plane" (params: ``width``,
    ``height``: a vertical rectangle facing +x standing on z = 0 before the transform), "cylinder" (``radius``,
    ``height``), "sphere" (``radius``), "ground" (``size``: a horizontal square at z = 0).
    Transform: tilt about the local y axis (degrees; turns the +x normal of a plane towards +z), then yaw
    about z (degrees), then translation ``position``. ``material`` names the material of the
    whole mesh; anny bodies use ``material`` on their exposed skin (head, neck, hands) and
    ``other_material`` elsewhere (clothing).
    """

    name: str
    kind: str
    material: str
    params: dict = field(default_factory=dict)
    position: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    yaw_deg: float = 0.0
    other_material: str | None = None
    tilt_deg: float = 0.0

    def __post_init__(self):
        if self.kind not in ("anny", "file", "plane", "cylinder", "sphere", "ground"):
            raise ValueError(f"mesh kind must be anny, file, plane, cylinder, sphere or ground, got {self.kind!r}")
        if len(self.position) != 3:
            raise ValueError(f"mesh {self.name!r}: position needs 3 coordinates")
        if self.kind == "anny" and self.other_material is None:
            raise ValueError(f"anny mesh {self.name!r} needs other_material for its non-skin regions")

    def build(self) -> TriMesh:
        p = self.params
        mats = [self.material]
        fm = None
        normals = None  # analytic vertex normals of primitives (local frame), else area-weighted
        if self.kind == "anny":
            v, f, skin = anny_body(p.get("phenotype"), p.get("pose"), cache=bool(p.get("cache", True)))
            mats = [self.other_material, self.material]
            fm = skin.astype(np.int32)
        elif self.kind == "file":
            v, f = load_mesh_file(p["path"])
        elif self.kind == "plane":
            v, f = _grid_plane(float(p.get("width", 1.0)), float(p.get("height", 1.0)), int(p.get("nu", 1)),
                               int(p.get("nv", 1)))
        elif self.kind == "cylinder":
            v, f = cylinder_mesh(float(p.get("radius", 0.1)), float(p.get("height", 1.0)), int(p.get("segments", 256)))
            normals = np.c_[v[:, :2], np.zeros(len(v))]
        elif self.kind == "sphere":
            v, f = sphere_mesh(float(p.get("radius", 0.5)), int(p.get("subdivisions", 5)))
            normals = v.copy()
        else:  # ground
            s = float(p.get("size", 50.0))
            v = np.array([[-s, -s, 0], [s, -s, 0], [s, s, 0], [-s, s, 0]], dtype=np.float64)
            f = np.array([[0, 1, 2], [0, 2, 3]])
        for k in ("width", "height", "radius", "size"):
            if k in p and not float(p[k]) > 0:
                raise ValueError(f"mesh {self.name!r}: {k} must be > 0, got {p[k]}")
        c, s = math.cos(math.radians(self.yaw_deg)), math.sin(math.radians(self.yaw_deg))
        ct, st = math.cos(math.radians(self.tilt_deg)), math.sin(math.radians(self.tilt_deg))

        def turn(x):
            x = np.stack([ct * x[:, 0] - st * x[:, 2], x[:, 1], st * x[:, 0] + ct * x[:, 2]], 1)  # tilt
            return np.stack([c * x[:, 0] - s * x[:, 1], s * x[:, 0] + c * x[:, 1], x[:, 2]], 1)  # yaw

        v = turn(np.asarray(v, dtype=np.float64)) + np.asarray(self.position)
        f = np.asarray(f, dtype=np.int32)
        _check_mesh(self.name, v, f)
        fm = np.zeros(len(f), dtype=np.int32) if fm is None else fm
        v32 = v.astype(np.float32)
        if normals is not None:
            normals = turn(normals)
            normals = (normals / np.linalg.norm(normals, axis=1, keepdims=True)).astype(np.float32)
        else:
            normals = vertex_normals(v32, f)
        return TriMesh(self.name, v32, f, fm, mats, normals)


# ------------------------------------------------------------------------------------------ camera and sun
def direction(zenith_deg, azimuth_deg) -> np.ndarray:
    """Unit vector for a zenith angle (from +z) and azimuth (from +x towards +y), degrees."""
    z, a = math.radians(zenith_deg), math.radians(azimuth_deg)
    return np.array([math.sin(z) * math.cos(a), math.sin(z) * math.sin(a), math.cos(z)])


@dataclass
class Camera:
    """A pinhole camera placed by zenith/azimuth/range around ``target`` and looking at it.

    ``fov_deg`` is the horizontal field of view (or give ``focal_px``). ``roll_deg`` turns the image about the
    optical axis.
    """

    width: int = 512
    height: int = 512
    zenith_deg: float = 90.0
    azimuth_deg: float = 0.0
    range_m: float = 9.449
    target: list[float] = field(default_factory=lambda: [0.0, 0.0, 1.0])
    fov_deg: float | None = 14.0
    focal_px: float | None = None

    def __post_init__(self):
        _finite("camera", width=self.width, height=self.height, zenith_deg=self.zenith_deg,
                azimuth_deg=self.azimuth_deg, range_m=self.range_m)
        if len(self.target) != 3 or not all(math.isfinite(float(v)) for v in self.target):
            raise ValueError(f"camera target must be 3 finite coordinates (m), got {self.target}")
        if int(self.width) != self.width or int(self.height) != self.height:
            raise ValueError(f"camera width and height must be whole pixels, got {self.width} x {self.height}")
        if int(self.width) < 1 or int(self.height) < 1:
            raise ValueError(f"camera resolution must be at least 1 x 1 pixels, got {self.width} x {self.height}")
        if not (0.0 <= self.zenith_deg <= 180.0):
            raise ValueError(f"camera zenith must lie in [0, 180] degrees, got {self.zenith_deg}")
        if not self.range_m > 0:
            raise ValueError(f"camera range must be > 0 m, got {self.range_m}")
        if self.focal_px is None and not (self.fov_deg is not None and 0 < self.fov_deg < 180):
            raise ValueError(f"camera fov_deg must lie in (0, 180) degrees, got {self.fov_deg}")

    @property
    def focal(self) -> float:
        if self.focal_px is not None:
            return float(self.focal_px)
        return 0.5 * self.width / math.tan(math.radians(self.fov_deg) / 2)

    @property
    def position(self) -> np.ndarray:
        return np.asarray(self.target, dtype=np.float64) + self.range_m * direction(self.zenith_deg, self.azimuth_deg)

    def world_to_camera(self) -> np.ndarray:
        """4x4 extrinsics (OpenCV convention: x right, y down, z forward)."""
        eye = self.position
        fwd = np.asarray(self.target, dtype=np.float64) - eye
        fwd /= np.linalg.norm(fwd)
        up = np.array([0.0, 0.0, 1.0]) if abs(fwd[2]) < 0.999 else np.array([1.0, 0.0, 0.0])
        right = np.cross(fwd, up)
        right /= np.linalg.norm(right)
        down = np.cross(fwd, right)
        R = np.stack([right, down, fwd])
        E = np.eye(4)
        E[:3, :3] = R
        E[:3, 3] = -R @ eye
        return E

    def kornia(self, dtype=torch.float64):
        """The camera as a ``kornia.geometry.camera.PinholeCamera`` (batch of one)."""
        from kornia.geometry.camera import PinholeCamera

        K = torch.eye(4, dtype=dtype)
        K[0, 0] = K[1, 1] = self.focal
        K[0, 2], K[1, 2] = self.width / 2, self.height / 2
        E = torch.as_tensor(self.world_to_camera(), dtype=dtype)
        return PinholeCamera(K[None], E[None], torch.tensor([float(self.height)], dtype=dtype),
                             torch.tensor([float(self.width)], dtype=dtype))

    def rays(self) -> torch.Tensor:
        """Primary rays (H, W, 6) float32: origin and unit direction through each pixel centre, from the
        kornia camera's inverse intrinsics and camera-to-world rotation."""
        cam = self.kornia()
        Kinv = cam.intrinsics_inverse()[0, :3, :3]
        R = cam.rotation_matrix[0]  # world -> camera
        M = (R.T @ Kinv).to(torch.float32)  # pixel (u, v, 1) -> world direction
        v, u = torch.meshgrid(torch.arange(self.height, dtype=torch.float32) + 0.5,
                              torch.arange(self.width, dtype=torch.float32) + 0.5, indexing="ij")
        d = u[..., None] * M[:, 0] + v[..., None] * M[:, 1] + M[:, 2]
        d = d / d.norm(dim=-1, keepdim=True)
        o = torch.as_tensor(self.position, dtype=torch.float32).expand_as(d)
        return torch.cat([o, d], -1)


def planck_radiance(wavelength_nm, temperature_k: float) -> torch.Tensor:
    """Blackbody spectral radiance, W m^-2 sr^-1 nm^-1 (eq 2.1.8)."""
    wl = torch.as_tensor(wavelength_nm, dtype=torch.float64) * 1e-9
    h, c, k = 6.62607015e-34, 2.99792458e8, 1.380649e-23
    return 2 * h * c**2 / wl**5 / torch.expm1(h * c / (wl * k * temperature_k)) * 1e-9


SUN_SOLID_ANGLE_SR = 6.794e-5  # the solar disc seen from Earth


@dataclass
class Sun:
    """A directional source at (zenith, azimuth) with a 5950 K blackbody spectrum (thesis Fig 1) scaled to
    the solar disc's solid angle (top-of-atmosphere irradiance), plus an optional uniform sky whose
    irradiance on a horizontal surface is ``sky_fraction`` times the sun's normal irradiance."""

    zenith_deg: float = 30.0
    azimuth_deg: float = 0.0
    temperature_k: float = 5950.0
    scale: float = 1.0
    sky_fraction: float = 0.0

    def __post_init__(self):
        _finite("sun", zenith_deg=self.zenith_deg, azimuth_deg=self.azimuth_deg, temperature_k=self.temperature_k,
                scale=self.scale, sky_fraction=self.sky_fraction)
        if not (0.0 <= self.zenith_deg <= 180.0):
            raise ValueError(f"source zenith must lie in [0, 180] degrees, got {self.zenith_deg}")
        if not self.temperature_k > 0 or not self.scale > 0:
            raise ValueError("sun temperature_k and scale must be > 0")
        if not (0.0 <= self.sky_fraction <= 1.0):
            raise ValueError(f"sky_fraction must lie in [0, 1], got {self.sky_fraction}")

    @property
    def direction(self) -> np.ndarray:
        return direction(self.zenith_deg, self.azimuth_deg)

    def irradiance(self, wavelength_nm) -> torch.Tensor:
        """Spectral irradiance normal to the beam, W m^-2 nm^-1."""
        return self.scale * SUN_SOLID_ANGLE_SR * planck_radiance(wavelength_nm, self.temperature_k)


# ---------------------------------------------------------------------------------------------------- scene
BACKGROUNDS = ("void", "sky")


@dataclass
class Scene:
    """Materials (by name), meshes, cameras and suns; ``bands`` as (centre, fwhm) pairs in nm.

    ``panels`` names the two reference-panel meshes used for ELM (bright first). ``background``: what a camera
    ray that hits nothing sees: "void" (no radiance, the default) or "sky" (above the horizon, the uniform sky
    of each sun, radiance sky_fraction · E / π; below it still void).
    """

    materials: dict[str, Material]
    meshes: list[MeshSpec]
    cameras: list[Camera]
    suns: list[Sun]
    bands: list[list[float]] = field(default_factory=lambda: [[b.center_nm, b.fwhm_nm] for b in DEFAULT_BANDS])
    panels: list[str] = field(default_factory=lambda: ["panel_white", "panel_dark"])
    background: str = "void"

    def __post_init__(self):
        if self.background not in BACKGROUNDS:
            raise ValueError(f"background must be one of {BACKGROUNDS}, got {self.background!r}")
        names = [m.name for m in self.meshes]
        if len(set(names)) != len(names):
            raise ValueError(f"mesh names must be unique, got {names}")
        for m in self.meshes:
            for mat in (m.material, m.other_material):
                if mat is not None and mat not in self.materials:
                    raise ValueError(f"mesh {m.name!r} uses unknown material {mat!r}")
        for p in self.panels:
            if p not in names:
                raise ValueError(f"reference panel {p!r} is not a mesh of the scene")
            if self.materials[self.mesh(p).material].kind == "skin":
                raise ValueError(f"reference panel {p!r} must be lambertian or spectralon")
        if not self.cameras or not self.suns:
            raise ValueError("a scene needs at least one camera and one sun")
        as_bands([tuple(b) for b in self.bands])

    @property
    def band_list(self) -> tuple[Band, ...]:
        return as_bands([tuple(b) for b in self.bands])

    def mesh(self, name: str) -> MeshSpec:
        for m in self.meshes:
            if m.name == name:
                return m
        raise ValueError(f"no mesh named {name!r}")

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    def to_json(self, path: str | os.PathLike | None = None) -> str:
        text = json.dumps(self.to_dict(), indent=1)
        if path is not None:
            write_text(path, text)
        return text

    @classmethod
    def from_dict(cls, d: dict) -> Scene:
        """A scene from ``to_dict``'s form; a missing or malformed entry raises ``ValueError`` naming it."""
        if not isinstance(d, dict):
            raise ValueError(f"a scene must be a JSON object, got {type(d).__name__}")
        try:
            return cls._from_dict(d)
        except KeyError as e:
            raise ValueError(f"scene lacks the entry {e.args[0]!r} (materials, meshes, cameras and suns are "
                             "required)") from None
        except (TypeError, AttributeError) as e:
            raise ValueError(f"malformed scene: {' '.join(str(e).split())}") from None

    @classmethod
    def _from_dict(cls, d: dict) -> Scene:
        return cls(
            materials={k: Material(**v) for k, v in d["materials"].items()},
            meshes=[MeshSpec(**m) for m in d["meshes"]],
            cameras=[Camera(**c) for c in d["cameras"]],
            suns=[Sun(**s) for s in d["suns"]],
            bands=[list(b) for b in d.get("bands", [[b.center_nm, b.fwhm_nm] for b in DEFAULT_BANDS])],
            panels=list(d.get("panels", ["panel_white", "panel_dark"])),
            background=d.get("background", "void"),
        )

    @classmethod
    def from_json(cls, text_or_path: str | os.PathLike) -> Scene:
        s = str(text_or_path)
        where = "scene JSON"
        if not s.lstrip().startswith("{"):
            where = f"scene file {s!r}"
            try:
                s = Path(s).read_text(encoding="utf-8")
            except (OSError, UnicodeDecodeError) as e:
                raise ValueError(f"cannot read {where}: {e}") from None
        try:
            d = json.loads(s)
        except json.JSONDecodeError as e:
            raise ValueError(f"{where} is not valid JSON: {e}") from None
        return cls.from_dict(d)


PANEL_KINDS = ("lambertian", "spectralon", "spectralon-brdf")


def panel_materials(panels: str = "lambertian") -> dict[str, Material]:
    """Materials "white" and "dark" for the reference panels: "lambertian" (0.97 / 0.03, the thesis's
    simulation), "spectralon" (Table 3 DHR, Lambertian) or "spectralon-brdf" (Table 3 DHR with the
    Spectralon-like BRDF)."""
    if panels == "lambertian":
        return {"white": Material("lambertian", reflectance=0.97), "dark": Material("lambertian", reflectance=0.03)}
    if panels in ("spectralon", "spectralon-brdf"):
        b = panels == "spectralon-brdf"
        return {"white": Material("spectralon", panel="white", brdf=b),
                "dark": Material("spectralon", panel="dark", brdf=b)}
    raise ValueError(f"panels must be one of {', '.join(PANEL_KINDS)}, got {panels!r}")


def default_scene(
    subject: str = "anny",
    mesh_path: str | None = None,
    skin: str | dict = "I-II",
    camera: Camera | None = None,
    sun: Sun | None = None,
    panels: str = "lambertian",
    diffuse_only: bool = False,
    ground: bool = True,
    surface: str = "thesis",
) -> Scene:
    """The thesis's layout: a subject at the origin facing +x, reference panels either side of it facing the
    camera (vertical for the default horizontal camera in front at 31 ft, 9.449 m; level for a camera overhead;
    turned with the camera's azimuth), 0.9 m off the subject's axis. ``panels``: see ``panel_materials``;
    ``surface``: the skin surface model (``Material``). Metres, z up."""
    mats = {
        "skin": Material("skin", skin=skin, specular=not diffuse_only, surface=surface),
        "clothing": Material("lambertian", reflectance=[0.12, 0.10, 0.35, 0.30]),
        "ground": Material("lambertian", reflectance=[0.15, 0.18, 0.30, 0.25]),
    }
    mats.update(panel_materials(panels))
    if subject == "anny":
        body = MeshSpec("subject", "anny", "skin", other_material="clothing")
    elif subject == "file":
        if not mesh_path:
            raise ValueError("a file subject needs mesh_path")
        body = MeshSpec("subject", "file", "skin", params={"path": str(mesh_path)})
    else:
        raise ValueError(f"subject must be 'anny' or 'file', got {subject!r}")
    cam = camera or Camera()
    # the panels stand either side of the subject across the view and face the camera, wherever it is: vertical
    # for a horizontal camera (the thesis's layout), level for one overhead, tilted towards it in between
    az = math.radians(cam.azimuth_deg)
    side = (-math.sin(az), math.cos(az))
    tilt = float(np.clip(90.0 - cam.zenith_deg, 0.0, 90.0))
    meshes = [body] + [
        MeshSpec(name, "plane", mat, params={"width": 0.6, "height": 0.6},
                 position=[sign * 0.9 * side[0], sign * 0.9 * side[1], 0.9], yaw_deg=cam.azimuth_deg, tilt_deg=tilt)
        for name, mat, sign in (("panel_white", "white", 1.0), ("panel_dark", "dark", -1.0))]
    if ground:
        meshes.append(MeshSpec("ground", "ground", "ground", params={"size": 4000.0}))
    return Scene(mats, meshes, [cam], [sun or Sun()])

"""Stage 2 of the renderer: ray casting with open3d's ``RaycastingScene`` (Embree, CPU). Camera rays -> a
G-buffer (the "Fragments" of this renderer), shadow rays -> a shadow mask per sun. ``rasterize(scene)`` does it
all; ``Raycaster`` keeps the built scene to cast many times (datasets, benchmarks).

The G-buffer holds, per camera and pixel: hit mask, hit distance, position, smooth normal (vertex normals
interpolated with the hit's barycentrics, turned towards the viewer), geometric normal, unit vector to the
viewer, material id and mesh id; and per sun: a shadow mask from ``test_occlusions`` (True: in a cast shadow),
tested only at hit pixels facing that sun (False elsewhere: a pixel turned away from the sun is unlit anyway);
and, for the light models' sky and ground light, each hit pixel's view of the sky and of lit ground
(``Raycaster.with_sky_view``: hemisphere rays).
It is built on the CPU and moved to the target device once (``GBuffer.to``); everything after it runs there.
The per-pixel assembly after the ray cast is one kernel (``kernels.gbuffer_fields``), eager or compiled.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from ..optics import dot3
from .kernels import KERNELS, cos_to, gbuffer_fields, point_along, table_rows
from .meshes import TriMesh, build_meshes
from .scene import Camera, Scene
from .visibility import VisibilityField, pattern_angle, tangent_frame

SHADOW_OFFSET_M = 1e-3  # shadow-ray origins are pushed this far off the surface along the geometric normal
#: pixels with n·ω_sun above -FACING_MARGIN cast shadow rays (the margin keeps every pixel that shading may find
#: facing the sun in another dtype)
FACING_MARGIN = 1e-6
#: hemisphere rays per pixel for its sky and ground view (``Raycaster.with_sky_view``): a fixed cosine-weighted
#: Fibonacci pattern, so a view fraction is a count out of this many (standard error <= 0.5 / sqrt(32) = 0.09 for
#: a single pixel's partial horizon, less for stratified samples; band ratios do not depend on it)
SKY_RAYS = 32
#: a hemisphere ray that hits a surface whose normal is at most 60° from +z (cos >= 0.5) sees lit ground: the
#: ground plane and patches lying on it; anything steeper (the subject, panel stands) is counted as dark
GROUND_UP_COS = 0.5
#: rays per open3d call when casting hemisphere rays (bounds the memory of a large frame)
SKY_RAY_CHUNK = 1 << 20
#: a group of pixels that shares one view of the sky (``Raycaster.with_sky_view``'s ``shared``: the reference
#: panels' interiors) casts hemisphere rays from a regular subset of at most this many of its pixels
SHARED_SKY_PIXELS = 64


@dataclass
class GBuffer:
    """Per-pixel geometry; shapes (C, H, W[, 3]) for C cameras, ``shadow`` (S, C, H, W) for S suns (None: not
    cast yet, ``Raycaster.with_shadows``)."""

    hit: torch.Tensor
    t: torch.Tensor
    rays: torch.Tensor  # (C, H, W, 6) the camera rays: origin, unit direction
    normal: torch.Tensor
    geometric_normal: torch.Tensor
    material: torch.Tensor
    mesh: torch.Tensor
    shadow: torch.Tensor | None
    material_names: list
    mesh_names: list
    sky: torch.Tensor | None = None  # (C, H, W) cosine-weighted fraction of the hemisphere that sees the sky
    ground: torch.Tensor | None = None  # (C, H, W, M) the same, of up-facing surfaces, by their material id
    face: torch.Tensor | None = None  # (C, H, W) int64 the hit face (over all meshes; a sentinel at misses)
    uv: torch.Tensor | None = None  # (C, H, W, 2) the hit's barycentric weights of the face's corners 1 and 2

    @property
    def position(self) -> torch.Tensor:
        """Hit positions (C, H, W, 3), inf or NaN at misses."""
        return point_along(self.rays[..., :3], self.rays[..., 3:], self.t[..., None])

    @property
    def view(self) -> torch.Tensor:
        """Unit vectors (C, H, W, 3) from the surface to the viewer (minus the ray direction)."""
        return -self.rays[..., 3:]

    def sky_views(self) -> tuple[torch.Tensor, torch.Tensor]:
        """``sky`` and ``ground``, or ValueError when they have not been cast (``Raycaster.with_sky_view``)."""
        if self.sky is None or self.ground is None:
            raise ValueError("the G-buffer has no sky view (Raycaster.with_sky_view casts it)")
        return self.sky, self.ground

    def shadow_masks(self) -> torch.Tensor:
        """``shadow``, or ValueError when it has not been cast (``Raycaster.with_shadows``)."""
        if self.shadow is None:
            raise ValueError("the G-buffer has no shadow masks (Raycaster.with_shadows casts them)")
        return self.shadow

    def to(self, device: torch.device | str | None = None, dtype: torch.dtype | None = None) -> GBuffer:
        """The G-buffer on ``device`` with floating tensors in ``dtype`` (itself when nothing changes)."""
        same = all(v.device == torch.device(device or v.device) and (not v.is_floating_point() or dtype in (None, v.dtype))
                   for v in (self.normal, self.hit))
        if same:
            return self
        out: dict[str, Any] = {}
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if isinstance(v, torch.Tensor):
                out[f.name] = v.to(device=device, dtype=dtype if v.is_floating_point() and dtype else None)
            else:
                out[f.name] = v
        return GBuffer(**out)


class Raycaster:
    """An open3d ``RaycastingScene`` over a list of ``TriMesh``; build once, cast many times."""

    def __init__(self, meshes: list[TriMesh], material_names: list[str]) -> None:
        import open3d as o3d

        if not meshes:
            raise ValueError("the scene has no meshes")
        self.o3d = o3d
        self.scene = o3d.t.geometry.RaycastingScene()
        self.mesh_names = [m.name for m in meshes]
        self.material_names = list(material_names)
        gid_to_mesh, face_off = {}, []
        faces, normals, fmat = [], [], []
        nv = nf = 0
        for k, m in enumerate(meshes):
            tm = o3d.t.geometry.TriangleMesh()
            tm.vertex.positions = o3d.core.Tensor(np.ascontiguousarray(m.vertices, dtype=np.float32))  # type: ignore[call-overload]
            tm.triangle.indices = o3d.core.Tensor(np.ascontiguousarray(m.faces, dtype=np.uint32))  # type: ignore[call-overload]
            gid = self.scene.add_triangles(tm)
            gid_to_mesh[gid] = k
            face_off.append(nf)
            faces.append(m.faces.astype(np.int64) + nv)
            normals.append(m.vertex_normals)
            ids = np.array([self.material_names.index(n) for n in m.material_names], dtype=np.int64)
            fmat.append(ids[m.face_material])
            nv += len(m.vertices)
            nf += len(m.faces)
        n_gid = max(gid_to_mesh) + 1
        # lookup tables indexed by geometry id + 1 (open3d's INVALID_ID reads as -1 in int32); a miss maps
        # to a sentinel face nf (a dummy triangle of material -1); padded to ``kernels.table_rows`` rows, so that
        # scenes with another mesh count (more confusers) reuse the compiled kernels
        rows = table_rows(n_gid + 1)
        self._gid_mesh = torch.full((rows,), -1, dtype=torch.int64)
        self._gid_face_off = torch.full((rows,), nf, dtype=torch.int64)
        for gid, k in gid_to_mesh.items():
            self._gid_mesh[gid + 1] = k
            self._gid_face_off[gid + 1] = face_off[k]
        tri = np.concatenate(faces + [np.zeros((1, 3), dtype=np.int64)])
        # the vertex normals of each face's three corners, (F+1, 9): one gather per pixel instead of two
        self._corner_normals = torch.from_numpy(np.concatenate(normals).astype(np.float32)[tri].reshape(-1, 9))
        self._fmat = torch.from_numpy(np.concatenate(fmat + [np.array([-1])]))
        self.rays: dict = {}  # camera rays by camera parameters: a fixed camera's rays are computed once
        self.meshes = list(meshes)
        self._field: VisibilityField | None = None
        # the field's sky view at a cached camera's pixels (``with_sky_view``): id of its rays -> (rays, shared
        # groups, sky, ground); a fixed camera sees the same surfaces in every frame
        self._camera_views: dict[int, tuple] = {}
        self._shadow_rays = torch.empty((0, 6), dtype=torch.float32)  # reused between frames

    @classmethod
    def from_scene(cls, scene: Scene) -> Raycaster:
        """The ray caster of ``scene``'s meshes (built with ``meshes.build_meshes``)."""
        return cls(build_meshes(scene), list(scene.materials))

    def camera_rays(self, camera: Camera) -> torch.Tensor:
        """``camera_rays(camera)``, kept by the camera's parameters on this ray caster."""
        key = tuple(sorted((k, tuple(v) if isinstance(v, list) else v) for k, v in dataclasses.asdict(camera).items()))
        r = self.rays.get(key)
        if r is None:
            if len(self.rays) > 16:
                self.rays.clear()
            r = self.rays[key] = camera_rays(camera)
        return r

    def _tensor(self, x: torch.Tensor) -> Any:
        return self.o3d.core.Tensor.from_numpy(np.ascontiguousarray(x.numpy()))

    def cast(self, rays: torch.Tensor) -> dict:
        """open3d ``cast_rays`` on (..., 6) float32 rays; ids come back as int32 (-1: no hit)."""
        ans = self.scene.cast_rays(self._tensor(rays))
        out = {}
        for k, v in ans.items():
            a = v.numpy()
            if a.dtype == np.uint32:
                a = a.view(np.int32)
            out[k] = torch.from_numpy(a)
        return out

    def occluded(self, rays: torch.Tensor) -> torch.Tensor:
        """open3d ``test_occlusions`` on (..., 6) float32 rays (to infinity)."""
        if rays.numel() == 0:
            return torch.zeros(rays.shape[:-1], dtype=torch.bool)
        return torch.from_numpy(self.scene.test_occlusions(self._tensor(rays)).numpy().astype(bool))

    def gbuffer(self, cameras: list[Camera], sun_directions: np.ndarray, compile: bool = False,
                shadows: bool = True) -> GBuffer:
        """G-buffer for every camera (same resolution) and shadow masks for every sun direction (S, 3)
        (arguments as ``gbuffer_from_rays``)."""
        if len({(c.width, c.height) for c in cameras}) != 1:
            raise ValueError("all cameras of one G-buffer must share a resolution")
        rays = self.camera_rays(cameras[0])[None] if len(cameras) == 1 else torch.stack([self.camera_rays(c) for c in cameras])
        return self.gbuffer_from_rays(rays, sun_directions, compile, shadows)

    def gbuffer_from_rays(self, rays: torch.Tensor, sun_directions: np.ndarray, compile: bool = False,
                          shadows: bool = True) -> GBuffer:
        """G-buffer of (C, H, W, 6) float32 rays. Values at missed pixels are unspecified except ``hit``
        (False), ``t`` (inf), ``material`` and ``mesh`` (-1). ``compile``: the per-pixel assembly as a fused
        compiled kernel (``kernels.gbuffer_fields``). ``shadows=False`` leaves ``shadow`` None (cast it later for
        the pixels that need it: ``with_shadows``)."""
        ans = self.cast(rays)
        shp = ans["t_hit"].shape
        sun = torch.as_tensor(np.asarray(sun_directions, dtype=np.float32)).reshape(-1, 3)
        if not shadows:  # which pixels face which sun is only needed to cast shadow rays now
            sun = sun[:1]
        fields = KERNELS.get(gbuffer_fields, compile)(
            rays.reshape(-1, 6), ans["t_hit"].reshape(-1), ans["geometry_ids"].reshape(-1),
            ans["primitive_ids"].reshape(-1), ans["primitive_uvs"].reshape(-1, 2),
            ans["primitive_normals"].reshape(-1, 3), self._gid_face_off, self._corner_normals, self._fmat,
            self._gid_mesh, sun, FACING_MARGIN, SHADOW_OFFSET_M)
        hit, n, ng, mat, mesh, facing, origin, face = fields
        gb = GBuffer(hit=hit.reshape(shp), t=ans["t_hit"], rays=rays, normal=n.reshape(*shp, 3),
                     geometric_normal=ng.reshape(*shp, 3), material=mat.reshape(shp),
                     mesh=mesh.reshape(shp), shadow=None, material_names=self.material_names,
                     mesh_names=self.mesh_names, face=face.reshape(shp),
                     # copied out of open3d's memory: a G-buffer alive at exit would hold open3d's block past its
                     # memory manager, which then reports a leak and makes the process exit with status 1
                     uv=ans["primitive_uvs"].reshape(*shp, 2).clone())
        return self._cast_shadows(gb, sun, facing, origin) if shadows else gb

    def with_shadows(self, gb: GBuffer, sun_directions: np.ndarray | torch.Tensor) -> GBuffer:
        """``gb`` with its shadow masks cast for every sun direction (S, 3) (a new G-buffer)."""
        sun = torch.as_tensor(np.asarray(sun_directions, dtype=np.float32)).reshape(-1, 3)
        n = gb.normal.reshape(-1, 3).to(torch.float32)
        facing = (cos_to(n, sun) > -FACING_MARGIN) & gb.hit.reshape(1, -1).cpu()
        origin = point_along(gb.position.reshape(-1, 3), gb.geometric_normal.reshape(-1, 3),
                             SHADOW_OFFSET_M).to("cpu", torch.float32)
        return self._cast_shadows(gb, sun, facing, origin)

    def visibility_field(self) -> VisibilityField:
        """The sky and ground view of this ray caster's surfaces (``visibility.VisibilityField``), made on first
        use and kept: its sample points are cast lazily, once per mesh and side."""
        if self._field is None:
            self._field = VisibilityField(self, self.meshes, offset=SHADOW_OFFSET_M)
        return self._field

    @property
    def field_seconds(self) -> float:
        """Seconds spent casting the ``visibility_field``'s sample points so far (0 before any)."""
        return 0.0 if self._field is None else self._field.cast_seconds

    def with_sky_view(self, gb: GBuffer, rays: int = SKY_RAYS, shared: Sequence[torch.Tensor] = (),
                      method: str = "rays") -> GBuffer:
        """``gb`` with each hit pixel's view of the sky and of up-facing surfaces (a new G-buffer).

        ``method="field"``: interpolated from this geometry's ``visibility_field`` (cast once, reused by every
        frame of these meshes: any camera, sun or band set). ``method="rays"``: ``rays`` hemisphere rays per pixel
        (``hemisphere_directions``, turned to the pixel's smooth normal and rotated by a fixed per-pixel angle, a
        hash of its camera ray, so that neighbours do not share one pattern and a pixel gets the same rays in a
        frame and in any subset of it), from points ``SHADOW_OFFSET_M`` off the surface along the geometric
        normal: the cheaper choice for a few pixels (a dataset's sampled rows).

        A ray that escapes upwards sees sky; one that hits a surface facing up (``GROUND_UP_COS``) sees that
        surface's material, lit by the open sky and sun (one bounce); anything else sees nothing. Being
        cosine-weighted, each fraction of rays is the view factor itself: for an open plane tilted by β, sky
        (1 + cos β)/2 and ground (1 - cos β)/2. Counts, not sums: the same bits for any thread count. Missed
        pixels get 0. ``shared``: groups of flat pixel indices (into all cameras' C·H·W pixels) whose pixels share
        one view, the mean of ``rays`` rays from each of a regular subset of at most ``SHARED_SKY_PIXELS`` of them
        (sorted indices, every k-th), with either method: the reference panels' interiors, flat, open and read by
        ELM through their median, which would otherwise cast 40 % of a dataset's sky rays."""
        if method not in ("rays", "field"):
            raise ValueError(f"method must be 'rays' or 'field', got {method!r}")
        hit = gb.hit.reshape(-1).cpu()
        n_px, n_mat = hit.numel(), len(self.material_names)
        groups = [torch.as_tensor(g, dtype=torch.long).cpu().sort().values for g in shared]
        groups = [g[hit.index_select(0, g)] for g in groups if g.numel()]
        cast_px = hit.clone()
        subsets = []
        for g in groups:
            cast_px[g] = False
            subsets.append(g[::max(1, -(-g.numel() // SHARED_SKY_PIXELS))])
        shp, dev, dtype = gb.hit.shape, gb.hit.device, gb.normal.dtype
        base = gb.rays if gb.rays._base is None else gb.rays._base
        # a camera's own G-buffer: its cached rays whole (``gbuffer`` of one camera), not a crop or view of them
        whole = (gb.rays.shape[1:] == base.shape and gb.rays.data_ptr() == base.data_ptr()
                 and gb.rays.stride()[1:] == base.stride())
        key = (rays, int(hit.sum()))
        kept = self._camera_views.get(id(base)) if method == "field" and whole else None
        if (kept is not None and kept[0] is base and kept[1] == key and len(kept[2]) == len(groups)
                and all(torch.equal(a, b) for a, b in zip(kept[2], groups))):  # this camera's views, found before
            return dataclasses.replace(gb, sky=kept[3].reshape(shp).to(device=dev, dtype=dtype, copy=True),
                                       ground=kept[4].reshape(*shp, n_mat).to(device=dev, dtype=dtype, copy=True))
        sky = torch.zeros(n_px, dtype=torch.float32)
        ground = torch.zeros(n_px, n_mat, dtype=torch.float32)
        if method == "field":
            own = cast_px.nonzero().flatten()
            field = self.visibility_field()
            left, rim = field.lookup(gb, own, sky, ground) if own.numel() else (own, own)
            idx = torch.cat([*subsets, left]).sort().values  # the panels' samples, and meshes too large for the field
            self._cast_views(gb, rim, field.rays, sky, ground)  # a plane's pixels beside what lies on it
        else:
            for sub in subsets:
                cast_px[sub] = True
            idx = cast_px.nonzero().flatten()
        cs, cg = self._cast_views(gb, idx, rays, sky, ground)
        for g, sub in zip(groups, subsets):  # integer sums: the same bits whatever the order
            sky[g] = float(cs[sub].sum()) / (rays * sub.numel())
            ground[g] = (cg[sub].sum(0).double() / (rays * sub.numel())).float()
        if method == "field" and whole and any(base is r for r in self.rays.values()):  # a cached camera's: kept
            if len(self._camera_views) > 4:
                self._camera_views.clear()
            self._camera_views[id(base)] = (base, key, groups, sky.clone(), ground.clone())
        return dataclasses.replace(gb, sky=sky.reshape(shp).to(device=dev, dtype=dtype),
                                   ground=ground.reshape(*shp, n_mat).to(device=dev, dtype=dtype))

    def _cast_views(self, gb: GBuffer, idx: torch.Tensor, rays: int, sky: torch.Tensor,
                    ground: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``rays`` hemisphere rays from each pixel of ``idx`` (flat indices into ``gb``'s pixels): their view
        fractions written into ``sky`` (N,) and ``ground`` (N, M), and the ray counts returned over all N pixels
        ((N,) and (N, M) int64, 0 outside ``idx``), for ``with_sky_view``'s shared groups."""
        n_px, n_mat = sky.shape[0], ground.shape[1]
        cs = torch.zeros(n_px, dtype=torch.int64)
        cg = torch.zeros(n_px, n_mat, dtype=torch.int64)
        if not idx.numel():
            return cs, cg

        def rows(x: torch.Tensor, k: int) -> torch.Tensor:  # the cast pixels' rows, in the G-buffer's dtype
            return x.reshape(-1, k).cpu().index_select(0, idx)

        ray = rows(gb.rays, 6)
        normal = rows(gb.normal, 3).double()
        position = point_along(ray[:, :3], ray[:, 3:], rows(gb.t, 1))  # as ``GBuffer.position``, then float64
        origin = point_along(position.double(), rows(gb.geometric_normal, 3).double(), SHADOW_OFFSET_M)
        counts_sky, counts_ground = self.hemisphere_counts(origin, normal, pattern_angle(ray[:, 3:].double()), rays,
                                                           n_mat)
        cs[idx], cg[idx] = counts_sky, counts_ground
        sky[idx] = (counts_sky.double() / rays).float()
        ground[idx] = (counts_ground.double() / rays).float()
        return cs, cg

    def hemisphere_counts(self, origin: torch.Tensor, normal: torch.Tensor, psi: torch.Tensor, rays: int,
                           n_mat: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Per pixel (P,): how many of its ``rays`` hemisphere rays (the pattern turned by ``psi`` about the
        normal) see sky, and (P, M) how many see an up-facing surface of each material (float64 geometry, float32
        rays for open3d)."""
        local = hemisphere_directions(rays)  # (K, 3)
        t, b = tangent_frame(normal)
        c, s = torch.cos(psi)[:, None], torch.sin(psi)[:, None]
        x = c * local[None, :, 0] - s * local[None, :, 1]
        y = s * local[None, :, 0] + c * local[None, :, 1]
        dirs = x[..., None] * t[:, None] + y[..., None] * b[:, None] + local[None, :, 2:3] * normal[:, None]  # (P, K, 3)
        P = origin.shape[0]
        ray = torch.cat([origin[:, None].expand(P, rays, 3), dirs], -1).reshape(-1, 6).float()
        pix = torch.arange(ray.shape[0]) // rays
        # a climbing ray that nothing occludes sees sky: one cheap occlusion test; the others (descending, or
        # occluded) are cast in full for the face they hit
        up = (ray[:, 5] > 0).nonzero().flatten()
        free = torch.zeros(ray.shape[0], dtype=torch.bool)
        free[up] = ~self.occluded(ray.index_select(0, up))
        counts_sky = torch.bincount(pix[free], minlength=P)
        counts_ground = torch.zeros(P * n_mat, dtype=torch.int64)
        rest = (~free).nonzero().flatten()
        for lo in range(0, rest.numel(), SKY_RAY_CHUNK):
            sel = rest[lo:lo + SKY_RAY_CHUNK]
            chunk = ray.index_select(0, sel)
            ans = self.cast(chunk)
            escaped = torch.isinf(ans["t_hit"])
            gid1 = ans["geometry_ids"].long() + 1
            face = self._gid_face_off[gid1] + ans["primitive_ids"].long().clamp_min(0)
            pn = ans["primitive_normals"]
            # the hit face's normal turned towards the ray's origin: up-facing if it points up
            side = torch.where(dot3(pn, chunk[:, 3:]) > 0, -1.0, 1.0)
            ok = ~escaped & (pn[:, 2] * side >= GROUND_UP_COS)
            mat = self._fmat[face]
            keep = ok & (mat >= 0)
            counts_ground += torch.bincount(pix[sel][keep] * n_mat + mat[keep], minlength=P * n_mat)
        return counts_sky, counts_ground.reshape(P, n_mat)

    def _cast_shadows(self, gb: GBuffer, sun: torch.Tensor, facing: torch.Tensor, origin: torch.Tensor) -> GBuffer:
        """Shadow rays from the pixels ``facing`` (S, N) each sun (a pixel turned away is unlit whatever lies
        between it and the sun: it casts no ray): origins pushed ``SHADOW_OFFSET_M`` off the surface along the
        geometric normal."""
        rows = facing.reshape(-1).nonzero().flatten()
        shadow = torch.zeros(facing.numel(), dtype=torch.bool)
        if rows.numel():
            if self._shadow_rays.shape[0] < rows.numel():
                self._shadow_rays = torch.empty((int(rows.numel() * 1.25), 6), dtype=torch.float32)
            srays = self._shadow_rays[:rows.numel()]
            if len(sun) == 1:
                torch.index_select(origin, 0, rows, out=srays[:, :3])
                srays[:, 3:] = sun
            else:
                n_px = facing.shape[1]
                torch.index_select(origin, 0, rows % n_px, out=srays[:, :3])
                torch.index_select(sun, 0, torch.div(rows, n_px, rounding_mode="floor"), out=srays[:, 3:])
            shadow.index_copy_(0, rows, self.occluded(srays))
        return dataclasses.replace(gb, shadow=shadow.reshape((len(sun),) + gb.hit.shape))


def hemisphere_directions(k: int) -> torch.Tensor:
    """``k`` cosine-weighted directions of the hemisphere about +z, (k, 3) float64: a Fibonacci spiral on the unit
    disc lifted to the hemisphere (Malley's method), so that each direction stands for an equal share of the
    cosine-weighted solid angle and the fraction of directions that see something is its view factor.

    >>> d = hemisphere_directions(32)
    >>> tuple(d.shape), round(float(d[:, 2].min()), 3) > 0, round(float((d * d).sum(1).max()), 6)
    ((32, 3), True, 1.0)
    """
    if k < 1:
        raise ValueError(f"hemisphere rays must be at least 1, got {k}")
    i = torch.arange(k, dtype=torch.float64)
    r = torch.sqrt((i + 0.5) / k)
    phi = i * (np.pi * (3.0 - np.sqrt(5.0)))  # the golden angle
    return torch.stack([r * torch.cos(phi), r * torch.sin(phi), torch.sqrt((1 - r * r).clamp_min(0.0))], -1)


def kornia_camera(camera: Camera, dtype: torch.dtype = torch.float64) -> Any:
    """``camera`` as a ``kornia.geometry.camera.PinholeCamera`` (batch of one)."""
    from kornia.geometry.camera import PinholeCamera

    K = torch.eye(4, dtype=dtype)
    K[0, 0] = K[1, 1] = camera.focal
    K[0, 2], K[1, 2] = camera.width / 2, camera.height / 2
    E = torch.as_tensor(camera.world_to_camera(), dtype=dtype)
    return PinholeCamera(K[None], E[None], torch.tensor([float(camera.height)], dtype=dtype),
                         torch.tensor([float(camera.width)], dtype=dtype))


def camera_rays(camera: Camera) -> torch.Tensor:
    """Primary rays through each pixel centre, from the kornia camera's inverse intrinsics and camera-to-world
    rotation.

    Returns:
        (H, W, 6) float32: origin and unit direction per pixel.

    >>> from torchskin.render.scene import Camera
    >>> r = camera_rays(Camera(width=4, height=2, zenith_deg=90.0, azimuth_deg=0.0))
    >>> tuple(r.shape), round(float(r[..., 3].mean()), 2)  # looking along -x at the subject
    ((2, 4, 6), -1.0)
    """
    cam = kornia_camera(camera)
    Kinv = cam.intrinsics_inverse()[0, :3, :3]
    R = cam.rotation_matrix[0]  # world -> camera
    M = R.T @ Kinv  # pixel (u, v, 1) -> world direction
    v, u = torch.meshgrid(torch.arange(camera.height, dtype=M.dtype) + 0.5,
                          torch.arange(camera.width, dtype=M.dtype) + 0.5, indexing="ij")
    d = u[..., None] * M[:, 0] + v[..., None] * M[:, 1] + M[:, 2]
    d = (d / dot3(d, d).sqrt()[..., None]).to(torch.float32)  # float64, written out: the same bits everywhere
    o = torch.as_tensor(camera.position, dtype=torch.float32).expand_as(d)
    return torch.cat([o, d], -1)


def rasterize(scene: Scene, raycaster: Raycaster | None = None, compile: bool = False) -> GBuffer:
    """The G-buffer of every camera of ``scene`` and the shadow masks of every sun (on the CPU).

    Args:
        scene: cameras (one resolution), suns and meshes.
        raycaster: a ray caster of the scene's meshes to reuse (default: built from ``scene``).
        compile: assemble the G-buffer with the compiled kernel (``kernels``).

    Shape:
        G-buffer fields (C, H, W[, 3]); ``shadow`` (S, C, H, W).
    """
    raycaster = raycaster or Raycaster.from_scene(scene)
    return raycaster.gbuffer(scene.cameras, np.stack([s.direction for s in scene.suns]), compile)

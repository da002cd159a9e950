"""Sky and ground view once per geometry: a ``VisibilityField`` over every surface of a ``Raycaster``'s meshes,
looked up per pixel through the G-buffer.

A surface point's view of the sky and of lit ground depends on the meshes alone: not on the sun, the camera,
the bands, the skin or the atmosphere. So it is cast once per geometry, at sample points on the surfaces, and
every frame of that geometry (any camera, sun or band set) interpolates it:

- **curved meshes** (a body, a scan, a sphere, a cylinder): at every vertex, and inside triangles longer than
  ``EDGE_MAX_M`` at a regular barycentric grid of points; a pixel interpolates the three sample points around it
  with its hit's barycentric coordinates, as it does the vertex normals;
- **planar meshes** (the ground, reference panels, flat confusers): on a grid in the plane, spaced
  ``PLANE_SPACING_M`` where the other objects stand and wider by ``PLANE_GROWTH`` per step away from them, out
  to the plane's edge (the ground's open sky far away is smooth); a pixel interpolates bilinearly. Where
  something lies or stands on the plane (a patch on the ground, a foot), the view changes within millimetres of
  its rim, finer than the grid: a pixel whose grid cell has a corner under it, or next to one under it, casts
  its own rays instead.

Each sample point casts ``FIELD_RAYS`` cosine-weighted hemisphere rays (``Raycaster.hemisphere_counts``), so its
view is a count out of that many: the same bits at any thread count. A surface seen from its back (a panel from
behind) gets its own field for that side, cast the first time a pixel needs it.

Accuracy against a per-pixel 64-ray cast, and what it costs: ``docs/guide/rendering.md``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
import torch

if TYPE_CHECKING:
    from .meshes import TriMesh
    from .raycast import GBuffer, Raycaster

#: hemisphere rays per sample point of a ``VisibilityField`` (cast once per geometry)
FIELD_RAYS = 128
#: a curved mesh's triangles are sampled inside on a barycentric grid whose steps are at most this long
EDGE_MAX_M = 0.1
#: a curved mesh that would take more sample points than this (a large scan or terrain) is left to per-pixel rays:
#: casting it would cost more than most frames of it (128 rays a sample: ~30 M rays, seconds, at the cap)
MAX_MESH_SAMPLES = 250_000
#: at most this many steps along a triangle edge (a triangle longer than EDGE_MAX_M times this is sampled coarser)
MAX_SUBDIVISION = 16
#: a planar mesh's grid spacing where other objects stand (their bounding box, widened by ``PLANE_MARGIN_M``)
PLANE_SPACING_M = 0.05
#: beyond that region, each grid step is this many times the one before, out to the plane's edge
PLANE_GROWTH = 1.25
#: at most this many grid steps across a plane's dense region (wider steps over a wider region)
PLANE_MAX_DENSE = 256
#: sample points cast per call (bounds the memory of a large mesh's field: its rays, directions and counts)
FIELD_CHUNK = 8192
#: the dense region of a plane's grid reaches this far beyond the other objects' bounding box
PLANE_MARGIN_M = 0.5
#: objects larger than this (a bounding-box diagonal: the ground, a backdrop) do not set where grids are dense
BACKDROP_M = 50.0
#: sample points sit this far inside their surface (towards their faces' centres; a plane's edge rows inside its
#: edge): a vertex where a body meets the ground, or a wall's foot, would otherwise sample on the ground itself
SAMPLE_INSET_M = 0.005
#: a plane's sample with another surface closer than this along its normal is covered (``_fill_covered``)
COVER_M = 0.01
#: a mesh is planar when every vertex lies within this share of its size of one plane
PLANAR_TOLERANCE = 1e-6


@dataclass
class _Plane:
    """A planar mesh's grid: origin, in-plane axes and normal (float64, (3,)), the grid's ticks along each axis."""

    origin: torch.Tensor
    e1: torch.Tensor
    e2: torch.Tensor
    normal: torch.Tensor
    xs: torch.Tensor
    ys: torch.Tensor

    def points(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Sample positions (Nx * Ny, 3), x-major, the edge rows ``SAMPLE_INSET_M`` inside the plane's edge (so
        that a wall standing on the ground samples above it), and their normals (the plane's)."""
        xs, ys = (t.clamp(float(t[0]) + SAMPLE_INSET_M, float(t[-1]) - SAMPLE_INSET_M) for t in (self.xs, self.ys))
        gx, gy = torch.meshgrid(xs, ys, indexing="ij")
        pos = self.origin + gx.reshape(-1, 1) * self.e1 + gy.reshape(-1, 1) * self.e2
        return pos, self.normal.expand_as(pos)

    corners: torch.Tensor  # (F, 3, 3) float64 the faces' corner positions
    face_normals: torch.Tensor  # (F, 3) float64 unit

    def __post_init__(self) -> None:  # float32 tables for the per-pixel lookup
        self.face_normals32 = self.face_normals.float()
        d = self.corners - self.origin
        # per face and axis: the in-plane coordinate of corner 0, and of corners 1 and 2 relative to it
        self._face_xy = []
        for axis in (self.e1, self.e2):
            x = d @ axis  # (F, 3)
            self._face_xy.append((x[:, 0].float(), (x[:, 1] - x[:, 0]).float(), (x[:, 2] - x[:, 0]).float()))
        self._ticks32 = [self.xs.float(), self.ys.float()]
        self._inv32 = [(1.0 / (x[1:] - x[:-1])).float() for x in (self.xs, self.ys)]

    def weights(self, face: torch.Tensor, u: torch.Tensor, v: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The four grid samples around each hit (local face (P,), barycentric weights u, v (P,) of corners 1 and
        2: its in-plane coordinates from the face's corners') and their bilinear weights, both (4, P)."""
        base, frac = None, []
        for a in (0, 1):
            c0, c1, c2 = (t.index_select(0, face) for t in self._face_xy[a])
            x = c0 + u * c1 + v * c2
            ticks = self._ticks32[a]
            i = (torch.searchsorted(ticks, x, right=True) - 1).clamp_(0, len(ticks) - 2)
            frac.append(((x - ticks.index_select(0, i)) * self._inv32[a].index_select(0, i)).clamp_(0.0, 1.0))
            base = i * len(self.ys) if base is None else base + i
        assert base is not None
        ny = len(self.ys)
        fx, fy = frac
        gx, gy = 1 - fx, 1 - fy
        return (torch.stack([base, base + 1, base + ny, base + ny + 1]),
                torch.stack([gx * gy, gx * fy, fx * gy, fx * fy]))


@dataclass
class _Curved:
    """A curved mesh's sample points: its vertices, then the grid points inside its long triangles. Per face
    (its local index): the grid's steps ``m`` and where its grid points' sample indices start in ``block``."""

    positions: torch.Tensor  # (Q, 3) float64
    normals: torch.Tensor  # (Q, 3) unit, float64
    face_normals: torch.Tensor  # (F, 3) unit, float64
    m: torch.Tensor  # (F,) int64
    start: torch.Tensor  # (F,) int64, into block
    block: torch.Tensor  # (sum over faces of (m+1)(m+2)/2,) int64: sample index of each face's grid point
    inward: torch.Tensor  # (Q, 3) unit (or 0): each sample's way into its faces (``SAMPLE_INSET_M``)
    corners: torch.Tensor | None = None  # (F, 3) the faces' vertices when every face has m == 1 (the fast path)

    def __post_init__(self) -> None:
        self.face_normals32 = self.face_normals.float()
        if int(self.m.max()) == 1:
            # grid order (0, 0), (0, 1), (1, 0): corners 0, 2, 1
            self.corners = self.block.reshape(-1, 3)[:, [0, 2, 1]].contiguous()

    def weights(self, face: torch.Tensor, u: torch.Tensor, v: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The three sample points around each hit (local face (P,), barycentric weights u, v (P,) of corners 1
        and 2) and their weights, both (3, P): the sub-triangle of the face's grid that holds the hit."""
        if self.corners is not None:  # every face a single step: its three vertices
            return self.corners.index_select(0, face).t(), torch.stack([1 - u - v, u, v]).clamp_min(0.0)
        m = self.m[face]
        mf = m.to(u.dtype)
        a, b = u.clamp(0.0, 1.0) * mf, v.clamp(0.0, 1.0) * mf
        p = torch.minimum(a.floor().long(), m - 1).clamp_min(0)
        q = torch.minimum(b.floor().long(), m - 1 - p).clamp_min(0)
        fa, fb = a - p, b - q
        upper = (fa + fb > 1) & (p + q + 2 <= m)  # on the hypotenuse (u + v = 1 to rounding) the lower triangle

        def point(pp: torch.Tensor, qq: torch.Tensor) -> torch.Tensor:  # grid point (pp, qq): row pp holds m+1-pp
            return self.block[self.start[face] + pp * (m + 1) - pp * (pp - 1) // 2 + qq]

        one = torch.ones_like(p)
        lower_pts = torch.stack([point(p, q), point(p + one, q), point(p, q + one)], -1)
        upper_pts = torch.stack([point(torch.where(upper, p + 1, p), torch.where(upper, q + 1, q)),
                                 point(p, q + one), point(p + one, q)], -1)
        w_lower = torch.stack([1 - fa - fb, fa, fb], -1)
        w_upper = torch.stack([fa + fb - 1, 1 - fa, 1 - fb], -1)
        up = upper[:, None]
        return torch.where(up, upper_pts, lower_pts).t(), torch.where(up, w_upper, w_lower).clamp_min(0.0).t()


def _is_planar(v: np.ndarray, faces: np.ndarray) -> np.ndarray | None:
    """The unit normal of a planar mesh (every vertex within ``PLANAR_TOLERANCE`` of its size of the plane of its
    largest face), else None."""
    from .meshes import face_cross

    cross = face_cross(v, faces)
    k = int(np.argmax(np.linalg.norm(cross, axis=1)))
    ln = float(np.linalg.norm(cross[k]))
    if ln == 0.0:
        return None
    n = cross[k] / ln
    size = float(np.linalg.norm(v.max(0) - v.min(0)))
    return n if float(np.abs((v - v[faces[k, 0]]) @ n).max()) <= PLANAR_TOLERANCE * max(size, 1.0) else None


def _ticks(lo: float, hi: float, dense_lo: float, dense_hi: float) -> np.ndarray:
    """Grid ticks over [lo, hi]: ``PLANE_SPACING_M`` apart over [dense_lo, dense_hi] (clipped to [lo, hi]; wider
    where that would take more than ``PLANE_MAX_DENSE`` steps), each step ``PLANE_GROWTH`` times the last beyond
    it, the ends exactly lo and hi (at least two ticks)."""
    if hi - lo <= 1e-9:
        return np.array([lo, lo + 1.0])
    a, b = min(max(dense_lo, lo), hi), max(min(dense_hi, hi), lo)
    if b < a:  # the dense region lies off this plane: dense around its nearest point
        a = b = min(max(0.5 * (dense_lo + dense_hi), lo), hi)
    spacing = max(PLANE_SPACING_M, (b - a) / PLANE_MAX_DENSE)
    n = max(1, math.ceil((b - a) / spacing))
    mid = list(np.linspace(a, b, n + 1)) if b > a else [a]
    left, right, step = [], [], spacing
    x = a
    while x - step > lo + 0.5 * step:
        x -= step
        left.append(x)
        step *= PLANE_GROWTH
    step, x = spacing, b
    while x + step < hi - 0.5 * step:
        x += step
        right.append(x)
        step *= PLANE_GROWTH
    ticks = left[::-1] + mid + right
    if ticks[0] > lo:
        ticks = [lo] + ticks
    if ticks[-1] < hi:
        ticks = ticks + [hi]
    return np.array(ticks, dtype=np.float64)


def _plane(mesh: TriMesh, normal: np.ndarray, dense: tuple[np.ndarray, np.ndarray] | None) -> _Plane:
    """The grid of a planar ``mesh``: dense over the other objects' box ``dense`` (lo, hi corners) projected into
    the plane (None: no other object, sparse everywhere)."""
    n = torch.as_tensor(normal, dtype=torch.float64)
    e1, e2 = (x[0] for x in tangent_frame(n[None]))
    v = torch.as_tensor(mesh.vertices, dtype=torch.float64)
    o = v[0]
    ticks = []
    for axis in (e1, e2):
        s = (v - o) @ axis
        lo, hi = float(s.min()), float(s.max())
        if dense is None:  # nothing else stands in the scene: open everywhere, one dense tick at the centre
            d_lo = d_hi = 0.5 * (lo + hi)
        else:
            corners = torch.as_tensor(np.array(np.meshgrid(*zip(*dense), indexing="ij")).reshape(3, -1).T)
            c = (corners - o) @ axis
            d_lo, d_hi = float(c.min()) - PLANE_MARGIN_M, float(c.max()) + PLANE_MARGIN_M
        ticks.append(torch.as_tensor(_ticks(lo, hi, d_lo, d_hi)))
    c = v[torch.as_tensor(mesh.faces, dtype=torch.int64)]
    fn = torch.linalg.cross(c[:, 1] - c[:, 0], c[:, 2] - c[:, 0])
    fn = fn / fn.norm(dim=1, keepdim=True).clamp_min(1e-300)
    return _Plane(o, e1, e2, n, ticks[0], ticks[1], c, fn)


def _curved(mesh: TriMesh) -> _Curved | None:
    """The sample points of a curved ``mesh``: its vertices, and each long triangle's barycentric grid of ``m``
    steps a side (``EDGE_MAX_M``, at most ``MAX_SUBDIVISION``) with normals interpolated as the G-buffer's; None
    for a mesh that would take more than ``MAX_MESH_SAMPLES``."""
    v = torch.from_numpy(np.array(mesh.vertices, dtype=np.float64))  # copies: a mesh's arrays may be read-only
    vn = torch.from_numpy(np.array(mesh.vertex_normals, dtype=np.float64))
    f = torch.from_numpy(np.array(mesh.faces, dtype=np.int64))
    c = v[f]  # (F, 3 corners, 3)
    fn = torch.linalg.cross(c[:, 1] - c[:, 0], c[:, 2] - c[:, 0])
    fn = fn / fn.norm(dim=1, keepdim=True).clamp_min(1e-300)
    edge = torch.stack([(c[:, 1] - c[:, 0]).norm(dim=1), (c[:, 2] - c[:, 1]).norm(dim=1),
                        (c[:, 0] - c[:, 2]).norm(dim=1)], 1).amax(1)
    m = torch.ceil(edge / EDGE_MAX_M).clamp(1, MAX_SUBDIVISION).long()
    size = (m + 1) * (m + 2) // 2
    if len(v) + int((size - 3).sum()) > MAX_MESH_SAMPLES:  # too large to sample: per-pixel rays
        return None
    start = torch.cumsum(size, 0) - size
    block = torch.empty(int(size.sum()), dtype=torch.int64)
    positions, normals = [v], [vn / vn.norm(dim=1, keepdim=True).clamp_min(1e-300)]
    q_next = len(v)
    for mm in torch.unique(m).tolist():  # faces by their step count: one barycentric pattern each
        sel = (m == mm).nonzero().flatten()
        pq = [(p, q) for p in range(mm + 1) for q in range(mm + 1 - p)]  # row p holds m+1-p points, p-major
        bary = torch.tensor([(1 - (p + q) / mm, p / mm, q / mm) for p, q in pq], dtype=torch.float64)  # (K, 3)
        corner = {(0, 0): 0, (mm, 0): 1, (0, mm): 2}
        slots = start[sel][:, None] + torch.arange(len(pq))[None]  # (Fs, K)
        inner = [k for k, pq_k in enumerate(pq) if pq_k not in corner]
        for k, pq_k in enumerate(pq):
            if pq_k in corner:
                block[slots[:, k]] = f[sel, corner[pq_k]]
        if inner:
            b = bary[inner]  # (Ki, 3)
            pos = torch.einsum("kc,fcx->fkx", b, c[sel]).reshape(-1, 3)
            nrm = torch.einsum("kc,fcx->fkx", b, vn[f[sel]]).reshape(-1, 3)
            positions.append(pos)
            normals.append(nrm / nrm.norm(dim=1, keepdim=True).clamp_min(1e-300))
            block[slots[:, inner].reshape(-1)] = torch.arange(q_next, q_next + len(pos))
            q_next += len(pos)
    centroid = c.mean(1)
    # each sample's way into its surface. A vertex on the mesh's open edge (a cylinder's rim, a scan's cut) moves
    # towards its faces, along the surface: the sum of its faces' centroids about it, without its normal part,
    # is long there and about 0 inside the mesh (faces all round). A grid point moves towards its face's centre
    to_faces, reach, count = np.zeros((len(v), 3)), np.zeros(len(v)), np.zeros(len(v))
    fi = f.numpy()
    for k in range(3):  # np.add.at: sequential, the same sums at any thread count
        off = (centroid - c[:, k]).numpy()
        np.add.at(to_faces, fi[:, k], off)
        np.add.at(reach, fi[:, k], np.linalg.norm(off, axis=1))
        np.add.at(count, fi[:, k], 1.0)
    d = torch.from_numpy(to_faces)
    n0 = normals[0]
    d = d - (d * n0).sum(1, keepdim=True) * n0
    rim = d.norm(dim=1) > 0.25 * torch.from_numpy(reach)  # a half ring gives ~0.64 of its faces' reach
    inward = [torch.where(rim[:, None], d / d.norm(dim=1, keepdim=True).clamp_min(1e-300), torch.zeros_like(d))]
    for mm in torch.unique(m).tolist():  # the grid points in the order they were added
        sel = (m == mm).nonzero().flatten()
        pq = [(p, q) for p in range(mm + 1) for q in range(mm + 1 - p) if (p, q) not in ((0, 0), (mm, 0), (0, mm))]
        if pq:
            b = torch.tensor([(1 - (p + q) / mm, p / mm, q / mm) for p, q in pq], dtype=torch.float64)
            g = (centroid[sel][:, None] - torch.einsum("kc,fcx->fkx", b, c[sel])).reshape(-1, 3)
            inward.append(g / g.norm(dim=1, keepdim=True).clamp_min(1e-12))  # 0 at the centroid itself
    d = torch.cat(inward)
    return _Curved(torch.cat(positions), torch.cat(normals), fn, m, start, block, d)


@dataclass
class VisibilityField:
    """Sky and ground view sample points of every mesh of a ``Raycaster``, cast lazily per mesh and side (the
    first time a pixel of that mesh seen from that side is looked up) and kept. ``lookup`` interpolates them at a
    G-buffer's pixels.

    >>> from torchskin.render.meshes import build_mesh
    >>> from torchskin.render.raycast import Raycaster
    >>> from torchskin.render.scene import Camera, MeshSpec
    >>> rc = Raycaster([build_mesh(MeshSpec("ground", "ground", "soil", {"size": 50.0}))], ["soil"])
    >>> cam = Camera(width=8, height=8, zenith_deg=0.0, range_m=5.0, target=[0.0, 0.0, 0.0])
    >>> gb = rc.with_sky_view(rc.gbuffer([cam], [[0.0, 0.0, 1.0]]), method="field")
    >>> float(gb.sky.min()), rc.visibility_field().samples  # an open plane: the whole sky, a sparse grid
    (1.0, 2601)
    """

    raycaster: Raycaster
    meshes: list[TriMesh]
    rays: int = FIELD_RAYS
    offset: float = 1e-3  # sample rays start this far off the surface (the ray caster's ``SHADOW_OFFSET_M``)
    shapes: list[_Plane | _Curved | None] = field(default_factory=list)  # None: a mesh left to per-pixel rays
    face_offset: list[int] = field(default_factory=list)
    values: dict[tuple[int, int], torch.Tensor] = field(default_factory=dict)  # (mesh, side) -> (Q, 1 + M)
    # a plane's (mesh, side) -> (Q,) bool: its samples covered or next to a covered one (``lookup``: per-pixel rays)
    covered: dict[tuple[int, int], torch.Tensor] = field(default_factory=dict)
    cast_seconds: float = 0.0

    def __post_init__(self) -> None:
        boxes = [(m.vertices.min(0), m.vertices.max(0)) for m in self.meshes]
        off = 0
        for k, mesh in enumerate(self.meshes):
            self.face_offset.append(off)
            off += len(mesh.faces)
            n = _is_planar(mesh.vertices.astype(np.float64), mesh.faces)
            if n is None:
                self.shapes.append(_curved(mesh))
                continue
            others = [b for j, b in enumerate(boxes) if j != k and np.linalg.norm(b[1] - b[0]) < BACKDROP_M]
            dense = None if not others else (np.min([b[0] for b in others], 0).astype(np.float64),
                                             np.max([b[1] for b in others], 0).astype(np.float64))
            self.shapes.append(_plane(mesh, n, dense))

    @property
    def samples(self) -> int:
        """Sample points of one side of every mesh."""
        return sum(len(s.xs) * len(s.ys) if isinstance(s, _Plane) else len(s.positions) for s in self.shapes
                   if s is not None)

    def _values(self, k: int, side: int) -> torch.Tensor:
        """Mesh ``k``'s sample points seen from ``side`` (+1: the side its normals point to), cast on first use:
        their view fractions (Q, 1 + M) float32, the sky then the ground of each material."""
        got = self.values.get((k, side))
        if got is not None:
            return got
        import time

        t0 = time.perf_counter()
        s = self.shapes[k]
        if s is None:
            raise ValueError(f"mesh {k} is left to per-pixel rays (more than {MAX_MESH_SAMPLES} sample points)")
        if isinstance(s, _Plane):
            pos, nrm = s.points()
        else:
            pos, nrm = s.positions + SAMPLE_INSET_M * s.inward, s.normals
        nrm = nrm * side
        origin = pos + self.offset * nrm
        n_mat = len(self.raycaster.material_names)
        psi = pattern_angle(pos + 0.5 * nrm)
        parts = [self.raycaster.hemisphere_counts(origin[i:i + FIELD_CHUNK], nrm[i:i + FIELD_CHUNK],
                                                  psi[i:i + FIELD_CHUNK], self.rays, n_mat)
                 for i in range(0, len(pos), FIELD_CHUNK)]  # integer counts: chunks change nothing
        sky, ground = torch.cat([p[0] for p in parts]), torch.cat([p[1] for p in parts])
        vals = (torch.cat([sky[:, None], ground], 1).double() / self.rays).float()
        if isinstance(s, _Plane):
            vals, covered = self._fill_covered(s, origin, nrm, vals)
            # covered samples and their eight neighbours: a sample just beside a patch's edge sees the patch's
            # underside over half its hemisphere, a darkness ~1 cm wide that its grid cells must not spread
            near = torch.nn.functional.max_pool2d(covered.reshape(1, 1, len(s.xs), len(s.ys)).float(), 3, 1, 1)
            self.covered[(k, side)] = near.reshape(-1) > 0
        self.values[(k, side)] = vals
        self.cast_seconds += time.perf_counter() - t0
        return vals

    def _fill_covered(self, s: _Plane, origin: torch.Tensor, nrm: torch.Tensor,
                      vals: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """A plane's grid values with its covered samples (another surface within ``COVER_M`` above them: the
        ground under a patch lying on it, or under a body's sole) replaced, ring by ring from their uncovered
        neighbours, by the mean of those, and which samples were covered ((Q,) bool). The fill keeps the dark
        beneath a patch out of the bilinear weights of the open ground beside it; ``lookup`` sends the pixels of
        cells with a covered corner to per-pixel rays."""
        ans = self.raycaster.cast(torch.cat([origin, nrm], 1).float())
        covered = (ans["t_hit"] < COVER_M).reshape(len(s.xs), len(s.ys))
        if not bool(covered.any()) or bool(covered.all()):
            return vals, covered.reshape(-1)
        grid = vals.reshape(len(s.xs), len(s.ys), -1).clone()
        valid = ~covered
        while True:
            total = torch.zeros_like(grid)
            count = torch.zeros(valid.shape, dtype=grid.dtype)
            for dim, step in ((0, 1), (0, -1), (1, 1), (1, -1)):  # a fixed order: the same sums on every run
                v = torch.roll(valid, step, dim)
                g = torch.roll(grid, step, dim)
                edge = [slice(None), slice(None)]
                edge[dim] = slice(0, 1) if step == 1 else slice(-1, None)  # no wrapping round the grid
                v[tuple(edge)] = False
                total += g * v[..., None]
                count += v
            fill = ~valid & (count > 0)
            if not bool(fill.any()):
                break
            grid[fill] = total[fill] / count[fill][:, None]
            valid = valid | fill
        return grid.reshape(len(vals), -1), covered.reshape(-1)

    def lookup(self, gb: GBuffer, pixels: torch.Tensor, sky: torch.Tensor,
               ground: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The sky view and ground view by material at the hit pixels ``pixels`` (flat indices into all cameras'
        pixels of ``gb``, a G-buffer with ``face`` and ``uv``), written into ``sky`` (N,) and ``ground`` (N, M),
        float32 over all N pixels (the others are left as they are). Returns the pixels of ``pixels`` it left
        out, for per-pixel rays: those on a mesh too large for the field (``MAX_MESH_SAMPLES``), and those on a
        plane in a grid cell with a corner covered or next to a covered sample (the rim of a patch lying on it,
        the ground round a foot: cast with the field's ``rays``)."""
        if gb.face is None or gb.uv is None:
            raise ValueError("the G-buffer has no face ids and barycentrics (Raycaster.gbuffer records them)")
        mesh = gb.mesh.reshape(-1).cpu().index_select(0, pixels)
        left, rim = [], []
        for k, s in enumerate(self.shapes):
            rows = (mesh == k).nonzero().flatten()
            if not rows.numel():
                continue
            if s is None:
                left.append(pixels.index_select(0, rows))
                continue
            px = pixels.index_select(0, rows)
            g = gb.geometric_normal.reshape(-1, 3).cpu().float().index_select(0, px).t()  # (3, P)
            face = gb.face.reshape(-1).cpu().index_select(0, px) - self.face_offset[k]
            uv = gb.uv.reshape(-1, 2).cpu().float().index_select(0, px).t()
            if isinstance(s, _Plane):  # one normal: the side the viewer is on
                n = s.normal.tolist()
                side = g[0] * n[0] + g[1] * n[1] + g[2] * n[2] >= 0
            else:
                fn = s.face_normals32.index_select(0, face).t()
                side = g[0] * fn[0] + g[1] * fn[1] + g[2] * fn[2] >= 0
            n_front = int(side.sum())
            for sd in (1, -1):
                if n_front == (len(side) if sd == -1 else 0):
                    continue
                vals = self._values(k, sd)
                every = n_front == (len(side) if sd == 1 else 0)
                sel = None if every else (side if sd == 1 else ~side).nonzero().flatten()

                def pick(x: torch.Tensor, sel: torch.Tensor | None = sel) -> torch.Tensor:
                    return x if sel is None else x.index_select(-1, sel)

                at = pick(px)
                idx, w = s.weights(pick(face), pick(uv[0]).contiguous(), pick(uv[1]).contiguous())
                cov = self.covered.get((k, sd))
                if cov is not None and bool(cov.any()):  # cells at a cover's rim: per-pixel rays
                    near = cov.index_select(0, idx.reshape(-1)).reshape(idx.shape).any(0)
                    rim.append(at[near])
                    keep = (~near).nonzero().flatten()
                    at, idx, w = at.index_select(0, keep), idx.index_select(1, keep), w.index_select(1, keep)
                # v0 + sum of w_j (v_j - v0), term by term: a view shared by all corners (the open sky's 1) comes
                # back exactly, and the same bits at any thread count
                v0 = vals.index_select(0, idx[0])
                acc = v0.clone()
                for j in range(1, idx.shape[0]):
                    acc += (vals.index_select(0, idx[j]) - v0) * w[j, :, None]
                sky.index_copy_(0, at, acc[:, 0])
                ground.index_copy_(0, at, acc[:, 1:])
        return (torch.cat(left) if left else pixels[:0]), (torch.cat(rim).sort().values if rim else pixels[:0])


def pattern_angle(direction: torch.Tensor) -> torch.Tensor:
    """A fixed angle in [0, 2π) per camera ray direction (P, 3), float64: a hash of the direction's components
    (the same ray gives the same angle in a frame and in any subset of its pixels)."""
    h = direction[:, 0] * 12.9898e3 + direction[:, 1] * 78.233e3 + direction[:, 2] * 37.719e3
    return torch.frac(torch.frac(h) * 43758.5453) * (2 * np.pi)


def tangent_frame(normal: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Two unit vectors (P, 3) orthogonal to the unit normals ``normal`` (P, 3) and to each other (t, b, n
    right-handed), written out component by component."""
    nx, ny, nz = normal.unbind(-1)
    use_x = nz.abs() > 0.9  # helper axis: +z, or +x for normals near the z axis
    ax = torch.where(use_x, torch.ones_like(nx), torch.zeros_like(nx))
    az = 1 - ax
    # t = normalize(helper x n), b = n x t
    tx, ty, tz = -az * ny, az * nx - ax * nz, ax * ny
    inv = 1 / torch.sqrt(tx * tx + ty * ty + tz * tz)
    tx, ty, tz = tx * inv, ty * inv, tz * inv
    bx, by, bz = ny * tz - nz * ty, nz * tx - nx * tz, nx * ty - ny * tx
    return torch.stack([tx, ty, tz], -1), torch.stack([bx, by, bz], -1)


__all__ = ["BACKDROP_M", "EDGE_MAX_M", "FIELD_RAYS", "PLANE_GROWTH", "PLANE_MARGIN_M", "PLANE_SPACING_M",
           "VisibilityField", "pattern_angle", "tangent_frame"]

"""The scene as plain data: materials, meshes, cameras, suns and the bands, with a JSON round trip.

Nothing here computes light or geometry, so this module imports neither torch nor the skin model: a scene can
be written, read and checked anywhere. The renderer's stages turn it into pictures: ``meshes`` builds the
triangles of each ``MeshSpec``, ``raycast`` casts the cameras' rays, ``materials`` compiles each ``Material``
through its kind's registry entry, ``light`` gives each ``Sun``'s spectrum.

World frame: metres, z up; subjects stand on z = 0 facing +x. Directions are given by zenith (from +z) and
azimuth (from +x towards +y) in degrees; a camera or sun at azimuth 0 is in front of the subject.

>>> s = default_scene(subject="file", mesh_path="body.obj")
>>> Scene.from_json(s.to_json()) == s
True
>>> [m.name for m in s.meshes]
['subject', 'panel_white', 'panel_dark', 'ground']
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..bands import INDEX_BANDS_NM, Band, as_bands, at_wavelengths, check_ascending
from ..io import write_text


def default_bands() -> list[list[float]]:
    """The thesis's four detection bands (``bands.INDEX_BANDS_NM``, monochromatic) as [centre, fwhm] pairs, nm."""
    return [[c, 0.0] for c in INDEX_BANDS_NM]


def check_finite(what: str, **values: Any) -> None:
    """``ValueError`` naming the first value that is not a finite number."""
    for k, v in values.items():
        try:
            ok = math.isfinite(float(v))
        except (TypeError, ValueError):
            ok = False
        if not ok:
            raise ValueError(f"{what} {k} must be a finite number, got {v!r}")


# ------------------------------------------------------------------------------------------------ materials
@dataclass
class Material:
    """A surface material, described by its ``kind`` (an entry of ``render.materials.KINDS``) and parameters.

    Built-in kinds (``render.materials`` checks the parameters when the scene is compiled):

    - ``kind="lambertian"``: ``reflectance`` is one value, one per band, or a spectrum given at wavelengths
      (``bands.at_wavelengths``: ``{"wavelengths_nm": [...], "values": [...]}``, interpolated linearly in
      wavelength at each band, as the default scene's clothing and ground are given at ``INDEX_BANDS_NM``);
    - ``kind="spectralon"``: the Table 3 DHR of ``panel`` ("white" or "dark"), Lambertian, or with
      ``brdf=True`` the Spectralon-like BRDF of ``optics.spectralon_brdf_cos`` (a weak forward lobe growing
      with incidence, Appendix B);
    - ``kind="skin"``: the combined skin BRDF (eq 3.1.1) with skin parameters ``skin`` (a preset name or a
      dict of ``tissue`` parameters; default "I-II") and the section 3.3.3 microfacet parameters per band
      (``specular`` False gives the diffuse-only model). ``surface`` is the skin surface model of eq 3.1.1's
      diffuse term (``optics.skin_diffuse``): "thesis" (default; ρ_d is the total diffuse-model reflectance,
      front surface included, as the thesis defines it and as its measured images support) or "conserving"
      (the subsurface part only: energy-conserving).
    - ``kind="rtlsr"``: the MODIS kernel-driven Ross-Thick / Li-Sparse-Reciprocal BRDF (``render.rtlsr``) with
      ``reflectance`` its white-sky albedo (as a lambertian reflectance, at most ``rtlsr.RHO_MAX``) and the shape
      of Roy et al. (2016)'s global Landsat kernel weights; ``params`` may name the table, ``{"kernels":
      "roy2016"}`` (the default and only one).

    ``params`` holds the parameters of kinds registered by users (``render.materials.register``).
    """

    kind: str = "lambertian"
    reflectance: float | list[float] | dict[str, list[float]] | None = None
    panel: str | None = None
    skin: str | dict | None = None
    specular: bool = True
    brdf: bool = False
    surface: str = "thesis"
    params: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not isinstance(self.kind, str) or not self.kind:
            raise ValueError(f"material kind must be a non-empty string, got {self.kind!r}")
        if self.kind == "skin" and self.skin is None:
            self.skin = "I-II"

    def to_dict(self) -> dict:
        """The material as JSON-ready data (``params`` only when set)."""
        d = dataclasses.asdict(self)
        if not d["params"]:
            del d["params"]
        return d


# ------------------------------------------------------------------------------------------------- geometry
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

    def __post_init__(self) -> None:
        if self.kind not in ("anny", "file", "plane", "cylinder", "sphere", "ground"):
            raise ValueError(f"mesh kind must be anny, file, plane, cylinder, sphere or ground, got {self.kind!r}")
        if len(self.position) != 3:
            raise ValueError(f"mesh {self.name!r}: position needs 3 coordinates")
        if self.kind == "anny" and self.other_material is None:
            raise ValueError(f"anny mesh {self.name!r} needs other_material for its non-skin regions")


# ------------------------------------------------------------------------------------------ camera and sun
def direction(zenith_deg: float, azimuth_deg: float) -> np.ndarray:
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

    def __post_init__(self) -> None:
        check_finite("camera", width=self.width, height=self.height, zenith_deg=self.zenith_deg,
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
        assert self.fov_deg is not None  # __post_init__ guarantees a field of view without focal_px
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


SUN_SOLID_ANGLE_SR = 6.794e-5  # the solar disc seen from Earth

#: the ranges ``Atmosphere`` accepts (what SPECTRL2 was built for, Bird & Riordan 1986; wider values are refused)
ATMOSPHERE_RANGES = {"aerosol_500nm": (0.0, 2.0), "precipitable_water_cm": (0.0, 10.0),
                     "ozone_atm_cm": (0.0, 1.0), "pressure_pa": (30000.0, 110000.0), "day_of_year": (1, 366),
                     "angstrom_alpha": (0.0, 3.0), "ground_albedo": (0.0, 1.0)}


@dataclass
class Atmosphere:
    """A clear-sky atmosphere, the inputs of the SPECTRL2 light model (``render.light``; Bird & Riordan 1986):
    aerosol optical depth at 500 nm, precipitable water (cm), ozone (atm-cm), surface pressure (Pa), day of year
    (the Earth-Sun distance), the Angström exponent of the aerosol, and the regional ground albedo of SPECTRL2's
    multiple reflection between ground and sky (it brightens the diffuse sky; the light a scene's own ground
    reflects into a pixel comes from that ground's material). The defaults are a reference clear sky (aerosol
    0.1, water 1.42 cm, ozone 0.344 atm-cm, sea level, midsummer, rural aerosol, albedo 0.2)."""

    aerosol_500nm: float = 0.1
    precipitable_water_cm: float = 1.42
    ozone_atm_cm: float = 0.344
    pressure_pa: float = 101325.0
    day_of_year: int = 172
    angstrom_alpha: float = 1.14
    ground_albedo: float = 0.2

    def __post_init__(self) -> None:
        check_finite("atmosphere", **dataclasses.asdict(self))
        for k, (lo, hi) in ATMOSPHERE_RANGES.items():
            v = getattr(self, k)
            if not (lo <= v <= hi):
                raise ValueError(f"atmosphere {k} must lie in [{lo:g}, {hi:g}], got {v}")
        if int(self.day_of_year) != self.day_of_year:
            raise ValueError(f"atmosphere day_of_year must be a whole day, got {self.day_of_year}")


@dataclass
class Sun:
    """A directional source at (zenith, azimuth) and what lights the scene with it, read by the scene's light
    model (``Scene.illumination``, ``render.light``):

    - "spectrl2" (the outdoor default): the clear-sky direct and diffuse spectra of ``atmosphere`` for this sun;
    - "thesis": a ``temperature_k`` blackbody (thesis Fig 1) scaled to the solar disc's solid angle
      (top-of-atmosphere irradiance) times ``scale``, plus a uniform grey sky whose irradiance on an open
      horizontal surface is ``sky_fraction`` times the sun's normal irradiance.
    """

    zenith_deg: float = 30.0
    azimuth_deg: float = 0.0
    temperature_k: float = 5950.0
    scale: float = 1.0
    sky_fraction: float = 0.0
    atmosphere: Atmosphere = field(default_factory=Atmosphere)

    def __post_init__(self) -> None:
        check_finite("sun", zenith_deg=self.zenith_deg, azimuth_deg=self.azimuth_deg, temperature_k=self.temperature_k,
                scale=self.scale, sky_fraction=self.sky_fraction)
        if not (0.0 <= self.zenith_deg <= 180.0):
            raise ValueError(f"source zenith must lie in [0, 180] degrees, got {self.zenith_deg}")
        if not self.temperature_k > 0 or not self.scale > 0:
            raise ValueError("sun temperature_k and scale must be > 0")
        if not (0.0 <= self.sky_fraction <= 1.0):
            raise ValueError(f"sky_fraction must lie in [0, 1], got {self.sky_fraction}")
        if isinstance(self.atmosphere, dict):
            self.atmosphere = Atmosphere(**self.atmosphere)
        if not isinstance(self.atmosphere, Atmosphere):
            raise ValueError(f"sun atmosphere must be an Atmosphere, got {type(self.atmosphere).__name__}")

    @property
    def direction(self) -> np.ndarray:
        return direction(self.zenith_deg, self.azimuth_deg)


# ---------------------------------------------------------------------------------------------------- scene
BACKGROUNDS = ("void", "sky")
#: the light model of a scene that names none: the clear-sky outdoor model (``render.light``)
DEFAULT_ILLUMINATION = "spectrl2"


@dataclass
class Scene:
    """Materials (by name), meshes, cameras and suns; ``bands`` as (centre, fwhm) pairs in nm.

    ``panels`` names the two reference-panel meshes used for ELM (bright first). ``background``: what a camera
    ray that hits nothing sees: "void" (no radiance, the default) or "sky" (above the horizon, the isotropic
    sky of each sun, radiance E_sky / π; below it still void). ``illumination``: the light model that turns the
    suns into direct, sky and ground-reflected irradiance (``render.light``: "spectrl2", the default, or
    "thesis").
    """

    materials: dict[str, Material]
    meshes: list[MeshSpec]
    cameras: list[Camera]
    suns: list[Sun]
    bands: list = field(default_factory=default_bands)  # [centre, fwhm] pairs, or Band.to_dict (response curves)
    panels: list[str] = field(default_factory=lambda: ["panel_white", "panel_dark"])
    background: str = "void"
    illumination: str = DEFAULT_ILLUMINATION

    def __post_init__(self) -> None:
        if not isinstance(self.illumination, str) or not self.illumination:
            raise ValueError(f"illumination must name a light model, got {self.illumination!r}")
        if self.background not in BACKGROUNDS:
            raise ValueError(f"background must be one of {BACKGROUNDS}, got {self.background!r}")
        names = [m.name for m in self.meshes]
        if len(set(names)) != len(names):
            raise ValueError(f"mesh names must be unique, got {names}")
        for m in self.meshes:
            for mat in (m.material, m.other_material):
                if mat is not None and mat not in self.materials:
                    raise ValueError(f"mesh {m.name!r} uses unknown material {mat!r}")
        if len(self.panels) not in (0, 2):
            raise ValueError(f"panels must name two reference panels (bright first) or none, got {self.panels}")
        for p in self.panels:
            if p not in names:
                raise ValueError(f"reference panel {p!r} is not a mesh of the scene")
            if self.materials[self.mesh(p).material].kind == "skin":
                raise ValueError(f"reference panel {p!r} must be lambertian or spectralon")
        if not self.cameras or not self.suns:
            raise ValueError("a scene needs at least one camera and one sun")
        check_ascending(self.band_list, "scene bands")

    @property
    def band_list(self) -> tuple[Band, ...]:
        return as_bands(self.bands)

    def mesh(self, name: str) -> MeshSpec:
        for m in self.meshes:
            if m.name == name:
                return m
        raise ValueError(f"no mesh named {name!r}")

    def to_dict(self) -> dict:
        """The scene as JSON-ready data (``from_dict`` reads it back)."""
        d = dataclasses.asdict(self)
        d["materials"] = {k: m.to_dict() for k, m in self.materials.items()}
        return d

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
            bands=[dict(b) if isinstance(b, dict) else list(b) for b in d.get("bands", default_bands())],
            panels=list(d.get("panels", ["panel_white", "panel_dark"])),
            background=d.get("background", "void"),
            illumination=d.get("illumination", DEFAULT_ILLUMINATION),
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


def reference_panels(camera_azimuth_deg: float, tilt_deg: float, size_m: float, height_m: float,
                     offset_m: float = 0.9) -> list[MeshSpec]:
    """The two ELM reference panels, "panel_white" (material "white") and "panel_dark" (material "dark"): square
    planes of side ``size_m`` standing either side of the subject across the view of a camera at azimuth
    ``camera_azimuth_deg``, ``offset_m`` off the subject's axis, their lower edge ``height_m`` above the ground,
    facing the camera and tilted by ``tilt_deg`` (``MeshSpec.tilt_deg``: 0 vertical, 90 level).

    >>> [p.position for p in reference_panels(0.0, 90.0, size_m=0.5, height_m=0.8)]
    [[-0.0, 0.9, 0.8], [0.0, -0.9, 0.8]]
    """
    az = math.radians(camera_azimuth_deg)
    side = (-math.sin(az), math.cos(az))
    return [MeshSpec(name, "plane", mat, params={"width": size_m, "height": size_m},
                     position=[sign * offset_m * side[0], sign * offset_m * side[1], height_m],
                     yaw_deg=camera_azimuth_deg, tilt_deg=tilt_deg)
            for name, mat, sign in (("panel_white", "white", 1.0), ("panel_dark", "dark", -1.0))]


def default_scene(
    subject: str | MeshSpec = "anny",
    mesh_path: str | None = None,
    skin: str | dict = "I-II",
    camera: Camera | None = None,
    sun: Sun | None = None,
    panels: str = "lambertian",
    diffuse_only: bool = False,
    ground: bool = True,
    surface: str = "thesis",
    illumination: str = DEFAULT_ILLUMINATION,
) -> Scene:
    """The thesis's layout: a subject at the origin facing +x, reference panels either side of it facing the
    camera (vertical for the default horizontal camera in front at 31 ft, 9.449 m; level for a camera overhead;
    turned with the camera's azimuth), 0.9 m off the subject's axis. ``panels``: see ``panel_materials``;
    ``surface``: the skin surface model (``Material``). ``subject``: "anny" (a parametric body), "file" (the
    OBJ/PLY ``mesh_path``, all skin) or any ``MeshSpec`` of materials "skin" / "clothing" (e.g. a sphere). Metres,
    z up."""
    mats = {
        "skin": Material("skin", skin=skin, specular=not diffuse_only, surface=surface),
        # four-value spectra at the INDEX_BANDS_NM: interpolated in wavelength for any --bands (bands.per_band)
        "clothing": Material("lambertian", reflectance=at_wavelengths([0.12, 0.10, 0.35, 0.30])),
        "ground": Material("lambertian", reflectance=at_wavelengths([0.15, 0.18, 0.30, 0.25])),
    }
    mats.update(panel_materials(panels))
    if isinstance(subject, MeshSpec):
        body = subject
    elif subject == "anny":
        body = MeshSpec("subject", "anny", "skin", other_material="clothing")
    elif subject == "file":
        if not mesh_path:
            raise ValueError("a file subject needs mesh_path")
        body = MeshSpec("subject", "file", "skin", params={"path": str(mesh_path)})
    else:
        raise ValueError(f"subject must be 'anny', 'file' or a MeshSpec, got {subject!r}")
    cam = camera or Camera()
    # the panels face the camera wherever it is: vertical for a horizontal camera (the thesis's layout), level for
    # one overhead, tilted towards it in between
    tilt = float(np.clip(90.0 - cam.zenith_deg, 0.0, 90.0))
    meshes = [body, *reference_panels(cam.azimuth_deg, tilt, size_m=0.6, height_m=0.9)]
    if ground:
        meshes.append(MeshSpec("ground", "ground", "ground", params={"size": 4000.0}))
    return Scene(mats, meshes, [cam], [sun or Sun()], illumination=illumination)

"""Stage 3 of the renderer: materials -> per-band tables and BRDFs, through a registry of material kinds.

Each ``Material`` of a scene resolves (``kind_name``) to an entry of ``KINDS``, a ``MaterialKind``:

- ``compile(material, spectral, skins)`` -> ``Compiled``: the material's hemispherical reflectance per band
  (``albedo``, (n, B): the sky term, the ELM reference of a panel, and the whole sunlit term of a Lambertian
  kind) and the per-band parameters of its BRDF (``params``, each (n, X));
- ``brdf(cos_i, cos_r, cos_2β, params)`` -> sr^-1, or ``None`` for a Lambertian kind (f = albedo / π);
- ``check(material)``: ``ValueError`` naming what is wrong, before anything is computed.

A new kind is one ``register("name", MaterialKind(...))`` call (as Mitsuba registers BSDF plugins); the skin
surface models are entries ("skin-thesis", "skin-conserving", "skin-diffuse"), and so are the panels
("lambertian", "spectralon", "spectralon-brdf") and the MODIS kernel-driven BRDF ("rtlsr", ``render.rtlsr``).

>>> import torch
>>> from torchskin.render.scene import Material
>>> register("grey-ramp", MaterialKind(
...     compile=lambda m, sp, skins: Compiled(albedo=(sp.wavelengths / 2000.0)[None])))
>>> tables = compile_materials({"m": Material("grey-ramp")}, [[500.0, 0.0], [1000.0, 0.0]], [Sun()])
>>> tables.albedo.tolist()
[[0.25, 0.5]]
>>> unregister("grey-ramp")
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from typing import cast

import torch

from .. import data, tissue
from ..bands import Band, PerBand, as_bands, band_sampling, per_band, setting_values, spectrum_at
from ..optics import SURFACE_MODELS, THESIS_SPECULAR, skin_brdf_cos, spectralon_brdf_cos, surface_front
from .light import check_light
from .rtlsr import DEFAULT_KERNELS, check_rtlsr, kernel_weights, rtlsr_brdf_cos
from .scene import Material, Sun

#: Spectralon reference panels, directional-hemispherical reflectance per band (thesis Table 3)
SPECTRALON_DHR = {
    "white": {544.0: 0.989, 633.0: 0.990, 1080.0: 0.992, 1580.0: 0.988},
    "dark": {544.0: 0.075, 633.0: 0.079, 1080.0: 0.104, 1580.0: 0.133},
}
#: the most a band centre may lie from a Table 3 wavelength for the Spectralon DHR to apply, nm
SPECTRALON_MATCH_NM = 30.0
#: the front-surface reflectance at normal incidence of the skin's albedo (sky term, diffuse-only skin)
SKIN_R0 = 0.04


@dataclass(frozen=True)
class Spectral:
    """What a material kind needs to compile its per-band tables (float64, CPU).

    Shape:
        ``grid`` (G,) nm; ``weights`` (G, B) band responses; ``sun_weights`` (G, B) band responses under the
        first sun's direct spectrum (the scene's light model), each column summing to 1; ``wavelengths`` (B,)
        band centres, nm.
    """

    bands: tuple[Band, ...]
    grid: torch.Tensor
    weights: torch.Tensor
    sun_weights: torch.Tensor
    wavelengths: torch.Tensor


@dataclass
class Compiled:
    """A material's tables: ``albedo`` (n, B) and the BRDF's ``params`` (each (n, X)); n = 1, or the batch of
    skins for the material named "skin" when ``compile_materials`` gets ``skins``."""

    albedo: torch.Tensor
    params: dict[str, torch.Tensor] = field(default_factory=dict)


BRDF = Callable[[torch.Tensor, torch.Tensor, torch.Tensor, dict[str, torch.Tensor]], torch.Tensor]


@dataclass(frozen=True)
class MaterialKind:
    """A registry entry: how one kind of material is compiled and shaded (module docstring)."""

    compile: Callable[[Material, Spectral, tissue.SkinParams | None], Compiled]
    brdf: BRDF | None = None
    check: Callable[[Material], None] | None = None


KINDS: dict[str, MaterialKind] = {}
_registry_version = [0]  # bumped by every register / unregister: compiled tables are keyed on it


def registry_version() -> int:
    """The version of ``KINDS``: every ``register`` or ``unregister`` increments it (``MaterialCache`` keys on
    it, so a replaced kind is never served the old kind's tables)."""
    return _registry_version[0]


def register(name: str, kind: MaterialKind) -> None:
    """Add (or replace) the material kind ``name``: a ``Material(kind=name)`` then renders with it."""
    if not isinstance(kind, MaterialKind):
        raise TypeError(f"register needs a MaterialKind, got {type(kind).__name__}")
    KINDS[name] = kind
    _registry_version[0] += 1


def unregister(name: str) -> None:
    """Remove the material kind ``name`` (``ValueError`` if it is not registered)."""
    if name not in KINDS:
        raise ValueError(f"no material kind {name!r} is registered")
    del KINDS[name]
    _registry_version[0] += 1


def kind_name(material: Material) -> str:
    """The registry entry of ``material``: its ``kind``, except "spectralon" with ``brdf`` ("spectralon-brdf")
    and "skin" ("skin-<surface>", or "skin-diffuse" without the specular lobe)."""
    if material.brdf and material.kind != "spectralon":
        raise ValueError("brdf=True is for spectralon materials")
    if material.kind == "spectralon" and material.brdf:
        return "spectralon-brdf"
    if material.kind == "skin":
        return "skin-diffuse" if not material.specular else f"skin-{material.surface}"
    return material.kind


#: registry entries that ``Material`` fields select (``kind_name``), never written as a material's ``kind``
VARIANTS = {"spectralon-brdf": "kind='spectralon', brdf=True", "skin-thesis": "kind='skin', surface='thesis'",
            "skin-conserving": "kind='skin', surface='conserving'", "skin-diffuse": "kind='skin', specular=False"}


def check_material(material: Material, bands: Sequence[Band] | None = None) -> MaterialKind:
    """The registry entry of ``material`` after its own ``check`` (and, with ``bands``, its per-band values);
    ``ValueError`` naming what is wrong."""
    if material.kind in VARIANTS:
        raise ValueError(f"material kind {material.kind!r} is chosen by the material's fields: use "
                         f"{VARIANTS[material.kind]}")
    if material.kind == "skin" and material.surface not in SURFACE_MODELS:
        raise ValueError(f"surface must be one of {', '.join(SURFACE_MODELS)} (skin surface model), "
                         f"got {material.surface!r}")
    name = kind_name(material)
    if name not in KINDS:
        known = sorted({k for k in KINDS if k not in VARIANTS} | {"skin"})
        raise ValueError(f"material kind must be one of {', '.join(known)}, got {material.kind!r}")
    entry = KINDS[name]
    try:
        if entry.check is not None:
            entry.check(material)
        if bands is not None and name == "lambertian":
            per_band(cast(PerBand, material.reflectance), bands, "a lambertian reflectance")
    except TypeError as e:
        raise ValueError(f"malformed {material.kind} material: {e}") from None
    return entry


def check_materials(materials: dict[str, Material], bands: Sequence[Band] | None = None) -> None:
    """``check_material`` of every material (names the first bad one): cheap, so renderers call it before any
    geometry is built."""
    for name, material in materials.items():
        try:
            check_material(material, bands)
        except ValueError as e:
            raise ValueError(f"material {name!r}: {e}") from None


# ------------------------------------------------------------------------------------------ built-in kinds
def _check_lambertian(m: Material) -> None:
    if m.reflectance is None:
        raise ValueError("a lambertian material needs reflectance (one value, one per band or a spectrum at "
                         "wavelengths)")
    for v in setting_values(m.reflectance, "reflectance"):
        if not (0.0 <= float(v) <= 1.0):
            raise ValueError(f"reflectance must lie in [0, 1], got {v}")


def band_reflectance(values: PerBand, sp: Spectral, what: str) -> torch.Tensor:
    """A material's reflectance per band (B,) float64. A spectrum given at wavelengths (``at_wavelengths``) is
    averaged over each band's response under the first sun's direct spectrum (``Spectral.sun_weights``), as skin's
    is: a 40 nm filter sees the spectrum's mean over its band, not its value at the centre. A monochromatic band
    reads the spectrum at its centre; a number or one value per band is taken as it is (``bands.per_band``)."""
    on_grid = spectrum_at(values, sp.grid.tolist(), what)
    if on_grid is None:
        return torch.tensor(per_band(values, sp.bands, what), dtype=torch.float64)
    return torch.tensor(on_grid, dtype=torch.float64) @ sp.sun_weights


def _lambertian(m: Material, sp: Spectral, skins: tissue.SkinParams | None) -> Compiled:
    r = band_reflectance(cast(PerBand, m.reflectance), sp, "a lambertian reflectance")  # checked: not None
    return Compiled(albedo=r[None])


def _check_spectralon(m: Material) -> None:
    if m.panel not in SPECTRALON_DHR:
        raise ValueError(f"spectralon panel must be 'white' or 'dark', got {m.panel!r}")


def spectralon_dhr(panel: str, bands: Sequence[Band]) -> list[float]:
    """Table 3 DHR of the Spectralon ``panel`` ("white", "dark") at each band (the nearest tabulated wavelength,
    at most ``SPECTRALON_MATCH_NM`` away)."""
    table = SPECTRALON_DHR[panel]
    out = []
    for b in bands:
        near = min(table, key=lambda c: abs(c - b.center_nm))
        if abs(near - b.center_nm) > SPECTRALON_MATCH_NM:
            raise ValueError(f"no Spectralon value near {b.center_nm:g} nm (Table 3 has {list(table)})")
        out.append(table[near])
    return out


def _spectralon(m: Material, sp: Spectral, skins: tissue.SkinParams | None) -> Compiled:
    r = torch.tensor(spectralon_dhr(str(m.panel), sp.bands), dtype=torch.float64)[None]
    return Compiled(albedo=r, params={"dhr": r, "wavelength": sp.wavelengths[None]})


def _spectralon_brdf(ci: torch.Tensor, cr: torch.Tensor, c2b: torch.Tensor, p: dict[str, torch.Tensor]) -> torch.Tensor:
    return spectralon_brdf_cos(ci, cr, c2b, p["dhr"], p["wavelength"])


def _check_skin(m: Material) -> None:
    skin_params(m)


def skin_params(material: Material, dtype: torch.dtype = torch.float64) -> tissue.SkinParams:
    """The ``tissue.SkinParams`` of a skin material (a preset name or a parameter dict)."""
    if isinstance(material.skin, str):
        return tissue.preset(material.skin, dtype=dtype)
    if not isinstance(material.skin, dict):
        raise ValueError(f"skin must be a preset name or a dict of tissue parameters, got {material.skin!r}")
    return tissue.SkinParams.create(dtype=dtype, **dict(material.skin))


def skin_batch(skins: tissue.SkinParams | Sequence[str | dict]) -> tissue.SkinParams:
    """A 1-D batch of skins from a ``SkinParams`` batch or a list of presets / parameter dicts."""
    if isinstance(skins, (str, dict)):
        raise ValueError(f"skins must be a SkinParams batch or a list of presets / parameter dicts, got {skins!r}")
    if isinstance(skins, tissue.SkinParams):
        return tissue.SkinParams.cat([skins])  # 0-D -> one skin; N-D -> flat
    if not skins:
        raise ValueError("skins needs at least one skin")
    return tissue.SkinParams.cat([skin_params(Material("skin", skin=s)) for s in skins])


def _skin(m: Material, sp: Spectral, skins: tissue.SkinParams | None) -> Compiled:
    """R_sub per band (under the first sun's spectrum) of one skin or a batch, once: the albedo (front surface
    R0 = ``SKIN_R0`` over it) and the BRDF's parameters derive from it."""
    p = (skins if skins is not None else skin_params(m)).to(device="cpu", dtype=torch.float64)  # tables: CPU float64
    r_sub_grid = tissue.subsurface_reflectance(p, sp.grid).reshape(-1, len(sp.grid))
    r_sub = r_sub_grid @ sp.sun_weights  # (n, B)
    albedo = tissue.surface_total(torch.tensor(SKIN_R0, dtype=torch.float64), r_sub_grid) @ sp.sun_weights
    if not m.specular:  # the diffuse-only model: a Lambertian surface with the normal-incidence skin reflectance
        return Compiled(albedo=albedo)
    sigma2, rho0 = THESIS_SPECULAR.at(sp.wavelengths)
    front = torch.tensor([[surface_front(m.surface)]], dtype=torch.float64)
    return Compiled(albedo=albedo, params={"r_sub": r_sub, "sigma2": sigma2[None], "rho0": rho0[None],
                                           "front": front})


def _skin_brdf(ci: torch.Tensor, cr: torch.Tensor, c2b: torch.Tensor, p: dict[str, torch.Tensor]) -> torch.Tensor:
    """Eq 3.1.1 with ρ_d from the exact closed form in R0 = Schlick(ρ0, θi), per the material's skin surface
    model (``optics.skin_brdf_cos``)."""
    return skin_brdf_cos(ci, cr, c2b, p["r_sub"], p["sigma2"], p["rho0"], p["front"])


def _check_rtlsr(m: Material) -> None:
    if m.reflectance is None:
        raise ValueError("an rtlsr material needs reflectance (its white-sky albedo: one value, one per band or a "
                         "spectrum at wavelengths)")
    _check_lambertian(m)
    check_rtlsr(setting_values(cast(PerBand, m.reflectance)), m.params)


def _rtlsr(m: Material, sp: Spectral, skins: tissue.SkinParams | None) -> Compiled:
    """The white-sky albedo per band is the albedo; the Roy et al. (2016) kernel weights scaled to it
    (``rtlsr.kernel_weights``) are the BRDF's parameters."""
    rho = band_reflectance(cast(PerBand, m.reflectance), sp, "an rtlsr reflectance")
    f_iso, f_vol, f_geo = kernel_weights(rho, sp.wavelengths, m.params.get("kernels", DEFAULT_KERNELS))
    return Compiled(albedo=rho[None], params={"f_iso": f_iso[None], "f_vol": f_vol[None], "f_geo": f_geo[None]})


def _rtlsr_brdf(ci: torch.Tensor, cr: torch.Tensor, c2b: torch.Tensor, p: dict[str, torch.Tensor]) -> torch.Tensor:
    return rtlsr_brdf_cos(ci, cr, c2b, p["f_iso"], p["f_vol"], p["f_geo"])


register("lambertian", MaterialKind(_lambertian, None, _check_lambertian))
register("spectralon", MaterialKind(_spectralon, None, _check_spectralon))
register("spectralon-brdf", MaterialKind(_spectralon, _spectralon_brdf, _check_spectralon))
for _surface in SURFACE_MODELS:
    register(f"skin-{_surface}", MaterialKind(_skin, _skin_brdf, _check_skin))
register("skin-diffuse", MaterialKind(_skin, None, _check_skin))
register("rtlsr", MaterialKind(_rtlsr, _rtlsr_brdf, _check_rtlsr))


# ---------------------------------------------------------------------------------------------- compilation
@dataclass
class BrdfGroup:
    """The materials shaded by one BRDF: ``ids`` (host tuple), ``member`` (M,) bool, ``params`` each
    ([N,] M, X) with zero rows for the other materials, or (X,) when shared by every member (``group_param``)."""

    brdf: BRDF
    ids: tuple[int, ...]
    member: torch.Tensor
    params: dict[str, torch.Tensor]


@dataclass
class MaterialTables:
    """Per-material, per-band quantities gathered by material id (M materials, B bands, S suns; N = K·S
    skin-major rows for a batch of K skins, else the leading axis is absent).

    Shape:
        ``lambert_f`` ([N,] M, B): albedo/π of Lambertian kinds, 0 for BRDF kinds; ``albedo`` ([N,] M, B);
        ``reference`` (M, B): hemispherical reflectance (ELM references, the ground light's reflectance);
        ``wavelengths`` (B,) nm; ``is_skin`` (M,) bool. (The light is not a material matter: ``light.LightTables``.)
    """

    names: list[str]
    lambert_f: torch.Tensor
    albedo: torch.Tensor
    reference: torch.Tensor
    wavelengths: torch.Tensor
    is_skin: torch.Tensor
    groups: dict[str, BrdfGroup]


def group_param(rows: list[torch.Tensor | None], table: Callable[[list[torch.Tensor]], torch.Tensor]) -> torch.Tensor:
    """One BRDF parameter of a group from its members' rows (n, X) (``None``: not a member): the table ([N,] M, X)
    with zero rows for the other materials, or, when every member and batch row holds the same values, that one
    row (X,), shared by every pixel without a gather (``shade.gather_params``)."""
    members = [r for r in rows if r is not None]
    first = members[0][:1]
    if all(bool((r == first).all()) for r in members):
        return first[0]
    return table([r if r is not None else torch.zeros_like(first) for r in rows])


def spectral_context(bands: Sequence[Band], suns: Sequence[Sun], illumination: str = "thesis") -> Spectral:
    """The band sampling of ``bands``, weighted within each band by the first sun's direct spectrum under the
    light model ``illumination`` (a band where it is 0 keeps its plain response), float64."""
    grid, W = band_sampling(bands, dtype=torch.float64)
    E = check_light(illumination, suns[:1]).spectra(suns[:1], grid).direct_normal[0]  # (G,)
    wE = W * E[:, None]  # band responses under the first sun's spectrum
    total = wE.sum(0)
    wE = torch.where(total > 0, wE / total.clamp_min(1e-300), W)
    wl = torch.tensor([b.center_nm for b in bands], dtype=torch.float64)
    return Spectral(tuple(bands), grid, W, wE, wl)


def compile_materials(materials: dict[str, Material], bands: Sequence[Sequence[float]] | Sequence[Band],
                      suns: Sequence[Sun], names: Sequence[str] | None = None, dtype: torch.dtype = torch.float32,
                      device: torch.device | str = "cpu", skins: tissue.SkinParams | None = None,
                      illumination: str = "thesis") -> MaterialTables:
    """Compile the materials ``names`` (default: all, in order) for ``bands`` under ``suns``.

    Args:
        materials: name -> ``Material``.
        bands: ``Band`` objects or (centre, fwhm) pairs, nm.
        suns: the sources (the first sun's direct spectrum under the light model ``illumination`` weights each
            band's values within the band; the number of suns sets the batch layout with ``skins``).
        names: the material order of the tables (a G-buffer's ``material_names``).
        skins: a batch of K skins for the material named "skin": every table row is then repeated per sun,
            skin-major (N = K·S rows), as ``render(..., skins=...)`` shades every skin under every sun.

    Returns:
        ``MaterialTables`` on ``device`` in ``dtype`` (float64 computation, cast once).
    """
    names = list(materials) if names is None else list(names)
    bands = as_bands(bands)
    if skins is not None and ("skin" not in names or materials["skin"].kind != "skin"):
        raise ValueError("skins needs a material named 'skin' of kind 'skin'")
    entries = {n: check_material(materials[n]) for n in names}
    spectral = spectral_context(bands, suns, illumination)
    compiled = {n: entries[n].compile(materials[n], spectral, skins if n == "skin" else None) for n in names}
    K = 1 if skins is None else skins.shape[0]
    S = len(suns)

    def table(rows: list[torch.Tensor]) -> torch.Tensor:  # (n, X) per material -> ([N,] M, X)
        t = torch.stack([r.expand(K, -1) for r in rows], dim=1)  # (K, M, X)
        return t[0] if skins is None else t.repeat_interleave(S, 0)

    def to(x: torch.Tensor) -> torch.Tensor:
        return x.to(device=device, dtype=dtype) if x.is_floating_point() else x.to(device)

    albedo = [compiled[n].albedo for n in names]
    lam = [a / math.pi if entries[n].brdf is None else torch.zeros_like(a) for n, a in zip(names, albedo)]
    groups: dict[str, BrdfGroup] = {}
    for n in names:
        kn, brdf = kind_name(materials[n]), entries[n].brdf
        if brdf is not None and kn not in groups:
            ids = tuple(k for k, m in enumerate(names) if kind_name(materials[m]) == kn)
            params = {key: to(group_param([compiled[m].params[key] if k in ids else None for k, m in enumerate(names)],
                                          table)) for key in compiled[n].params}
            member = torch.tensor([k in ids for k in range(len(names))])
            groups[kn] = BrdfGroup(brdf, ids, member.to(device), params)
    is_skin = torch.tensor([materials[n].kind == "skin" for n in names], device=device)
    return MaterialTables(names, to(table(lam)), to(table(albedo)), to(torch.stack([a[0] for a in albedo])),
                          to(spectral.wavelengths), is_skin, groups)


class MaterialCache:
    """Compiled tables kept by everything they depend on (the materials and their order, bands, the suns'
    spectra, dtype, device, ``data.tables_version()`` and ``registry_version()``, so neither a
    ``data.register_table`` nor a re-registered kind is ever served stale tables). ``render`` uses ``SHARED_CACHE`` unless given one; ``clear()`` frees it. Materials whose ``params``
    are not JSON data are compiled every time."""

    def __init__(self, max_entries: int = 64) -> None:
        self.max_entries = max_entries
        self.entries: dict[tuple, MaterialTables] = {}

    def compile(self, materials: dict[str, Material], bands: Sequence[Sequence[float]], suns: Sequence[Sun],
                names: Sequence[str] | None = None, dtype: torch.dtype = torch.float32,
                device: torch.device | str = "cpu", illumination: str = "thesis") -> MaterialTables:
        """``compile_materials`` through the cache (single skins; batches are compiled directly), keyed on the
        first sun and the light model too (they weight each band)."""
        names = list(materials) if names is None else list(names)
        band_list = as_bands(bands)
        try:
            spec = json.dumps([names, [asdict(materials[n]) for n in names],
                               [b.to_dict() for b in band_list], asdict(suns[0]), len(suns),
                               illumination], sort_keys=True)
        except TypeError:  # parameters that are not JSON data: no reliable key
            return compile_materials(materials, band_list, suns, names, dtype, device, illumination=illumination)
        key = (spec, str(dtype), str(torch.device(device)), data.tables_version(), registry_version())
        hit = self.entries.get(key)
        if hit is None:
            if len(self.entries) >= self.max_entries:
                self.entries.clear()
            hit = self.entries[key] = compile_materials(materials, band_list, suns, names, dtype, device,
                                                        illumination=illumination)
        return hit

    def clear(self) -> None:
        """Forget every compiled table."""
        self.entries.clear()


#: the cache ``render`` uses when none is passed (keyed on everything the tables depend on, see ``MaterialCache``)
SHARED_CACHE = MaterialCache()

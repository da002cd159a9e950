"""The light stage: a scene's suns -> per-band irradiance tables, through a registry of light models.

A light model (``LightModel``, registered by name: ``register``) turns the suns of a scene into spectra on a
wavelength grid, which ``light_tables`` averages over each band's response. Shading reads three tables per sun
and band (W m^-2 nm^-1, ``LightTables``):

- ``beam``: the irradiance normal to the sun's direction that reaches a sunlit surface with cos θi and is
  shadowed like the sun: the direct beam, plus, where the model has one, the circumsolar part of the sky
  (Hay & Davies 1980: the anisotropy index A = DNI / DNI_extra of the diffuse irradiance comes from the sun's
  direction, so it enters as A · DHI / cos θz normal to the beam);
- ``sky``: the isotropic sky, (1 - A) · DHI, the irradiance an open horizontal surface receives from it; a pixel
  receives it times its cosine-weighted sky visibility (``raycast.Raycaster.sky_view``);
- ``ground``: the global horizontal irradiance DNI cos θz + DHI reaching the open ground, which the ground (and
  any up-facing surface a pixel sees) reflects into the pixel's view of it: one bounce, the ground lit without
  shadows.

Built-in models:

- ``"spectrl2"`` (the outdoor default): the clear-sky model SPECTRL2 (Bird & Riordan 1986) through
  ``pvlib.spectrum.spectrl2`` (BSD-3), from each sun's zenith and ``scene.Atmosphere`` (aerosol, water, ozone,
  pressure, day of year, Angström exponent, regional albedo), relative air mass by Kasten & Young (1989),
  pvlib's default (``AIRMASS_MODEL``); the circumsolar split per wavelength. Its 122 wavelengths
  (about 10 nm apart in the visible, 15-45 nm in the SWIR) are interpolated linearly to the band grid. Suns must
  be above the horizon (zenith < 90°).
- ``"thesis"``: the thesis's lamp, a ``Sun.temperature_k`` blackbody scaled to the solar disc's solid angle
  (thesis Fig 1, eq 2.1.8) times ``Sun.scale``, the same at every sun height, and a grey sky of ``sky_fraction``
  times it; no circumsolar part, no ground-reflected light and no atmosphere: ``Sun.atmosphere`` is not read, and
  ``render.json`` and the dataset's rows leave it empty (``uses_atmosphere``; ``torchskin experiment`` renders with
  it).

>>> import torch
>>> from torchskin.render.scene import Sun
>>> round(float(sun_irradiance(Sun(), torch.tensor([550.0]))), 3)  # W m^-2 nm^-1 at the top of the atmosphere
2.005
>>> t = light_tables("spectrl2", [Sun(zenith_deg=10.0)], [[544.0, 0.0], [1580.0, 0.0]])
>>> [round(float(x), 3) for x in t.diffuse_horizontal[0] / t.direct_horizontal[0]]  # the sky is blue
[0.159, 0.022]
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np
import torch

from ..bands import Band, as_bands, band_sampling
from .scene import SUN_SOLID_ANGLE_SR, Atmosphere, Sun

H_PLANCK = 6.62607015e-34
C_LIGHT = 2.99792458e8
K_BOLTZMANN = 1.380649e-23
#: the smallest cos θz the circumsolar term is divided by (pvlib's Hay-Davies guard: a sun 89° from the zenith)
MIN_COS_ZENITH = math.cos(math.radians(89.0))


def planck_radiance(wavelength_nm: torch.Tensor | float, temperature_k: float) -> torch.Tensor:
    """Blackbody spectral radiance, W m^-2 sr^-1 nm^-1 (eq 2.1.8), float64.

    Shape:
        ``wavelength_nm`` (...) -> (...).
    """
    wl = torch.as_tensor(wavelength_nm, dtype=torch.float64) * 1e-9
    h, c, k = H_PLANCK, C_LIGHT, K_BOLTZMANN
    return 2 * h * c**2 / wl**5 / torch.expm1(h * c / (wl * k * temperature_k)) * 1e-9


def sun_irradiance(sun: Sun, wavelength_nm: torch.Tensor | float) -> torch.Tensor:
    """Spectral irradiance of ``sun`` normal to the beam under the thesis's lamp, W m^-2 nm^-1: its blackbody
    radiance times the solar disc's solid angle times ``sun.scale``."""
    return sun.scale * SUN_SOLID_ANGLE_SR * planck_radiance(wavelength_nm, sun.temperature_k)


@dataclass(frozen=True)
class LightSpectra:
    """A light model's spectra on a wavelength grid, float64, W m^-2 nm^-1 (module docstring).

    Shape:
        each (S, G) for S suns and G wavelengths.
    """

    direct_normal: torch.Tensor
    diffuse_horizontal: torch.Tensor
    circumsolar_horizontal: torch.Tensor  # A · DHI: the circumsolar part of DHI (0 where the model has none)
    ground_lit: bool  # whether the ground reflects light into the scene under this model


@dataclass(frozen=True)
class LightModel:
    """A registry entry: ``spectra(suns, grid)`` -> ``LightSpectra``; ``check(sun)``: ``ValueError`` naming what a
    sun lacks for this model, before anything is computed; ``atmosphere``: whether the model reads
    ``Sun.atmosphere`` (``uses_atmosphere``: what ``render.json`` and the dataset's rows record; a model that reads
    none, as "thesis", leaves it empty there)."""

    spectra: Callable[[Sequence[Sun], torch.Tensor], LightSpectra]
    check: Callable[[Sun], None] | None = None
    atmosphere: bool = True


def uses_atmosphere(name: str) -> bool:
    """Whether the light model ``name`` reads its suns' ``scene.Atmosphere`` ("spectrl2": yes; "thesis": no; a
    name not registered: yes, so nothing is dropped from a record). Reports record the atmosphere only then.

    >>> uses_atmosphere("spectrl2"), uses_atmosphere("thesis")
    (True, False)
    """
    model = MODELS.get(name)
    return model is None or model.atmosphere


MODELS: dict[str, LightModel] = {}


def register(name: str, model: LightModel) -> None:
    """Add (or replace) the light model ``name``: a ``Scene(illumination=name)`` then renders with it."""
    if not isinstance(model, LightModel):
        raise TypeError(f"register needs a LightModel, got {type(model).__name__}")
    MODELS[name] = model


def unregister(name: str) -> None:
    """Remove the light model ``name`` (``ValueError`` if it is not registered)."""
    if name not in MODELS:
        raise ValueError(f"no light model {name!r} is registered")
    del MODELS[name]


def check_light(name: str, suns: Sequence[Sun]) -> LightModel:
    """The light model ``name`` after checking every sun against it (``ValueError`` naming the problem)."""
    if name not in MODELS:
        raise ValueError(f"unknown illumination {name!r}; registered light models: {', '.join(sorted(MODELS))}")
    model = MODELS[name]
    if model.check is not None:
        for s in suns:
            model.check(s)
    return model


@dataclass
class LightTables:
    """Per sun and band, W m^-2 nm^-1, averaged over each band's response (module docstring): ``beam``, ``sky``,
    ``ground`` (what shading reads) and ``direct_horizontal`` (DNI cos θz), ``diffuse_horizontal`` (DHI) for
    reports.

    Shape:
        each (S, B); (N, B) for a batch of K skins (``repeat``: N = K·S rows, skin-major).
    """

    model: str
    beam: torch.Tensor
    sky: torch.Tensor
    ground: torch.Tensor
    direct_horizontal: torch.Tensor
    diffuse_horizontal: torch.Tensor
    ground_lit: bool

    TABLES: ClassVar[tuple[str, ...]] = ("beam", "sky", "ground", "direct_horizontal", "diffuse_horizontal")

    def _map(self, fn: Callable[[torch.Tensor], torch.Tensor]) -> LightTables:
        new: dict[str, Any] = {k: fn(getattr(self, k)) for k in self.TABLES}
        return dataclasses.replace(self, **new)

    def repeat(self, k: int) -> LightTables:
        """The tables for a batch of ``k`` skins: every sun's rows repeated, skin-major (as ``compile_materials``)."""
        return self if k == 1 else self._map(lambda t: t.repeat(k, 1))

    def to(self, device: torch.device | str, dtype: torch.dtype) -> LightTables:
        return self._map(lambda t: t.to(device=device, dtype=dtype))

    @property
    def needs_sky_view(self) -> bool:
        """Whether shading needs each pixel's view of the sky and the ground (any sky or ground light at all)."""
        return bool((self.sky > 0).any()) or (self.ground_lit and bool((self.ground > 0).any()))

    def summary(self, bands: Sequence[Band]) -> dict:
        """JSON-ready per-band tables for reports: the model, band centres and, per sun, the direct and diffuse
        horizontal irradiance (W m^-2 nm^-1)."""
        return {"model": self.model, "bands_nm": [b.center_nm for b in bands],
                "direct_horizontal": [[round(float(x), 6) for x in row] for row in self.direct_horizontal],
                "diffuse_horizontal": [[round(float(x), 6) for x in row] for row in self.diffuse_horizontal],
                "unit": "W m^-2 nm^-1"}


def light_tables(model: str, suns: Sequence[Sun], bands: Sequence[Sequence[float]] | Sequence[Band],
                 dtype: torch.dtype = torch.float64, device: torch.device | str = "cpu") -> LightTables:
    """The light model ``model``'s tables for ``suns`` and ``bands``: its spectra on the bands' sampling grid
    (``bands.band_sampling``), averaged over each band's response, computed in float64 and cast once.

    Shape:
        each table (S, B).
    """
    entry = check_light(model, suns)
    band_list = as_bands(bands)
    grid, W = band_sampling(band_list, dtype=torch.float64)
    sp = entry.spectra(suns, grid)
    cz = torch.tensor([math.cos(math.radians(s.zenith_deg)) for s in suns], dtype=torch.float64)[:, None]
    dni, dhi, circ = sp.direct_normal, sp.diffuse_horizontal, sp.circumsolar_horizontal
    beam = dni + circ / cz.clamp_min(MIN_COS_ZENITH)
    sky = dhi - circ
    ground = (dni * cz.clamp_min(0) + dhi) if sp.ground_lit else torch.zeros_like(dni)
    b, k, g, dh, df = (x @ W for x in (beam, sky, ground, dni * cz.clamp_min(0), dhi))
    return LightTables(model, b, k, g, dh, df, sp.ground_lit).to(device, dtype)


#: scale heights of the air molecules (R T / M g at 288 K) and of the boundary-layer aerosol (an assumption:
#: typical values are 1-2 km), m: the horizontal path's optical depth is the column's over the scale height
RAYLEIGH_SCALE_HEIGHT_M = 8434.0
AEROSOL_SCALE_HEIGHT_M = 1500.0
STANDARD_PRESSURE_PA = 101325.0


def path_transmittance(atmosphere: Atmosphere, bands: Sequence[Sequence[float]] | Sequence[Band],
                       range_m: float) -> list[float]:
    """Per band, the transmittance of a horizontal path of ``range_m`` near the ground through ``atmosphere``:
    exp(-r (τ_R(λ) p/p0 / H_R + τ_a(λ) / H_a)), with SPECTRL2's Rayleigh optical depth (Bird & Riordan 1986,
    τ_R = 1 / (λ⁴ (115.6406 - 1.335 / λ²)), λ in µm) and the aerosol's Angström law τ_a = τ_500 (λ / 0.5 µm)^-α,
    each column spread over its scale height (``RAYLEIGH_SCALE_HEIGHT_M``, ``AEROSOL_SCALE_HEIGHT_M``); gas
    absorption is left out (the index bands sit in windows). What the sensor's path transmittance is when the
    light model has an atmosphere (``torchskin render`` and ``generate`` with "spectrl2").

    >>> [round(x, 4) for x in path_transmittance(Atmosphere(), [[544, 0], [1580, 0]], 1000.0)]
    [0.9298, 0.982]
    """
    if not (math.isfinite(range_m) and range_m >= 0):
        raise ValueError(f"range_m must be a finite distance >= 0 m, got {range_m}")
    out = []
    for b in as_bands(bands):
        um = b.center_nm / 1000.0
        tau_r = 1.0 / (um**4 * (115.6406 - 1.335 / um**2)) * atmosphere.pressure_pa / STANDARD_PRESSURE_PA
        tau_a = atmosphere.aerosol_500nm * (um / 0.5) ** -atmosphere.angstrom_alpha
        out.append(math.exp(-range_m * (tau_r / RAYLEIGH_SCALE_HEIGHT_M + tau_a / AEROSOL_SCALE_HEIGHT_M)))
    return out


def path_terms(atmosphere: Atmosphere, sky: Sequence[float], bands: Sequence[Sequence[float]] | Sequence[Band],
               range_m: float) -> dict[str, list[float]]:
    """The sensor's atmosphere (``sensor.Sensor`` keyword arguments) consistent with a light model's
    ``atmosphere``: the path transmittance T (``path_transmittance``) and the airlight of Koschmieder's law,
    L_path = (1 - T) L_horizon, with the horizon sky's radiance taken as the isotropic sky's, ``sky`` / π
    (``sky``: the isotropic sky irradiance per band, ``LightTables.sky``, W m^-2 nm^-1)."""
    T = path_transmittance(atmosphere, bands, range_m)
    if len(sky) != len(T):
        raise ValueError(f"sky needs one value per band ({len(T)}), got {len(sky)}")
    return {"atmosphere_transmittance": T, "path_radiance": [(1 - t) * float(e) / math.pi for t, e in zip(T, sky)]}


# ------------------------------------------------------------------------------------------------ the models
def _thesis(suns: Sequence[Sun], grid: torch.Tensor) -> LightSpectra:
    E = torch.stack([sun_irradiance(s, grid) for s in suns])  # normal to the beam, every sun height alike
    # the thesis's grey sky: sky_fraction x E on an open horizontal surface, whatever the sun's height
    sky = torch.tensor([s.sky_fraction for s in suns], dtype=torch.float64)[:, None] * E
    return LightSpectra(E, sky, torch.zeros_like(E), ground_lit=False)


def _check_spectrl2(sun: Sun) -> None:
    if not sun.zenith_deg < 90.0:
        raise ValueError(f"illumination 'spectrl2' needs a sun above the horizon (zenith < 90°), got "
                         f"{sun.zenith_deg}° (illumination 'thesis' renders any source direction)")


#: the relative air mass of the "spectrl2" model: pvlib's default (Kasten & Young 1989; the SPECTRL2 report used
#: Kasten 1966, which differs by < 0.5 % in DHI / DNI up to a sun 85° from the zenith)
AIRMASS_MODEL = "kastenyoung1989"


def spectrl2_spectra(suns: Sequence[Sun]) -> dict[str, np.ndarray]:
    """``pvlib.spectrum.spectrl2`` for ``suns`` on its own 122 wavelengths: keys "wavelength" (122,) and
    "dni", "dhi", "dni_extra" (122, S), W m^-2 nm^-1, for a horizontal surface."""
    from pvlib import atmosphere as pv_atmosphere  # the render extra: a ModuleNotFoundError names it
    from pvlib import spectrum as pv_spectrum
    zen = np.array([s.zenith_deg for s in suns], dtype=np.float64)
    atm = [s.atmosphere for s in suns]
    day = np.array([a.day_of_year for a in atm], dtype=np.float64)
    kw = {"apparent_zenith": zen, "aoi": zen, "surface_tilt": 0.0,
          "ground_albedo": np.array([a.ground_albedo for a in atm]),
          "surface_pressure": np.array([a.pressure_pa for a in atm]),
          "relative_airmass": pv_atmosphere.get_relative_airmass(zen, model=AIRMASS_MODEL),
          "precipitable_water": np.array([a.precipitable_water_cm for a in atm]),
          "ozone": np.array([a.ozone_atm_cm for a in atm]),
          "aerosol_turbidity_500nm": np.array([a.aerosol_500nm for a in atm]),
          "alpha": np.array([a.angstrom_alpha for a in atm]), "dayofyear": day}
    out = pv_spectrum.spectrl2(**kw)
    return {k: np.asarray(out[k], dtype=np.float64).reshape(len(out["wavelength"]), -1) if k != "wavelength"
            else np.asarray(out[k], dtype=np.float64) for k in ("wavelength", "dni", "dhi", "dni_extra")}


def _interp_rows(grid: torch.Tensor, wl: np.ndarray, values: np.ndarray) -> torch.Tensor:
    """(S, G): each column of ``values`` (122, S), linear in wavelength, at ``grid`` (G,)."""
    g = grid.numpy()
    return torch.from_numpy(np.stack([np.interp(g, wl, values[:, k]) for k in range(values.shape[1])]))


def _spectrl2(suns: Sequence[Sun], grid: torch.Tensor) -> LightSpectra:
    lo, hi = float(grid.min()), float(grid.max())
    if lo < 300.0 or hi > 4000.0:
        raise ValueError(f"illumination 'spectrl2' covers 300-4000 nm; the bands need {lo:g}-{hi:g} nm")
    sp = spectrl2_spectra(suns)
    wl = sp["wavelength"]
    # Hay-Davies per wavelength, on SPECTRL2's own grid (A = DNI / DNI_extra; as pvlib.irradiance.haydavies),
    # then interpolated: across absorption bands A is a small difference that interpolation would magnify
    A = np.clip(np.divide(sp["dni"], sp["dni_extra"], out=np.zeros_like(sp["dni"]), where=sp["dni_extra"] > 0), 0, 1)
    dni, dhi = _interp_rows(grid, wl, sp["dni"]), _interp_rows(grid, wl, sp["dhi"])
    return LightSpectra(dni, dhi, _interp_rows(grid, wl, A * sp["dhi"]), ground_lit=True)


register("spectrl2", LightModel(_spectrl2, _check_spectrl2))
register("thesis", LightModel(_thesis, atmosphere=False))

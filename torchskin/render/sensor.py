"""Stage 5 of the renderer: the radiometric sensor chain of eq 2.5.2 and the atmosphere of eq 2.5.1, radiance
(W m^-2 sr^-1 nm^-1) -> digital numbers.

>>> import torch
>>> from torchskin.bands import as_bands
>>> L = torch.full((1, 1, 2, 2, 4), 0.01)  # (S, C, H, W, B) radiance
>>> dn = sensor_signal(L, Sensor(noise=False), as_bands([544, 633, 1080, 1580]), focal_px=1000.0)
>>> dn.shape, float(dn.max()) == round(0.8 * 2**14)  # auto exposure: the brightest pixel at 80 % of full well
(torch.Size([1, 1, 2, 2, 4]), True)
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import torch

from ..bands import Band, PerBand, at_wavelengths, per_band
from .kernels import KERNELS, aperture_radiance, band_tiles, sensor_dn, tile
from .light import C_LIGHT, H_PLANCK


@dataclass
class Sensor:
    """Radiometric chain of eq 2.5.2 and the atmosphere of eq 2.5.1, per band: each per-band field is one value,
    one per band or a spectrum at wavelengths (``bands.per_band``); the defaults are spectra at the
    ``INDEX_BANDS_NM`` (``bands.at_wavelengths``), interpolated in wavelength for other bands.

    L_aperture = τ_atm L + L_path; photoelectrons = L_aperture Ω_pixel A_optic τ_filter Δλ (λ/hc) t_int η;
    then shot noise (Gaussian approximation of Poisson, valid above ~100 e-), read noise, full-well
    clipping and an ADC of ``adc_bits`` with gain full_well / 2^bits e-/DN. Ω_pixel = 1/f_px² comes from
    the camera. Each stage can be switched off: ``atmosphere``, ``noise``, ``quantize``.
    ``integration_time_s="auto"`` exposes each band (each camera of a multi-camera system) so that the
    brightest pixel of the frame fills ``auto_fill`` of the full well (nothing saturates); a number fixes
    it (seconds).
    """

    aperture_diameter_m: float = 0.05
    integration_time_s: float | str = "auto"
    auto_fill: float = 0.8
    quantum_efficiency: PerBand = field(default_factory=lambda: at_wavelengths([0.55, 0.65, 0.75, 0.70]))
    filter_transmittance: PerBand = 0.9
    band_width_nm: PerBand | None = None  # default: each band's FWHM, or 10 nm for monochromatic bands
    atmosphere_transmittance: PerBand = field(default_factory=lambda: at_wavelengths([0.95, 0.96, 0.97, 0.93]))
    path_radiance: PerBand = field(default_factory=lambda: at_wavelengths([0.004, 0.003, 0.001, 0.0003]))
    read_noise_e: float = 50.0
    full_well_e: float = 2.0e6
    adc_bits: int = 14
    noise: bool = True
    atmosphere: bool = True
    quantize: bool = True
    seed: int = 0

    def __post_init__(self) -> None:
        for k in ("aperture_diameter_m", "full_well_e"):
            if not getattr(self, k) > 0:
                raise ValueError(f"sensor {k} must be > 0, got {getattr(self, k)}")
        if self.integration_time_s != "auto" and not float(self.integration_time_s) > 0:
            raise ValueError(f"sensor integration_time_s must be 'auto' or > 0 s, got {self.integration_time_s}")
        if not (0 < self.auto_fill <= 1):
            raise ValueError(f"sensor auto_fill must lie in (0, 1], got {self.auto_fill}")
        if not (1 <= int(self.adc_bits) <= 32):
            raise ValueError(f"sensor adc_bits must lie in [1, 32], got {self.adc_bits}")

    def tables(self, bands: tuple[Band, ...], dtype: torch.dtype, device: torch.device | str) -> dict[str, torch.Tensor]:
        """The per-band constants of the chain as (B,) tensors: quantum efficiency, filter transmittance, band
        width (nm), atmospheric transmittance, path radiance and the band centre (m)."""
        widths = self.band_width_nm
        if widths is None:
            widths = [b.fwhm_nm if b.fwhm_nm > 0 else 10.0 for b in bands]
        t = {
            "qe": per_band(self.quantum_efficiency, bands, "sensor quantum_efficiency"),
            "filter": per_band(self.filter_transmittance, bands, "sensor filter_transmittance"),
            "width": per_band(widths, bands, "sensor band_width_nm"),
            "tau": per_band(self.atmosphere_transmittance, bands, "sensor atmosphere_transmittance"),
            "path": per_band(self.path_radiance, bands, "sensor path_radiance"),
            "wavelength_m": [b.center_nm * 1e-9 for b in bands],
        }
        for k in ("qe", "filter", "tau"):
            if not all(0 < v <= 1 for v in t[k]):
                raise ValueError(f"sensor {k} values must lie in (0, 1], got {t[k]}")
        return {k: torch.tensor(v, dtype=dtype, device=device) for k, v in t.items()}


def band_max(x: torch.Tensor) -> torch.Tensor:
    """Max over axis 2 of (S, C, N, B) -> (S, C, B). Reducing a strided middle axis with 4 bands innermost is
    ~60x slower on CPU than two reductions over 64-wide contiguous rows, so the frame is viewed that way."""
    S, C, N, B = x.shape
    per = max(1, 64 // B)  # pixels per 64-wide row
    whole = N - N % per
    if not x.is_contiguous() or whole == 0:
        return x.amax(dim=2)
    head = x[:, :, :whole].reshape(S * C, -1, per * B).amax(dim=1).reshape(S * C, per, B).amax(dim=1)
    if whole < N:  # the last N mod per pixels
        head = torch.maximum(head, x[:, :, whole:].reshape(S * C, -1, B).amax(dim=1))
    return head.reshape(S, C, B)


def sensor_signal(radiance: torch.Tensor, sensor: Sensor | None, bands: Sequence[Band], focal_px: float,
                  generator: torch.Generator | None = None, reference: torch.Tensor | None = None,
                  compile: bool = False, noise: torch.Tensor | None = None) -> torch.Tensor:
    """Digital numbers from at-surface radiance (W m^-2 sr^-1 nm^-1) of shape ``(S, C, ..., B)``.
    ``sensor=None`` returns the radiance unchanged (an ideal linear sensor). ``reference`` (S, C, B): the
    radiance that automatic exposure maps to ``auto_fill`` of the full well (default: the frame's maximum).

    Shot and read noise are independent Gaussians, drawn as one: σ² = N_e + σ_read² (electrons), from
    ``generator`` in eager mode, or given: ``noise``, standard normal draws of the radiance's shape (another
    render's draws, reused). ``compile``: the rest as one fused compiled kernel (``kernels.sensor_dn``).
    """
    if sensor is None:
        return radiance
    tb = sensor.tables(tuple(bands), radiance.dtype, radiance.device)
    S, C, B = radiance.shape[0], radiance.shape[1], radiance.shape[-1]
    mid = (1,) * (radiance.dim() - 3)
    omega = 1.0 / focal_px**2
    area = math.pi * (sensor.aperture_diameter_m / 2) ** 2
    k = omega * area * tb["filter"] * tb["width"] * tb["wavelength_m"] * tb["qe"] / (H_PLANCK * C_LIGHT)
    if sensor.integration_time_s == "auto":
        if reference is None:
            reference = band_max(radiance.reshape(S, C, -1, B))
        ref = aperture_radiance(reference, tb["path"], tb["tau"]) if sensor.atmosphere else reference
        t_int = sensor.auto_fill * sensor.full_well_e / (k * ref).clamp_min(1e-30)  # (S, C, B)
        k = (k * t_int).reshape(S, C, *mid, B)
    else:
        k = k * float(sensor.integration_time_s)
    levels = 2 ** int(sensor.adc_bits)
    g = levels / sensor.full_well_e  # DN per electron
    if noise is not None and noise.shape != radiance.shape:
        raise ValueError(f"noise must have the radiance's shape {tuple(radiance.shape)}, got {tuple(noise.shape)}")
    z = None if not sensor.noise else noise.to(radiance) if noise is not None else \
        torch.randn(radiance.shape, generator=generator, dtype=radiance.dtype, device=radiance.device)  # eagerly
    gain = k * g
    x, gain, tiles = band_tiles(radiance, gain if gain.dim() == 1 else gain.reshape(S, C, B))
    dn_per_e, read2 = (torch.tensor(v, dtype=radiance.dtype, device=radiance.device)
                       for v in (g, (sensor.read_noise_e * g) ** 2))
    dn = KERNELS.get(sensor_dn, compile, radiance.device)(
        x, tile(tb["path"], tiles), tile(tb["tau"], tiles), gain, None if z is None else z.view(x.shape), dn_per_e,
        read2, levels, sensor.atmosphere, sensor.quantize)
    return dn.view(radiance.shape)

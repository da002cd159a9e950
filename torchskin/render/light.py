"""The sources: each ``Sun``'s spectrum, a blackbody scaled to the solar disc (thesis Fig 1, eq 2.1.8).

>>> import torch
>>> from torchskin.render.scene import Sun
>>> round(float(sun_irradiance(Sun(), torch.tensor([550.0]))), 3)  # W m^-2 nm^-1 at the top of the atmosphere
2.005
"""

from __future__ import annotations

import torch

from .scene import SUN_SOLID_ANGLE_SR, Sun

H_PLANCK = 6.62607015e-34
C_LIGHT = 2.99792458e8
K_BOLTZMANN = 1.380649e-23


def planck_radiance(wavelength_nm: torch.Tensor | float, temperature_k: float) -> torch.Tensor:
    """Blackbody spectral radiance, W m^-2 sr^-1 nm^-1 (eq 2.1.8), float64.

    Shape:
        ``wavelength_nm`` (...) -> (...).
    """
    wl = torch.as_tensor(wavelength_nm, dtype=torch.float64) * 1e-9
    h, c, k = H_PLANCK, C_LIGHT, K_BOLTZMANN
    return 2 * h * c**2 / wl**5 / torch.expm1(h * c / (wl * k * temperature_k)) * 1e-9


def sun_irradiance(sun: Sun, wavelength_nm: torch.Tensor | float) -> torch.Tensor:
    """Spectral irradiance of ``sun`` normal to the beam, W m^-2 nm^-1: its blackbody radiance times the solar
    disc's solid angle times ``sun.scale``."""
    return sun.scale * SUN_SOLID_ANGLE_SR * planck_radiance(wavelength_nm, sun.temperature_k)

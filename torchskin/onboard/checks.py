"""The reflectance range a cube must lie in to be calibrated reflectance: the bounds the onboard runtime refuses a
cube outside (``REFLECTANCE_MIN``, ``REFLECTANCE_MAX`` in more than ``REFLECTANCE_MAX_SHARE`` of its values,
``REFLECTANCE_CEILING``) and ``check_reflectance_range``, their one-line refusals. numpy only."""

from __future__ import annotations

import numpy as np

#: reflectance above this in more than ``REFLECTANCE_MAX_SHARE`` of a cube's values is not calibrated reflectance:
#: the detector refuses the cube. The ELM maps the white panel (0.97-0.99) near the top of the sensor's range; a
#: calibrated frame reads more only where a surface receives more light than the panels (a surface facing a low
#: sun that grazes level panels: ``render.elm.panel_irradiance_ratio`` times its reflectance) or in a specular
#: glint (water, glass, a car), which is why a few such values are allowed. Digital numbers (up to 2^bits) and per cent (up to 100) put
#: nearly every value above it
REFLECTANCE_MAX = 1.5
#: the share of a cube's values that may read above ``REFLECTANCE_MAX`` (glints, sun-facing surfaces), each at
#: most ``REFLECTANCE_CEILING``
REFLECTANCE_MAX_SHARE = 0.01
#: no value of a calibrated cube, glint or not, reads above this: reflectance is (signal - offset) / gain after
#: the empirical line, whose white panel (0.97-0.99) sits between the sensor's full scale and 1/16 of it (the range
#: of the sensor model: ``REFLECTANCE_MIN``, ``render.elm.panel_median_noise_dn``), so a saturated pixel, the most
#: light a camera records, reads at most about 16 x 0.99 = 16; 50 leaves a factor 3 (a panel set darker still, an
#: offset below 0). A value above it is not light but a corrupt or fill value (1e30, 65535) or a digital number:
#: refused whatever its share
REFLECTANCE_CEILING = 50.0
#: reflectance below this anywhere in a frame is refused too: the ELM's noise on a black pixel is σ_DN / gain, about
#: 1e-4 with the white panel near full scale and 1e-3 with it at 1/16 of it (read noise 20-80 e-, 14-bit ADC:
#: ``render.elm.panel_median_noise_dn``), so -0.2 is hundreds of σ away: an offset or a line that is wrong, not noise
#: (``negative="clip"`` clips only values above this)
REFLECTANCE_MIN = -0.2


#: the float32 bit pattern of ``REFLECTANCE_MAX``: non-negative float32 values order as their bits (as unsigned
#: integers), while negative ones (the sign bit, -0.0 included) and NaN lie above it; one integer maximum of a tile
#: at or below this proves every value finite and within [0, REFLECTANCE_MAX]
_MAX_BITS = int(np.array(REFLECTANCE_MAX, dtype=np.float32).view(np.uint32))


def check_reflectance_range(low: float, high: float, above: float = 1.0, where: str = "cube") -> None:
    """``ValueError`` with a hint when a cube's reflectance lies out of meaning: its smallest value ``low`` below
    ``REFLECTANCE_MIN``, its largest ``high`` above ``REFLECTANCE_MAX`` in more than ``REFLECTANCE_MAX_SHARE``
    of its values (``above``: that share; 1 when not counted), or ``high`` above ``REFLECTANCE_CEILING`` at all
    (one value is enough: no camera records it). Values far outside [0, 1.2] are not calibrated reflectance.
    ``where`` names the cube in the message (a file: ``--cube 'x.npy'``).

    >>> check_reflectance_range(0.0, 4.0, above=0.0005)  # a glint: fine
    >>> check_reflectance_range(0.0, 49.0, above=0.0005)  # brighter than a glint, but a camera could record it
    >>> check_reflectance_range(0.0, 97.0, above=0.9)
    Traceback (most recent call last):
    ...
    ValueError: cube reads reflectance above 1.5 in 90.0 % of its values (up to 97; refused above 1 %): is this uncalibrated signal (digital numbers; torchskin calibrate converts it)? per cent (divide by 100)?
    >>> check_reflectance_range(0.0, 1e30, above=0.0001, where="--cube 'c.npy'")
    Traceback (most recent call last):
    ...
    ValueError: --cube 'c.npy' reads reflectance 1e+30, which no camera records (refused above 50: a saturated pixel reads at most about 16 times the white panel's reflectance): a corrupt or fill value, or uncalibrated signal?
    """
    if high > REFLECTANCE_MAX and above > REFLECTANCE_MAX_SHARE:
        raise ValueError(f"{where} reads reflectance above {REFLECTANCE_MAX:g} in {100 * above:.1f} % of its values "
                         f"(up to {high:.4g}; refused above {100 * REFLECTANCE_MAX_SHARE:g} %): is this uncalibrated "
                         "signal (digital numbers; torchskin calibrate converts it)? per cent (divide by 100)?")
    if high > REFLECTANCE_CEILING:
        raise ValueError(f"{where} reads reflectance {high:.4g}, which no camera records (refused above "
                         f"{REFLECTANCE_CEILING:g}: a saturated pixel reads at most about 16 times the white panel's "
                         "reflectance): a corrupt or fill value, or uncalibrated signal?")
    if low < np.float32(REFLECTANCE_MIN):  # cubes are float32: -0.2 as a float32 is at the bound, not below it
        raise ValueError(f"{where} reads reflectance down to {low:.4g}, far below 0 (refused below "
                         f"{REFLECTANCE_MIN:g}; sensor noise reaches about -0.001): is this uncalibrated signal "
                         "with an offset, or calibrated with swapped panels?")

"""Angle helpers that need no torch: they work on Python floats, numpy arrays and torch tensors alike, so the
numpy-only onboard runtime can use them too (this module imports nothing but the standard library).

Convention (DESIGN.md): azimuths in degrees at the CLI and in file metadata; the relative azimuth between the
sun and the camera is folded to [0, 180] degrees (0: the sun behind the camera, 180: facing it).
"""

from __future__ import annotations

from typing import TypeVar

A = TypeVar("A")

#: a configuration is back-lit, the camera looking towards the sun, from this relative azimuth on (degrees)
BACKLIT_MIN_DEG = 120.0


def relative_azimuth_deg(azimuth_a_deg: A, azimuth_b_deg: A | float) -> A:
    """The relative azimuth ``|φa − φb|`` folded to [0, 180] degrees: ``|(φa − φb + 180) mod 360 − 180|``.

    Args:
        azimuth_a_deg: an azimuth in degrees, e.g. the sun's (any real value; a float, numpy array or tensor).
        azimuth_b_deg: another, e.g. the camera's; broadcasts with ``azimuth_a_deg``.

    Shape:
        Arrays and tensors broadcast; the result has the broadcast shape.

    Returns:
        The folded difference in [0, 180] degrees, of the inputs' kind (float, numpy array or tensor).

    >>> relative_azimuth_deg(350.0, 10.0), relative_azimuth_deg(20.0, 200.0), relative_azimuth_deg(-90.0, 90.0)
    (20.0, 180.0, 180.0)
    """
    return abs((azimuth_a_deg - azimuth_b_deg + 180.0) % 360.0 - 180.0)  # type: ignore[operator]


__all__ = ["BACKLIT_MIN_DEG", "relative_azimuth_deg"]

"""The rows of a pose group's sampled pixels: each configuration's (sun x skin) columns (``configuration_rows``),
what the pixels show (``pixel_labels``), their angles, stored indices, atmosphere and light columns, and whether the
empirical line holds (``line_valid``)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, cast

import numpy as np
import torch

from .. import tissue
from ..angles import BACKLIT_MIN_DEG, relative_azimuth_deg
from ..bands import INDEX_BANDS_NM, BandSet, per_band
from ..detect import normalized_difference
from ..optics import local_angles
from ..render.elm import elm_line_valid, panel_median_noise_dn
from ..render.light import LightTables, uses_atmosphere
from ..render.pipeline import RenderResult
from ..render.raycast import GBuffer
from ..render.scene import Scene
from ..render.sensor import Sensor
from .config import LIGHT_ATMOSPHERE, PoseGroup
from .schema import INDICES, SINGLE_BAND_COLUMNS, STORED_INDICES, columns_for, has_band

PHENOTYPES = ("gender", "age", "muscle", "weight", "height", "proportions")
#: the bands whose direct share each row records (544 and 1580 nm: direct_share_544, direct_share_1580): their
#: positions in the index bands; ``share_bands`` finds them in any band set
SHARE_BANDS = (0, 3)

#: ``day_of_year`` of the rows of a light model without an atmosphere ("thesis"; the float atmosphere columns are
#: NaN there): no day of year is 0
NO_DAY_OF_YEAR = 0


def band_position(bands: BandSet, nm: float) -> int | None:
    """The position of ``bands``' band at ``nm`` (within ``bands.BAND_MATCH_NM``), None without one."""
    return bands.index(nm) if has_band(bands, nm) else None


def share_bands(bands: BandSet) -> dict[str, int]:
    """The direct-share columns the band set defines -> the position of their band (``SINGLE_BAND_COLUMNS``).

    >>> share_bands(BandSet.of(INDEX_BANDS_NM)), share_bands(BandSet.of([450.0, 1580.0]))
    ({'direct_share_544': 0, 'direct_share_1580': 3}, {'direct_share_1580': 1})
    """
    out = {k: band_position(bands, SINGLE_BAND_COLUMNS[k]) for k in ("direct_share_544", "direct_share_1580")}
    return {k: v for k, v in out.items() if v is not None}


def pixel_angles_deg(gb: GBuffer, idx: torch.Tensor, sun_dir: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """Local (θi, θr, Δφ) in degrees of the flat pixels ``idx`` of camera 0 (``optics.local_angles``, float64)."""
    normal = gb.normal.reshape(-1, 3)[idx].double()
    view = -gb.rays.reshape(-1, 6)[idx][:, 3:].double()
    return tuple(a * (180.0 / math.pi) for a in local_angles(normal, sun_dir.double(), view))


@dataclass
class PixelLabels:
    """What each pixel of camera 0 of a group's G-buffer shows (flat H*W arrays)."""

    skin: np.ndarray  # flat indices of skin pixels
    other: np.ndarray  # flat indices of the other hit pixels (not skin, not a reference panel)
    mesh: np.ndarray  # (H*W,) mesh id of each pixel (-1: no hit)
    material: np.ndarray  # (H*W,) material id of each pixel (-1: no hit)
    confuser_names: np.ndarray  # by mesh id + 1: the earthlib confuser name ("" for none)
    material_labels: np.ndarray  # by material id + 1: skin, clothing, ground, confuser, white/dark ("" for no hit)


def pixel_labels(group: PoseGroup, scene: Scene, gb: GBuffer) -> PixelLabels:
    """The skin and candidate non-skin pixels of a group's frame, and each pixel's confuser and material."""
    conf_names = np.full(len(gb.mesh_names) + 1, "", dtype=object)  # indexed by mesh id + 1 (-1: no hit)
    for k, c in enumerate(group.confusers):
        conf_names[gb.mesh_names.index(f"confuser{k}") + 1] = c["name"]
    mat_labels = np.array(["", *("confuser" if n.startswith("confuser") else n for n in gb.material_names)],
                          dtype=object)  # indexed by material id + 1
    is_panel = torch.zeros_like(gb.hit[0].reshape(-1))
    for k in [gb.mesh_names.index(p) for p in scene.panels]:
        is_panel |= gb.mesh[0].reshape(-1) == k
    hit = gb.hit[0].reshape(-1)
    skin_px = hit & (gb.material[0].reshape(-1) == gb.material_names.index("skin"))
    other_px = hit & ~is_panel & ~skin_px
    return PixelLabels(skin_px.nonzero().flatten().numpy(), other_px.nonzero().flatten().numpy(),
                       gb.mesh[0].reshape(-1).numpy(), gb.material[0].reshape(-1).numpy(), conf_names, mat_labels)


def line_valid(res: RenderResult, sensor: Sensor) -> np.ndarray:
    """Per configuration (the render's leading axis, (S·K,)), whether the empirical line through the reference
    panels' medians is a line (``elm.elm_line_valid``): the panels separated by ``ELM_MIN_SEPARATION_SIGMA``
    σ of the medians' noise in every band (``elm.panel_median_noise_dn``, from the sensor's shot, read and ADC
    noise and each panel's sample size) and a finite positive gain."""
    names = list(res.panels)
    pv = torch.tensor([res.panels[p]["signal"] for p in names], dtype=torch.float64)[:, :, 0].transpose(0, 1)
    refs = torch.tensor([res.panels[p]["reference"] for p in names], dtype=torch.float64)[:, :, 0].transpose(0, 1)
    n = torch.tensor([float(len(per_cam[0])) for per_cam in res.panel_pixels], dtype=torch.float64)[:, None]
    dn_per_e = 2.0 ** int(sensor.adc_bits) / sensor.full_well_e
    noise = panel_median_noise_dn(pv, n, sensor.read_noise_e, dn_per_e, sensor.quantize, sensor.noise)
    return elm_line_valid(pv, refs, noise).numpy()


def configuration_rows(group: PoseGroup, res: RenderResult, idx: np.ndarray, pos: np.ndarray, gb: GBuffer,
                       sun_dirs: torch.Tensor, labels: PixelLabels, elm_valid: np.ndarray,
                       light: LightTables, sensor: Sensor, irradiance_ratio: np.ndarray,
                       elm_line_valid: np.ndarray) -> dict[str, np.ndarray]:
    """The rows of every configuration (skin x sun, skin-major) of a group as one table: configuration c's 2m
    rows (first half skin, second half other pixels) are the flat pixels ``idx[c·2m:(c+1)·2m]`` of camera 0,
    found at ``pos`` (same slice) of the pixel render ``res``'s row c (rendered with ``irradiance``);
    ``elm_valid`` (S·K,) per configuration; ``light``: the scene's light tables (S rows, float64); ``sensor``: the group's
    (``group_sensor``); ``irradiance_ratio`` (S,): per sun, ``elm.panel_irradiance_ratio``; ``elm_line_valid``
    (S·K,): ``elm_valid`` but for the irradiance-ratio bound."""
    n_suns, n_skins = len(group.suns), len(group.skin_types)
    n_cfg = n_suns * n_skins
    per = len(idx) // n_cfg  # 2m
    cfg = np.repeat(np.arange(n_cfg), per)
    ki, si = cfg // n_suns, cfg % n_suns
    skins = cast(tissue.SkinParams, group.skins)
    bands = group.bands
    k544 = band_position(bands, SINGLE_BAND_COLUMNS["atmosphere_transmittance"])
    const = {"group": group.index, "camera_zenith_deg": group.camera["zenith_deg"],
             "camera_azimuth_deg": group.camera["azimuth_deg"], "range_m": group.camera["range_m"],
             "atmosphere_transmittance": math.nan if k544 is None else
             per_band(sensor.atmosphere_transmittance, bands.bands, "transmittance")[k544],
             "path_radiance_scale": group.atmosphere["path_radiance_scale"],
             **atmosphere_columns(group.light),
             "subject_yaw_deg": group.subject["yaw_deg"], "subject": group.subject.get("path", "anny"),
             "head_yaw_deg": group.subject.get("head_yaw_deg", math.nan),
             "head_pitch_deg": group.subject.get("head_pitch_deg", math.nan),
             **{k: group.subject.get("phenotype", {}).get(k, math.nan) for k in PHENOTYPES},
             "panels": group.panels, "surface": group.surface, "clothing": group.clothing}
    n = len(idx)
    rows: dict[str, Any] = {k: strings(np.zeros(n, np.int32), [v]) if isinstance(v, str) else np.full(n, v)
                            for k, v in const.items()}

    def per_sun(values: list) -> np.ndarray:
        return np.array(values)[si]

    rows.update({"sun": si, "skin": ki, "sun_zenith_deg": per_sun([s["zenith_deg"] for s in group.suns]),
                 "sun_azimuth_deg": per_sun([s["azimuth_deg"] for s in group.suns]),
                 "relative_azimuth_deg": per_sun([relative_azimuth_deg(s["azimuth_deg"], group.camera["azimuth_deg"])
                                                  for s in group.suns]),
                 "sky_fraction": (np.full(n_suns, np.nan, np.float32) if k544 is None else
                                  sky_fraction(light, [s["zenith_deg"] for s in group.suns], k544))[si],
                 "panel_irradiance_ratio": irradiance_ratio.astype(np.float32)[si],
                 "backlit": per_sun([relative_azimuth_deg(s["azimuth_deg"], group.camera["azimuth_deg"])
                                     >= BACKLIT_MIN_DEG for s in group.suns]),
                 "skin_type": strings(ki, group.skin_types),
                 **{k: np.array([float(x) for x in getattr(skins, k)])[ki]
                    for k in ("melanosome", "blood", "oxygenation", "reticular_depth", "collagen", "subcutaneous_scale")}})
    at = (torch.from_numpy(cfg), torch.from_numpy(pos))
    refl = res.reflectance[:, 0, 0].cpu()[at].float()
    ti, tr, dp = pixel_angles_deg(gb, torch.from_numpy(idx), sun_dirs[torch.from_numpy(si)])
    rows.update({"confuser": strings(labels.mesh[idx] + 1, labels.confuser_names),
                 "material": strings(labels.material[idx] + 1, labels.material_labels),
                 "label": np.tile(np.repeat(np.array([True, False]), per // 2), n_cfg), "theta_i_deg": ti.numpy(),
                 "theta_r_deg": tr.numpy(), "delta_phi_deg": dp.numpy(),
                 "shadow": (~res.lit[:, 0, 0].cpu()[at]).numpy(),  # cast shadow or facing away from the sun
                 "elm_valid": elm_valid[cfg],
                 "elm_line_valid": elm_line_valid[cfg],
                 **stored_indices(res, at, refl, bands)})
    rows.update({name: refl[:, b].numpy() for b, name in enumerate(bands.columns)})
    shadow = rows["shadow"]
    rows["light"] = strings(shadow, ["sunlit", "shadow"])
    sky = res.gbuffer.sky  # None where the light has no sky or ground light (no sky rays cast): NaN
    rows["sky_view"] = np.full(n, np.nan, dtype=np.float32) if sky is None else \
        sky.reshape(-1).cpu()[torch.from_numpy(pos)].float().numpy()
    shares = share_bands(bands)  # the irradiance bands render_pixels was asked for, in this order
    rows["direct_share_544"] = rows["direct_share_1580"] = np.full(n, np.nan, dtype=np.float32)
    if shares:
        direct, diffuse = (x[:, 0, 0].cpu().double()[at] for x in cast(tuple, res.irradiance))  # (n, B')
        total = direct + diffuse
        share = torch.where(total > 0, direct / total.clamp_min(1e-300), torch.zeros_like(total)).float().numpy()
        rows.update({name: share[:, j] for j, name in enumerate(shares)})
    return {k: rows[k] for k in columns_for(bands)}


def stored_indices(res: RenderResult, at: tuple[torch.Tensor, torch.Tensor], refl: torch.Tensor,
                   bands: BandSet) -> dict[str, np.ndarray]:
    """The stored indices of the rows (``STORED_INDICES``) at ``at`` of the render ``res``: the renderer's own where
    the bands hold all four index bands (within ``bands.BAND_MATCH_NM``); else, per index, from the rows' float32
    reflectance ``refl`` (n, B) where its two bands are there, NaN where one is not (the renderer matches bands
    within 30 nm: a 540 nm band is not the 544 nm the column names)."""
    if all(has_band(bands, w) for w in INDEX_BANDS_NM):
        return {name: getattr(res, name)[:, 0, 0].cpu()[at].numpy() for name in STORED_INDICES}
    out = {}
    for name in STORED_INDICES:
        (a,), (b,) = INDICES[name]
        ia, ib = band_position(bands, a), band_position(bands, b)
        out[name] = np.full(len(refl), np.nan, np.float32) if ia is None or ib is None else \
            normalized_difference(refl[:, ia], refl[:, ib]).float().numpy()
    return out


def atmosphere_columns(light: dict) -> dict[str, float | int]:
    """The light-model atmosphere columns of a pose group's rows (``LIGHT_ATMOSPHERE``): the drawn atmosphere
    under a light model that reads one (``light.uses_atmosphere``: "spectrl2"); under one that does not
    ("thesis"), empty: NaN, and ``NO_DAY_OF_YEAR`` for the integer ``day_of_year``.

    >>> atmosphere_columns({"model": "thesis", "aerosol_500nm": 0.2, "precipitable_water_cm": 1.0,
    ...                     "ozone_atm_cm": 0.3, "pressure_pa": 9e4, "day_of_year": 100})
    {'aerosol_500nm': nan, 'precipitable_water_cm': nan, 'ozone_atm_cm': nan, 'pressure_pa': nan, 'day_of_year': 0}
    """
    if uses_atmosphere(light["model"]):
        return {k: light[k] for k in LIGHT_ATMOSPHERE}
    return {k: NO_DAY_OF_YEAR if k == "day_of_year" else math.nan for k in LIGHT_ATMOSPHERE}


def strings(codes: np.ndarray, vocabulary: Sequence[str] | np.ndarray):
    """A string column chunk as a pyarrow dictionary array: ``vocabulary[codes]`` (written as plain strings,
    ``write_shard``; building it costs a fraction of converting Python strings one by one)."""
    import pyarrow as pa

    return pa.DictionaryArray.from_arrays(pa.array(np.asarray(codes, dtype=np.int32)),
                                          pa.array([str(v) for v in vocabulary], type=pa.string()))


def sky_fraction(light: LightTables, zenith_deg: list[float], band: int = 0) -> np.ndarray:
    """Per sun, diffuse horizontal over direct normal irradiance in band ``band`` (the 544 nm band: the index bands'
    first): the thesis model's ``sky_fraction``, derived (NaN where no direct light reaches a horizontal surface)."""
    cz = torch.cos(torch.deg2rad(torch.tensor(zenith_deg, dtype=torch.float64)))
    dni = light.direct_horizontal[:, band].double() / cz
    return torch.where(dni > 0, light.diffuse_horizontal[:, band].double() / dni, torch.nan).float().numpy()

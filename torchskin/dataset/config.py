"""Dataset configuration: a TOML file of ranges with documented defaults, validated, and a deterministic
sampler of *pose groups* (one camera and subject pose, several sun directions and skins) from a master seed.

A group is the unit of work: its rays are cast once and every sun x skin x band of it is shaded in one
batch. Group ``i`` is drawn from ``SeedSequence([master_seed, i])`` alone, so it does not depend on how many
groups are drawn, in which order, or by which worker.

Ranges are ``[min, max]`` (uniform); angles in degrees. See ``DEFAULT_CONFIG`` for every key.
"""

from __future__ import annotations

import copy
import math
import os
import tomllib
from dataclasses import asdict, dataclass, field

import numpy as np
import torch

from .. import tissue
from ..bands import INDEX_BANDS, INDEX_BANDS_NM, BandSet
from ..optics import DEFAULT_SURFACE, SURFACE_MODELS
from ..render.scene import PANEL_KINDS

#: every key with its default and allowed domain: section -> key -> (default, domain or kind)
SCHEMA: dict[str, dict[str, tuple]] = {
    "sun": {
        "zenith_deg": ([0.0, 89.0], (0.0, 90.0)),
        "azimuth_deg": ([0.0, 360.0], (0.0, 360.0)),
        "per_pose": (16, "int>=1"),
    },
    # the light model (render.light) and its clear-sky atmosphere, drawn per pose group (one place and day: its
    # suns share it). Ranges: aerosol optical depth at 500 nm from clean air to haze and smoke (AERONET: annual
    # means of continental sites 0.03-0.4, Holben et al. 2001, J Geophys Res 106:12067; hazy and smoky days 1 and
    # more, Eck et al. 1999, J Geophys Res 104:31333); precipitable water of dry to tropical humid air masses
    # (0.5-6 cm; SMARTS, Gueymard 2001, Solar Energy 71:325); total ozone (TOMS/OMI climatology: 250-450 Dobson
    # units, 0.25-0.45 atm-cm); surface pressure from sea level to about 1500 m.
    "light": {
        "model": ("spectrl2", ("spectrl2", "thesis")),
        "aerosol_500nm": ([0.03, 1.0], (0.0, 2.0)),
        "precipitable_water_cm": ([0.5, 6.0], (0.0, 10.0)),
        "ozone_atm_cm": ([0.25, 0.45], (0.0, 1.0)),
        "pressure_pa": ([85000.0, 102000.0], (30000.0, 110000.0)),
        "day_of_year": ([1.0, 365.0], (1.0, 366.0)),
        "sky_fraction": ([0.0, 0.2], (0.0, 1.0)),  # the "thesis" model's grey sky only
    },
    "camera": {
        "zenith_deg": ([0.0, 90.0], (0.0, 90.0)),  # 90: a horizontal, ground-level camera (the thesis)
        "azimuth_deg": ([0.0, 360.0], (0.0, 360.0)),
        "range_m": ([5.0, 100.0], (0.5, 10000.0)),
        "width": (256, "int>=16"),
        "height": (256, "int>=16"),
        "subject_fraction": (0.7, (0.05, 1.0)),  # subject height / frame height (sets the field of view)
    },
    "subject": {
        "yaw_deg": ([0.0, 360.0], (0.0, 360.0)),
        "gender": ([0.0, 1.0], (0.0, 1.0)),
        "age": ([0.4, 0.9], (0.0, 1.0)),
        "muscle": ([0.2, 0.8], (0.0, 1.0)),
        "weight": ([0.2, 0.8], (0.0, 1.0)),
        "height": ([0.3, 0.8], (0.0, 1.0)),
        "proportions": ([0.3, 0.7], (0.0, 1.0)),
        "head_yaw_deg": ([-40.0, 40.0], (-90.0, 90.0)),  # anny pose: the head turned left/right
        "head_pitch_deg": ([-20.0, 20.0], (-60.0, 60.0)),  # and tilted down/up
        "meshes": ([], "paths"),  # OBJ/PLY files used instead of anny bodies when given
    },
    "skin": {
        "types": (list(tissue.FITZPATRICK_TYPES), "types"),
        "per_pose": (3, "int>=1"),
        "surface": (DEFAULT_SURFACE, SURFACE_MODELS),  # skin surface model of eq 3.1.1 (optics.skin_diffuse)
    },
    "clothing": {
        # the subject's clothing: a measured earthlib spectrum of this partition from the families that stand in
        # for dyed and natural fabrics (confusers.CLOTHING_FAMILIES), or "fixed": the one grey-brown spectrum
        "partition": ("train", ("train", "test", "fixed")),
    },
    # the sensor's path between subject and camera: with the "spectrl2" light, its transmittance and airlight
    # come from the light's atmosphere (light.path_terms) and the airlight is scaled by path_radiance_scale;
    # with "thesis", the transmittance is drawn from this range and the airlight is the sensor default's, scaled
    "atmosphere": {
        "transmittance": ([0.85, 1.0], (0.0, 1.0)),
        "path_radiance_scale": ([0.0, 2.0], (0.0, 100.0)),
    },
    "sensor": {
        "noise": (True, "bool"),
        "read_noise_e": ([20.0, 80.0], (0.0, 1e6)),
    },
    "confusers": {
        "count": ([0, 3], (0, 32)),
        "partition": ("train", ("train", "test")),
    },
    # reference panel kinds (render.scene.PANEL_KINDS); Spectralon's Table 3 DHR is known only near the index bands
    # (render.materials.SPECTRALON_DHR): for other [bands] the default is lambertian alone (spectralon is refused)
    "panels": {
        "kinds": (["lambertian", "spectralon"], "panels"),
    },
    # the BRDF of the ground and the confuser patches: "rtlsr", the Ross-Thick/Li-Sparse-Reciprocal kernels with
    # Roy et al. (2016)'s global per-band shape (render.rtlsr), or "lambertian"
    "ground": {
        "brdf": ("rtlsr", ("rtlsr", "lambertian")),
    },
    "sampling": {
        "pixels_per_class": (128, "int>=1"),
        "groups_per_shard": (16, "int>=1"),
    },
    # the camera's bands: a --bands list (bands.BandSet.parse: "544,633,1080/20,1580/40", ranges "450:1650:10"),
    # one reflectance column each (r<centre>); default the thesis's four index bands. generate --bands overrides it
    "bands": {
        "spec": (",".join(f"{w:g}" for w in INDEX_BANDS_NM), "bands"),
    },
}


def default_config() -> dict:
    """The defaults as a plain dict (section -> key -> value)."""
    return {s: {k: copy.deepcopy(v[0]) for k, v in keys.items()} for s, keys in SCHEMA.items()}


def _is_number(x) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool)


def _refuse_non_finite(name: str, value) -> None:
    """``ValueError`` naming ``section.key`` if ``value`` is, or holds, a NaN or infinite number (TOML has
    ``nan`` and ``inf`` literals; every comparison with NaN is false, so a range check alone lets it through)."""
    items = value if isinstance(value, (list, tuple)) else [value]
    for x in items:
        if _is_number(x) and not math.isfinite(x):
            raise ValueError(f"{name} must hold finite numbers, got {value!r}")


def _check(section: str, key: str, value, domain):
    name = f"{section}.{key}"
    _refuse_non_finite(name, value)
    if isinstance(domain, tuple) and len(domain) == 2 and all(isinstance(x, (int, float)) for x in domain):
        lo_d, hi_d = domain
        if isinstance(value, (list, tuple)):
            if len(value) != 2 or not all(_is_number(x) for x in value):
                raise ValueError(f"{name} must be [min, max], got {value!r}")
            lo, hi = float(value[0]), float(value[1])
            if lo > hi:
                raise ValueError(f"{name}: min {lo:g} > max {hi:g}")
            if lo < lo_d or hi > hi_d:
                raise ValueError(f"{name} must lie within [{lo_d:g}, {hi_d:g}], got [{lo:g}, {hi:g}]")
            return [lo, hi]
        if not isinstance(value, (int, float)) or isinstance(value, bool) or not (lo_d <= value <= hi_d):
            raise ValueError(f"{name} must be a number in [{lo_d:g}, {hi_d:g}], got {value!r}")
        return float(value)
    if isinstance(domain, tuple):  # choices
        if value not in domain:
            raise ValueError(f"{name} must be one of {list(domain)}, got {value!r}")
        return value
    if domain.startswith("int>="):
        m = int(domain[5:])
        if not isinstance(value, int) or isinstance(value, bool) or value < m:
            raise ValueError(f"{name} must be an integer >= {m}, got {value!r}")
        return value
    if domain == "bool":
        if not isinstance(value, bool):
            raise ValueError(f"{name} must be true or false, got {value!r}")
        return value
    if domain == "types":
        if not value or any(t not in tissue.FITZPATRICK_TYPES for t in value):
            raise ValueError(f"{name} must list Fitzpatrick types from {list(tissue.FITZPATRICK_TYPES)}, got {value!r}")
        return list(value)
    if domain == "panels":
        if not value or any(p not in PANEL_KINDS for p in value):
            raise ValueError(f"{name} must list panel kinds from {list(PANEL_KINDS)}, got {value!r}")
        return list(value)
    if domain == "bands":
        if not isinstance(value, str):
            raise ValueError(f"{name} must be a band list in the --bands syntax (a string such as "
                             f"\"544,633,1080/20,1580/40\", \"450:1650:10\", \"rededge-mx\" or a response table "
                             f"\"filters.csv\"), got {value!r}")
        got = config_bands({section: {key: value}}, name)  # a bad band: one line naming the key
        # a response table is read once: the configuration (and a dataset's manifest) keeps its curves, not a path
        return got.to_json() if value.strip().lower().endswith(".csv") else value.strip()
    if domain == "paths":
        if not isinstance(value, list) or any(not isinstance(p, str) for p in value):
            raise ValueError(f"{name} must be a list of OBJ/PLY paths, got {value!r}")
        return list(value)
    raise AssertionError(domain)  # pragma: no cover


def resolve_config(overrides: dict | None = None) -> dict:
    """Defaults merged with ``overrides`` (section -> key -> value), validated: unknown sections or keys,
    ranges with min > max and values outside their domain raise ``ValueError`` naming ``section.key``."""
    cfg = default_config()
    for section, keys in (overrides or {}).items():
        if section not in SCHEMA:
            raise ValueError(f"unknown config section {section!r}; known: {', '.join(SCHEMA)}")
        if not isinstance(keys, dict):
            raise ValueError(f"config section {section!r} must be a table of keys")
        for key, value in keys.items():
            if (section, key) == ("sun", "sky_fraction"):
                raise ValueError("config key sun.sky_fraction has moved: the sky comes from the light model "
                                 "([light] model); light.sky_fraction sets the 'thesis' model's grey sky")
            if key not in SCHEMA[section]:
                raise ValueError(f"unknown config key {section}.{key}; known: {', '.join(SCHEMA[section])}")
            cfg[section][key] = value
    for s, keys in cfg.items():  # a range key given one number: say so (not a TypeError later)
        for k, v in keys.items():
            if isinstance(SCHEMA[s][k][0], list) and _is_number(SCHEMA[s][k][0][0] if SCHEMA[s][k][0] else None) \
                    and not isinstance(v, (list, tuple)):
                raise ValueError(f"{s}.{k} must be [min, max] (a range; [x, x] for one value), got {v!r}")
    out = {s: {k: _check(s, k, v, SCHEMA[s][k][1]) for k, v in keys.items()} for s, keys in cfg.items()}
    _panels_for_bands(out, "kinds" in (overrides or {}).get("panels", {}))
    lo_d, hi_d = out["light"]["day_of_year"]
    if math.ceil(lo_d) > math.floor(hi_d):
        raise ValueError(f"light.day_of_year must hold a whole day, got [{lo_d:g}, {hi_d:g}]")
    return out


def _panels_for_bands(cfg: dict, given: bool) -> None:
    """Spectralon panels need Table 3's DHR at every band (``materials.spectralon_dhr``: only near the index bands):
    with bands it lacks, the default panel kinds become lambertian alone; kinds ``given`` with a Spectralon kind
    are refused in one line naming ``panels.kinds`` and the bands."""
    from ..render.materials import spectralon_dhr

    if not any(k.startswith("spectralon") for k in cfg["panels"]["kinds"]):
        return
    try:
        spectralon_dhr("white", config_bands(cfg).bands)
    except ValueError as e:
        if given:
            raise ValueError(f"panels.kinds {cfg['panels']['kinds']} with bands.spec {cfg['bands']['spec']!r}: {e}; "
                             "use [panels] kinds = [\"lambertian\"]") from None
        cfg["panels"]["kinds"] = ["lambertian"]


def config_bands(cfg: dict, option: str = "bands.spec") -> BandSet:
    """The bands of a configuration (its ``bands.spec``, ``BandSet.parse``; ``option`` is named in errors).

    >>> config_bands(default_config()).columns
    ('r544', 'r633', 'r1080', 'r1580')
    """
    return BandSet.parse(cfg["bands"]["spec"], option=option)


def load_config(path: str | os.PathLike | None = None, bands: str | None = None) -> dict:
    """Read and validate a TOML configuration (``None``: the built-in defaults); ``bands``: a ``--bands`` list
    that replaces its ``bands.spec``."""
    over = {"bands": {"spec": bands}} if bands is not None else {}
    if path is None:
        return resolve_config(over)
    try:
        with open(path, "rb") as fh:
            data = tomllib.load(fh)
    except FileNotFoundError:
        raise ValueError(f"config file {str(path)!r} does not exist") from None
    except tomllib.TOMLDecodeError as e:
        raise ValueError(f"config file {str(path)!r} is not valid TOML: {e}") from None
    if bands is not None and isinstance(data.get("bands", {}), dict):  # a [bands] that is not a table: refused below
        data = {**data, "bands": {**data.get("bands", {}), "spec": bands}}
    return resolve_config(data)


# ------------------------------------------------------------------------------------------------- sampling
@dataclass
class PoseGroup:
    """One camera and subject pose with several suns and skins: everything needed to render it."""

    index: int
    seed: int
    camera: dict  # zenith_deg, azimuth_deg, range_m, width, height, fov_deg
    subject: dict  # kind "anny" (phenotype) or "file" (path); yaw_deg
    suns: list[dict] = field(default_factory=list)  # zenith_deg, azimuth_deg
    skins: tissue.SkinParams | None = None  # (K,) float64 batch of the group's skins (``tissue.sample``)
    skin_types: list[str] = field(default_factory=list)  # their Fitzpatrick types
    atmosphere: dict = field(default_factory=dict)
    sensor: dict = field(default_factory=dict)
    panels: str = "lambertian"
    confusers: list[dict] = field(default_factory=list)  # earthlib spectrum name, ground position, size
    clothing: str = ""  # earthlib spectrum name of the subject's clothing ("": the fixed clothing spectrum)
    surface: str = DEFAULT_SURFACE  # skin surface model
    light: dict = field(default_factory=dict)  # model, the atmosphere's fields (scene.Atmosphere), sky_fraction
    ground_brdf: str = "lambertian"  # material kind of the ground and the confuser patches
    bands: BandSet = INDEX_BANDS  # the camera's bands (the config's bands.spec)

    def as_dict(self) -> dict:
        """The group as JSON-ready data (skins as parameter lists)."""
        d = asdict(self)
        d["skins"] = None if self.skins is None else self.skins.as_dict()
        return d


def group_seed(master_seed: int, index: int) -> int:
    """The 63-bit seed of group ``index``: a pure function of (master seed, index)."""
    return int(np.random.SeedSequence([int(master_seed), int(index)]).generate_state(2, np.uint32).astype(
        np.uint64) @ np.array([1 << 32, 1], dtype=np.uint64) >> np.uint64(1))


SUBJECT_HEIGHT_M = 1.8  # for the field of view: the subject spans ``subject_fraction`` of the frame


def sample_group(cfg: dict, master_seed: int, index: int) -> PoseGroup:
    """Draw pose group ``index`` (deterministic in (config, master seed, index))."""
    seed = group_seed(master_seed, index)
    rng = np.random.default_rng(seed)

    def u(r):
        return float(rng.uniform(r[0], r[1])) if r[0] < r[1] else float(r[0])

    c = cfg["camera"]
    rng_m = u(c["range_m"])
    fov_v = 2 * math.degrees(math.atan(0.5 * SUBJECT_HEIGHT_M / c["subject_fraction"] / rng_m))
    fov_h = 2 * math.degrees(math.atan(math.tan(math.radians(fov_v) / 2) * c["width"] / c["height"]))
    camera = {"zenith_deg": u(c["zenith_deg"]), "azimuth_deg": u(c["azimuth_deg"]) % 360.0, "range_m": rng_m,
              "width": c["width"], "height": c["height"], "fov_deg": fov_h}
    s = cfg["subject"]
    if s["meshes"]:
        subject = {"kind": "file", "path": s["meshes"][int(rng.integers(len(s["meshes"])))]}
    else:
        subject = {"kind": "anny", "phenotype": {k: u(s[k]) for k in ("gender", "age", "muscle", "weight",
                                                                       "height", "proportions")},
                   "head_yaw_deg": u(s["head_yaw_deg"]), "head_pitch_deg": u(s["head_pitch_deg"])}
    subject["yaw_deg"] = u(s["yaw_deg"]) % 360.0
    sn = cfg["sun"]
    suns = [{"zenith_deg": u(sn["zenith_deg"]), "azimuth_deg": u(sn["azimuth_deg"]) % 360.0}
            for _ in range(sn["per_pose"])]
    skins, skin_types = tissue.sample(cfg["skin"]["per_pose"], rng, cfg["skin"]["types"], dtype=torch.float64)
    a = cfg["atmosphere"]
    atmosphere = {"transmittance": u(a["transmittance"]), "path_radiance_scale": u(a["path_radiance_scale"])}
    sensor = {"noise": cfg["sensor"]["noise"], "read_noise_e": u(cfg["sensor"]["read_noise_e"]),
              "seed": int(rng.integers(2**31))}
    kinds = cfg["panels"]["kinds"]
    panels = kinds[int(rng.integers(len(kinds)))]
    lo, hi = cfg["confusers"]["count"]
    count = int(rng.integers(int(lo), int(hi) + 1))
    confusers = []
    if count:
        from ..confusers import library

        names = library(cfg["confusers"]["partition"])[0]
        for _ in range(count):
            ang, dist = float(rng.uniform(0, 2 * math.pi)), float(rng.uniform(0.6, 1.2))
            confusers.append({"name": names[int(rng.integers(len(names)))], "x": dist * math.cos(ang),
                              "y": dist * math.sin(ang), "size": 0.5})
    clothing = ""
    if cfg["clothing"]["partition"] != "fixed":
        from ..confusers import clothing_library

        wardrobe = list(clothing_library(cfg["clothing"]["partition"]))
        clothing = wardrobe[int(rng.integers(len(wardrobe)))]
    lc = cfg["light"]
    light = {"model": lc["model"], **{k: u(lc[k]) for k in LIGHT_ATMOSPHERE}, "sky_fraction": u(lc["sky_fraction"])}
    lo_d, hi_d = lc["day_of_year"]  # a whole day inside the configured range (resolve_config: there is one)
    light["day_of_year"] = int(min(max(round(light["day_of_year"]), math.ceil(lo_d)), math.floor(hi_d)))
    return PoseGroup(index, seed, camera, subject, suns, skins, skin_types, atmosphere, sensor, panels, confusers, clothing,
                     cfg["skin"]["surface"], light, cfg["ground"]["brdf"],
                     config_bands(cfg) if "bands" in cfg else INDEX_BANDS)


#: the ``light`` keys that are ``scene.Atmosphere`` fields (the others take its defaults)
LIGHT_ATMOSPHERE = ("aerosol_500nm", "precipitable_water_cm", "ozone_atm_cm", "pressure_pa", "day_of_year")

"""Generate labelled pixel samples: pose groups -> one ray cast each -> every sun x skin shaded -> balanced
skin / non-skin pixels -> Parquet shards with a manifest (checksums), resumable and verifiable.

Layout of an output folder:
    _manifest.json           schema version, package version, resolved config, band set, master seed, shards
    shard-00000.parquet ...  one row per sampled pixel (``dataset.schema.columns_for`` the config's bands)

The band set is the config's ``[bands] spec``; with the index bands, the default, the columns are ``COLUMNS``.

Every shard holds ``sampling.groups_per_shard`` consecutive pose groups; a shard depends only on the config,
the master seed and its index, so runs are bit-identical whatever the worker count or order, and an
interrupted run resumes by regenerating the shards whose checksum does not match.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import cast

import numpy as np
import torch

from .. import __version__
from ..bands import INDEX_BANDS_NM, BandSet, PerBand, at_wavelengths, band_sampling, scene_bands
from ..errors import check_folder_empty
from ..io import atomic_path, write_text
from ..render.elm import (
    ELM_MAX_IRRADIANCE_RATIO,
    ELM_MIN_SUNLIT,
    panel_irradiance_ratio,
    panel_normals,
    panel_pixels,
    panel_subset,
)
from ..render.kernels import cos_to
from ..render.light import LightTables, path_terms
from ..render.meshes import anny_batch
from ..render.pipeline import render, render_pixels, scene_light
from ..render.raycast import GBuffer, Raycaster
from ..render.rtlsr import RHO_MAX
from ..render.scene import Atmosphere, Camera, Material, MeshSpec, Scene, Sun, panel_materials, reference_panels
from ..render.sensor import Sensor
from .config import LIGHT_ATMOSPHERE, PoseGroup, config_bands, default_config, sample_group
from .files import IMAGES_DIR, MANIFEST, RENDER_REVISION, dataset_files, intact, sha256_file, shard_name
from .images import frame_cubes, write_images
from .ray_backend import _run_ray, wait_for_cluster
from .ray_backend import ray_endpoint as ray_endpoint
from .rows import NO_DAY_OF_YEAR as NO_DAY_OF_YEAR
from .rows import PHENOTYPES as PHENOTYPES
from .rows import SHARE_BANDS as SHARE_BANDS
from .rows import PixelLabels as PixelLabels
from .rows import atmosphere_columns as atmosphere_columns
from .rows import band_position as band_position
from .rows import configuration_rows, line_valid, pixel_labels, share_bands
from .rows import pixel_angles_deg as pixel_angles_deg
from .rows import sky_fraction as sky_fraction
from .rows import stored_indices as stored_indices
from .rows import strings as strings
from .schema import SCHEMA_VERSION, columns_for

SUBJECT_TARGET_Z = 0.9  # cameras aim here (mid-body)
#: a dataset's sky view: rays per sampled pixel (``render.raycast.SKY_RAYS``), not the per-geometry field that
#: ``render`` uses: a pose group renders a few hundred pixels of its meshes, whose rays cost a fraction of casting
#: the field over every surface (``docs/guide/rendering.md``); its frames (``--images``) use the same rays
SKY_VIEW = "rays"
#: the ground's reflectance (white-sky albedo for "rtlsr") at 544, 633, 1080, 1580 nm: a bare soil
GROUND_REFLECTANCE = [0.12, 0.16, 0.30, 0.28]
#: the reference panels' interior pixels a group renders for its ELM medians (per panel, a regular sample:
#: ``elm.panel_subset``); the median ELM reflectance moves by ~0.2 % against the whole interior
PANEL_SAMPLE = 256
#: a shard's anny bodies are built this many at a time in one batched anny call (``meshes.anny_batch``): ~4 ms a
#: body instead of ~20 ms one by one, and memory bounded whatever ``sampling.groups_per_shard`` says
BODY_BATCH = 16
#: the clothing reflectance at 544, 633, 1080, 1580 nm when the config's clothing partition is "fixed"
FIXED_CLOTHING = [0.12, 0.10, 0.35, 0.30]


def _arrow_schema(columns: dict[str, tuple[str, str, str]]):
    import pyarrow as pa

    types = {"bool": pa.bool_(), "string": pa.string()}
    return pa.schema([(k, types.get(v[0]) or getattr(pa, v[0])()) for k, v in columns.items()])


#: the steepest view onto a reference panel, degrees from its normal (level panels up to this camera zenith)
PANEL_MAX_VIEW_DEG = 70.0


def panel_tilt_deg(camera_zenith_deg: float) -> float:
    """``MeshSpec.tilt_deg`` of the reference panels (90: level; smaller: turned towards the camera). Level
    while the camera sees them at most ``PANEL_MAX_VIEW_DEG`` from their normal; beyond, tilted just enough to
    keep that view angle (a horizontal camera sees level panels edge-on: no ELM), so a sun lower than
    90° - PANEL_MAX_VIEW_DEG behind them may leave them unlit (``elm_valid`` false)."""
    return 90.0 - max(0.0, float(camera_zenith_deg) - PANEL_MAX_VIEW_DEG)


def group_scene(group: PoseGroup) -> Scene:
    """The scene of a pose group: subject at the origin (yawed), two reference panels beside it on 0.8 m
    stands, level as panels are laid out for ELM in the field (every sun above the horizon lights them unless
    the subject shadows them) and tilted towards cameras lower than 20° elevation (``panel_tilt_deg``), a
    ground plane, the group's camera and suns. The skin material is set per skin later."""
    cam_cfg, subject = group.camera, group.subject
    cam = Camera(width=cam_cfg["width"], height=cam_cfg["height"], zenith_deg=cam_cfg["zenith_deg"],
                 azimuth_deg=cam_cfg["azimuth_deg"], range_m=cam_cfg["range_m"],
                 target=[0.0, 0.0, SUBJECT_TARGET_Z], fov_deg=cam_cfg["fov_deg"])
    from ..confusers import spectrum

    # earthlib spectra on the bands' sampling grid (their centres for monochromatic bands; a wide band's response
    # sampled every nm): the renderer averages them over each band (materials.band_reflectance). The fixed spectra
    # are at the INDEX_BANDS_NM, interpolated in wavelength for any bands (bands.at_wavelengths)
    grid = band_sampling(list(group.bands), dtype=torch.float64)[0].tolist()
    clothing = at_wavelengths(spectrum(group.clothing, grid), grid) if group.clothing else \
        at_wavelengths(FIXED_CLOTHING)
    mats = {"skin": Material("skin", skin="I-II", surface=group.surface),
            "clothing": Material("lambertian", reflectance=clothing),
            "ground": Material(group.ground_brdf, reflectance=at_wavelengths(GROUND_REFLECTANCE)),
            **panel_materials(group.panels)}
    if subject["kind"] == "anny":
        phenotype, pose = group_body(group)
        body = MeshSpec("subject", "anny", "skin", params={"phenotype": phenotype, "pose": pose, "cache": False},
                        yaw_deg=subject["yaw_deg"], other_material="clothing")
    else:
        body = MeshSpec("subject", "file", "skin", params={"path": subject["path"]}, yaw_deg=subject["yaw_deg"])
    panels = reference_panels(cam_cfg["azimuth_deg"], panel_tilt_deg(cam_cfg["zenith_deg"]), size_m=0.5,
                              height_m=0.8)
    ground = MeshSpec("ground", "ground", "ground", params={"size": 40.0})
    confusers = []
    for k, c in enumerate(group.confusers):  # flat patches on the ground around the subject
        refl = spectrum(c["name"], grid)
        # "rtlsr" where its energy bound allows (rtlsr.RHO_MAX): brighter spectra stay Lambertian
        kind = group.ground_brdf if max(refl) <= RHO_MAX else "lambertian"
        mats[f"confuser{k}"] = Material(kind, reflectance=at_wavelengths(refl, grid))
        confusers.append(MeshSpec(f"confuser{k}", "plane", f"confuser{k}",
                                  params={"width": c["size"], "height": c["size"]},
                                  position=[c["x"], c["y"], 0.002 * (k + 1)], tilt_deg=90.0))
    atm = Atmosphere(**{k: group.light[k] for k in LIGHT_ATMOSPHERE})
    thesis = group.light["model"] == "thesis"
    suns = [Sun(zenith_deg=s["zenith_deg"], azimuth_deg=s["azimuth_deg"], atmosphere=atm,
                sky_fraction=group.light["sky_fraction"] if thesis else 0.0) for s in group.suns]
    return Scene(mats, [body, *panels, ground, *confusers], [cam], suns, illumination=group.light["model"],
                 bands=scene_bands(group.bands))


def group_body(group: PoseGroup) -> tuple[dict, dict]:
    """The anny phenotype and pose of a pose group's subject (an anny subject only)."""
    subject = group.subject
    return subject["phenotype"], {"head": [subject["head_pitch_deg"], 0.0, subject["head_yaw_deg"]]}


def group_sensor(group: PoseGroup, light: LightTables | None = None) -> Sensor:
    """The sensor of a pose group: its noise draw, read noise and path. Under a light model with an atmosphere
    ("spectrl2") the path's transmittance and airlight come from it (``light.path_terms``, the airlight of the
    group's suns' mean isotropic sky, ``light``: the scene's light tables) and the airlight is scaled by
    ``path_radiance_scale``; under "thesis" the drawn transmittance and the sensor default's airlight, scaled."""
    scale = group.atmosphere["path_radiance_scale"]
    path: PerBand
    if group.light["model"] == "spectrl2" and light is not None:
        atm = Atmosphere(**{k: group.light[k] for k in LIGHT_ATMOSPHERE})
        p = path_terms(atm, light.sky.double().mean(0).tolist(), list(group.bands), group.camera["range_m"])
        tau, path = p["atmosphere_transmittance"], [x * scale for x in p["path_radiance"]]
    else:
        default = cast(dict, Sensor().path_radiance)  # a spectrum at the INDEX_BANDS_NM (bands.at_wavelengths)
        tau = group.atmosphere["transmittance"]
        path = at_wavelengths([p * scale for p in default["values"]], default["wavelengths_nm"])
    return Sensor(noise=group.sensor["noise"], read_noise_e=group.sensor["read_noise_e"], seed=group.sensor["seed"],
                  atmosphere_transmittance=tau, path_radiance=path)


def panels_sunlit(gb: GBuffer, panel_names: list[str], sun_dirs: torch.Tensor,
                  min_fraction: float = ELM_MIN_SUNLIT, pixels: list[list[torch.Tensor]] | None = None) -> torch.Tensor:
    """Per sun (S,): whether every reference panel has at least ``min_fraction`` of its interior pixels
    sunlit (facing the sun and not in a cast shadow). Without sunlit panels the ELM gain is set by sky light
    alone and the frame's reflectance is meaningless. ``pixels``: the panels' interior pixels if already found
    (``elm.panel_pixels``)."""
    ok = torch.ones(sun_dirs.shape[0], dtype=torch.bool)
    normal = gb.normal[0].reshape(-1, 3).float()
    shadow = gb.shadow_masks()[:, 0].reshape(sun_dirs.shape[0], -1)
    for per_cam in panel_pixels(gb, panel_names) if pixels is None else pixels:
        ix = per_cam[0]
        lit = (cos_to(normal[ix], sun_dirs.to(normal.dtype)) > 0) & ~shadow[:, ix]  # (S, K)
        ok &= lit.float().mean(1) >= min_fraction
    return ok


def group_rows(group: PoseGroup, pixels_per_class: int, device: torch.device | str = "cpu",
               images: list | None = None, compile: bool = False) -> dict[str, list]:
    """Rows for every sun x skin of a pose group, as column -> list of numpy chunks: ``pixels_per_class`` skin
    and as many non-skin pixels (fewer if fewer are visible; balanced), drawn once for the group, under every
    configuration (sun x skin). With a list ``images``, the full reflectance cubes of the group, (skins, suns,
    bands, H, W) float16, are appended to it, made with the rows' sensor draw (``frame_cubes``: a row is its
    cube's pixel). Shadow and sky rays are cast only for the sampled pixels and the
    panels' capped sample (``PANEL_SAMPLE``; every pixel with ``images``). ``compile``: the renderer's compiled
    kernels (``render.kernels``)."""
    scene = group_scene(group)
    rc = Raycaster.from_scene(scene)
    sun_dirs = torch.tensor(np.stack([s.direction for s in scene.suns]), dtype=torch.float32)
    gb = rc.gbuffer(scene.cameras, sun_dirs.numpy(), compile, shadows=images is not None)
    labels = pixel_labels(group, scene, gb)
    light = scene_light(scene, torch.float64)
    sensor = group_sensor(group, light)
    rng = np.random.default_rng(group.seed)
    out: dict[str, list] = {k: [] for k in columns_for(group.bands)}
    # the panels' interior, capped to a regular sample (PANEL_SAMPLE), found once for the group's renders
    pix = panel_subset(panel_pixels(gb, list(scene.panels)), PANEL_SAMPLE)
    m = min(pixels_per_class, len(labels.skin), len(labels.other))
    n_suns, n_skins = len(group.suns), len(group.skin_types)
    skins = group.skins
    if skins is None:
        raise ValueError(f"pose group {group.index} has no skins")
    if m == 0:
        if images is not None:  # no rows to agree with: the frames' own exposure and noise
            full = render(scene, device=device, sensor=sensor, gbuffer=gb, raycaster=rc, skins=skins,
                          panel_pixels=pix, compile=compile, sky_view=SKY_VIEW)
            cube = full.reflectance[:, 0].permute(0, 3, 1, 2).cpu().numpy().astype(np.float16)
            images.append(cube.reshape(n_skins, n_suns, *cube.shape[1:]))
        return out
    # one set of pixels for the whole group (m skin, m other), shaded under every sun x skin in one batch: only the
    # kept pixels are shaded (each configuration's rows are these pixels under its sun and skin)
    picks = np.concatenate([rng.choice(labels.skin, m, replace=False), rng.choice(labels.other, m, replace=False)])
    res = render_pixels(scene, torch.from_numpy(picks), device=device, sensor=sensor, gbuffer=gb, skins=skins,
                        panel_pixels=pix, raycaster=rc, compile=compile,
                        irradiance=list(share_bands(group.bands).values()) or None, light=light, sky_view=SKY_VIEW)
    if images is not None:  # full frames of every skin x sun in one batch, with the rows' exposure, noise and ELM
        cube = frame_cubes(scene, gb, rc, sensor, skins, pix, picks, res, device, compile)
        images.append(cube.reshape(n_skins, n_suns, *cube.shape[1:]))
    sub = res.gbuffer  # the rendered pixels' G-buffer, shadows cast; rows skin-major, the first n_suns: skin 0
    sunlit = panels_sunlit(dataclasses.replace(sub, shadow=cast(torch.Tensor, sub.shadow)[:n_suns]).to("cpu"),
                           list(scene.panels), sun_dirs, pixels=[[ix.cpu() for ix in p] for p in res.panel_pixels])
    n_cfg = n_suns * n_skins
    ratio = panel_irradiance_ratio(light.beam, light.sky, sun_dirs.double(), panel_normals(gb, pix).double()).numpy()
    sun_of = np.arange(n_cfg) % n_suns
    line_ok = sunlit.numpy()[sun_of] & line_valid(res, sensor)  # per configuration
    elm_valid = line_ok & (ratio <= ELM_MAX_IRRADIANCE_RATIO)[sun_of]
    rows = configuration_rows(group, res, np.tile(picks, n_cfg), np.tile(np.arange(2 * m), n_cfg), gb, sun_dirs,
                              labels, elm_valid, light, sensor, ratio, line_ok)
    return {k: [v] for k, v in rows.items()}


# -------------------------------------------------------------------------------------------------- shards
def write_shard(out_dir: Path, k: int, rows: dict[str, list], bands: BandSet | None = None) -> dict:
    """Write one shard atomically (temporary name, fsync, rename) of a dataset of ``bands`` (default the index
    bands; its columns: ``schema.columns_for``); return its manifest entry."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    columns = columns_for(bands or BandSet.of(INDEX_BANDS_NM))
    schema = _arrow_schema(columns)
    cols = {}
    for c in columns:
        chunks = rows[c]
        if schema.field(c).type == pa.string():  # dictionary chunks (``strings``) or object arrays
            cols[c] = pa.concat_arrays([x.cast(pa.string()) if isinstance(x, pa.Array)
                                        else pa.array(np.asarray(x, dtype=object), type=pa.string()) for x in chunks]) \
                if chunks else pa.array([], type=pa.string())
            continue
        arr = np.concatenate(chunks) if chunks else np.zeros(0)
        cols[c] = pa.array(arr, type=schema.field(c).type)
    table = pa.table(cols, schema=schema)
    path = out_dir / shard_name(k)
    with atomic_path(path, suffix=".tmp") as tmp:
        # dictionary pages for the string columns only: trying them on the float columns (the default) tripled the
        # write time and grew the file
        pq.write_table(table, tmp, compression="zstd", write_statistics=False,
                       use_dictionary=[c for c in columns if columns[c][0] == "string"])
    return {"name": path.name, "rows": table.num_rows, "sha256": sha256_file(path), "bytes": path.stat().st_size}


def plan(cfg: dict, n_configs: int) -> tuple[int, int]:
    """(number of pose groups, number of shards) for ``n_configs`` configurations (group x sun x skin)."""
    if n_configs < 1:
        raise ValueError(f"--configs must be >= 1, got {n_configs}")
    per_group = cfg["sun"]["per_pose"] * cfg["skin"]["per_pose"]
    groups = math.ceil(n_configs / per_group)
    return groups, math.ceil(groups / cfg["sampling"]["groups_per_shard"])


def shard_groups(cfg: dict, k: int, n_groups: int) -> range:
    gps = cfg["sampling"]["groups_per_shard"]
    return range(k * gps, min((k + 1) * gps, n_groups))


def generate_shard(cfg: dict, seed: int, k: int, n_groups: int, out_dir: Path, device: torch.device | str = "cpu",
                   images: bool = False, compile: bool = False) -> dict:
    """Generate and write shard ``k`` (a pure function of config, seed and k); with ``images`` also the
    full reflectance cubes of its groups; ``compile``: with the renderer's compiled kernels."""
    bands = config_bands(cfg)
    columns = columns_for(bands)
    rows: dict[str, list] = {c: [] for c in columns}
    cubes: list | None = [] if images else None
    ids = shard_groups(cfg, k, n_groups)
    for lo in range(0, len(ids), BODY_BATCH):  # anny bodies built BODY_BATCH at a time (the same bits in any batch)
        groups = [sample_group(cfg, seed, gi) for gi in ids[lo:lo + BODY_BATCH]]
        with anny_batch([group_body(g) for g in groups if g.subject["kind"] == "anny"]):
            for group in groups:
                part = group_rows(group, cfg["sampling"]["pixels_per_class"], device, cubes, compile)
                for c in columns:
                    rows[c].extend(part[c])  # lists of numpy chunks
    entry = {**write_shard(out_dir, k, rows, bands), "compiled": compile}
    if cubes is not None:
        entry["images"] = write_images(out_dir, k, cubes)
    return entry


def _manifest(cfg, seed, n_configs, n_groups, n_shards, done: dict[int, dict], images: bool = False) -> dict:
    per_group = cfg["sun"]["per_pose"] * cfg["skin"]["per_pose"]
    bands = config_bands(cfg)
    return {"schema_version": SCHEMA_VERSION, "render_revision": RENDER_REVISION, "package_version": __version__,
            "config": cfg, "master_seed": seed, "light_model": cfg["light"]["model"],
            "configs": n_groups * per_group, "requested_configs": n_configs, "groups": n_groups,
            "n_shards": n_shards, "images": images, "bands": json.loads(bands.to_json()),
            "columns": {k: {"type": v[0], "description": v[1], "unit": v[2]} for k, v in columns_for(bands).items()},
            "shards": [done[k] for k in sorted(done)]}


#: the measured size of a row in a Parquet shard (zstd): 26-27 bytes on the default config, rounded up; with the
#: shards' fixed overhead, what ``estimate_bytes`` counts per row
ROW_BYTES = 32
#: what each band beyond the index bands' four adds to a row: a float32 reflectance, at most (zstd compresses
#: little of a noisy reflectance)
BAND_BYTES = 4
#: bytes a shard takes whatever its rows (Parquet footer and metadata), and the manifest's entry for it
SHARD_OVERHEAD_BYTES = 64 * 1024


def estimate_bytes(cfg: dict, n_configs: int, images: bool = False, shards: Sequence[int] | None = None) -> int:
    """The bytes ``generate`` will write for ``n_configs`` configurations of ``cfg`` (or only for the shard indices
    ``shards``): ``ROW_BYTES`` per row (and ``BAND_BYTES`` for each band beyond the index bands' four), 2 x
    ``pixels_per_class`` rows a configuration at most, plus ``SHARD_OVERHEAD_BYTES`` a shard; with ``images`` the
    float16 cubes (skins x suns x bands x H x W x 2 bytes a pose group), which are stored uncompressed.

    >>> from torchskin.dataset.config import default_config
    >>> estimate_bytes(default_config(), 48) // 2**20  # 48 configurations: one pose group, 256 rows each
    0
    >>> estimate_bytes(default_config(), 10**9) // 10**12  # terabytes
    8
    """
    n_groups, n_shards = plan(cfg, n_configs)
    ks = range(n_shards) if shards is None else shards
    groups = sum(len(shard_groups(cfg, k, n_groups)) for k in ks)
    per_group = cfg["sun"]["per_pose"] * cfg["skin"]["per_pose"]
    rows = groups * per_group * 2 * cfg["sampling"]["pixels_per_class"]
    n_bands = len(config_bands(cfg)) if "bands" in cfg else len(INDEX_BANDS_NM)
    total = rows * (ROW_BYTES + BAND_BYTES * max(0, n_bands - len(INDEX_BANDS_NM))) + len(ks) * SHARD_OVERHEAD_BYTES
    if images:
        total += groups * per_group * n_bands * cfg["camera"]["width"] * cfg["camera"]["height"] * 2
    return total


def check_disk_space(out_dir: str | os.PathLike, need: int, reclaim: int = 0) -> None:
    """Raise ``ValueError`` (one line) when ``need`` bytes exceed the free space of the filesystem that holds
    ``out_dir`` (its nearest existing folder) plus ``reclaim`` bytes that will be deleted first."""
    import shutil

    p = Path(out_dir).absolute()
    while not p.exists() and p != p.parent:
        p = p.parent
    free = shutil.disk_usage(p).free + reclaim
    if need > free:
        raise ValueError(f"--configs: the dataset would take about {need / 1e9:.3g} GB, but {str(p)!r} has "
                         f"{free / 1e9:.3g} GB free: ask for fewer configurations or another --out")


def _ray_shard(cfg, seed, k, n_groups, out_dir, device, images, compile):
    return generate_shard(cfg, seed, k, n_groups, Path(out_dir), device, images, compile)


#: ``generate(compile="auto")`` compiles the renderer's kernels for runs of at least this many configurations: on
#: a 2-core CPU compiling costs 5-25 s (warm or cold Inductor cache) and, since schema 5 (~768 pixels shaded per
#: pose group), saves little: within +-10 % of eager
COMPILE_MIN_CONFIGS = 20_000


def resolve_compile(compile: bool | str, n_configs: int, device: torch.device | str = "cpu") -> bool:
    """``compile`` as a bool: "auto" is True when a compiler serves ``device`` and the run has at least
    ``COMPILE_MIN_CONFIGS`` configurations."""
    from ..render.kernels import compiler_available

    if compile == "auto":
        return n_configs >= COMPILE_MIN_CONFIGS and compiler_available(device)
    if not isinstance(compile, bool):
        raise ValueError(f"compile must be True, False or 'auto', got {compile!r}")
    if compile and not compiler_available(device):
        warnings.warn(f"no compiler for {device}: generating with the eager kernels", RuntimeWarning, stacklevel=3)
        return False
    return compile


def same_draw(old: dict, cfg: dict, seed: int, n_configs: int) -> bool:
    """Whether the dataset whose manifest is ``old`` was drawn from the resolved config ``cfg``, ``seed`` and
    ``n_configs`` configurations (what ``--resume`` requires; a manifest written before ``[bands]``: the index
    bands)."""
    old_cfg = old.get("config")
    if isinstance(old_cfg, dict) and "bands" not in old_cfg:
        old_cfg = {**old_cfg, "bands": default_config()["bands"]}
    return (old_cfg == cfg and old.get("master_seed") == seed
            and old.get("requested_configs", old.get("configs")) == n_configs)


def generate(cfg: dict, n_configs: int, seed: int, out_dir: str | os.PathLike, *, resume: bool = False,
             overwrite: bool = False, quiet: bool = False, device: torch.device | str = "cpu", backend: str = "local", address: str | None = None,
             workers: int | None = None, images: bool = False, compile: bool | str = False) -> dict:
    """Generate a dataset into ``out_dir``. Returns the manifest.

    ``backend="local"`` runs the shards in this process; ``backend="ray"`` runs one Ray task per shard on the
    cluster at ``address`` (a local cluster of ``workers`` CPUs when None; GPUs requested when ``device`` is
    cuda); a cluster that accepts no connection within ``ray_backend.RAY_CONNECT_TIMEOUT_S`` (30 s) is an error. Ray tasks write their shards themselves, so on a multi-machine cluster ``out_dir`` must be a
    shared filesystem. Both backends give the same bytes. ``images`` also stores every group's full
    reflectance cubes in ``images-NNNNN.npy`` shards (much larger, and slower: full frames are rendered).
    ``compile``: render with the compiled kernels (``render.kernels``; "auto": for runs of at least
    ``COMPILE_MIN_CONFIGS`` configurations); compiled and eager shards agree to ~1e-5 but not bit for bit: each
    shard's manifest entry records which ran, and the manifest's ``compiled`` whether all shards were compiled."""
    if backend not in ("local", "ray"):
        raise ValueError(f"backend must be 'local' or 'ray', got {backend!r}")
    out = Path(out_dir)
    n_groups, n_shards = plan(cfg, n_configs)
    compile = resolve_compile(compile, n_configs, device)
    if out.exists() and not out.is_dir():
        raise ValueError(f"output {str(out)!r} exists and is not a folder")
    existing = [p for p in out.iterdir()] if out.is_dir() else []
    check_folder_empty(out, "output", resume or overwrite, "--resume to continue")
    reclaim = sum(p.stat().st_size for p in dataset_files(out)) if existing and overwrite and not resume else 0
    if not resume:  # a resumed run checks once it knows which shards are still to write
        check_disk_space(out, estimate_bytes(cfg, n_configs, images), reclaim)
    done: dict[int, dict] = {}
    if existing and overwrite and not resume:
        for p in dataset_files(out):
            if p.name == MANIFEST or p.name.startswith(("shard-", ".shard-", "images-", ".images-")):
                p.unlink()
        if (out / IMAGES_DIR).is_dir() and not any((out / IMAGES_DIR).iterdir()):
            (out / IMAGES_DIR).rmdir()
    if existing and resume and (out / MANIFEST).is_file():
        old = json.loads((out / MANIFEST).read_text())
        if old.get("schema_version") != SCHEMA_VERSION:
            raise ValueError(f"--resume: {str(out)!r} holds a dataset of schema {old.get('schema_version')}, this "
                             f"torchskin writes schema {SCHEMA_VERSION} (other rows for the same seed): regenerate it "
                             "with --overwrite")
        if not same_draw(old, cfg, seed, n_configs):
            raise ValueError("--resume needs the same config, seed and --configs as the interrupted run")
        if bool(old.get("images")) != images:
            raise ValueError("--resume needs the same --images setting as the interrupted run")
        if old.get("render_revision", 1) != RENDER_REVISION:
            raise ValueError(f"--resume: {str(out)!r} was rendered by renderer revision {old.get('render_revision', 1)}, "
                             f"this torchskin renders revision {RENDER_REVISION} (other bytes for the same seed): "
                             "regenerate it with --overwrite")
        for s in old["shards"]:
            if all(intact(out, e) for e in (s, s.get("images")) if e):
                done[int(s["name"][6:11])] = s
    if resume:
        check_disk_space(out, estimate_bytes(cfg, n_configs, images, [k for k in range(n_shards) if k not in done]))
    for p in (dataset_files(out) if out.is_dir() else []):
        if p.name.startswith((".shard-", ".images-")):  # temporaries of a killed run
            p.unlink()
    if backend == "ray" and address:  # before the folder is made: a cluster that is not there fails in bounded time
        import ray  # noqa: F401 - the ray extra: a ModuleNotFoundError names it (errors.missing_extra)

        wait_for_cluster(address)
    created = not out.exists()
    had_manifest = (out / MANIFEST).exists()  # else a failure before the first shard leaves the folder as it was
    out.mkdir(parents=True, exist_ok=True)
    if not os.access(out, os.W_OK):
        raise ValueError(f"output folder {str(out)!r} is not writable")
    try:
        return _generate_into(out, cfg, n_configs, seed, n_groups, n_shards, done, quiet, device, backend, address,
                              workers, images, compile)
    except BaseException:
        if not had_manifest and not done:  # no shard finished: remove the manifest (and the folder we made)
            (out / MANIFEST).unlink(missing_ok=True)
            if created and not any(out.iterdir()):
                out.rmdir()
        raise


def _generate_into(out: Path, cfg, n_configs, seed, n_groups, n_shards, done, quiet, device, backend, address,
                   workers, images, compile) -> dict:
    def manifest() -> dict:  # "compiled": every shard rendered with the compiled kernels (each shard says so too)
        every = all(e.get("compiled", False) for e in done.values()) if done else compile
        return {**_manifest(cfg, seed, n_configs, n_groups, n_shards, done, images), "compiled": every}

    write_text(out / MANIFEST, json.dumps(manifest(), indent=1))
    from tqdm import tqdm

    per_group = cfg["sun"]["per_pose"] * cfg["skin"]["per_pose"]

    def per_shard(k: int) -> int:  # configurations of shard k (the last shard may hold fewer groups)
        return len(shard_groups(cfg, k, n_groups)) * per_group

    todo = [k for k in range(n_shards) if k not in done]

    def record(k, entry):
        done[k] = entry
        write_text(out / MANIFEST, json.dumps(manifest(), indent=1))

    with tqdm(total=n_groups * per_group, initial=sum(per_shard(k) for k in done), unit="config",
              disable=quiet, desc="generate") as bar:
        if backend == "local":
            for k in todo:
                try:
                    entry = generate_shard(cfg, seed, k, n_groups, out, device, images, compile)
                except OSError as e:  # full disk, permissions: the temporary shard is already removed
                    raise ValueError(f"writing {shard_name(k)} into {str(out)!r} failed: {e.strerror or e}") from None
                record(k, entry)
                bar.update(per_shard(k))
        else:
            _run_ray(_ray_shard, cfg, seed, todo, n_groups, out, device, address, workers, images, compile,
                     lambda k, e: (record(k, e), bar.update(per_shard(k))))
    return manifest()

"""The thesis experiment (section 3.4, chapter 4) and Appendix C, rendered with every skin model.

A Type I/II subject faces the camera at 31 ft (9.449 m) with reference panels beside the head; a sun-like
directional source sits in the horizontal plane 10, 30, 60 and 85 degrees off the camera axis. For each
angle: calibrated reflectance images, the rules-detector scatter of sunlit skin pixels, 2-D NDSI x NDGRI
histograms, for the diffuse-only model (the Lambertian skin that set the box) and the combined model of
eq 3.1.1 under both skin surface models ("thesis": ρ_d with the front surface, as the thesis defines it;
"conserving": the subsurface part only; ``optics.skin_diffuse``); and the Bhattacharyya coefficient between
the diffuse-only and each combined model's histograms.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from .bands import at_wavelengths
from .detect import DEFAULT_BOX, bhattacharyya, histogram2d
from .io import write_text
from .optics import DEFAULT_SURFACE, SURFACE_MODELS, check_surface
from .render.elm import apply_elm, panel_pixels, panel_references, panel_values
from .render.materials import compile_materials
from .render.pipeline import render
from .render.raycast import rasterize
from .render.scene import Camera, Material, MeshSpec, Scene, Sun, panel_materials
from .render.sensor import Sensor

ANGLES_DEG = (10.0, 30.0, 60.0, 85.0)
HIST_BINS = 48
HIST_RANGE_NDGRI = (-1.0, 0.5)
HIST_RANGE_NDSI = (-0.2, 1.0)


#: the models rendered side by side: the diffuse-only skin and eq 3.1.1 under each surface model
MODELS = ("diffuse", *SURFACE_MODELS)


def experiment_scene(angles: Sequence[float] = ANGLES_DEG, skin: str | dict = "I-II", diffuse_only: bool = False,
                     width: int = 512, height: int = 512, panels: str = "lambertian",
                     surface: str = DEFAULT_SURFACE) -> Scene:
    """The thesis experiment's scene (section 3.4): an anny subject facing a horizontal camera at 9.449 m, two
    0.3 m reference panels beside its head, and one horizontal source per angle of ``angles`` (azimuth from the
    subject's facing direction, degrees)."""
    mats = {
        "skin": Material("skin", skin=skin, specular=not diffuse_only, surface=surface),
        "clothing": Material("lambertian", reflectance=at_wavelengths([0.12, 0.10, 0.35, 0.30])),  # INDEX_BANDS_NM
        **panel_materials(panels),
    }
    meshes = [
        MeshSpec("subject", "anny", "skin", other_material="clothing"),
        MeshSpec("panel_white", "plane", "white", params={"width": 0.3, "height": 0.3}, position=[0.0, 0.42, 1.4]),
        MeshSpec("panel_dark", "plane", "dark", params={"width": 0.3, "height": 0.3}, position=[0.0, -0.42, 1.4]),
    ]
    cam = Camera(width=width, height=height, zenith_deg=90.0, azimuth_deg=0.0, range_m=9.449,
                 target=[0.0, 0.0, 1.3], fov_deg=6.5)
    suns = [Sun(zenith_deg=90.0, azimuth_deg=float(a)) for a in angles]
    return Scene(mats, meshes, [cam], suns, illumination="thesis")  # the thesis's lab lamp


def appendix_c(sensor: Sensor | None = None, width: int = 192, height: int = 96) -> float:
    """Appendix C: Lambertian panels 0.97 and 0.02 with a 0.40 panel between them, source and camera normal
    to the panels. Returns the median ELM reflectance of the middle panel (mean over bands)."""
    mats = {"white": Material("lambertian", reflectance=0.97), "dark": Material("lambertian", reflectance=0.02),
            "mid": Material("lambertian", reflectance=0.40)}
    meshes = [
        MeshSpec("panel_white", "plane", "white", params={"width": 1.0, "height": 1.0}, position=[0.0, 1.1, 0.5]),
        MeshSpec("middle", "plane", "mid", params={"width": 1.0, "height": 1.0}, position=[0.0, 0.0, 0.5]),
        MeshSpec("panel_dark", "plane", "dark", params={"width": 1.0, "height": 1.0}, position=[0.0, -1.1, 0.5]),
    ]
    cam = Camera(width=width, height=height, zenith_deg=90.0, azimuth_deg=0.0, range_m=9.449,
                 target=[0.0, 0.0, 1.0], fov_deg=21.0)
    sc = Scene(mats, meshes, [cam], [Sun(zenith_deg=90.0, azimuth_deg=0.0)], illumination="thesis")
    res = render(sc, sensor=sensor)
    k = res.gbuffer.mesh_names.index("middle")
    mid = res.gbuffer.mesh[0] == k
    return float(res.reflectance[0, 0][mid].median(dim=0).values.mean())


def run(out_dir: str | Path, angles: Sequence[float] = ANGLES_DEG, width: int = 512, height: int = 512,
        sensor: Sensor | None = None, device: torch.device | str = "cpu", panels: str = "lambertian", surface: str = DEFAULT_SURFACE) -> dict:
    """Run the experiment, write its figures and ``experiment.json`` into ``out_dir``; return the summary.

    Three skin models share one ray cast: "diffuse" (diffuse-only), "thesis" and "conserving" (eq 3.1.1 under
    each skin surface model, ``optics.skin_diffuse``). ``surface`` names the combined model reported as
    ``detected_fraction_combined`` and ``bhattacharyya`` (default "thesis"); ``detected_fraction_<model>``
    and ``bhattacharyya_<surface>`` hold every model.

    ``panels="spectralon-brdf"`` uses Spectralon-like panels (Table 3 DHR with the Appendix B forward lobe):
    the images are then calibrated with BRDF-ELM, and the summary adds ``lambertian_panel_error``, the
    median relative error per angle and band of skin reflectance when the panels are assumed Lambertian
    (ELM on their DHR) - the error the thesis estimates at up to 4.1 % (VIS) and 7.4 % (NIR) - and
    ``detected_fraction_<model>_lambertian_elm``, the detected fractions with that (plain) ELM."""
    from . import plots

    check_surface(surface)
    sensor = sensor if sensor is not None else Sensor()
    scenes = {m: experiment_scene(angles, diffuse_only=(m == "diffuse"), width=width, height=height,
                                  panels=panels, surface=m if m != "diffuse" else DEFAULT_SURFACE) for m in MODELS}
    elm = "brdf" if panels == "spectralon-brdf" else "dhr"
    gb = rasterize(scenes[surface])
    pix = panel_pixels(gb, list(scenes[surface].panels))  # one geometry for every model
    res = {m: render(sc, device=device, sensor=sensor, gbuffer=gb, elm=elm, panel_pixels=pix) for m, sc in scenes.items()}
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    summary: dict[str, Any] = {"angles_deg": [float(a) for a in angles], "surface": surface, "panels": panels,
               **{f"detected_fraction_{m}": [] for m in MODELS},
               **{f"bhattacharyya_{m}": [] for m in SURFACE_MODELS}, "sunlit_skin_pixels": []}
    hists = {}
    for si, _ in enumerate(angles):
        for m, r in res.items():
            lit = r.skin[0] & r.lit[si, 0]
            summary[f"detected_fraction_{m}"].append(_fraction(r.mask[si, 0], lit))
            hists[(m, si)] = histogram2d(r.ndgri[si, 0][lit], r.ndsi[si, 0][lit], HIST_BINS, HIST_RANGE_NDGRI,
                                         HIST_RANGE_NDSI)
        summary["sunlit_skin_pixels"].append(int((res[surface].skin[0] & res[surface].lit[si, 0]).sum()))
        for m in SURFACE_MODELS:
            h1, h2 = hists[("diffuse", si)], hists[(m, si)]
            bc = float(bhattacharyya(h1, h2)) if float(h1.sum()) > 0 and float(h2.sum()) > 0 else 0.0
            summary[f"bhattacharyya_{m}"].append(bc)
    summary["detected_fraction_combined"] = summary[f"detected_fraction_{surface}"]
    summary["bhattacharyya"] = summary[f"bhattacharyya_{surface}"]
    summary["appendix_c_middle_reflectance"] = appendix_c(sensor)
    if elm == "brdf":
        summary["lambertian_panel_error"] = _lambertian_panel_error(res[surface], scenes[surface], gb)
        for m in MODELS:
            summary[f"detected_fraction_{m}_lambertian_elm"] = _lambertian_elm_detection(res[m], scenes[m], gb)
    _figures(out, angles, res, hists, summary)
    summary["surface_energy"] = plots.surface_energy(out / "surface_energy.png")
    write_text(out / "experiment.json", json.dumps(summary, indent=1))
    return summary


def _fraction(mask: torch.Tensor, where: torch.Tensor) -> float:
    """The fraction of the pixels ``where`` that ``mask`` holds (0 when there are none)."""
    return float(mask[where].float().mean()) if bool(where.any()) else 0.0


def _lambertian_elm(r, scene, gb) -> torch.Tensor:
    """The render ``r`` (made with BRDF-ELM) recalibrated with plain ELM on the panels' DHR."""
    sun_dirs = torch.tensor(np.stack([s.direction for s in scene.suns]), dtype=r.signal.dtype)
    g = gb.to(dtype=r.signal.dtype)
    tables = compile_materials(scene.materials, scene.bands, scene.suns, g.material_names, r.signal.dtype,
                               r.signal.device)
    ids = [g.material_names.index(scene.mesh(p).material) for p in scene.panels]
    refs = panel_references(ids, g, tables, sun_dirs, r.panel_pixels, "dhr")
    return apply_elm(r.signal, panel_values(r.signal, r.panel_pixels), refs)


def _lambertian_elm_detection(r, scene, gb) -> list[float]:
    """Per angle, the sunlit skin fraction inside the box when the panels are taken as Lambertian."""
    from .detect import indices, rules_detector

    g, s = indices(_lambertian_elm(r, scene, gb), r.bands)
    mask = rules_detector(g, s, DEFAULT_BOX)
    return [_fraction(mask[si, 0], r.skin[0] & r.lit[si, 0]) for si in range(mask.shape[0])]


def _lambertian_panel_error(r, scene, gb) -> list[list[float]]:
    """Median |ρ_DHR-ELM / ρ_BRDF-ELM - 1| over sunlit skin pixels, per angle and band."""
    dhr = _lambertian_elm(r, scene, gb)
    out = []
    for si in range(r.signal.shape[0]):
        lit = r.skin[0] & r.lit[si, 0]
        rel = (dhr[si, 0][lit] / r.reflectance[si, 0][lit] - 1).abs()
        out.append(rel.median(dim=0).values.tolist() if rel.numel() else [float("nan")] * rel.shape[-1])
    return out


_LABELS = {"diffuse": "diffuse-only", "thesis": "eq 3.1.1, thesis surface", "conserving": "eq 3.1.1, conserving"}
_COLORS = {"diffuse": "C0", "thesis": "C3", "conserving": "C1"}


def _figures(out: Path, angles, res, hists, summary) -> None:
    """The experiment's four figures."""
    from .plots import pyplot

    plt = pyplot()
    _reflectance_figure(plt, out, angles, res, summary)
    _scatter_figure(plt, out, angles, res, summary)
    _histogram_figure(plt, out, angles, hists)
    _angle_figure(plt, out, angles, summary)


def _reflectance_figure(plt, out: Path, angles, res, summary) -> None:
    """Reflectance images of the chosen combined model: rows = angles, columns = bands, like Figs 29/35."""
    from .plots import save_figure

    surface = summary["surface"]
    # reflectance images of the chosen combined model: rows = angles, columns = bands, like Figs 29/35
    r = res[surface]
    B = r.reflectance.shape[-1]
    fig, axes = plt.subplots(len(angles), B, figsize=(3.0 * B + 1.0, 3.0 * len(angles)), squeeze=False,
                             layout="constrained")
    lo, hi = float(r.reflectance[:, 0].min()), float(r.reflectance[:, 0].max())
    for si, a in enumerate(angles):
        for k in range(B):
            ax = axes[si, k]
            im = ax.imshow(r.reflectance[si, 0, :, :, k].cpu().float().numpy(), cmap="jet", vmin=0, vmax=1)
            ax.set_title(f"{r.bands[k].center_nm:g} nm, source {a:g}°", fontsize=9)
            ax.axis("off")
    fig.colorbar(im, ax=axes, fraction=0.02, extend={(False, False): "neither", (True, False): "min",
                                                     (False, True): "max", (True, True): "both"}[(lo < 0, hi > 1)],
                 label=f"reflectance (ELM; {_LABELS[surface]}); colour clipped to [0, 1];\n"
                       f"images min {lo:.3g}, max {hi:.3g}")
    save_figure(fig, out / "reflectance_combined.png")


def _scatter_figure(plt, out: Path, angles, res, summary) -> None:
    """Sunlit skin in the rules-detector plane, Fig 32/37 style: one row per model."""
    from .plots import rules_scatter, save_figure

    # rules scatter, Fig 32/37 style: one row per model
    fig, axes = plt.subplots(len(MODELS), len(angles), figsize=(3.6 * len(angles), 3.4 * len(MODELS)),
                             sharex=True, sharey=True, squeeze=False)
    for mi, m in enumerate(MODELS):
        rr = res[m]
        for si, a in enumerate(angles):
            lit = rr.skin[0] & rr.lit[si, 0]
            rules_scatter(axes[mi, si], rr.ndgri[si, 0][lit], rr.ndsi[si, 0][lit], DEFAULT_BOX, color=_COLORS[m])
            axes[mi, si].set_title(f"{_LABELS[m]}, {a:g}°: {summary[f'detected_fraction_{m}'][si]:.2f} in box",
                                   fontsize=9)
            axes[mi, si].label_outer()
    fig.suptitle("Sunlit skin pixels in the rules-detector plane (black: rules box, eq 2.5.10)", fontsize=10)
    fig.tight_layout()
    save_figure(fig, out / "rules_scatter.png")


def _histogram_figure(plt, out: Path, angles, hists) -> None:
    """2-D NDSI x NDGRI histograms, Fig 33/38 style: counts per bin (log colour scale), the box drawn."""
    from matplotlib.colors import LogNorm
    from matplotlib.patches import Rectangle

    from .plots import save_figure

    # 2-D histograms, Fig 33/38 style: counts per bin (log colour scale), the box drawn
    fig, axes = plt.subplots(len(MODELS), len(angles), figsize=(3.6 * len(angles) + 1.0, 3.2 * len(MODELS)),
                             sharex=True, sharey=True, squeeze=False, layout="constrained")
    ext = [*HIST_RANGE_NDGRI, *HIST_RANGE_NDSI]
    vmax = max(float(h.max()) for h in hists.values()) or 1.0
    b = DEFAULT_BOX
    for mi, m in enumerate(MODELS):
        for si, a in enumerate(angles):
            h = hists[(m, si)].cpu().numpy().T
            ax = axes[mi, si]
            im = ax.imshow(np.ma.masked_equal(h, 0), origin="lower", extent=ext, aspect="auto", cmap="viridis",
                           norm=LogNorm(vmin=1, vmax=vmax))
            ax.add_patch(Rectangle((b.b1, b.c1), b.b2 - b.b1, b.c2 - b.c1, fill=False, ec="r", lw=1.2,
                                   label="rules box (eq 2.5.10)"))
            ax.grid(alpha=0.25)
            ax.set_title(f"{_LABELS[m]}, {a:g}°", fontsize=9)
            if mi == len(MODELS) - 1:
                ax.set_xlabel("NDGRI")
            if si == 0:
                ax.set_ylabel("NDSI")
    axes[0, 0].legend(fontsize=7, loc="lower left")
    fig.colorbar(im, ax=axes, fraction=0.02, label="sunlit skin pixels per bin (count, log scale; empty bins white)")
    fig.suptitle(f"NDSI x NDGRI histograms of sunlit skin ({h.shape[1]} x {h.shape[0]} bins)", fontsize=10)
    save_figure(fig, out / "histograms.png")


def _angle_figure(plt, out: Path, angles, summary) -> None:
    """Detected fraction and Bhattacharyya coefficient against angle, Fig 39 style."""
    from .plots import save_figure

    # detected fraction and Bhattacharyya coefficient vs angle, Fig 39 style
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(10.5, 3.9))
    for m, marker in zip(MODELS, "os^"):
        a1.plot(angles, summary[f"detected_fraction_{m}"], marker + "-", color=_COLORS[m], label=_LABELS[m])
    a1.set_xlabel("source angle off normal (deg)")
    a1.set_ylabel("sunlit skin pixels inside the box")
    a1.set_ylim(0, 1.02)
    a1.grid(alpha=0.3)
    a1.legend(fontsize=8)
    x = np.arange(len(angles))
    for k, m in enumerate(SURFACE_MODELS):
        a2.bar(x + (k - 0.5) * 0.38, summary[f"bhattacharyya_{m}"], 0.38, color=_COLORS[m], label=_LABELS[m])
    a2.set_xticks(x, [f"{a:g}" for a in angles])
    a2.set_xlabel("source angle off normal (deg)")
    a2.set_ylabel("Bhattacharyya coefficient")
    a2.set_ylim(0, 1)
    a2.legend(fontsize=8)
    a2.set_title("diffuse-only vs eq 3.1.1 NDSI x NDGRI histograms", fontsize=10)
    fig.tight_layout()
    save_figure(fig, out / "detection_vs_angle.png")

"""Figures: skin spectra like the thesis's Fig 17 with the NDSI x NDGRI rules box beside them, render and
experiment images, fits."""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from typing import TYPE_CHECKING, Any

import torch

from .bands import DEFAULT_BANDS
from .detect import DEFAULT_BOX, RulesBox
from .io import StrPath, atomic_path

if TYPE_CHECKING:
    import numpy as np
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure
    from numpy.typing import ArrayLike


def plot_spectra(
    path: StrPath,
    wavelengths: torch.Tensor,
    reflectance: torch.Tensor,
    names: list[str],
    ndgri: torch.Tensor,
    ndsi: torch.Tensor,
    box: RulesBox = DEFAULT_BOX,
    title: str = "Diffuse skin reflectance (normal incidence)",
    shade: torch.Tensor | None = None,
    shade_label: str = "melanosome volume fraction",
    shade_max: float = 0.45,
) -> None:
    """Write a PNG: reflectance spectra (left) and the skins in the rules-detector plane (right).

    ``shade`` (one value per skin in [0, 1], e.g. melanosome fraction / 0.45) colours the curves and points;
    a colour bar beside the plane is the key: ``shade_label`` from 0 to ``shade_max`` (shade 1), and when the
    label names the melanosome fraction, the Fitzpatrick types' melanosome ranges
    (``tissue.FITZPATRICK_RANGES``) marked on its other side. Without ``shade`` the skins are coloured in
    order: named in a legend when there are at most 12, else keyed by a colour bar of the skin's index.

    Args:
        path: the PNG to write.
        wavelengths: (W,) nm.
        reflectance: (N, W), one spectrum per skin (any shape that reshapes to it).
        names: the N skins' names.
        ndgri, ndsi: (N,) the skins' indices (eqs 2.5.8, 2.5.9).
        box: the rules box drawn in the plane.
        title: the spectra panel's title.
        shade: (N,) values in [0, 1] that colour the skins, or None.
        shade_label, shade_max: the colour bar's label and the value at shade 1.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    wl = wavelengths.detach().cpu().numpy()
    R = reflectance.detach().cpu().reshape(-1, wl.size).numpy()
    g = ndgri.detach().cpu().reshape(-1).numpy()
    s = ndsi.detach().cpu().reshape(-1).numpy()
    many = R.shape[0] > 12
    n = R.shape[0]
    c = (shade.detach().cpu().reshape(-1).clamp(0, 1).numpy() if shade is not None
         else [k / max(n - 1, 1) for k in range(n)])
    from matplotlib.colors import ListedColormap, Normalize

    cmap = ListedColormap(plt.get_cmap("copper_r")([0.1 + 0.85 * k / 255 for k in range(256)]))
    colors = [cmap(float(x)) for x in c]
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(12.6, 4.6), gridspec_kw={"width_ratios": [1.6, 1]},
                                 layout="constrained")
    for k in range(n):
        kw = {"lw": 0.6, "alpha": 0.35} if many else {"lw": 1.6, "label": names[k]}
        ax.plot(wl, R[k], color=colors[k], **kw)
    for b in DEFAULT_BANDS:
        ax.axvline(b.center_nm, color="0.6", ls=":", lw=1)
        ax.text(b.center_nm, 0.98, f"{b.center_nm:g}", transform=ax.get_xaxis_transform(), ha="center",
                va="top", fontsize=8, color="0.4")
    ax.set_xlabel("wavelength (nm)")
    ax.set_ylabel("reflectance")
    ax.set_xlim(wl.min(), wl.max())
    ax.set_ylim(0, max(0.8, float(R.max()) * 1.05))
    ax.set_title(title)
    ax.grid(alpha=0.3)
    if not many:
        ax.legend(fontsize=8, ncol=2)
    bx.add_patch(plt.Rectangle((box.b1, box.c1), box.b2 - box.b1, box.c2 - box.c1, fill=False, ec="k", lw=1.5,
                               label="rules box (eq 2.5.10)"))
    bx.scatter(g, s, s=8 if many else 30, c=colors, zorder=3, edgecolors="k" if not many else "none",
               linewidths=0.4)
    if not many:
        for k, n in enumerate(names):
            bx.annotate(n, (g[k], s[k]), fontsize=7, xytext=(3, 3), textcoords="offset points")
    bx.set_xlabel("NDGRI = (ρ544 - ρ633)/(ρ544 + ρ633)")
    bx.set_ylabel("NDSI = (ρ1080 - ρ1580)/(ρ1080 + ρ1580)")
    bx.set_xlim(min(-0.7, g.min() - 0.05), max(0.1, g.max() + 0.05))
    bx.set_ylim(min(0.55, s.min() - 0.03), max(0.85, s.max() + 0.03))
    bx.grid(alpha=0.3)
    bx.legend(fontsize=8, loc="lower left")
    bx.set_title("Rules-detector plane")
    if shade is not None or many:  # the colour key (a few skins without shade are named in the legend)
        top = shade_max if shade is not None else n - 1
        sm = plt.cm.ScalarMappable(norm=Normalize(0, top), cmap=cmap)
        cb = fig.colorbar(sm, ax=bx, fraction=0.06, pad=0.02,
                          label=shade_label if shade is not None else "skin (order given)")
        if shade is not None and shade_label.startswith("melanosome"):
            from .tissue import FITZPATRICK_RANGES

            cb.ax.yaxis.set_label_position("left")
            cb.ax.yaxis.set_ticks_position("left")
            ty = cb.ax.secondary_yaxis("right")
            ranges = {t: r["melanosome"] for t, r in FITZPATRICK_RANGES.items() if r["melanosome"][0] < top}
            ty.set_yticks([(a + min(b, top)) / 2 for a, b in ranges.values()], list(ranges), fontsize=8)
            ty.tick_params(length=0)
            ty.set_ylabel("Fitzpatrick type", fontsize=9)
            for a, _ in ranges.values():
                cb.ax.axhline(a, color="w", lw=0.8)
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)


def pyplot() -> Any:
    """``matplotlib.pyplot`` on the non-interactive Agg backend (figures are only written to files)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig: Figure, path: StrPath) -> None:
    """Write ``fig`` as a 100 dpi PNG (atomically) and close it.

    Args:
        fig: a matplotlib figure.
        path: the PNG to write.
    """
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=100, format="png")
    pyplot().close(fig)


def band_image(path: StrPath, image: torch.Tensor, title: str, vmin: float = 0.0, vmax: float = 1.0,
               label: str = "reflectance") -> None:
    """False-colour reflectance image of one band (like the thesis's Figs 29 and 35). The colour scale is
    clipped to [``vmin``, ``vmax``]; the colour bar's label says so and gives the image's own min and max, and
    the bar's ends are arrows on the side(s) where pixels lie outside the scale.

    Args:
        path: the PNG to write.
        image: (H, W) reflectance of one band.
        title: the figure's title.
        vmin, vmax: the colour scale's ends.
        label: what the values are (the colour bar's label).
    """
    band_images([path], [image], [title], vmin, vmax, label)


def band_images(paths: Sequence[StrPath], images: Sequence[torch.Tensor], titles: Sequence[str],
                vmin: float = 0.0, vmax: float = 1.0, label: str = "reflectance") -> None:
    """``band_image`` for many bands of one frame (a hyperspectral render's): the images share a shape, so each
    kind of colour bar (arrows at neither, one or both ends) is laid out once and its figure redrawn per band with
    that band's pixels, title and label, about half the time of a figure each (most of the rest is PNG encoding).

    Args:
        paths, images, titles: one per band; the images (H, W), all of one shape.
        vmin, vmax, label: as ``band_image``'s.
    """
    import numpy as np

    if not len(paths) == len(images) == len(titles):
        raise ValueError(f"band_images needs one path and title per image, got {len(paths)} paths, "
                         f"{len(images)} images and {len(titles)} titles")
    arrays = [image.detach().cpu().float().numpy() for image in images]
    if any(a.ndim != 2 for a in arrays) or len({a.shape for a in arrays}) > 1:
        raise ValueError(f"band_images needs (H, W) images of one shape, got {sorted({a.shape for a in arrays})}")
    plt = pyplot()
    figures: dict[str, tuple[Any, Any, Any, Any]] = {}  # extend -> (figure, image, title, colour bar)
    try:
        for path, img, title in zip(paths, arrays, titles, strict=True):
            h, w = img.shape
            finite = img[np.isfinite(img)]
            lo, hi = (float(finite.min()), float(finite.max())) if finite.size else (float("nan"), float("nan"))
            extend = {(False, False): "neither", (True, False): "min", (False, True): "max", (True, True): "both"}[
                (bool(lo < vmin), bool(hi > vmax))]
            text = f"{label} (colour clipped to [{vmin:g}, {vmax:g}];\nimage min {lo:.3g}, max {hi:.3g})"
            if extend not in figures:
                fig, ax = plt.subplots(figsize=(5.6, 5.2 * h / w + 0.4), layout="constrained")
                im = ax.imshow(img, cmap="jet", vmin=vmin, vmax=vmax, interpolation="nearest")
                ax.axis("off")
                bar = fig.colorbar(im, ax=ax, fraction=0.046, pad=0.03, extend=extend, label=text)
                figures[extend] = (fig, im, ax.set_title(title), bar)
            else:  # the layout of the kind's first band, kept: the same shape and bar, a title and label alike
                fig, im, handle, bar = figures[extend]
                im.set_data(img)
                handle.set_text(title)
                bar.set_label(text)
            with atomic_path(path, suffix=".png") as tmp:
                fig.savefig(tmp, dpi=100, format="png")
            if fig.get_layout_engine() is not None:  # laid out by that first draw; frozen for the next bands
                fig.set_layout_engine("none")
    finally:
        for fig, *_ in figures.values():
            plt.close(fig)


def _numpy(x: torch.Tensor | ArrayLike) -> np.ndarray:
    import numpy as np

    return x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)


#: 8-bit RGB of the mask classes, shared by ``mask_png`` (the pixel-aligned mask) and the annotated figures
MASK_COLORS = {"hit": (26, 217, 51), "missed": (230, 38, 26), "false_alarm": (255, 230, 26),
               "detected": (255, 255, 255), "background": (0, 0, 0)}
_MASK_NAMES = {"hit": "detected skin", "missed": "missed skin", "false_alarm": "false alarm",
               "detected": "detected", "background": "background"}


def _mask_classes(mask, truth=None) -> dict:
    """Boolean (H, W) arrays per mask class: hit / missed / false_alarm with ``truth``, else detected."""
    m = _numpy(mask).astype(bool)
    if truth is None:
        return {"detected": m}
    t = _numpy(truth).astype(bool)
    return {"hit": m & t, "missed": ~m & t, "false_alarm": m & ~t}


def _mask_rgb8(mask, truth=None):
    """(H, W, 3) uint8 RGB of a detector mask in ``MASK_COLORS``: detected skin green, missed skin red, false
    alarms yellow, the rest black (without truth: detected white)."""
    import numpy as np

    m = _numpy(mask).astype(bool)
    rgb = np.zeros(m.shape + (3,), np.uint8)
    for name, sel in _mask_classes(m, truth).items():
        rgb[sel] = MASK_COLORS[name]
    return rgb


def _mask_rgb(mask, truth=None):
    """``_mask_rgb8`` as floats in [0, 1] (for imshow)."""
    return _mask_rgb8(mask, truth) / 255.0


def _mask_legend(fig_or_ax, classes, **kw) -> None:
    """A colour key of the mask classes: ``classes`` a list of class names, or a dict of class name to its
    boolean array (the key then gives each class's pixel count)."""
    from matplotlib.patches import Patch

    def label(k):
        return f"{_MASK_NAMES[k]} ({int(classes[k].sum())} px)" if isinstance(classes, dict) else _MASK_NAMES[k]

    handles = [Patch(fc=[v / 255 for v in MASK_COLORS[k]], ec="0.5", label=label(k)) for k in classes]
    fig_or_ax.legend(handles=handles, **kw)


def mask_png(path: StrPath, mask: torch.Tensor, truth: torch.Tensor | None = None) -> None:
    """The detector mask as a pixel-aligned RGB PNG of the frame's size (one PNG pixel per frame pixel, no
    axes or title), colour-coded with ``MASK_COLORS``: with ``truth`` detected skin green (26, 217, 51), missed
    skin red (230, 38, 26), false alarms yellow (255, 230, 26); without it detected pixels white; everything else
    black.

    Args:
        path: the PNG to write.
        mask: (H, W) the detector's decision per pixel.
        truth: (H, W) the skin pixels, or None.
    """
    from .io import write_png

    write_png(path, _mask_rgb8(mask, truth))


def mask_image(path: StrPath, mask: torch.Tensor, truth: torch.Tensor | None = None,
               title: str = "rules detector") -> None:
    """Annotated figure of a detector mask: detected skin (green), missed skin (red), false alarms (yellow),
    with a colour key giving each class's pixel count (``mask_png`` writes the bare, pixel-aligned mask).

    Args:
        path: the PNG to write.
        mask: (H, W) the detector's decision per pixel.
        truth: (H, W) the skin pixels, or None.
        title: the figure's title.
    """
    plt = pyplot()
    rgb = _mask_rgb(mask, truth)
    h, w = rgb.shape[:2]
    fig, ax = plt.subplots(figsize=(5.2, 5.2 * h / w + 0.9), layout="constrained")
    ax.imshow(rgb, interpolation="nearest")
    ax.set_title(title, fontsize=10)
    ax.set_xticks([])
    ax.set_yticks([])
    _mask_legend(fig, _mask_classes(mask, truth), loc="outside lower center", ncol=3, fontsize=8, frameon=False)
    save_figure(fig, path)


def mask_comparison(path: StrPath, image: torch.Tensor | np.ndarray, masks: Mapping[str, torch.Tensor | np.ndarray],
                    truth: torch.Tensor | np.ndarray, image_title: str = "reflectance", crop: float = 0.25) -> None:
    """One reflectance band of a frame beside several detectors' masks of it (green: detected skin, red: missed
    skin, yellow: false alarm). The masks are shown around the skin pixels (their bounding box widened by
    ``crop`` of its size on every side).

    Args:
        path: the PNG to write.
        image: (H, W) reflectance of one band.
        masks: a title per detector -> its (H, W) mask.
        truth: (H, W) the skin pixels.
        image_title: the band panel's title.
        crop: the margin around the skin's bounding box, as a fraction of its size.
    """
    import numpy as np

    plt = pyplot()
    img = _numpy(image)
    t = _numpy(truth).astype(bool)
    rows, cols = np.flatnonzero(t.any(1)), np.flatnonzero(t.any(0))
    if len(rows):
        dy, dx = crop * (rows[-1] - rows[0] + 1), crop * (cols[-1] - cols[0] + 1)
        ys = slice(max(0, int(rows[0] - dy)), min(t.shape[0], int(rows[-1] + 1 + dy)))
        xs = slice(max(0, int(cols[0] - dx)), min(t.shape[1], int(cols[-1] + 1 + dx)))
    else:
        ys, xs = slice(None), slice(None)
    fig, axes = plt.subplots(1, 1 + len(masks), figsize=(3.6 * (1 + len(masks)) + 0.6, 4.4), layout="constrained")
    im = axes[0].imshow(img, cmap="gray", vmin=0.0, vmax=max(float(img.max()), 1e-6), interpolation="nearest")
    axes[0].set_title(image_title, fontsize=9)
    cb = fig.colorbar(im, ax=axes[0], fraction=0.046, pad=0.02, extend="min" if float(img.min()) < 0 else "neither")
    cb.set_label("reflectance (0 to image max)", fontsize=8)
    cb.ax.tick_params(labelsize=7)
    for ax, (title, m) in zip(axes[1:], masks.items()):
        ax.imshow(_mask_rgb(_numpy(m)[ys, xs], t[ys, xs]), interpolation="nearest")
        ax.set_title(title, fontsize=9)
    for ax in axes:
        ax.axis("off")
    _mask_legend(fig, ["hit", "missed", "false_alarm"], loc="outside lower center", ncol=3, fontsize=8,
                 frameon=False)
    save_figure(fig, path)


def rules_scatter(ax: Axes, ndgri: torch.Tensor, ndsi: torch.Tensor, box: RulesBox = DEFAULT_BOX,
                  label: str | None = None, color: str = "C0") -> None:
    """Skin pixels in the NDGRI x NDSI plane with the rules box (Fig 32/37 style).

    Args:
        ax: the axes to draw in.
        ndgri, ndsi: the pixels' indices (any shape, flattened).
        box: the rules box drawn with them.
        label: the points' legend label, or None.
        color: the points' matplotlib colour.
    """
    plt = pyplot()
    g = ndgri.detach().cpu().reshape(-1).numpy()
    s = ndsi.detach().cpu().reshape(-1).numpy()
    ax.scatter(g, s, s=2, alpha=0.4, color=color, label=label, rasterized=True)
    ax.add_patch(plt.Rectangle((box.b1, box.c1), box.b2 - box.b1, box.c2 - box.c1, fill=False, ec="k", lw=1.4))
    ax.set_xlim(-1, 0.5)
    ax.set_ylim(-0.2, 1.0)
    ax.set_xlabel("NDGRI")
    ax.set_ylabel("NDSI")
    ax.grid(alpha=0.3)


def fit_spectra(path: StrPath, names: Sequence[str], wavelengths: torch.Tensor, measured: torch.Tensor,
                fitted: torch.Tensor, rmse: torch.Tensor | Sequence[float], max_panels: int = 12) -> None:
    """Measured (dots) and fitted (line) spectra, one panel each, up to ``max_panels`` of them.

    Args:
        path: the PNG to write.
        names: the N spectra's names.
        wavelengths: (W,) nm.
        measured, fitted: (N, W) reflectance.
        rmse: (N,) each fit's root-mean-square error (in the panel titles).
        max_panels: the most spectra drawn.
    """
    plt = pyplot()
    n = min(len(names), max_panels)
    cols = min(n, 4)
    rows = (n + cols - 1) // cols
    fig, axes = plt.subplots(rows, cols, figsize=(3.6 * cols, 2.8 * rows), squeeze=False)
    wl = wavelengths.detach().cpu().numpy()
    for k in range(rows * cols):
        ax = axes[k // cols][k % cols]
        if k >= n:
            ax.axis("off")
            continue
        ax.plot(wl, measured[k].detach().cpu().numpy(), ".", ms=3, color="0.3", label="measured")
        ax.plot(wl, fitted[k].detach().cpu().numpy(), "-", color="C3", label="fit")
        ax.set_title(f"{names[k]}  RMSE {float(rmse[k]):.4f}", fontsize=9)
        ax.set_ylim(0, 0.8)
        ax.grid(alpha=0.3)
        if k == 0:
            ax.legend(fontsize=8)
    fig.supxlabel("wavelength (nm)")
    fig.supylabel("reflectance")
    fig.tight_layout()
    save_figure(fig, path)


def fit_brdf_curves(path: StrPath, theta_i: torch.Tensor, theta_r: torch.Tensor, delta_phi: torch.Tensor,
                    measured: torch.Tensor, fitted_fn: Callable[[torch.Tensor, torch.Tensor, torch.Tensor], torch.Tensor],
                    bands_nm: Sequence[float]) -> None:
    """In-plane BRDF, measured (dots) and fitted (lines), per band and incidence (like the thesis's Fig 21).

    Args:
        path: the PNG to write.
        theta_i, theta_r, delta_phi: (M,) the measurements' angles, radians (in plane: cos(delta_phi) = ±1).
        measured: (M, B) BRDF values, 1/sr.
        fitted_fn: ``fitted_fn(ti, tr, dphi)`` -> (M, B) model values.
        bands_nm: the B bands' centres, nm.
    """
    import numpy as np

    plt = pyplot()
    ti_deg = np.round(np.degrees(theta_i.cpu().numpy()), 3)
    inplane = (np.abs(np.cos(delta_phi.cpu().numpy())) > 0.999)
    incid = sorted(set(ti_deg[inplane].tolist()))
    B = measured.shape[1]
    fig, axes = plt.subplots(B, max(len(incid), 1), figsize=(4 * max(len(incid), 1), 2.8 * B), squeeze=False)
    for b in range(B):
        for k, a in enumerate(incid):
            ax = axes[b][k]
            sel = inplane & (ti_deg == a)
            sign = np.where(np.cos(delta_phi.cpu().numpy()[sel]) < 0, 1.0, -1.0)  # + forward plane
            x = sign * np.degrees(theta_r.cpu().numpy()[sel])
            o = np.argsort(x)
            ax.semilogy(x[o], measured[sel][o, b].cpu().numpy(), ".", ms=3, color="C3", label="measured")
            xs = torch.linspace(-89, 89, 357, dtype=torch.float64)
            tr = xs.abs() * math.pi / 180
            dp = torch.where(xs >= 0, math.pi, 0.0)
            f = fitted_fn(torch.full_like(tr, a * math.pi / 180), tr, dp)[:, b]
            ax.semilogy(xs.numpy(), f.detach().cpu().numpy(), "-", color="C0", label="fit")
            ax.set_title(f"{bands_nm[b]:g} nm, incidence {a:g}°", fontsize=9)
            ax.set_xlabel("θr (deg, + forward)")
            ax.set_ylabel("BRDF (1/sr)")
            ax.grid(alpha=0.3, which="both")
            if b == 0 and k == 0:
                ax.legend(fontsize=8)
    fig.tight_layout()
    save_figure(fig, path)


def surface_energy(path: StrPath, skin: str = "I-II", n_quad: int = 128) -> dict[str, Any]:
    """The energy of the two skin surface models (``optics.skin_diffuse``): the directional-hemispherical
    reflectance of eq 3.1.1 (``optics.dhr``, quadrature) against incidence for a ``skin`` preset at 633 and
    1580 nm, each model with and without Smith shadowing; DHR > 1 means more light out than in.

    Args:
        path: the PNG to write.
        skin: the ``tissue`` preset.
        n_quad: quadrature points per hemisphere axis.

    Returns:
        ``{"angles_deg": [...], "dhr": {label: {band_nm: [DHR per angle]}}}``.
    """
    from . import tissue
    from .optics import SURFACE_MODELS, THESIS_SPECULAR, dhr, skin_brdf

    angles = torch.linspace(0.0, 89.5, 60, dtype=torch.float64)
    wl = torch.tensor([633.0, 1580.0], dtype=torch.float64)
    r_sub = tissue.subsurface_reflectance(tissue.preset(skin, dtype=torch.float64), wl)[:, None, None, None]
    sig, rho0 = (x[:, None, None, None] for x in THESIS_SPECULAR.at(wl))
    curves: dict[str, dict[str, list[float]]] = {}
    for surface in SURFACE_MODELS:
        for shadowing in (False, True):
            def brdf(a: torch.Tensor, b: torch.Tensor, c: torch.Tensor, s: str = surface,
                     g: bool = shadowing) -> torch.Tensor:
                return skin_brdf(a, b, c, r_sub, sig, rho0, s, shadowing=g)

            d = dhr(brdf, angles * (math.pi / 180), n_quad, n_quad)  # (2, angles)
            label = f"{surface}{', Smith shadowing' if shadowing else ''}"
            curves[label] = {f"{w:g}": d[k].tolist() for k, w in enumerate(wl.tolist())}
    plt = pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.9), sharey=True)
    styles = {"thesis": ("C3", "-"), "thesis, Smith shadowing": ("C3", "--"), "conserving": ("C0", "-"),
              "conserving, Smith shadowing": ("C0", "--")}
    for ax, w in zip(axes, ("633", "1580")):
        for label, c in curves.items():
            color, ls = styles[label]
            ax.plot(angles.numpy(), c[w], color=color, ls=ls, lw=1.6, label=label)
        ax.axhline(1.0, color="k", lw=0.8, ls=":")
        ax.set_xlabel("incidence angle θi (deg)")
        ax.set_title(f"{w} nm, skin {skin}")
        ax.set_ylim(0, 2.0)
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("directional-hemispherical reflectance")
    axes[0].legend(fontsize=8, loc="upper left")
    fig.suptitle("Energy of eq 3.1.1 under the two skin surface models (DHR > 1: not energy-conserving)", fontsize=10)
    fig.tight_layout()
    save_figure(fig, path)
    return {"angles_deg": angles.tolist(), "dhr": curves}

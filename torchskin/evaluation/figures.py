"""The figures of an evaluation (the only module of ``torchskin.evaluation`` that draws; matplotlib is imported
inside its functions, through ``torchskin.plots``): the ROC and the Pd heat map (``plots``), the comparison bars
(``compare_plot``), the boxes against the configuration (``boxes_plot``), all of them for one result
(``write_figures``) and the render demo's masks (``thesis_frame_plot``)."""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ..dataset.files import read_rows
from ..detect import DEFAULT_BOX
from ..detectors.features import confuser_indices
from .candidates import box_function, load_candidate
from .metrics import CAMERA_BINS, SUN_BINS


def boxes_plot(data_dir: str | os.PathLike, model_path: str | os.PathLike, path: str | os.PathLike,
               configs: Sequence[tuple[float, ...]] = ((15.0, 60.0, 30.0), (60.0, 60.0, 30.0), (80.0, 60.0, 30.0),
                                                       (80.0, 60.0, 160.0)),
               max_points: int = 20000) -> None:
    """How the boxes move with the configuration. Left: held-out skin pixels on (NDGRI, NDSI) (sunlit, colour:
    sun zenith; shadowed, grey), the earthlib test spectra, the static box and the learned box at a few
    configurations. Right: the learned edges (b1, b2, c1, c2 and the NDVN rule d1) against the sun zenith, camera
    zenith 60°, sun behind the camera (relative azimuth 0°), across (90°) and ahead of it (180°, back-lit)."""
    from matplotlib.patches import Rectangle

    from ..plots import pyplot, save_figure

    features, boxes_of = box_function(model_path)
    rows = read_rows(data_dir, ["ndgri", "ndsi", "label", "shadow", "sun_zenith_deg"])
    label, shadow = rows["label"], rows["shadow"]
    rng = np.random.default_rng(0)

    def pick(m):
        cols = [rows[c][m] for c in ("ndgri", "ndsi", "sun_zenith_deg")]
        if len(cols[0]) > max_points:
            k = rng.choice(len(cols[0]), max_points, replace=False)
            cols = [c[k] for c in cols]
        return cols

    g, s, sz = pick(label & ~shadow)
    gs, ss, _ = pick(label & shadow)
    conf = confuser_indices("test").numpy()
    plt = pyplot()
    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(13.0, 5.4), layout="constrained", width_ratios=[1.15, 1.0])
    ax.scatter(gs, ss, s=2, alpha=0.25, c="0.6", rasterized=True, label="shadowed skin")
    sc = ax.scatter(g, s, c=sz, s=2, alpha=0.35, cmap="viridis", vmin=0, vmax=90, rasterized=True)
    ax.scatter(conf[:, 0], conf[:, 1], s=5, c="k", marker="x", lw=0.6, label="earthlib test spectra")
    b = DEFAULT_BOX
    ax.add_patch(Rectangle((b.b1, b.c1), b.b2 - b.b1, b.c2 - b.c1, fill=False, ec="r", lw=1.8, label="static box (thesis)"))
    if len(features) == 3:
        boxes = boxes_of(np.array(configs, dtype=np.float32)).numpy()
        for k, (c, bx) in enumerate(zip(configs, boxes)):
            d1 = f", NDVN ≥ {bx[4]:.2f}" if len(bx) > 4 and bx[4] > -1 else ""
            ax.add_patch(Rectangle((bx[0], bx[2]), bx[1] - bx[0], bx[3] - bx[2], fill=False, ec=f"C{k + 1}", lw=1.4,
                                   ls=("-", "--", ":", "-.")[k % 4],
                                   label=f"learned: sun {c[0]:g}°, camera {c[1]:g}°, rel. az. {c[2]:g}°{d1}"))
        sun = np.linspace(0.0, 89.0, 90, dtype=np.float32)
        for ra, ls in ((0.0, "-"), (90.0, "--"), (180.0, ":")):
            bx = boxes_of(np.stack([sun, np.full_like(sun, 60.0), np.full_like(sun, ra)], -1)).numpy()
            for j, name in enumerate(("b1 NDGRI min", "b2 NDGRI max", "c1 NDSI min", "c2 NDSI max", "d1 NDVN min")):
                if j < bx.shape[1]:
                    ax2.plot(sun, bx[:, j], color=f"C{j}", ls=ls, lw=1.4, label=name if ra == 0.0 else None)
        for ra, ls in ((0.0, "-"), (90.0, "--"), (180.0, ":")):
            ax2.plot([], [], color="k", ls=ls, label=f"relative azimuth {ra:g}°")
        ax2.set_xlabel("sun zenith (deg), camera zenith 60°")
        ax2.set_ylabel("box edge (index units)")
        ax2.set_title("learned edges against the configuration")
        ax2.legend(fontsize=7, ncol=2, loc="best")
        ax2.grid(alpha=0.3)
    ax.set_xlim(-1.0, 0.6)
    ax.set_ylim(-0.2, 1.1)
    ax.set_xlabel("NDGRI (544, 633 nm)")
    ax.set_ylabel("NDSI (1080, 1580 nm)")
    ax.set_title("held-out skin (sunlit: colour = sun zenith; shadowed: grey) and confusers")
    cb = fig.colorbar(sc, ax=ax, fraction=0.04, label="sun zenith (deg)")
    cb.solids.set_alpha(1.0)  # the key at full colour, not at the points' transparency
    ax.legend(fontsize=6.5, loc="lower left")
    save_figure(fig, path)


def plots(result: dict, out_dir: str | os.PathLike) -> None:
    """The ROC (``roc.png``) and the Pd heat map per (sun zenith x camera zenith) bin (``pd_heatmap.png``) of an
    ``evaluate`` result, in ``out_dir``."""
    from ..plots import pyplot, save_figure

    plt = pyplot()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    first = result["models"][0]["name"] if result.get("models") else "learned"
    fig, ax = plt.subplots(figsize=(5.5, 4.2))
    for name in ("learned", "static") if "roc" in result else ():
        pts = np.array(result["roc"][name], dtype=float)
        ax.plot(np.maximum(pts[:, 2], 1e-5), pts[:, 1], "o-", ms=3, label=f"{name} (scene non-skin pixels)")
        ax.plot(np.maximum(pts[:, 0], 1e-5), pts[:, 1], "s--", ms=3, label=f"{name} (earthlib test spectra)")
    ax.set_xscale("log")
    ax.set_xlabel("false-alarm probability (0 drawn at 1e-5)")
    ax.set_ylabel("Pd, sunlit skin")
    ax.grid(alpha=0.3, which="both")
    if "roc" in result:
        ax.legend(fontsize=7)
    ax.set_title(f"ROC: boxes scaled about their centres\n(learned: {first})" if "roc" in result
                 else "ROC: the first model has no boxes to scale", fontsize=9)
    fig.tight_layout()
    save_figure(fig, out / "roc.png")
    static = any(b.get("static") is not None for b in result["bins"])  # the static box: index-band models only
    names = ("learned", "static") if static else ("learned",)
    fig, axes = plt.subplots(1, len(names), figsize=(5.6 * len(names), 4.4), layout="constrained", squeeze=False)
    for ax, name in zip(axes[0], names):
        grid = np.full((len(SUN_BINS) - 1, len(CAMERA_BINS) - 1), np.nan)
        for b in result["bins"]:
            i = SUN_BINS.index(b["sun_zenith_deg"][0])
            j = CAMERA_BINS.index(b["camera_zenith_deg"][0])
            grid[i, j] = b[name]["pd_sunlit"]
        im = ax.imshow(grid, vmin=0, vmax=1, cmap="viridis", origin="lower")
        ax.set_xticks(range(len(CAMERA_BINS) - 1), [f"{a:g}-{b:g}" for a, b in zip(CAMERA_BINS, CAMERA_BINS[1:])])
        ax.set_yticks(range(len(SUN_BINS) - 1), [f"{a:g}-{b:g}" for a, b in zip(SUN_BINS, SUN_BINS[1:])])
        ax.set_xlabel("camera zenith (deg)")
        ax.set_ylabel("sun zenith (deg)")
        ax.set_title(f"Pd sunlit skin, {name}" + (f" ({first})" if name == "learned" else " box (thesis)"),
                     fontsize=10)
        for (i, j), v in np.ndenumerate(grid):
            if np.isfinite(v):
                ax.text(j, i, f"{v:.2f}", ha="center", va="center", color="k" if v > 0.6 else "w", fontsize=7)
    fig.colorbar(im, ax=axes[0].tolist(), fraction=0.03, label="Pd, sunlit skin (fraction detected)")
    save_figure(fig, out / "pd_heatmap.png")


def compare_plot(result: dict, path: str | os.PathLike) -> None:
    """Bars per model: Pd (sunlit without glint, glint-affected, shadowed, back-lit, sun >= 60° mean over
    configurations), false alarms (earthlib test and scene non-skin, log scale) and the decision-region area."""
    from ..plots import pyplot, save_figure

    plt = pyplot()
    models = result["models"]
    names = [m["name"] for m in models]
    fig, (a1, a2, a3) = plt.subplots(1, 3, figsize=(14, 4.2), gridspec_kw={"width_ratios": [2.2, 1.2, 1]})
    cats = [("sunlit, no glint", lambda m: m["overall"]["pd_sunlit_no_glint"]),
            ("glint-affected", lambda m: m["overall"]["pd_glint"]),
            ("shadowed", lambda m: m["overall"]["pd_shadow"]),
            ("back-lit (all skin)", lambda m: m["overall"]["pd_backlit"]),
            ("sun ≥ 60°, mean/config", lambda m: m["sun_zenith_ge_60"]["pd_sunlit_mean_over_configs"])]
    x = np.arange(len(cats))
    w = 0.8 / len(models)
    for k, m in enumerate(models):
        a1.bar(x + (k - (len(models) - 1) / 2) * w, [f(m) for _, f in cats], w, label=names[k])
    a1.set_xticks(x, [c for c, _ in cats], fontsize=8)
    a1.set_ylabel("Pd (held-out skin pixels)")
    a1.set_ylim(0, 1.3)
    a1.set_yticks(np.linspace(0, 1, 6))
    a1.grid(alpha=0.3, axis="y")
    a1.legend(fontsize=7, loc="upper center", ncol=min(4, len(models)))
    x2 = np.arange(2)
    for k, m in enumerate(models):
        a2.bar(x2 + (k - (len(models) - 1) / 2) * w, [max(m["overall"]["pfa"], 1e-6), max(m["overall"]["pfa_scene"], 1e-6)],
               w)
    a2.set_yscale("log")
    a2.set_ylim(5e-7, 1)
    a2.set_xticks(x2, ["earthlib test", "scene non-skin"], fontsize=8)
    a2.set_ylabel("Pfa (0 drawn at 1e-6)")
    a2.grid(alpha=0.3, axis="y", which="both")
    a3.bar(np.arange(len(models)), [m["area"]["mean"] for m in models], color=[f"C{k}" for k in range(len(models))])
    a3.set_xticks(np.arange(len(models)), names, fontsize=7, rotation=25, ha="right")
    a3.set_ylabel("decision-region area, (NDGRI, NDSI) units²")
    a3.grid(alpha=0.3, axis="y")
    fig.suptitle(f"Held-out comparison ({result['configurations']} configurations)", fontsize=10)
    fig.tight_layout()
    save_figure(fig, path)


def write_figures(result: dict, out_dir: str | os.PathLike) -> None:
    """Every figure of an ``evaluate`` result in ``out_dir``: ``roc.png`` and ``pd_heatmap.png`` (``plots``),
    ``comparison.png`` (``compare_plot``) and, when the first model has boxes (any box kind), ``boxes.png``
    (``boxes_plot`` on the result's ``data``)."""
    plots(result, out_dir)
    compare_plot(result, Path(out_dir) / "comparison.png")
    first = result["models"][0]
    if load_candidate(first["path"]).boxes is not None:  # any box kind: its edges against the sun
        boxes_plot(result["data"], first["path"], Path(out_dir) / "boxes.png")


def thesis_frame_plot(path: str | os.PathLike, reflectance_1080: np.ndarray, static: np.ndarray,
                      learned: np.ndarray, skin: np.ndarray, sunlit: np.ndarray, sun_zenith_deg: float) -> None:
    """The render demo's figure (``evaluation.demo.thesis_frame``): the 1080 nm reflectance beside the static
    box's and the learned detector's masks, each titled with its sunlit-skin detection and false alarms."""
    from ..plots import mask_comparison

    n = max(int(sunlit.sum()), 1)
    rate = lambda m: f"{(m & sunlit).sum() / n:.2f} of sunlit skin, {int((m & ~skin).sum())} false alarms"  # noqa: E731
    mask_comparison(path, reflectance_1080, {f"static box (thesis)\n{rate(static)}": static,
                                             f"learned boundaries (detector.onnx)\n{rate(learned)}": learned}, skin,
                    f"1080 nm reflectance (onboard ELM)\nsun zenith {sun_zenith_deg:g}°, camera horizontal")


__all__ = ["boxes_plot", "compare_plot", "plots", "thesis_frame_plot", "write_figures"]

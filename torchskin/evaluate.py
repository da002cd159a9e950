"""Evaluate learned boundaries against the static box on held-out configurations and on the earthlib test
partition: detection probability Pd of skin pixels (sunlit and shadowed), false-alarm probability Pfa (test
spectra inside each configuration's box, and the scene's non-skin pixels), overall and per (sun zenith x
camera zenith) bin; ROC curves and a Pd heat map as PNG."""

from __future__ import annotations

import numpy as np
import torch

from .boundaries import FEATURES, confuser_indices, false_alarm_rate, inside_box
from .dataset.files import read_valid
from .detect import DEFAULT_BOX

SUN_BINS = (0.0, 15.0, 30.0, 45.0, 60.0, 75.0, 90.0)
CAMERA_BINS = (0.0, 15.0, 30.0, 45.0, 60.0, 75.0, 90.0)


def box_function(model_path):
    """``features (N, k) -> boxes (N, 4)`` from a torch checkpoint (.pt) or an exported boundaries.onnx."""
    p = str(model_path)
    if p.endswith(".onnx"):
        from .onboard import Boundaries

        b = Boundaries(p)
        return list(b.features), lambda x: torch.from_numpy(b(np.asarray(x, dtype=np.float32))["boxes"])
    from .boundaries import load

    m = load(p)
    return list(m.features), lambda x: m(torch.as_tensor(x, dtype=torch.float32)).detach()


ROC_SCALES = tuple(float(x) for x in np.linspace(0.25, 3.0, 23))


def evaluate(data_dir, model_path, scales=ROC_SCALES) -> dict:
    """Pd / Pfa of the boxes of ``model_path`` and of the static box on the dataset at ``data_dir``."""
    features, boxes_of = box_function(model_path)
    cols = sorted(set(features) | {"sun_zenith_deg", "camera_zenith_deg", "label", "shadow", "ndgri", "ndsi",
                                   "group", "sun", "skin"})
    t, excluded = read_valid(data_dir, cols)  # frames without sunlit panels have no physical ELM
    if len(t) == 0:
        raise ValueError(f"no rows with a valid ELM in {str(data_dir)!r}")
    col = {c: torch.from_numpy(np.array(t.column(c).to_numpy(zero_copy_only=False))) for c in cols}
    X = torch.stack([col[f].float() for f in features], -1)
    g, s = col["ndgri"].float(), col["ndsi"].float()
    label, shadow = col["label"].bool(), col["shadow"].bool()
    learned = boxes_of(X)
    static = torch.tensor([DEFAULT_BOX.b1, DEFAULT_BOX.b2, DEFAULT_BOX.c1, DEFAULT_BOX.c2]).expand_as(learned)
    test_pts = confuser_indices("test")
    keys = torch.stack([col["group"].long(), col["sun"].long(), col["skin"].long()], -1)

    def summary(boxes, mask=None):
        m = torch.ones_like(label) if mask is None else mask
        hit = inside_box(boxes, g, s)
        sk, lit = label & m, label & m & ~shadow
        # Pfa on the earthlib test partition: each configuration's box (its first row) against every test spectrum
        pos = m.nonzero().flatten()
        if pos.numel():
            _, inv = torch.unique(keys[pos], dim=0, return_inverse=True)
            first = torch.full((int(inv.max()) + 1,), pos.numel(), dtype=torch.long).scatter_reduce(
                0, inv, torch.arange(pos.numel()), "amin")
            pfa = float(false_alarm_rate(boxes[pos[first]], test_pts).mean())
        else:
            pfa = float("nan")
        nonskin = ~label & m
        # mean over configurations of each configuration's sunlit-skin Pd
        lit_pos = lit.nonzero().flatten()
        if lit_pos.numel():
            _, cinv = torch.unique(keys[lit_pos], dim=0, return_inverse=True)
            n_c = int(cinv.max()) + 1
            hits = torch.zeros(n_c).index_add_(0, cinv, hit[lit_pos].float())
            cnt = torch.zeros(n_c).index_add_(0, cinv, torch.ones(lit_pos.numel()))
            pd_cfg = float((hits / cnt).mean())
        else:
            pd_cfg = float("nan")
        return {"pd": float(hit[sk].float().mean()) if bool(sk.any()) else float("nan"),
                "pd_sunlit_mean_over_configs": pd_cfg,
                "pd_sunlit": float(hit[lit].float().mean()) if bool(lit.any()) else float("nan"),
                "pd_shadow": float(hit[sk & shadow].float().mean()) if bool((sk & shadow).any()) else float("nan"),
                "pfa": pfa,
                "pfa_scene": float(hit[nonskin].float().mean()) if bool(nonskin.any()) else float("nan"),
                "skin_pixels": int(sk.sum())}

    out = {"learned": summary(learned), "static": summary(static), "bins": []}
    sz, cz = col["sun_zenith_deg"].float(), col["camera_zenith_deg"].float()
    for i in range(len(SUN_BINS) - 1):
        for j in range(len(CAMERA_BINS) - 1):
            m = (sz >= SUN_BINS[i]) & (sz < SUN_BINS[i + 1]) & (cz >= CAMERA_BINS[j]) & (cz < CAMERA_BINS[j + 1])
            if not bool((m & label).any()):
                continue
            out["bins"].append({"sun_zenith_deg": [SUN_BINS[i], SUN_BINS[i + 1]],
                                "camera_zenith_deg": [CAMERA_BINS[j], CAMERA_BINS[j + 1]],
                                "learned": summary(learned, m), "static": summary(static, m)})
    hi = sz >= 60
    out["sun_zenith_ge_60"] = {"learned": summary(learned, hi), "static": summary(static, hi)}
    # ROC: scale every box about its centre
    roc = {}
    for name, bx in (("learned", learned), ("static", static)):
        c = torch.stack([(bx[:, 0] + bx[:, 1]) / 2, (bx[:, 0] + bx[:, 1]) / 2, (bx[:, 2] + bx[:, 3]) / 2,
                         (bx[:, 2] + bx[:, 3]) / 2], -1)
        pts = []
        for k in scales:
            b = c + float(k) * (bx - c)
            r = summary(b)
            pts.append([r["pfa"], r["pd_sunlit"], r["pfa_scene"]])
        roc[name] = pts
    out["roc"] = {"scales": [float(k) for k in scales], **roc}
    out["features"] = features
    out["rows"] = len(t)
    out["rows_excluded_no_sunlit_panels"] = excluded
    return out


def thesis_frame(detector_path, size: int = 160, sun_zenith_deg: float = 45.0, sun_azimuth_deg: float = 20.0,
                 min_reflectance: float = 0.005, plot=None) -> dict:
    """The shipped detector on the thesis geometry, end to end: ``render``'s default scene (horizontal camera at
    9.449 m, Type I/II subject between a 0.97 and a 0.03 panel, sensor noise on) at ``size`` x ``size`` under
    the given sun, its signal frame calibrated by the onboard ELM through the panels' pixel regions, then
    ``detector.onnx`` through the onboard runtime (negative noise clipped, brightness floor). Returns the
    sunlit-skin detection of the learned boundaries and of the static box, the learned false alarms and the
    largest difference between the onboard and the renderer's ELM reflectance. ``plot``: a PNG of the 1080 nm
    reflectance beside both masks."""
    from .onboard import Detector, elm_apply, elm_fit
    from .render import Sensor, panel_regions, render
    from .scene import Camera, Sun, default_scene

    sc = default_scene(camera=Camera(width=size, height=size),
                       sun=Sun(zenith_deg=sun_zenith_deg, azimuth_deg=sun_azimuth_deg, sky_fraction=0.1))
    res = render(sc, sensor=Sensor())
    signal = res.signal[0, 0].permute(2, 0, 1).cpu().numpy()
    regions = panel_regions(res.gbuffer, list(sc.panels))
    refs = {p: sc.materials[sc.mesh(p).material].band_reflectance(sc.band_list) for p in sc.panels}
    fit = elm_fit(signal, [(regions[p], refs[p]) for p in sc.panels])
    cube = elm_apply(signal, fit["gain"], fit["offset"])[None]
    rel = abs((sun_azimuth_deg - sc.cameras[0].azimuth_deg + 180.0) % 360.0 - 180.0)
    out = Detector(detector_path)(cube, [[sun_zenith_deg, sc.cameras[0].zenith_deg, rel]], negative="clip",
                                  min_reflectance=min_reflectance)
    skin, lit = res.skin[0].cpu().numpy(), res.lit[0, 0].cpu().numpy()
    sunlit = skin & lit
    learned, static = out["mask"][0], res.mask[0, 0].cpu().numpy()
    n = max(int(sunlit.sum()), 1)
    if plot is not None:
        from .plots import mask_comparison

        rate = lambda m: f"{(m & sunlit).sum() / n:.2f} of sunlit skin, {int((m & ~skin).sum())} false alarms"  # noqa: E731
        mask_comparison(plot, cube[0, 2], {f"static box (thesis)\n{rate(static)}": static,
                                            f"learned boundaries (detector.onnx)\n{rate(learned)}": learned}, skin,
                        f"1080 nm reflectance (onboard ELM)\nsun zenith {sun_zenith_deg:g}°, camera horizontal")
    return {"sunlit_skin_pixels": int(sunlit.sum()), "pd_sunlit_learned": float((learned & sunlit).sum() / n),
            "pd_sunlit_static": float((static & sunlit).sum() / n), "false_alarms_learned": int((learned & ~skin).sum()),
            "out_of_domain": bool(out["out_of_domain"].any()),
            "elm_max_diff": float(np.abs(cube[0] - res.reflectance[0, 0].permute(2, 0, 1).cpu().numpy()).max())}


def boxes_plot(data_dir, model_path, path, configs=((15.0, 20.0, 150.0), (50.0, 40.0, 90.0), (80.0, 60.0, 10.0)),
               max_points: int = 20000) -> None:
    """The picture behind the numbers: held-out sunlit skin pixels (colour: sun zenith), the earthlib test
    spectra, the static box and the learned box at a few configurations, on (NDGRI, NDSI)."""
    from matplotlib.patches import Rectangle

    from .plots import _plt, save_figure

    features, boxes_of = box_function(model_path)
    t, _ = read_valid(data_dir, ["ndgri", "ndsi", "label", "shadow", "sun_zenith_deg"])
    keep = t.column("label").to_numpy(zero_copy_only=False) & ~t.column("shadow").to_numpy(zero_copy_only=False)
    g, s, sz = (t.column(c).to_numpy(zero_copy_only=False)[keep] for c in ("ndgri", "ndsi", "sun_zenith_deg"))
    if len(g) > max_points:
        pick = np.random.default_rng(0).choice(len(g), max_points, replace=False)
        g, s, sz = g[pick], s[pick], sz[pick]
    conf = confuser_indices("test").numpy()
    plt = _plt()
    fig, ax = plt.subplots(figsize=(7.0, 5.2))
    sc = ax.scatter(g, s, c=sz, s=2, alpha=0.35, cmap="viridis", vmin=0, vmax=90, rasterized=True)
    ax.scatter(conf[:, 0], conf[:, 1], s=5, c="k", marker="x", lw=0.6, label="earthlib test spectra")
    b = DEFAULT_BOX
    ax.add_patch(Rectangle((b.b1, b.c1), b.b2 - b.b1, b.c2 - b.c1, fill=False, ec="r", lw=1.8, label="static box (thesis)"))
    if len(features) == 3:
        boxes = boxes_of(np.array(configs, dtype=np.float32)).numpy()
        for k, (c, bx) in enumerate(zip(configs, boxes)):
            ax.add_patch(Rectangle((bx[0], bx[2]), bx[1] - bx[0], bx[3] - bx[2], fill=False, ec=f"C{k + 1}", lw=1.4,
                                   ls=("-", "--", ":")[k % 3],
                                   label=f"learned: sun {c[0]:g}°, camera {c[1]:g}°, rel. az. {c[2]:g}°"))
    ax.set_xlim(-1.0, 0.6)
    ax.set_ylim(-0.2, 1.1)
    ax.set_xlabel("NDGRI (544, 633 nm)")
    ax.set_ylabel("NDSI (1080, 1580 nm)")
    ax.set_title("held-out sunlit skin (colour: sun zenith, deg) and confusers")
    fig.colorbar(sc, ax=ax, fraction=0.04)
    ax.legend(fontsize=7, loc="upper right")
    fig.tight_layout()
    save_figure(fig, path)


def plots(result: dict, out_dir) -> None:
    from pathlib import Path

    from .plots import _plt, save_figure

    plt = _plt()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    fig, ax = plt.subplots(figsize=(5.5, 4.2))
    for name in ("learned", "static"):
        pts = np.array(result["roc"][name], dtype=float)
        ax.plot(np.maximum(pts[:, 2], 1e-5), pts[:, 1], "o-", ms=3, label=f"{name} (scene non-skin pixels)")
        ax.plot(np.maximum(pts[:, 0], 1e-5), pts[:, 1], "s--", ms=3, label=f"{name} (earthlib test spectra)")
    ax.set_xscale("log")
    ax.set_xlabel("false-alarm probability (0 drawn at 1e-5)")
    ax.set_ylabel("Pd, sunlit skin")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=7)
    ax.set_title("ROC: boxes scaled about their centres")
    fig.tight_layout()
    save_figure(fig, out / "roc.png")
    fig, axes = plt.subplots(1, 2, figsize=(10, 4.2))
    for ax, name in zip(axes, ("learned", "static")):
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
        ax.set_title(f"Pd sunlit skin, {name}")
        for (i, j), v in np.ndenumerate(grid):
            if np.isfinite(v):
                ax.text(j, i, f"{v:.2f}", ha="center", va="center", color="k" if v > 0.6 else "w", fontsize=7)
    fig.colorbar(im, ax=axes, fraction=0.03)
    save_figure(fig, out / "pd_heatmap.png")


__all__ = ["FEATURES", "evaluate", "plots"]

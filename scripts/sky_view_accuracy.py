"""The sky view cast once per geometry against per-pixel rays, on two frames, with a figure.

    python scripts/sky_view_accuracy.py [--out docs/sky_view.png] [--json FILE] [--width 512]

Frames: ``torchskin render``'s default (anny subject, vertical panels, ground; ``--width`` square); the same with
the confusers of a dataset pose group lying on its ground; and that pose group's own full frame (``generate``'s
default config, group 0 of seed 0: level panels on stands, flat confusers on the ground, its camera, 256 x 256). For each, every hit pixel's sky view from:

- the field (``render.visibility``, ``FIELD_RAYS`` rays per sample point, interpolated);
- per-pixel rays: 32 (the renderer's ``SKY_RAYS``, today's per-pixel answer), 64 (the reference the issue
  names) and 512 (the per-pixel noise averaged away: the closest to the exact view factor); 64 against 512 is
  the 64-ray reference's own noise.

Prints the mean and 99th percentile of the absolute sky-view error (and of the ground view, summed over
materials) of the field and of 32 rays against 64 and 512, per mesh, and the seconds each took. The figure, one
row each for the default frame and the dataset frame: the field's sky-view map, its error against 64 rays per
pixel, and against 512.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]


def frames(width: int) -> dict:
    from torchskin.dataset.config import resolve_config, sample_group
    from torchskin.dataset.generate import group_scene
    from torchskin.render.scene import Camera, Sun, default_scene

    group = group_scene(sample_group(resolve_config(None), 0, 0))
    with_confusers = default_scene(camera=Camera(width=width, height=width), sun=Sun(zenith_deg=45.0, azimuth_deg=20.0))
    for m in group.meshes:  # the dataset group's flat confusers, on render's ground
        if m.name.startswith("confuser"):
            with_confusers.meshes.append(m)
            with_confusers.materials[m.material] = group.materials[m.material]
    return {"default frame": default_scene(camera=Camera(width=width, height=width),
                                           sun=Sun(zenith_deg=45.0, azimuth_deg=20.0)),
            "default frame with the dataset group's confusers": with_confusers,
            "dataset frame (panels on stands, confusers)": group}


def measure(scene) -> dict:
    from torchskin.render.raycast import Raycaster

    rc = Raycaster.from_scene(scene)
    gb = rc.gbuffer(scene.cameras, np.stack([s.direction for s in scene.suns]))
    hit = gb.hit.reshape(-1)
    mesh = gb.mesh.reshape(-1)[hit]
    views, seconds = {}, {}
    for name, kw in (("field", {"method": "field"}), ("rays32", {"rays": 32}), ("rays64", {"rays": 64}),
                     ("rays512", {"rays": 512})):
        t0 = time.perf_counter()
        out = rc.with_sky_view(gb, **kw)
        seconds[name] = time.perf_counter() - t0
        views[name] = (out.sky.reshape(-1)[hit], out.ground.reshape(-1, out.ground.shape[-1])[hit].sum(1))
    t0 = time.perf_counter()
    rc.with_sky_view(gb, method="field")  # the camera's views, kept
    seconds["field, same camera again"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    rc.with_sky_view(dataclasses.replace(gb, rays=gb.rays.clone()), method="field")  # rays not the cached ones
    seconds["field lookup, a new camera"] = time.perf_counter() - t0
    seconds["field cast (once per geometry)"] = rc.field_seconds
    rows = {}
    groups = {"all hit pixels": torch.ones_like(mesh, dtype=torch.bool)}
    groups.update({n: mesh == k for k, n in enumerate(gb.mesh_names) if bool((mesh == k).any())})
    for est, ref in (("field", "rays64"), ("field", "rays512"), ("rays32", "rays64"), ("rays32", "rays512"),
                     ("rays64", "rays512")):
        for g, sel in groups.items():
            es = (views[est][0] - views[ref][0])[sel].abs()
            eg = (views[est][1] - views[ref][1])[sel].abs()
            rows.setdefault(g, {})[f"{est} vs {ref}"] = {
                "sky_mean": float(es.mean()), "sky_p99": float(es.quantile(0.99)),
                "ground_mean": float(eg.mean()), "ground_p99": float(eg.quantile(0.99)), "pixels": int(sel.sum())}
    maps = {k: torch.full((hit.numel(),), float("nan")).index_put_((hit.nonzero().flatten(),), v[0])
            .reshape(gb.hit.shape[-2:]).numpy() for k, v in views.items()}
    return {"errors": rows, "seconds": seconds, "samples": rc.visibility_field().samples, "maps": maps,
            "pixels": int(hit.sum()), "shape": list(gb.hit.shape[-2:])}


def figure(rows: dict, path: Path) -> None:
    """One row per frame: the field's sky view, its error against 64 and against 512 rays per pixel."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(len(rows), 3, figsize=(13.5, 4.4 * len(rows)), constrained_layout=True, squeeze=False)
    for r, (name, maps) in enumerate(rows.items()):
        panels = [(maps["field"], "sky view, field", "viridis", (0, 1)),
                  (np.abs(maps["field"] - maps["rays64"]), "|field - 64 rays per pixel|", "magma", (0, 0.1)),
                  (np.abs(maps["field"] - maps["rays512"]), "|field - 512 rays per pixel|", "magma", (0, 0.1))]
        for ax, (img, title, cmap, lim) in zip(axes[r], panels):
            cm = plt.get_cmap(cmap).copy()
            cm.set_bad("0.8")  # no surface
            im = ax.imshow(img, cmap=cm, vmin=lim[0], vmax=lim[1])
            ax.set_title(f"{name}: {title}", fontsize=10)
            ax.set_xticks([])
            ax.set_yticks([])
            fig.colorbar(im, ax=ax, shrink=0.85, label="cosine-weighted view fraction" if lim[1] == 1 else
                         "absolute error (clipped at 0.1)")
    fig.suptitle("Sky view cast once per geometry against per-pixel rays (grey: no surface)", fontsize=12)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.stem + ".tmp.png")
    fig.savefig(tmp, dpi=100, facecolor="white")
    plt.close(fig)
    tmp.replace(path)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "sky_view.png", help="the figure (PNG)")
    ap.add_argument("--json", type=Path, default=None, help="also write the figures as JSON here")
    ap.add_argument("--width", type=int, default=512, help="the default frame's width and height (default 512)")
    a = ap.parse_args()
    if not 16 <= a.width <= 2048:
        ap.error(f"--width must lie in [16, 2048], got {a.width}")
    if a.out.suffix.lower() != ".png":
        ap.error(f"--out must name a .png file, got {a.out}")
    for opt, path in (("--out", a.out), ("--json", a.json)):  # checked before a minute of casting
        if path is not None and (path.is_dir() or not path.parent.is_dir()):
            ap.error(f"{opt} must name a file in an existing folder, got {path}")
    results, maps = {}, {}
    for name, scene in frames(a.width).items():
        r = measure(scene)
        results[name] = {k: v for k, v in r.items() if k != "maps"}
        print(f"{name} ({r['shape'][0]} x {r['shape'][1]}, {r['pixels']} hit pixels, field {r['samples']} samples):")
        for g, cmp in r["errors"].items():
            print(f"  {g} ({cmp['field vs rays64']['pixels']} px): " + "; ".join(
                f"{k} sky {v['sky_mean']:.4f}/{v['sky_p99']:.4f} ground {v['ground_mean']:.4f}/{v['ground_p99']:.4f}"
                for k, v in cmp.items()))
        print("  seconds: " + ", ".join(f"{k} {v:.3f}" for k, v in r["seconds"].items()))
        if "with" not in name:
            maps["render's default frame" if name == "default frame" else "dataset frame"] = r["maps"]
    figure(maps, a.out)
    if a.json:
        tmp = a.json.with_name(a.json.name + ".tmp")
        tmp.write_text(json.dumps(results, indent=1))
        tmp.replace(a.json)
    print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

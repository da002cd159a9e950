#!/usr/bin/env python
"""How often detectors call the earthlib spectra skin when those lie in shade, against in the open sun.

    python scripts/shade_check.py [--data out/pipeline/test] [--model PATH ...] [--draws 20] [--seed 0]

A surface in the open reads, after the empirical line (fitted on sunlit panels), about its own reflectance times a
geometric factor: every band alike. A surface in shade is lit by the sky alone. It reads its reflectance times its
sky view V times the sky's share of the panels' light, D / (B cos(sun zenith) + D), band by band. The clear sky is
blue, so that share falls from the green band to 1580 nm: shade tilts a spectrum. It can give a bare soil skin's
high NDSI.

Each earthlib spectrum of a partition is drawn ``--draws`` times under the suns of ``--data`` (their zenith and
atmosphere: the SPECTRL2 light of that dataset in its bands, ``detectors.lut.train.training_skies``), a random camera
zenith (0-90°) and relative azimuth (0-180°), and a random factor (open sun) or sky view (shade) V in [0.3, 1]. Each
model judges the drawn pixels with its own configuration inputs (the diffuse share is the sun's, at 544 nm); the
pixels at or below the brightness floor are not judged. Prints a Markdown table: per model and partition, the share
of draws called skin in the open sun and in shade, and the earthlib classes of the shaded false alarms.

The light is simplified: no light from the ground, an isotropic sky, a horizontal panel. Default models:
exports/detector.onnx and the thesis's static box."""

from __future__ import annotations

import argparse
import sys
from collections import Counter
from pathlib import Path

import torch

from torchskin.confusers import band_reflectance, library
from torchskin.dataset.files import dataset_bands, manifest
from torchskin.detectors.features import DIFFUSE_SHARE, MIN_REFLECTANCE
from torchskin.detectors.lut.train import SKY_VIEW, training_skies
from torchskin.evaluation import load_candidate

#: the range of the open-sun factor and of the shaded surface's sky view (as the lut's training draws them)
VIEW = SKY_VIEW


def run(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default="out/pipeline/test", help="a dataset whose suns light the draws")
    ap.add_argument("--model", action="append", default=None, help="a model to judge (repeatable)")
    ap.add_argument("--draws", type=int, default=20, help="draws per earthlib spectrum")
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args(argv)
    data = Path(a.data)
    if manifest(data) is None:
        print(f"shade_check: error: --data {a.data!r} is not a torchskin dataset", file=sys.stderr)
        return 2
    if manifest(data).get("light_model") != "spectrl2":
        print(f"shade_check: error: --data {a.data!r} is not lit by SPECTRL2 (its sky has no colour)", file=sys.stderr)
        return 2
    if a.draws < 1:
        print(f"shade_check: error: --draws must be at least 1, got {a.draws}", file=sys.stderr)
        return 2
    models = a.model or ["exports/detector.onnx", "static"]
    try:
        cands = [load_candidate(p) for p in models]
    except ValueError as e:
        print(f"shade_check: error: {e}", file=sys.stderr)
        return 2
    bands = dataset_bands(data)
    skies = training_skies(data, "line", bands)
    assert skies is not None  # a SPECTRL2 dataset
    zen, share, sky = skies.zenith_deg, skies.diffuse_share, skies.sky
    takes_share = [c.name for c in cands if DIFFUSE_SHARE in c.features]
    if takes_share and not bool(share.isfinite().all()):
        print(f"shade_check: error: {', '.join(takes_share)} {'takes' if len(takes_share) == 1 else 'take'} the diffuse share, which --data {a.data!r} does not "
              "record (no band at 544 nm)", file=sys.stderr)
        return 2
    g = torch.Generator().manual_seed(a.seed)
    print(f"{len(zen)} suns of {data}; sky share of the light, mean per band "
          + ", ".join(f"{c:g} nm {v:.3f}" for c, v in zip(bands.centers, sky.mean(0).tolist())), flush=True)
    lines = ["| model | partition | called skin in the open sun | in shade | classes of the shaded false alarms |",
             "|---|---|---|---|---|"]
    for part in ("train", "test"):
        names, C = band_reflectance(list(bands.centers), part)
        classes = dict(zip(*library(part)[:2]))
        C = C.double()
        m, k = len(C), a.draws
        j = torch.randint(len(zen), (k, m), generator=g).reshape(-1)
        cam = torch.rand(k * m, generator=g, dtype=torch.float64) * 90.0
        rel = torch.rand(k * m, generator=g, dtype=torch.float64) * 180.0
        lo, hi = VIEW
        v = lo + (hi - lo) * torch.rand(k * m, 1, generator=g, dtype=torch.float64)
        R = C.repeat(k, 1)
        lit = {"sun": (R * v).float(), "shade": (R * v * sky[j]).float()}
        values = {"sun_zenith_deg": zen[j], "camera_zenith_deg": cam, "relative_azimuth_deg": rel,
                  DIFFUSE_SHARE: share[j], "range_m": torch.full_like(cam, 50.0)}
        for c in cands:
            X = torch.stack([values[f] for f in c.features], 1).float() if c.features else torch.zeros(k * m, 0)
            called = {}
            for light, Rl in lit.items():
                judged = Rl.mean(1) > MIN_REFLECTANCE
                called[light] = c.decide(Rl, X).bool() & judged
            top = Counter(classes[names[i % m]] for i in torch.nonzero(called["shade"]).squeeze(1).tolist())
            n_shade = int(called["shade"].sum())
            words = ", ".join(f"{cls} {n / max(n_shade, 1):.0%}" for cls, n in top.most_common(3)) or "none"
            lines.append(f"| {c.name} | {part} ({m} spectra x {k}) | {float(called['sun'].float().mean()):.2e} | "
                         f"{float(called['shade'].float().mean()):.2e} | {words} |")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(run())

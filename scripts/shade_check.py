#!/usr/bin/env python
"""How often detectors call the earthlib spectra skin when those lie in shade, against in the open sun.

    python scripts/shade_check.py [--data out/pipeline/test] [--model PATH ...] [--draws 20] [--seed 0]

A surface in the open reads, after the empirical line (fitted on sunlit panels), about its own reflectance times a
geometric factor: every band alike. A surface in shade is lit by the sky alone. It reads its reflectance times its
sky view V times the sky's share of the panels' light, band by band. The clear sky is blue, so that share falls
from the green band to 1580 nm: shade tilts a spectrum. It can give a bare soil skin's high NDSI.

Each earthlib spectrum of a partition is drawn ``--draws`` times under the suns of ``--data`` (their zenith and
atmosphere: the SPECTRL2 light of that dataset in its bands, ``detectors.lut.train.training_skies``), a random camera
zenith (0-90°) and relative azimuth (0-180°), and a random V in [0.3, 1] (the open sun's geometric factor, or the
shaded surface's sky view). Three lights:

- open sun: the spectrum times V;
- shade as the ``lut`` kind trains on it: times V and the whole diffuse light's share, D / (B cos(zenith) + D)
  (``Skies.sky``: the circumsolar part of D included);
- cast shadow: times V and the isotropic sky's share alone (``Skies.shadow``), as the renderer shades a shadow
  (the circumsolar light is blocked with the sun): darker and bluer.

No light from the ground enters either shade, which makes both bluer than a shadow on open ground. Each model
judges the drawn pixels in its own bands, with its own configuration inputs (the diffuse share is the sun's, at
544 nm); pixels at or below the brightness floor are not judged. Prints a Markdown table: per model and partition,
the share of draws called skin under each light, and the earthlib classes of the cast-shadow false alarms. Default
models: exports/detector.onnx and the thesis's static box."""

from __future__ import annotations

import argparse
import sys
from collections import Counter
from pathlib import Path

import torch

from torchskin.confusers import band_reflectance, library
from torchskin.dataset.files import dataset_bands, manifest, require_bands
from torchskin.detectors.features import DIFFUSE_SHARE, MIN_REFLECTANCE
from torchskin.detectors.lut.train import SKY_VIEW, training_skies
from torchskin.evaluation import load_candidate

#: the open sun's geometric factor and the shaded surface's sky view, uniform (the lut's shaded draws' range)
VIEW = SKY_VIEW
#: configuration inputs this check can give a model
CONFIG = ("sun_zenith_deg", "camera_zenith_deg", "relative_azimuth_deg", DIFFUSE_SHARE, "range_m")


def fail(text: str) -> int:
    print(f"shade_check: error: {text}", file=sys.stderr)
    return 2


def run(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default="out/pipeline/test", help="a dataset whose suns light the draws")
    ap.add_argument("--model", action="append", default=None, help="a model to judge (repeatable)")
    ap.add_argument("--draws", type=int, default=20, help="draws per earthlib spectrum")
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args(argv)
    if a.draws < 1:
        return fail(f"--draws must be at least 1, got {a.draws}")
    data = Path(a.data)
    try:
        m = manifest(data)
        if m is None:
            return fail(f"--data {a.data!r} is not a torchskin dataset")
        if m.get("light_model") != "spectrl2":
            return fail(f"--data {a.data!r} is not lit by SPECTRL2 (its sky has no colour)")
        cands = [load_candidate(p) for p in (a.model or ["exports/detector.onnx", "static"])]
        have = list(dataset_bands(data).centers)
        for c in cands:  # each model's bands, before any row is read
            require_bands(data, c.bands, "the static thesis box" if c.kind == "static" else f"--model {c.name}")
            unknown = [f for f in c.features if f not in CONFIG]
            if unknown:
                return fail(f"--model {c.name} takes {', '.join(unknown)}, which this check does not draw")
        skies = training_skies(data, "line", dataset_bands(data))
    except ValueError as e:
        return fail(str(e))
    if skies is None or len(skies.zenith_deg) == 0:
        return fail(f"--data {a.data!r} has no frame with a sunlit empirical line (no sun to light the draws)")
    zen, share = skies.zenith_deg, skies.diffuse_share
    takes_share = [c.name for c in cands if DIFFUSE_SHARE in c.features]
    if takes_share and not bool(share.isfinite().all()):
        return fail(f"{', '.join(takes_share)} {'takes' if len(takes_share) == 1 else 'take'} the diffuse share, "
                    f"which --data {a.data!r} does not record (no band at 544 nm)")
    g = torch.Generator().manual_seed(a.seed)
    print(f"{len(zen)} suns of {data}; the panels' light from the sky, mean per band (whole diffuse / isotropic "
          "sky): " + ", ".join(f"{c:g} nm {v:.3f} / {w:.3f}"
                               for c, v, w in zip(have, skies.sky.mean(0).tolist(), skies.shadow.mean(0).tolist())),
          flush=True)
    lines = ["| model | partition | called skin in the open sun | in shade, as the lut trains | in a cast shadow | "
             "classes of the cast-shadow false alarms |", "|---|---|---|---|---|---|"]
    for part in ("train", "test"):
        names, C = band_reflectance(have, part)
        classes = dict(zip(*library(part)[:2]))
        n, k = len(C), a.draws
        j = torch.randint(len(zen), (k * n,), generator=g)
        values = {"sun_zenith_deg": zen[j], "camera_zenith_deg": torch.rand(k * n, generator=g, dtype=torch.float64) * 90,
                  "relative_azimuth_deg": torch.rand(k * n, generator=g, dtype=torch.float64) * 180,
                  DIFFUSE_SHARE: share[j], "range_m": torch.full((k * n,), 50.0, dtype=torch.float64)}
        lo, hi = VIEW
        R = C.double().repeat(k, 1) * (lo + (hi - lo) * torch.rand(k * n, 1, generator=g, dtype=torch.float64))
        lights = {"sun": R, "trained": R * skies.sky[j], "shadow": R * skies.shadow[j]}
        for c in cands:
            cols = [min(range(len(have)), key=lambda i: abs(have[i] - b)) for b in c.bands]
            X = torch.stack([values[f] for f in c.features], 1).float() if c.features else torch.zeros(k * n, 0)
            called = {}
            for light, Rl in lights.items():
                Rc = Rl[:, cols].float()
                called[light] = c.decide(Rc, X).bool() & (Rc.mean(1) > MIN_REFLECTANCE)
            hits = torch.nonzero(called["shadow"]).squeeze(1).tolist()
            top = Counter(classes[names[i % n]] for i in hits)
            words = ", ".join(f"{cls} {v / len(hits):.0%}" for cls, v in top.most_common(3)) or "none"
            share_of = {light: float(v.float().mean()) for light, v in called.items()}
            lines.append(f"| {c.name} | {part} ({n} spectra x {k}) | {share_of['sun']:.2e} | {share_of['trained']:.2e} "
                         f"| {share_of['shadow']:.2e} | {words} |")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(run())

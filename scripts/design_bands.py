#!/usr/bin/env python
"""Which bands to buy: the best k bands (k = 1 ... K) for skin detection at the scene false-alarm budget, per
detector range, searched greedily over bands synthesised from datasets rendered once at fine spectral sampling.

    torchskin generate --bands 400:1700:10 --configs 960 --seed 1 --out fine_train
    torchskin generate --bands 400:1700:10 --configs 960 --seed 2 --config heldout.toml --out fine_heldout
    torchskin generate --bands 400:1700:10 --configs 960 --seed 3 --config heldout.toml --out fine_fresh
    python scripts/design_bands.py --data fine_train --heldout fine_heldout --fresh fine_fresh
                                   [--ranges silicon,ingaas,both] [--k-max 6] [--step 20] [--fwhm 20] [--trees 30]
                                   [--max-rows 100000] [--out out/design]

Each candidate band (every ``--step`` nm, ``--fwhm`` wide, inside the range: silicon 400-1000 nm, InGaAs
900-1700 nm, or both) is synthesised from the fine columns as ``detect`` synthesises a hyperspectral cube. A set is
scored by a proxy learner (the lookup-table kind's LightGBM, ``--trees`` trees, no table): held-out Pd of sunlit
skin at scene Pfa <= 1e-4, the threshold set on the held-out non-skin rows (``evaluation.band_design``). The
search chooses on the held-out rows, so every chosen set (and the thesis's four bands) is then scored on the
fresh set at the held-out threshold: Pd of sunlit skin and the scene Pfa it reaches there. Writes
OUT/design.json, OUT/design.md (the table) and OUT/design.png (fresh Pd against k per range, the thesis's bands
marked).

These are proxy scores, for ranking band sets; the detector kind itself, trained and calibrated on full datasets,
scores higher (``scripts/camera_compare.py``: the thesis's bands 0.994 where the proxy gives less).
"""

import argparse
import json
import sys
from pathlib import Path


def run(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", required=True, help="training dataset rendered at fine spectral sampling")
    ap.add_argument("--heldout", required=True, help="held-out dataset in the same bands (another seed)")
    ap.add_argument("--fresh", required=True, help="fresh dataset in the same bands (a third seed), for the final sets")
    ap.add_argument("--ranges", default="silicon,ingaas,both", help="detector ranges (silicon, ingaas, both)")
    ap.add_argument("--k-max", type=int, default=6)
    ap.add_argument("--step", type=float, default=20.0, help="candidate band centres every STEP nm")
    ap.add_argument("--fwhm", type=float, default=20.0, help="candidate bands' FWHM, nm (0: monochromatic)")
    ap.add_argument("--trees", type=int, default=30)
    ap.add_argument("--max-rows", type=int, default=60_000, help="rows drawn from each dataset")
    ap.add_argument("--budget", type=float, default=1e-4, help="scene false-alarm budget")
    ap.add_argument("--out", default="out/design")
    a = ap.parse_args(argv)
    from tqdm import tqdm

    from torchskin.bands import INDEX_BANDS, Band
    from torchskin.evaluation.band_design import RANGES, candidates, fresh_pd, greedy, load_design_rows
    from torchskin.io import write_text

    ranges = [r.strip() for r in a.ranges.split(",")]
    if any(r not in RANGES for r in ranges):
        ap.error(f"--ranges must name {', '.join(RANGES)}, got {a.ranges!r}")
    if not (1 <= a.k_max <= 10) or a.step <= 0 or a.fwhm < 0 or a.trees < 1 or not (0 < a.budget < 1):
        ap.error("--k-max in 1..10, --step > 0, --fwhm >= 0, --trees >= 1, --budget in (0, 1)")
    out = Path(a.out)
    try:  # before minutes of work
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        ap.error(f"--out {a.out!r} cannot be made a folder ({e.strerror})")
    try:
        rows = load_design_rows(a.data, a.heldout, a.max_rows, fresh_dir=a.fresh)
    except ValueError as e:
        ap.error(str(e))
    within = (min(rows.centres), max(rows.centres))
    result = {"options": vars(a), "ranges": {}}
    for r in ranges:
        cands = candidates(RANGES[r], a.step, a.fwhm, within)
        if len(cands) < a.k_max:
            ap.error(f"range {r}: {len(cands)} candidate bands inside the data's {within[0]:g}-{within[1]:g} nm")
        total = sum(len(cands) - k for k in range(a.k_max))
        with tqdm(total=total, desc=f"design {r}", unit="set") as bar:
            steps = greedy(rows, cands, a.k_max, a.trees, a.budget, progress=bar.update)
        result["ranges"][r] = [{"k": st["k"], **fresh_pd(rows, [Band(c, f) for c, f in st["bands"]], a.trees,
                                                         a.budget)} for st in steps]
    result["thesis"] = fresh_pd(rows, list(INDEX_BANDS), a.trees, a.budget)
    write_text(out / "design.json", json.dumps(result, indent=1))
    lines = ["| range | k | bands (centre/FWHM nm) | held-out Pd sunlit | fresh Pd sunlit | fresh Pfa scene |",
             "|---|---|---|---|---|---|"]

    def row(name, k, bands, s):
        return (f"| {name} | {k} | {bands} | {s['pd_sunlit']:.3f} | {s['fresh_pd_sunlit']:.3f} | "
                f"{s['fresh_pfa_scene']:.1e} |")

    for r, steps in result["ranges"].items():
        for st in steps:
            lines.append(row(r, st["k"], ", ".join(f"{c:g}/{f:g}" for c, f in st["bands"]), st))
    lines.append(row("thesis", 4, "544, 633, 1080, 1580 (monochromatic)", result["thesis"]))
    write_text(out / "design.md", "\n".join(lines) + "\n")
    print("\n".join(lines))
    figure(result, out / "design.png")
    print(f"wrote {out / 'design.json'}, {out / 'design.md'}, {out / 'design.png'}")
    return 0


def figure(result: dict, path: Path) -> None:
    from torchskin.plots import pyplot, save_figure

    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    for k, (r, steps) in enumerate(result["ranges"].items()):
        ax.plot([s["k"] for s in steps], [s["fresh_pd_sunlit"] for s in steps], "o-", color=f"C{k}", label=r)
    t = result["thesis"]
    ax.plot([4], [t["fresh_pd_sunlit"]], "k*", ms=12, label="thesis bands (544, 633, 1080, 1580 nm)")
    ax.set_xlabel("number of bands k (greedy forward selection)")
    ax.set_ylabel("proxy Pd, sunlit skin of the fresh set")
    ax.set_ylim(0, 1.02)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="lower right")
    ax.set_title(f"Best k bands, threshold at held-out scene Pfa <= {result['options']['budget']:g} (proxy learner)",
                 fontsize=10)
    fig.tight_layout()
    save_figure(fig, path)


if __name__ == "__main__":
    sys.exit(run())

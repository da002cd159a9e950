#!/usr/bin/env python
"""How much the held-out figures move when only the training data is drawn again: the demo's boundaries
training (`torchskin train` defaults, 1,000 steps) on train sets of the same sampling drawn with different
seeds, each calibrated to the budgets on one held-out set (seed 2, earthlib test partition, as
`pipeline_generate.py`) and evaluated on it. The spread is the noise floor of a comparison between two
samplings, or two training setups, made with one training run each.

    python scripts/seed_spread.py [--work out/seed_spread] [--seeds 1 11 21] [--train-configs 9600]
                                  [--heldout-configs 2400]

Seed 1 is the demo's own train set, so its row is the README's held-out row for `boundaries.pt`. Prints one row
per seed and the spread (range, sample standard deviation); datasets and models already in WORK are reused.
About four minutes a seed on two cores.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from torchskin.cli import main
from torchskin.evaluation import calibrate_to_budget

#: (column, section of the evaluation, key): the figures compared
FIGURES = (("Pd sunlit", "overall", "pd_sunlit"),
           ("mean over configs", "overall", "pd_sunlit_mean_over_configs"),
           ("sun >= 60 deg, mean over configs", "sun_zenith_ge_60", "pd_sunlit_mean_over_configs"),
           ("Pd shadowed", "overall", "pd_shadow"),
           ("Pd back-lit", "overall", "pd_backlit"))


def run(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--work", default="out/seed_spread")
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 11, 21])
    ap.add_argument("--train-configs", type=int, default=9600)
    ap.add_argument("--heldout-configs", type=int, default=2400)
    a = ap.parse_args(argv)
    if len(a.seeds) < 2 or 2 in a.seeds:
        ap.error("--seeds needs two or more seeds, not 2 (the held-out set's)")
    work = Path(a.work)
    work.mkdir(parents=True, exist_ok=True)
    for name, part in (("train", "train"), ("heldout", "test")):
        (work / f"{name}.toml").write_text(f'[confusers]\npartition = "{part}"\n\n[clothing]\npartition = "{part}"\n')

    def generate(out: Path, toml: str, n: int, seed: int) -> int:
        return main(["generate", "--config", str(work / toml), "--configs", str(n), "--seed", str(seed), "--out",
                     str(out), "--resume", "--quiet"])

    if generate(work / "heldout", "heldout.toml", a.heldout_configs, 2):
        return 1
    rows = []
    for seed in a.seeds:
        print(f"[seed_spread] seed {seed}", flush=True)
        trained, model, ev = work / f"boundaries{seed}.trained.pt", work / f"boundaries{seed}.pt", work / f"eval{seed}.json"
        if generate(work / f"train{seed}", "train.toml", a.train_configs, seed):
            return 1
        if not trained.exists() and main(["train", "--data", str(work / f"train{seed}"), "--steps", "1000", "--out",
                                          str(trained)]):
            return 1
        calibrate_to_budget(trained, str(work / "heldout"), model)
        if main(["evaluate", "--data", str(work / "heldout"), "--model", str(model), "--save", str(ev)]):
            return 1
        with open(ev) as fh:
            m = json.load(fh)["models"][0]
        rows.append([m[section][key] for _, section, key in FIGURES])
    x = np.array(rows)
    print("seed   " + " | ".join(name for name, *_ in FIGURES))
    for seed, r in zip(a.seeds, x, strict=True):
        print(f"{seed:<6d} " + " | ".join(f"{v:.4f}" for v in r))
    print("range  " + " | ".join(f"{v:.4f}" for v in x.max(0) - x.min(0)))
    print("sd     " + " | ".join(f"{v:.4f}" for v in x.std(0, ddof=1)))
    return 0


if __name__ == "__main__":
    sys.exit(run())

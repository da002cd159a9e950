"""Dataset generation speed of this checkout against another (an earlier commit's worktree), measured the same way
in both and alternated in fresh processes, so that the ratio is measured side by side on one machine:

    git worktree add /tmp/before <commit>
    .venv/bin/python scripts/bench_dataset_against.py --ref /tmp/before [--groups 32] [--rounds 3] [--json out.json]

Each process imports torchskin from its checkout, generates one warm-up shard and then ``--groups`` pose groups of
the default config at 256 x 256 (``dataset.generate.generate``, the public API both commits share; shards
written), eager and with the compiled kernels. ``--allow-avx2-compile`` lets the compiled kernels run on a CPU
whose capability torchskin has not validated for them (``devices.COMPILED_CPU_CAPABILITIES``; AVX2), for timing
only.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

CHILD = r"""
import json, sys, tempfile, time, warnings
warnings.filterwarnings("ignore")
groups, allow = int(sys.argv[1]), sys.argv[2] == "1"
import torchskin.devices as dv
if allow:
    dv.COMPILED_CPU_CAPABILITIES = ("AVX2", "AVX512")
from torch._dynamo.utils import counters
from torchskin.dataset.config import resolve_config
from torchskin.dataset.generate import generate
from torchskin.render.kernels import compiler_available
cfg = resolve_config({"camera": {"width": 256, "height": 256}})
per = cfg["sun"]["per_pose"] * cfg["skin"]["per_pose"]
out = {"groups_per_shard": cfg["sampling"]["groups_per_shard"], "compiler": compiler_available("cpu")}
with tempfile.TemporaryDirectory() as d:
    for compiled in (False, True):
        generate(cfg, per * cfg["sampling"]["groups_per_shard"], 99, d + f"/w{compiled}", quiet=True, compile=compiled)
        g0 = counters["stats"]["unique_graphs"]
        t0 = time.perf_counter()
        generate(cfg, per * groups, 0, d + f"/t{compiled}", quiet=True, compile=compiled)
        dt = time.perf_counter() - t0
        out["compiled" if compiled else "eager"] = {"configs_per_s": per * groups / dt, "seconds": dt,
                                                    "graphs_compiled_after_warmup": counters["stats"]["unique_graphs"] - g0}
print(json.dumps(out))
"""


def run(tree: Path, groups: int, allow: bool) -> dict:
    env_path = str(tree)
    # run in the checkout itself: ``python -c`` puts the working directory first on sys.path
    proc = subprocess.run([sys.executable, "-c", CHILD, str(groups), "1" if allow else "0"], capture_output=True,
                          text=True, env={**os.environ, "PYTHONPATH": env_path}, check=False, cwd=tree)
    if proc.returncode != 0:
        raise SystemExit(f"{tree}: {proc.stderr.strip().splitlines()[-1] if proc.stderr.strip() else proc.returncode}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ref", required=True, type=Path, help="the other checkout (e.g. a git worktree of an earlier commit)")
    ap.add_argument("--groups", type=int, default=32)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--allow-avx2-compile", action="store_true")
    ap.add_argument("--json", type=Path)
    a = ap.parse_args()
    here = Path(__file__).resolve().parents[1]
    rounds = []
    for r in range(a.rounds):
        ref, new = run(a.ref.resolve(), a.groups, a.allow_avx2_compile), run(here, a.groups, a.allow_avx2_compile)
        row = {"round": r, "ref": ref, "new": new,
               "ratio_eager": new["eager"]["configs_per_s"] / ref["eager"]["configs_per_s"],
               "ratio_compiled": new["compiled"]["configs_per_s"] / ref["compiled"]["configs_per_s"]}
        rounds.append(row)
        print(f"round {r}: ref eager {ref['eager']['configs_per_s']:.0f} compiled {ref['compiled']['configs_per_s']:.0f} "
              f"(graphs after warm-up {ref['compiled']['graphs_compiled_after_warmup']}) | new eager "
              f"{new['eager']['configs_per_s']:.0f} compiled {new['compiled']['configs_per_s']:.0f} (graphs after "
              f"warm-up {new['compiled']['graphs_compiled_after_warmup']}) | ratio eager {row['ratio_eager']:.2f} "
              f"compiled {row['ratio_compiled']:.2f} configs/s", flush=True)
    summary = {"median_ratio_eager": statistics.median(r["ratio_eager"] for r in rounds),
               "median_ratio_compiled": statistics.median(r["ratio_compiled"] for r in rounds), "rounds": rounds}
    print(f"median ratio: eager {summary['median_ratio_eager']:.2f}, compiled {summary['median_ratio_compiled']:.2f}")
    if a.json:
        a.json.write_text(json.dumps(summary, indent=1))


if __name__ == "__main__":
    main()

"""The onboard detector against an earlier commit's, in one process, frame by frame alternately.

    python scripts/bench_detector_against.py [COMMIT] [--graphs shipped|default] [--threads N] [--rounds R]
                                             [--tile T] [--dark SHARE]

COMMIT (default 2afa293, the four-edge graph before the NDVN rule and the brightness floor) is extracted with
``git archive`` into a temporary directory and imported as the package ``torchskin_old``. Each side runs its own
commit's onboard code on its own graph, 2afa293 without a brightness floor (it had none by default), this
checkout with the shipped floor (the shipped model's ``min_reflectance``, ``evaluation.MIN_REFLECTANCE``):

- ``--graphs shipped`` (default): the detector each commit shipped (``exports/detector.onnx`` at COMMIT; this
  checkout's ``torchskin/data/detector.onnx``), the trained boxes a user runs;
- ``--model PATH``: this checkout runs that ``detector.onnx`` (a new kind's export) against COMMIT's shipped one;
- ``--graphs default``: each commit's export code on a default box model (``BoxModel``; ``BoundaryModel`` in
  older commits) initialised from seed 0 (an untrained model's boxes, so the share of a frame they take, and with
  it the floor's path, is chance).

Both run the benchmark frame of ``torchskin bench --only detector_onnx`` (1024 x 1024 x 4 float32) in alternating
order; the read floor is one numpy sum of the frame. Prints the medians, the median of the paired ratios
(new / old), the ratio to the read floor and the share of the frame each detector takes.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


#: the benchmark frame's configuration, per feature (a model takes those it names, in its order)
BENCH_CONFIG = {"sun_zenith_deg": 40.0, "camera_zenith_deg": 30.0, "relative_azimuth_deg": 60.0, "diffuse_share": 0.2}
FEATURES = ("sun_zenith_deg", "camera_zenith_deg", "relative_azimuth_deg")


def config_of(features) -> np.ndarray:
    """The benchmark configuration (1, k) of a detector taking ``features``."""
    return np.array([[BENCH_CONFIG[f] for f in features]])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("commit", nargs="?", default="2afa293")
    ap.add_argument("--graphs", choices=("shipped", "default"), default="shipped")
    ap.add_argument("--dark", type=float, default=0.0,
                    help="share of the frame's pixels made dark in every band (reflectance 0-0.004, below the "
                         "floor: shadows), scattered over every tile (default 0: the benchmark frame)")
    ap.add_argument("--threads", type=int, default=min(os.cpu_count() or 1, 8))
    ap.add_argument("--rounds", type=int, default=60)
    ap.add_argument("--tile", type=int, default=65536)
    ap.add_argument("--model", default=None,
                    help="a detector.onnx this checkout runs instead of its shipped one (e.g. a new kind's export, "
                         "timed against COMMIT's shipped detector; its own brightness floor)")
    args = ap.parse_args()
    if not 0.0 <= args.dark <= 1.0:
        ap.error(f"--dark must be a share in [0, 1], got {args.dark}")
    if args.rounds < 1 or args.threads < 1:
        ap.error("--rounds and --threads must be at least 1")
    with tempfile.TemporaryDirectory() as d:
        src = os.path.join(d, "src")
        os.makedirs(src)
        archive = subprocess.run(["git", "-C", ROOT, "archive", args.commit, "torchskin"], check=True,
                                 capture_output=True).stdout
        subprocess.run(["tar", "-x", "-C", src], input=archive, check=True)
        # the old graph, exported by the old code (in a child, where its package is still named torchskin)
        os.makedirs(os.path.join(d, "old"))
        if args.graphs == "shipped":
            with open(os.path.join(d, "old", "detector.onnx"), "wb") as f:
                f.write(subprocess.run(["git", "-C", ROOT, "show", f"{args.commit}:exports/detector.onnx"],
                                       check=True, capture_output=True).stdout)
        else:
            code = ("import sys; sys.path.insert(0, sys.argv[1]); import torch; torch.manual_seed(0)\n"
                    "from torchskin.export import export\n"
                    "try:\n from torchskin.detectors import boxes as B\n"
                    "except ImportError:\n from torchskin import boundaries as B\n"  # commits before the kinds
                    "export((getattr(B, 'BoxModel', None) or B.BoundaryModel)(), sys.argv[2])")
            subprocess.run([sys.executable, "-c", code, src, os.path.join(d, "old")], check=True,
                           capture_output=True)
        os.rename(os.path.join(src, "torchskin"), os.path.join(src, "torchskin_old"))
        sys.path.insert(0, src)
        import torch
        import torchskin_old.onboard as old_onboard  # type: ignore[import-not-found]

        from torchskin.detectors.boxes import BoxModel
        from torchskin.evaluation import MIN_REFLECTANCE
        from torchskin.export import export
        from torchskin.onboard import SHIPPED_DETECTOR, OnboardDetector

        if args.model:
            path = args.model
        elif args.graphs == "shipped":
            path = str(SHIPPED_DETECTOR)
        else:
            torch.manual_seed(0)
            path = export(BoxModel(), os.path.join(d, "new"))["detector"]
        Old = getattr(old_onboard, "OnboardDetector", None) or old_onboard.Detector
        old = Old(os.path.join(d, "old", "detector.onnx"), threads=args.threads)
        new = OnboardDetector(path, threads=args.threads, tile=args.tile)
        rng = np.random.default_rng(0)
        cube = (rng.random((1, 4, 1024, 1024), dtype=np.float32) * 0.6 + 0.02).astype(np.float32)
        if args.dark > 0:
            dark = rng.random((1024, 1024)) < args.dark
            cube[0][:, dark] = rng.random((4, int(dark.sum())), dtype=np.float32) * 0.004
        cfg = config_of(getattr(old, "features", FEATURES))
        cfg_new = config_of(new.features)
        floor = new.default_min_reflectance if args.graphs == "shipped" or args.model else MIN_REFLECTANCE
        runs = {"old": lambda: old(cube, cfg), "new": lambda: new(cube, cfg_new, min_reflectance=floor),
                "read": lambda: float(cube.sum())}
        share = {k: float(runs[k]()["mask"].mean()) for k in ("old", "new")}
        for f in runs.values():
            for _ in range(5):
                f()
        times: dict[str, list[float]] = {k: [] for k in runs}
        for i in range(args.rounds):
            for k in (("old", "new", "read") if i % 2 else ("new", "old", "read")):
                t0 = time.perf_counter()
                runs[k]()
                times[k].append(time.perf_counter() - t0)
    t = {k: np.array(v) for k, v in times.items()}
    print(f"{args.threads} threads, {args.rounds} rounds: {args.commit} {1e3 * np.median(t['old']):.2f} ms, "
          f"this checkout {1e3 * np.median(t['new']):.2f} ms per 1 MP frame; median paired ratio "
          f"{np.median(t['new'] / t['old']):.3f}; read floor {1e3 * np.median(t['read']):.2f} ms, "
          f"this checkout / floor {np.median(t['new']) / np.median(t['read']):.2f}; {args.graphs} graphs, share "
          f"taken {share['old']:.3f} (old), {share['new']:.3f} (new, floor {floor:g})"
          + (f"; new: {args.model} ({new.head_name} head)" if args.model else ""))
    return 0


if __name__ == "__main__":
    sys.exit(main())

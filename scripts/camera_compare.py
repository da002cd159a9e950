#!/usr/bin/env python
"""Another camera's bands through the whole detector pipeline: generate, train, calibrate, evaluate, export and
detect on a rendered ENVI cube, with the lookup-table kind, beside the thesis's four bands.

    python scripts/camera_compare.py --bands thesis --bands rededge-mx [--work out/camera]
                                     [--train-configs 9600] [--heldout-configs 2400] [--test-configs 960]

For each band set (``--bands``, repeatable; any ``--bands`` value: a list, a preset, a response table), in
WORK/<name>:

1. datasets as ``make demo`` draws them (``pipeline_generate.py --bands``): WORK/train (seed 1, earthlib train
   partition), WORK/heldout (seed 2) and WORK/test (seed 3), both of the test partition;
2. the ``lut`` kind trained on WORK/train with its pipeline arguments, calibrated to the budgets on WORK/heldout
   (scene non-skin Pfa <= 1e-4, earthlib test Pfa <= 1e-3: ``evaluation.calibrate_to_budget``), evaluated on
   WORK/test, and exported (WORK/export/detector.onnx);
3. ``render``'s default frame (the thesis geometry, 256 x 256, sun at 45 deg zenith, noise on) in those bands,
   its ELM reflectance written as an ENVI cube and read by ``torchskin detect``: Pd of the frame's sunlit skin
   and its false-alarm pixels against the renderer's own labels.

Every set is drawn, trained and judged the same way, so the rows compare cameras, not procedures. Writes
WORK/camera.json and prints one table.
"""

import argparse
import json
import shutil
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent
sys.path.insert(0, str(ROOT))

FRAME = {"size": 256, "sun_zenith_deg": 45.0, "sun_azimuth_deg": 20.0}


def frame_check(detector: Path, bands: str | None, out: Path) -> dict:
    """The detector on ``render``'s default frame in ``bands`` (None: the index bands), through an ENVI cube and
    ``torchskin detect``: Pd of sunlit skin, false-alarm pixels, against the renderer's labels."""
    from PIL import Image

    from torchskin.angles import relative_azimuth_deg
    from torchskin.bands import BandSet, scene_bands
    from torchskin.cli import main
    from torchskin.cubefiles import write_cube
    from torchskin.render.pipeline import render
    from torchskin.render.scene import Camera, Sun, default_scene
    from torchskin.render.sensor import Sensor

    n = FRAME["size"]
    sc = default_scene(camera=Camera(width=n, height=n),
                       sun=Sun(zenith_deg=FRAME["sun_zenith_deg"], azimuth_deg=FRAME["sun_azimuth_deg"]))
    if bands is not None:
        sc.bands = scene_bands(BandSet.parse(bands))
    res = render(sc, sensor=Sensor(seed=0))
    cube = res.reflectance[0, 0].permute(2, 0, 1).cpu().numpy()
    out.mkdir(parents=True, exist_ok=True)
    hdr = write_cube(out / "frame.hdr", cube, "envi", [b.center_nm for b in res.bands], [b.fwhm_nm for b in res.bands])
    rel = relative_azimuth_deg(FRAME["sun_azimuth_deg"], sc.cameras[0].azimuth_deg)
    rc = main(["detect", "--model", str(detector), "--cube", str(hdr), "--sun-zenith", str(FRAME["sun_zenith_deg"]),
               "--camera-zenith", str(sc.cameras[0].zenith_deg), "--relative-azimuth", str(rel), "--clip-negative",
               "--out", str(out / "mask.png")])
    if rc:
        raise SystemExit(rc)
    mask = np.asarray(Image.open(out / "mask.png")) > 127
    skin, lit = res.skin[0].cpu().numpy(), res.lit[0, 0].cpu().numpy()
    sunlit = skin & lit
    return {"sunlit_skin_pixels": int(sunlit.sum()), "pd_sunlit": float((mask & sunlit).sum() / max(sunlit.sum(), 1)),
            "false_alarm_pixels": int((mask & ~skin).sum()), "nonskin_pixels": int((~skin).sum())}


def evaluated(model: Path, test: Path) -> dict:
    from torchskin.evaluation import evaluate

    r = evaluate(test, [str(model)])
    o, hi = r["learned"], r["sun_zenith_ge_60"]["learned"]
    return {"bands_nm": r["bands_nm"], "pd_sunlit": o["pd_sunlit"], "pd_shadow": o["pd_shadow"],
            "pd_backlit": o["pd_backlit"], "pd_sun_ge_60_mean_over_configs": hi["pd_sunlit_mean_over_configs"],
            "pfa_earthlib": o["pfa"], "pfa_scene": o["pfa_scene"], "nonskin_pixels": o["nonskin_pixels"],
            "skin_pixels": o["skin_pixels"]}


def camera(bands: str, work: Path, a: argparse.Namespace) -> dict:
    """One band set through the pipeline in ``work``: its test-set figures and its frame check."""
    import pipeline_generate

    from torchskin.cli import main
    from torchskin.detectors import registry
    from torchskin.evaluation import calibrate_to_budget

    rc = pipeline_generate.run(["--work", str(work), "--bands", bands, "--train-configs", str(a.train_configs),
                                "--heldout-configs", str(a.heldout_configs), "--test-configs", str(a.test_configs)])
    if rc:
        raise SystemExit(rc)
    run_args = next(r for r in registry.pipeline_runs() if r.name == "lut").args
    if main(["train", "--data", str(work / "train"), "--out", str(work / "lut.trained.pt"), *run_args]):
        raise SystemExit(1)
    rec = calibrate_to_budget(work / "lut.trained.pt", work / "heldout", work / "lut.pt")
    print(f"[camera] {bands}: calibrated on heldout: {rec['knob']} {rec['before']:.4g} -> {rec['after']:.4g}, scene "
          f"Pfa {rec['pfa_scene']:.2e}", flush=True)
    shutil.rmtree(work / "export", ignore_errors=True)  # this run's model, exported afresh
    if main(["export", "--model", str(work / "lut.pt"), "--out", str(work / "export")]):
        raise SystemExit(1)
    return {**evaluated(work / "lut.pt", work / "test"), "calibration": rec,
            "frame": frame_check(work / "export" / "detector.onnx", bands, work / "frame")}


def run(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--bands", required=True, action="append", help="a camera's bands (any --bands value; repeatable)")
    ap.add_argument("--work", default="out/camera", help="work folder (default out/camera)")
    ap.add_argument("--train-configs", type=int, default=9600)
    ap.add_argument("--heldout-configs", type=int, default=2400)
    ap.add_argument("--test-configs", type=int, default=960)
    a = ap.parse_args(argv)
    from torchskin.bands import BandSet
    from torchskin.io import write_text

    for b in a.bands:
        try:
            BandSet.parse(b)
        except ValueError as e:
            ap.error(str(e))
    work = Path(a.work)
    try:  # before minutes of work
        work.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        ap.error(f"--work {a.work!r} cannot be made a folder ({e.strerror})")
    rows = {b: camera(b, work / (Path(b).stem if b.lower().endswith(".csv") else b.replace("/", "_")), a)
            for b in a.bands}
    write_text(work / "camera.json", json.dumps(rows, indent=1))
    print(f"{'bands':<32}{'Pd sunlit':>10}{'shadow':>8}{'backlit':>8}{'sun>=60':>8}{'Pfa earthlib':>13}"
          f"{'Pfa scene':>11}{'frame Pd':>9}{'frame FA':>9}")
    for name, r in rows.items():
        f = r["frame"]
        print(f"{name[:31]:<32}{r['pd_sunlit']:>10.3f}{r['pd_shadow']:>8.3f}{r['pd_backlit']:>8.3f}"
              f"{r['pd_sun_ge_60_mean_over_configs']:>8.3f}{r['pfa_earthlib']:>13.2e}{r['pfa_scene']:>11.2e}"
              f"{f['pd_sunlit']:>9.3f}{f['false_alarm_pixels']:>9d}")
    print(f"(test sets of {a.test_configs} configurations; budgets calibrated on heldout: scene Pfa <= 1e-4, earthlib "
          f"test <= 1e-3; frame: render's default frame, {FRAME['size']}^2, sun {FRAME['sun_zenith_deg']:g} deg, "
          "through an ENVI cube and torchskin detect; wrote " + str(work / "camera.json") + ")")
    return 0


if __name__ == "__main__":
    sys.exit(run())

"""Run the onboard detector (``exports/detector.onnx``, numpy + onnxruntime, no torch) on a calibrated frame.

A small frame of a skin-covered sphere is rendered (as in ``render_custom_mesh.py``); its ELM reflectance cube
and the frame's configuration (sun zenith, camera zenith, relative azimuth and the sky's diffuse share) go to the
detector, which picks its decision region for that configuration. The script compares it with the thesis's static box.

    .venv/bin/python examples/onboard_detect.py                      # about 10 s on 2 CPU cores
    .venv/bin/python examples/onboard_detect.py --sun-zenith 70 --sun-azimuth 150

Writes ``mask.png`` to ``--out``: learned detector left, static box right; green: detected skin, red: missed
sunlit skin, yellow: false alarms.
"""

import argparse
from pathlib import Path

import numpy as np

from torchskin.angles import relative_azimuth_deg
from torchskin.detectors.features import diffuse_share
from torchskin.io import write_png
from torchskin.onboard import OnboardDetector
from torchskin.render.meshes import sphere_mesh, write_obj
from torchskin.render.pipeline import render
from torchskin.render.scene import Camera, Sun, default_scene
from torchskin.render.sensor import Sensor


def colour(mask: np.ndarray, skin: np.ndarray, sunlit: np.ndarray) -> np.ndarray:
    """An RGB picture of a detection mask against the truth."""
    rgb = np.zeros((*mask.shape, 3), np.uint8)
    rgb[mask & skin] = (26, 217, 51)
    rgb[sunlit & ~mask] = (230, 38, 26)
    rgb[mask & ~skin] = (255, 230, 26)
    return rgb


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", type=Path, default=Path(__file__).resolve().parents[1] / "exports" / "detector.onnx",
                    help="a detector exported by torchskin export (default: the shipped one)")
    ap.add_argument("--size", type=int, default=128, help="image width and height, pixels")
    ap.add_argument("--sun-zenith", type=float, default=45.0)
    ap.add_argument("--sun-azimuth", type=float, default=20.0)
    ap.add_argument("--out", type=Path, default=Path("out/examples/onboard_detect"))
    args = ap.parse_args()

    args.out.mkdir(parents=True, exist_ok=True)
    v, f = sphere_mesh(0.3, subdivisions=3)
    obj = args.out / "sphere.obj"
    write_obj(obj, v + [0.0, 0.0, 1.0], f)  # a skin-covered "head" where the default camera aims
    camera = Camera(width=args.size, height=args.size)  # horizontal (zenith 90), 9.449 m in front, azimuth 0
    scene = default_scene(subject="file", mesh_path=str(obj), camera=camera,
                          sun=Sun(zenith_deg=args.sun_zenith, azimuth_deg=args.sun_azimuth, sky_fraction=0.1))
    result = render(scene, sensor=Sensor())

    # what a camera system hands the detector: ELM reflectance, bands first, float32, one frame per batch row
    cube = result.cube()[None]  # (1, 4, H, W) float32, the layout of reflectance.npy
    det = OnboardDetector(args.model)
    # the frame's configuration in the detector's features: the angles and, for a lookup table, the sky's diffuse
    # share at 544 nm (what a shaded over a sunlit horizontal panel reads; the scene's sky gives sky_fraction times
    # the sun's normal irradiance on the horizontal)
    config = [det.config_row(sun_zenith_deg=args.sun_zenith, camera_zenith_deg=camera.zenith_deg,
                             relative_azimuth_deg=relative_azimuth_deg(args.sun_azimuth, camera.azimuth_deg),
                             diffuse_share=float(diffuse_share(0.1, args.sun_zenith)))]
    out = det(cube, config, negative="clip", min_reflectance=0.005)  # clip: sensor noise makes dark pixels < 0
    print(f"config {det.features} = {np.round(config[0], 1).tolist()}, out of domain: {bool(out['out_of_domain'][0])}")

    skin, sunlit = result.skin[0].numpy(), (result.skin[0] & result.lit[0, 0]).numpy()
    masks = {"learned": out["mask"][0], "static": result.mask[0, 0].numpy()}
    print(f"sunlit skin pixels: {int(sunlit.sum())}")
    for name, m in masks.items():
        print(f"{name}: detected fraction of sunlit skin {(m & sunlit).sum() / max(sunlit.sum(), 1):.3f}, "
              f"false alarms {int((m & ~skin).sum())}")
    gap = np.full((args.size, 4, 3), 128, np.uint8)
    write_png(args.out / "mask.png", np.concatenate([colour(masks["learned"], skin, sunlit), gap,
                                                     colour(masks["static"], skin, sunlit)], axis=1))
    print(f"wrote {args.out / 'mask.png'}")


if __name__ == "__main__":
    main()

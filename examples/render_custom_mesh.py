"""Render a custom mesh: a subject of your own (OBJ or PLY) in the thesis's scene, calibrated by ELM.

Without ``--mesh`` the script writes a small icosphere "head" (radius 0.3 m, centred 1 m above the ground) as
an OBJ and renders that. A mesh of your own must be in metres, +z up, facing +x, standing on z = 0.

    .venv/bin/python examples/render_custom_mesh.py                  # about 10 s on 2 CPU cores
    .venv/bin/python examples/render_custom_mesh.py --mesh me.obj --size 256 --skin V-VI

Writes the band PNGs, ``reflectance.npy`` (bands x H x W), ``mask.png`` and ``render.json`` to ``--out``.
"""

import argparse
import json
from pathlib import Path

from torchskin.render.meshes import sphere_mesh, write_obj
from torchskin.render.outputs import write_outputs
from torchskin.render.pipeline import render
from torchskin.render.scene import Camera, Sun, default_scene
from torchskin.render.sensor import Sensor


def write_sphere_obj(path: Path, radius: float = 0.3, centre_z: float = 1.0) -> Path:
    """An icosphere as an OBJ file: ``v x y z`` lines, then 1-based ``f a b c`` triangles."""
    v, f = sphere_mesh(radius, subdivisions=3)
    write_obj(path, v + [0.0, 0.0, centre_z], f)
    return path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--mesh", type=Path, help="OBJ/PLY subject (metres, z up, facing +x); default: a sphere")
    ap.add_argument("--skin", default="I-II", help="skin preset: a Fitzpatrick type I..VI, or the thesis fits I-II and V-VI")
    ap.add_argument("--size", type=int, default=128, help="image width and height, pixels")
    ap.add_argument("--sun-zenith", type=float, default=40.0)
    ap.add_argument("--sun-azimuth", type=float, default=20.0)
    ap.add_argument("--out", type=Path, default=Path("out/examples/render_custom_mesh"))
    args = ap.parse_args()
    if args.mesh is not None and not args.mesh.is_file():
        ap.error(f"--mesh {str(args.mesh)!r} does not exist")

    args.out.mkdir(parents=True, exist_ok=True)
    mesh = args.mesh or write_sphere_obj(args.out / "sphere.obj")
    scene = default_scene(subject="file", mesh_path=str(mesh), skin=args.skin,
                          camera=Camera(width=args.size, height=args.size),  # horizontal, 9.449 m, aimed at z = 1 m
                          sun=Sun(zenith_deg=args.sun_zenith, azimuth_deg=args.sun_azimuth, sky_fraction=0.1))
    result = render(scene, sensor=Sensor())  # sensor noise on; reflectance comes from the two panels (ELM)

    print(json.dumps(write_outputs(result, scene, args.out), indent=1))  # the frame's summary
    print(f"wrote {', '.join(sorted(p.name for p in args.out.iterdir()))} to {args.out}")


if __name__ == "__main__":
    main()

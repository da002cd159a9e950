"""``torchskin generate``: a randomized, labelled pixel dataset (Parquet shards with a checksummed manifest)."""

from __future__ import annotations

import argparse
import json

from ..errors import check_input_file, check_output_folder
from .options import add_bands, add_device, add_json, add_out_folder, add_overwrite, add_seed, add_surface

#: ``generate --compile`` choices -> ``dataset.generate.generate(compile=...)``
COMPILE_CHOICES: dict[str, bool | str] = {"auto": "auto", "on": True, "off": False}


def cmd_generate(args: argparse.Namespace) -> int:
    """Run ``torchskin generate`` (``dataset.generate.generate``) after checking every input and output."""
    from ..bands import BandSet
    from ..dataset.config import load_config
    from ..dataset.generate import generate
    from ..devices import check_device

    if args.resume and args.overwrite:
        raise ValueError("--resume and --overwrite exclude each other")
    check_output_folder(args.out, "--out")
    if args.config:
        check_input_file(args.config, "--config", (".toml",))
    if args.bands is not None:  # replaces the configuration's [bands] spec; a bad band: one line naming --bands
        BandSet.parse(args.bands)
    cfg = load_config(args.config, bands=args.bands)
    if args.surface:
        cfg["skin"]["surface"] = args.surface  # one of SURFACE_MODELS (argparse choices)
    for p in cfg["subject"]["meshes"]:
        check_input_file(p, "subject.meshes", (".obj", ".ply"))
    if args.backend == "local":
        check_device(args.device)
    if args.seed < 0:
        raise ValueError(f"--seed must be a non-negative integer, got {args.seed}")
    if args.workers is not None and args.workers < 1:
        raise ValueError(f"--workers must be >= 1, got {args.workers}")
    # the extras every dataset needs (render: the scene's rays and light; dataset: Parquet and the confuser
    # library), imported before the progress bar starts so that a missing one is the command's only line
    import earthlib  # noqa: F401
    import open3d  # noqa: F401
    import pvlib  # noqa: F401
    import pyarrow  # noqa: F401
    man = generate(cfg, args.configs, args.seed, args.out, resume=args.resume, overwrite=args.overwrite,
                   quiet=args.quiet or args.json, device=args.device, backend=args.backend, address=args.address,
                   workers=args.workers, images=args.images, compile=COMPILE_CHOICES[args.compile])
    rows = sum(s["rows"] for s in man["shards"])
    if args.json:
        print(json.dumps({"out": str(args.out), "configs": man["configs"], "groups": man["groups"],
                          "shards": len(man["shards"]), "rows": rows}))
    else:  # --quiet hides the progress bar, not the result
        print(f"wrote {len(man['shards'])} shards, {rows} rows ({man['groups']} pose groups) to {args.out}")
    return 0


def add_parser(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """The ``torchskin generate`` command."""
    gp = sub.add_parser("generate", help="generate a randomized labelled pixel dataset (Parquet shards)",
                        description="Draw random sun/camera/subject/skin configurations (TOML config, see "
                                    "torchskin/dataset/config.py), render them and write balanced labelled skin / "
                                    "non-skin pixels as Parquet shards with a checksummed manifest.")
    gp.add_argument("--config", metavar="TOML", help="configuration (default: the built-in one)")
    gp.add_argument("--configs", type=int, default=100, help="number of configurations (default 100)")
    add_surface(gp, lead="overrides the configuration's skin.surface (its default: thesis)", from_config=True)
    add_bands(gp, "the config's [bands] spec, else 544,633,1080,1580; one reflectance column r<centre> a band")
    add_seed(gp, "the dataset's draws, its master seed")
    add_out_folder(gp, "the Parquet shards and their manifest")
    gp.add_argument("--resume", action="store_true", help="keep valid shards of an earlier run, redo the rest")
    add_overwrite(gp, "an existing dataset")
    gp.add_argument("--quiet", action="store_true", help="no progress bar (the one-line summary is still printed)")
    add_device(gp)
    gp.add_argument("--images", action="store_true", help="also store full reflectance cubes (images-*.npy)")
    gp.add_argument("--compile", choices=list(COMPILE_CHOICES), default="auto",
                    help="render with the compiled kernels (torch.compile; seconds to compile, then faster): on, "
                         "off, or auto (default: on from 20,000 configurations when a C++ compiler is present)")
    gp.add_argument("--backend", choices=["local", "ray"], default="local", help="run shards here or on Ray")
    gp.add_argument("--address", help="Ray cluster address (default: start a local cluster)")
    gp.add_argument("--workers", type=int, help="CPUs of the local Ray cluster (default: all)")
    add_json(gp)
    gp.set_defaults(func=cmd_generate)
    return gp

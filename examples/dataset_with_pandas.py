"""Generate a tiny labelled-pixel dataset and read it with pandas (and, with ``--ray``, with Ray Data).

The subject is an icosphere OBJ (``subject.meshes``) rather than an anny body, and the frames are 64 x 64, so
generation takes seconds; the rows are sampled skin / non-skin pixels with their ELM reflectance and indices. The
columns are ``torchskin.dataset.schema.COLUMNS``; ``torchskin.dataset.files.read_rows`` is torchskin's own reader.

    .venv/bin/python examples/dataset_with_pandas.py                 # about 10 s on 2 CPU cores
    .venv/bin/python examples/dataset_with_pandas.py --configs 48 --ray

The command line does the same from a TOML file of these settings: ``torchskin generate --config FILE --configs 12
--out DIR``. Writes the dataset (``shard-*.parquet`` and ``_manifest.json``) to ``--out``/data.
"""

import argparse
from pathlib import Path

import numpy as np
import pandas as pd

from torchskin.dataset.config import resolve_config
from torchskin.dataset.files import manifest, open_dataset, read_rows
from torchskin.dataset.generate import generate
from torchskin.dataset.schema import BAND_COLUMNS
from torchskin.render.meshes import sphere_mesh


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--configs", type=int, default=12, help="sun x skin configurations to render")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--ray", action="store_true", help="also read the shards with ray.data (slow to start)")
    ap.add_argument("--out", type=Path, default=Path("out/examples/dataset_with_pandas"))
    args = ap.parse_args()

    args.out.mkdir(parents=True, exist_ok=True)
    v, f = sphere_mesh(0.35, subdivisions=3)  # a "head" centred 0.9 m up, where the dataset's cameras aim
    obj = args.out / "head.obj"
    obj.write_text("".join(f"v {x} {y} {z + 0.9}\n" for x, y, z in v) + "".join(f"f {a+1} {b+1} {c+1}\n" for a, b, c in f))
    cfg = resolve_config({  # every other key keeps its default (torchskin.dataset.config.SCHEMA)
        "subject": {"meshes": [str(obj)]},
        "camera": {"width": 64, "height": 64, "range_m": [5.0, 20.0]},
        "sun": {"per_pose": 3, "zenith_deg": [0.0, 60.0]},
        "skin": {"per_pose": 2, "types": ["I", "VI"]},
        "sampling": {"groups_per_shard": 1, "pixels_per_class": 32},
    })
    data = args.out / "data"
    man = generate(cfg, args.configs, args.seed, data, overwrite=True, quiet=True)
    print(f"{man['n_shards']} shards, {sum(s['rows'] for s in man['shards'])} rows in {data}")

    # the folder reads as one table: Parquet readers skip _manifest.json (leading underscore), so read it first:
    # manifest() refuses, in one line, a dataset of a schema this torchskin does not read (a newer one's)
    manifest(data)
    df = pd.read_parquet(data, columns=["label", "skin_type", "ndgri", "ndsi", "elm_valid"])
    df = df[df.elm_valid].copy()  # frames whose reference panels were sunlit: their ELM reflectance is physical
    df["pixel"] = df.label.map({True: "skin", False: "non-skin"})
    table = df.groupby(["skin_type", "pixel"]).agg(rows=("ndsi", "size"), ndgri=("ndgri", "mean"), ndsi=("ndsi", "mean"))
    print(table.round(3).reset_index().to_string(index=False))

    # pyarrow directly, with a check that the columns exist (a one-line error for a folder that is not a dataset)
    print("pyarrow rows:", open_dataset(data, ["label", "ndsi"]).count_rows())

    # torchskin's own reader (what training and evaluation read): the rows of frames with a physical ELM as numpy
    # columns, and any band pair's normalized difference as the detectors compute it (NDVN: visible against NIR)
    rows = read_rows(data, ["label", *BAND_COLUMNS])
    ndvn, skin = rows.index("ndvn"), rows["label"]
    print(f"read_rows: {len(rows)} rows ({rows.excluded} of frames without a physical ELM left out); mean NDVN "
          f"of skin {np.nanmean(ndvn[skin]):.3f}, of the rest {np.nanmean(ndvn[~skin]):.3f}")

    if args.ray:  # the same folder as a Ray dataset: one read task per shard, on a local cluster here
        import ray
        from ray.data.expressions import col

        ray.init(num_cpus=2, include_dashboard=False, logging_level="ERROR", log_to_driver=False)
        ray.data.DataContext.get_current().enable_progress_bars = False
        rd = ray.data.read_parquet(str(data), file_extensions=["parquet"])
        means = rd.filter(expr=col("elm_valid")).groupby("label", num_partitions=1).mean("ndsi").to_pandas()
        print("ray.data mean NDSI by label:", dict(zip(means["label"], means["mean(ndsi)"].round(3))))
        ray.shutdown()


if __name__ == "__main__":
    main()

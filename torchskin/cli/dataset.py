"""``torchskin dataset``: dataset utilities (``dataset verify``: shards against the manifest)."""

from __future__ import annotations

import argparse
import json

from .options import add_json


def cmd_dataset_verify(args: argparse.Namespace) -> int:
    """Run ``torchskin dataset verify``: status 0 when the shards match the manifest, 1 otherwise."""
    from ..dataset.generate import verify

    rep = verify(args.dir)
    if args.json:
        print(json.dumps(rep))
    else:
        print(("ok" if rep["ok"] else "PROBLEMS") + f": {rep['shards']} shards, {rep['rows']} rows; missing "
              f"{rep['missing'] or 'none'}, corrupted {rep['corrupted'] or 'none'}, partial {rep['partial'] or 'none'}")
    return 0 if rep["ok"] else 1


def add_parser(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """The ``torchskin dataset`` command and its ``verify`` subcommand."""
    dp = sub.add_parser("dataset", help="dataset utilities", description="Dataset utilities: verify.")
    dsub = dp.add_subparsers(dest="dataset_command", required=True)
    vp = dsub.add_parser("verify", help="check shards against the manifest (non-zero exit on problems)")
    vp.add_argument("dir")
    add_json(vp)
    vp.set_defaults(func=cmd_dataset_verify)
    return dp

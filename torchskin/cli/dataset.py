"""``torchskin dataset``: dataset utilities (``dataset verify``: shards against the manifest)."""

from __future__ import annotations

import argparse
import json

from .options import add_json


def cmd_dataset_verify(args: argparse.Namespace) -> int:
    """Run ``torchskin dataset verify``: status 0 when the shards match the manifest, 1 otherwise."""
    from ..dataset.verify import verify, verify_line, verify_summary  # the folder's files only: no renderer

    rep = verify(args.dir)
    print(json.dumps(verify_summary(rep)) if args.json else verify_line(rep))  # counts and ranges, never a list
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

"""``torchskin dataset verify``: a dataset folder against its manifest (missing, partial and corrupted shards), and
the report's short forms. Imports no renderer (nor torch): checking a dataset needs its files only
(``dataset.files``)."""

from __future__ import annotations

import os
import re
from collections.abc import Sequence
from pathlib import Path

from .files import MANIFEST, dataset_files, intact, manifest, shard_name


def verify(out_dir: str | os.PathLike) -> dict:
    """Check a dataset folder against its manifest: missing, partial (temporary leftovers or unreadable)
    and corrupted (checksum mismatch) shards. ``ok`` is True when everything matches. A manifest of a schema this
    torchskin does not read is a ``ValueError`` (``dataset.files.manifest``)."""
    out = Path(out_dir)
    man = manifest(out)  # a schema this torchskin does not read is refused (dataset.files.manifest)
    if man is None:
        raise ValueError(f"{str(out)!r} has no {MANIFEST}: not a torchskin dataset")
    listed = {s["name"]: s for s in man["shards"]}
    missing, corrupted = [], []
    for k in range(man["n_shards"]):
        name = shard_name(k)
        entries = [listed[name], listed[name].get("images")] if name in listed else []
        for e in [x for x in entries if x] or [{"name": name}]:
            p = out / e["name"]
            if "sha256" not in e or not p.is_file():
                missing.append(e["name"])
            elif not intact(out, e):
                corrupted.append(e["name"])
    partial = sorted(str(p.relative_to(out)) for p in dataset_files(out)
                     if p.name.startswith((".shard-", ".images-")) or p.name.endswith(".tmp"))
    return {"ok": not (missing or corrupted or partial), "shards": man["n_shards"], "missing": missing,
            "corrupted": corrupted, "partial": partial,
            "rows": sum(s["rows"] for s in man["shards"] if s["name"] not in corrupted)}


def name_ranges(names: Sequence[str], limit: int = 4) -> str:
    """A short text for a possibly huge list of shard file names: the count and the runs of consecutive indices,
    at most ``limit`` runs then how many more, e.g. ``"5: shard-00002.parquet..shard-00005.parquet,
    images/images-00009.npy"``; ``"none"`` for an empty list. Names without an index are listed as they are."""
    if not names:
        return "none"
    keyed = []
    for name in names:
        m = re.fullmatch(r"(.*?)(\d+)(\.[A-Za-z0-9]+)?", name)
        keyed.append((name, "", -1, "") if m is None else (m[1], m[3] or "", int(m[2]), m[2]))
    keyed.sort(key=lambda t: (t[0], t[1], t[2]))
    runs: list[list] = []  # [prefix, suffix, first, last, first text, last text]
    for head, tail, idx, digits in keyed:
        r = runs[-1] if runs else None
        if idx >= 0 and r is not None and r[0] == head and r[1] == tail and r[3] + 1 == idx:
            r[3], r[5] = idx, digits
        else:
            runs.append([head, tail, idx, idx, digits, digits])
    text = [r[0] if r[2] < 0 else f"{r[0]}{r[4]}{r[1]}" + (f"..{r[0]}{r[5]}{r[1]}" if r[3] > r[2] else "")
            for r in runs[:limit]]
    more = f", ... ({len(runs) - limit} more runs)" if len(runs) > limit else ""
    return f"{len(names)}: " + ", ".join(text) + more


def verify_summary(report: dict) -> dict:
    """``verify``'s report with its lists of names (missing, corrupted, partial) replaced by counts and ranges
    (``name_ranges``), so that a dataset of millions of shards reports in one short line (``dataset verify``)."""
    out = {k: v for k, v in report.items() if k not in ("missing", "corrupted", "partial")}
    for k in ("missing", "corrupted", "partial"):
        out[k] = len(report[k])
        out[f"{k}_ranges"] = name_ranges(report[k])
    return out


def verify_line(report: dict) -> str:
    """``verify``'s report as one line of text: ok or PROBLEMS, shards, rows, and the missing, corrupted and
    partial files as counts and ranges (``name_ranges``)."""
    return (("ok" if report["ok"] else "PROBLEMS") + f": {report['shards']} shards, {report['rows']} rows; missing "
            f"{name_ranges(report['missing'])}; corrupted {name_ranges(report['corrupted'])}; partial "
            f"{name_ranges(report['partial'])}")


__all__ = ["name_ranges", "verify", "verify_line", "verify_summary"]

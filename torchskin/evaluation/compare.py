"""The side-by-side comparison: every model and the static thesis box judged on one held-out dataset
(``evaluate``, a complete JSON-ready result, provenance included) and its text table (``table``)."""

from __future__ import annotations

import math
import os
from collections.abc import Sequence

from ..angles import BACKLIT_MIN_DEG
from ..dataset.files import dataset_bands, require_bands
from .candidates import Candidate, ModelPaths, load_candidates, static_candidate
from .metrics import GLINT_REFLECTANCE, MIN_REFLECTANCE, HeldOut, Judged, azimuth_bins, bins, held_out
from .provenance import provenance, render_revision
from .regions import ROC_SCALES, earthlib_test, is_index_bands, judge, roc, same_bands


def model_entry(cand: Candidate, judged: Judged, rows: HeldOut) -> dict:
    """One model's entry of ``evaluate``'s ``models``: overall, sun zenith >= 60°, per bin (sun x camera zenith,
    and relative azimuth), areas, scene Pfa by family."""
    area = judged.area_cfg
    return {"name": cand.name, "path": cand.path, "kind": cand.kind, "features": list(cand.features),
            "overall": judged.summary(rows),
            "sun_zenith_ge_60": judged.summary(rows, rows.sz >= 60), "bins": bins(judged, rows),
            "azimuth_bins": azimuth_bins(judged, rows),
            "area": {"mean": float(area.mean()), "median": float(area.median()),
                     "p10": float(area.quantile(0.1)), "p90": float(area.quantile(0.9))},
            "scene_pfa_by_family": judged.scene_by_family(rows)}


def evaluate(data_dir: str | os.PathLike, model_paths: ModelPaths, scales: Sequence[float] = ROC_SCALES,
             min_reflectance: float = MIN_REFLECTANCE, positional_bands: bool = False) -> dict:
    """Every model of ``model_paths`` and, when they read the index bands, the static box on the held-out dataset at
    ``data_dir``, all under the brightness floor ``min_reflectance``, in the models' own bands (any set the dataset
    holds; all models alike): Pd of skin pixels (sunlit, glint-affected, shadowed), Pfa on the
    earthlib test spectra and on the scene's non-skin pixels, decision-region areas, overall, at sun zenith >=
    60° and per (sun zenith x camera zenith) bin, and, when the first model has boxes, its ROC.

    Args:
        data_dir: a generated dataset folder (``torchskin generate``; rows of frames with a valid ELM).
        model_paths: one path or a list (see ``load_candidate``: .pt checkpoints, boundaries.onnx /
            baseline_box.onnx, detector.onnx, or "static"); each is given the configuration features it takes.
        scales: the box scale factors of the ROC (``ROC_SCALES``).
        min_reflectance: the brightness floor, in [0, 1) (``MIN_REFLECTANCE``).
        positional_bands: read the dataset's bands in order as the models' own, whatever their centres: a camera
            whose filters sit off the models' nominal bands (the filter-tolerance rows of
            ``scripts/shift_table.py``). The dataset must hold as many bands as the models read; the earthlib test
            spectra are read at the dataset's centres.

    Returns:
        A JSON-ready dict, complete (what ``torchskin evaluate --save`` writes): ``models`` (one entry per model,
        the static box last: name, path, kind, overall, sun_zenith_ge_60, bins, area, scene_pfa_by_family),
        ``learned`` / ``static`` (and ``bins``, ``sun_zenith_ge_60``, ``roc``) comparing the first model with
        the static box, the dataset's features, rows, rows_excluded_no_sunlit_panels, configurations,
        glint_reflectance, min_reflectance, and the provenance (``evaluation.provenance.provenance``:
        ``warnings`` when a model was trained in another world, ``data``, ``data_manifest_sha256``, ``model``).
    """
    if not (0.0 <= float(min_reflectance) < 1.0) or not math.isfinite(min_reflectance):
        raise ValueError(f"min_reflectance must lie in [0, 1), got {min_reflectance}")
    cands = load_candidates(model_paths)
    features, bands = cands[0].features, cands[0].bands
    for c in cands[1:]:
        if not same_bands(c.bands, bands):
            raise ValueError(f"models read different bands: --model {c.name} {', '.join(f'{b:g}' for b in c.bands)} "
                             f"nm, --model {cands[0].name} {', '.join(f'{b:g}' for b in bands)} nm")
    index = is_index_bands(bands)
    if index:  # the static box reads the index bands: the comparison of every evaluation in them
        cands.append(static_candidate())
    read = bands
    if positional_bands:  # the camera's own bands, in order, whatever their centres
        have = dataset_bands(data_dir)
        if len(have) != len(bands):
            raise ValueError(f"dataset {str(data_dir)!r} holds {len(have)} bands; the models read {len(bands)} "
                             "(positional_bands reads the dataset's bands in order as theirs)")
        read = have.centers
    else:
        for c in cands:  # each model's bands (its kind's required_bands), before any row is read
            require_bands(data_dir, c.bands, "the static thesis box" if c.kind == "static" else f"--model {c.name}")
    rows = held_out(data_dir, list(dict.fromkeys(f for c in cands for f in c.features)), read)
    test_R, test_pts = earthlib_test(read, indices=index)
    judged = [judge(c, rows, test_R, test_pts, float(min_reflectance)) for c in cands]
    models = [model_entry(c, j, rows) for c, j in zip(cands, judged)]
    first, static = models[0], (models[-1] if index else None)
    out = {"models": models, "learned": first["overall"], "static": static["overall"] if static else None,
           "sun_zenith_ge_60": {"learned": first["sun_zenith_ge_60"],
                                "static": static["sun_zenith_ge_60"] if static else None},
           "bins": [{"sun_zenith_deg": a["sun_zenith_deg"], "camera_zenith_deg": a["camera_zenith_deg"],
                     "learned": {k: v for k, v in a.items() if not k.endswith("_deg")},
                     "static": {k: v for k, v in b.items() if not k.endswith("_deg")} if b else None}
                    for a, b in zip(first["bins"], static["bins"] if static else [None] * len(first["bins"]))],
           "bands_nm": list(bands), "dataset_bands_nm": list(read),
           "features": features, "rows": rows.n, "rows_excluded_no_sunlit_panels": rows.excluded,
           "configurations": rows.n_cfg, "glint_reflectance": GLINT_REFLECTANCE,
           "render_revision": render_revision(data_dir),
           "backlit_min_relative_azimuth_deg": BACKLIT_MIN_DEG,
           "min_reflectance": float(min_reflectance)}
    if cands[0].boxes is not None:
        out["roc"] = roc(cands[0], cands[-1], rows, test_pts, scales, float(min_reflectance))
    out.update(provenance(data_dir, model_paths))
    return out


_TABLE = (("Pd sunlit", "pd_sunlit"), ("no glint", "pd_sunlit_no_glint"), ("glint", "pd_glint"),
          ("shadow", "pd_shadow"), ("backlit", "pd_backlit"), ("mean/config", "pd_sunlit_mean_over_configs"))


def table(result: dict) -> str:
    """The comparison as a text table: one row per model (the static box last)."""
    head = (f"{'model':<26}" + "".join(f"{h:>12}" for h, _ in _TABLE) + f"{'sun>=60 m/c':>12}{'Pfa earthlib':>13}"
            f"{'Pfa scene':>11}{'area':>7}")
    lines = [head]
    for m in result["models"]:
        o, hi = m["overall"], m["sun_zenith_ge_60"]
        lines.append(f"{m['name'][:25]:<26}" + "".join(f"{o[k]:>12.3f}" for _, k in _TABLE)
                     + f"{hi['pd_sunlit_mean_over_configs']:>12.3f}{o['pfa']:>13.2e}{o['pfa_scene']:>11.2e}"
                     + f"{m['area']['mean']:>7.3f}")
    lines.append(f"({result['rows']} rows, {result['configurations']} configurations; Pd sunlit split into glint-"
                 f"affected (specular >= {result['glint_reflectance']:g} at 1580 nm) and not; shadow: skin without "
                 f"direct sun; backlit: all skin of configurations with relative azimuth >= {BACKLIT_MIN_DEG:g}° (the "
                 "camera looks towards the sun); area: mean decision-region area per configuration in the (NDGRI, "
                 "NDSI) plane, nan for models of other bands)")
    return "\n".join(lines)


__all__ = ["evaluate", "model_entry", "table"]

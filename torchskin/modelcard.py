"""Model cards (Markdown) for the exported boundary models: what the model is, intended use, training data,
held-out metrics from ``torchskin evaluate`` and limits. What a card says of the detector itself (its intended
use and its false-alarm tuning) comes from the model's kind (``card_use``, ``card_false_alarms``), found through
``torchskin.detectors.registry``."""

from __future__ import annotations

import json
from typing import Any

from . import __version__

_INPUTS = {
    "boundaries": ("`config` float32 (N, k): configuration features in the order and units below",
                   "`boxes` float32 (N, 5): (b1, b2, c1, c2, d1) = NDGRI min, NDGRI max, NDSI min, NDSI max, "
                   "NDVN min"),
    "baseline_box": ("`config` float32 (N, k): configuration features in the order and units below (ignored: "
                     "one box for every configuration)",
                     "`boxes` float32 (N, 5): (b1, b2, c1, c2, d1) = NDGRI min, NDGRI max, NDSI min, NDSI max, "
                     "NDVN min"),
    "detector": ("`cube` float32 (B, 4, H, W): ELM-calibrated reflectance at 544, 633, 1080, 1580 nm (bands on "
                 "axis 1, values in [0, 1]); `config` float32 (B, k): the frame's configuration features",
                 "`mask` bool (B, H, W): skin; `score` float32 (B, H, W): positive for skin"),
}
_TITLES = {"boundaries": "configuration-dependent skin-detector boundaries (the auditable rules model)",
           "baseline_box": "the single refitted rules box (baseline: one box for every configuration)",
           "detector": "onboard skin detector (cube + configuration -> mask)"}


#: what ``torchskin train --frames`` learned from, for the model card
FRAMES_TEXT = {"line": "every frame with sunlit panels and a physical line, also where the panels receive less "
                       "light than sun-facing surfaces; calibrated and evaluated on physical frames only",
               "physical": "only frames whose ELM reflectance is physical, as evaluated"}


def _f(v, digits=3) -> str:
    if v is None:
        return "n/a"
    try:
        x = float(v)
    except (TypeError, ValueError):
        return str(v)
    if x != x:
        return "n/a"
    return f"{x:.2e}" if 0 < abs(x) < 10 ** -digits else f"{x:.{digits}f}"


def _entry(ev: dict, checkpoint: str) -> tuple[dict, dict]:
    """(overall, sun >= 60) of the evaluated model named ``checkpoint`` (else the first), and the static box's."""
    models = ev.get("models") or []
    mine = next((m for m in models if m.get("name") == checkpoint), models[0] if models else None)
    if mine is None:
        return ev["learned"], {"learned": ev["learned"], "static": ev["static"], **ev.get("sun_zenith_ge_60", {})}
    return mine["overall"], mine["sun_zenith_ge_60"]


def _metrics_section(ev: dict, checkpoint: str = "") -> list[str]:
    out = ["## Evaluation (held-out configurations)", ""]
    if ev.get("data"):
        out += [f"Held-out dataset: `{ev['data']}` (manifest SHA-256 `{ev.get('data_manifest_sha256', '')}`).", ""]
    mine, hi = _entry(ev, checkpoint)
    static = ev["static"]
    static_hi = (ev.get("sun_zenith_ge_60") or {}).get("static", {})
    out += ["| | this model | static box (thesis) |", "|---|---|---|"]
    rows = [("Pd, sunlit skin", "pd_sunlit"), ("Pd, sunlit skin, mean over configurations", "pd_sunlit_mean_over_configs"),
            ("Pd, sunlit skin without glint", "pd_sunlit_no_glint"), ("Pd, glint-affected sunlit skin", "pd_glint"),
            ("Pd, shadowed skin", "pd_shadow"), ("Pd, all skin", "pd"),
            ("Pfa, earthlib test spectra", "pfa"), ("Pfa, scene non-skin pixels", "pfa_scene"),
            ("decision-region area per configuration, mean ((NDGRI, NDSI) units²)", "area_mean")]
    for label, k in rows:
        out.append(f"| {label} | {_f(mine.get(k))} | {_f(static.get(k))} |")
    if hi:
        out.append(f"| Pd sunlit, sun zenith >= 60 deg, mean over configurations | "
                   f"{_f(hi.get('pd_sunlit_mean_over_configs'))} | {_f(static_hi.get('pd_sunlit_mean_over_configs'))} |")
    if ev.get("models"):
        out += ["", "Every model evaluated on the same held-out set (Pd sunlit / glint-affected / shadowed; mean over "
                "configurations at sun zenith >= 60 deg; Pfa earthlib test / scene non-skin; mean area):", "",
                "| model | Pd sunlit | Pd glint | Pd shadow | sun >= 60, mean/config | Pfa earthlib | Pfa scene | area |",
                "|---|---|---|---|---|---|---|---|"]
        for m in ev["models"]:
            o, h = m["overall"], m["sun_zenith_ge_60"]
            out.append(f"| {m['name']} | {_f(o['pd_sunlit'])} | {_f(o.get('pd_glint'))} | {_f(o['pd_shadow'])} | "
                       f"{_f(h['pd_sunlit_mean_over_configs'])} | {_f(o['pfa'])} | {_f(o['pfa_scene'])} | "
                       f"{_f(m.get('area', {}).get('mean'))} |")
    if ev.get("bins") and (not checkpoint or checkpoint == (ev.get("models") or [{}])[0].get("name")):
        out += ["", "Per configuration bin (Pd sunlit skin, this model / static; Pfa earthlib test, this model):", "",
                "| sun zenith (deg) | camera zenith (deg) | Pd this model | Pd static | Pfa this model | skin pixels |",
                "|---|---|---|---|---|---|"]
        for b in ev.get("bins", []):
            out.append(f"| {b['sun_zenith_deg'][0]:g}-{b['sun_zenith_deg'][1]:g} | "
                       f"{b['camera_zenith_deg'][0]:g}-{b['camera_zenith_deg'][1]:g} | {_f(b['learned']['pd_sunlit'])} | "
                       f"{_f(b['static']['pd_sunlit'])} | {_f(b['learned']['pfa'])} | {b['learned']['skin_pixels']} |")
    out.append("")
    return out


def _kind(train: dict) -> Any:
    """The detector kind a training summary describes (by its ``method``; ``detectors.registry.kind_for_method``:
    a box model unless the method is another kind's)."""
    from .detectors import registry

    return registry.kind_for_method(train.get("method"))


def _score_words() -> str:
    """What a ``detector.onnx`` score is, in each registered kind's words (``card_score``), "" when none has any."""
    from .detectors import registry

    words = registry.card_scores()
    return f" ({'; '.join(words)})" if words else ""


def _false_alarm_line(train: dict) -> str:
    # "calibration" here (and "calibrated threshold" in the classifier's ``card_score``) means the false-alarm tuning
    # (each kind's own: its ``card_false_alarms``); the words and the summary key
    # ``calibration_configs`` are part of the shipped cards and checkpoints (exports/), so they stay. Each kind
    # words its own tuning (``card_false_alarms``)
    kind = _kind(train)
    words = getattr(kind, "card_false_alarms", None)
    how = (words(train, _f) if words is not None else
           f"tuned to at most {_f(train.get('pfa_budget'))} of the earthlib *train* spectra called skin")
    return (f"- False alarms: {how}. The earthlib *test* partition (SHA-256 of the spectrum name) was never used "
            "in training.")


_COUNT = {2: "two", 3: "three", 4: "four", 5: "five", 6: "six", 7: "seven", 8: "eight"}


def _card_bands(meta: dict[str, str]) -> list[float]:
    """The band centres (nm) of a graph's metadata (``bands``, else ``bands_nm``, else the index bands)."""
    from .bands import INDEX_BANDS_NM, BandSet

    if "bands" in meta:
        return list(BandSet.from_json(meta["bands"]).centers)
    return [float(c) for c in json.loads(meta.get("bands_nm", "null") or "null") or INDEX_BANDS_NM]


def model_card(kind: str, meta: dict[str, str], train: dict, evaluation: dict | None = None) -> str:
    """Markdown card for ``kind`` in ("boundaries", "baseline_box", "detector"). ``meta``: the ONNX metadata;
    ``train``: the checkpoint's training summary; ``evaluation``: the ``torchskin evaluate`` result."""
    if kind not in _INPUTS:
        raise ValueError(f"kind must be one of {tuple(_INPUTS)}, got {kind!r}")
    features = json.loads(meta.get("features", "[]"))
    units = json.loads(meta.get("feature_units", "[]"))
    domain = json.loads(meta.get("feature_domain", "[]"))
    inp, outp = _INPUTS[kind]
    centres = _card_bands(meta)
    if kind == "detector":
        outp += _score_words()
        inp = inp.replace("(B, 4, H, W): ELM-calibrated reflectance at 544, 633, 1080, 1580 nm",
                          f"(B, {len(centres)}, H, W): ELM-calibrated reflectance at "
                          f"{', '.join(f'{c:g}' for c in centres)} nm")
    opts = train.get("options", {})
    lines = [
        f"# torchskin {kind}.onnx: {_TITLES[kind]}", "",
        f"torchskin {meta.get('torchskin_version', __version__)}, ONNX opset 17. Inputs: {inp}. Outputs: {outp}.", "",
        *(["## Which model", "", f"Made from `{meta.get('detector_model', '')}`: {meta.get('detector_reason', '')}",
           ""] if kind == "detector" else []),
        "## Intended use", "",
        getattr(_kind(train), "card_use", f"Onboard skin detection with the `{_kind(train).kind}` detector kind."),
        "Run it with `torchskin.onboard` or `torchskin detect` (numpy + onnxruntime only). Reflectance must be "
        "calibrated (empirical line with reference panels) first; pixels whose mean reflectance is not above "
        f"{meta.get('min_reflectance', '0.005')} are not skin (the brightness floor of the evaluation, applied by "
        "the onboard runtime by default for detector.onnx).", "",
        f"Skin model of the training renders: eq 3.1.1 with the `{meta.get('skin_surface_model') or 'n/a'}` skin "
        "surface model (`thesis`: eq 3.1.1's ρ_d is the total diffuse-model reflectance, front surface included, as "
        "the thesis defines it; `conserving`: its subsurface part only). Detectors learned under one model are not "
        "valid under the other.", "",
        *([f"Light model of the training renders: `{meta['light_model']}` (`torchskin light`).", ""]
          if meta.get("light_model") else []),
        "Configuration features (order, units, training domain; values outside it are flagged `out_of_domain`):", "",
        "| feature | units | domain |", "|---|---|---|",
    ]
    for i, f in enumerate(features):
        d = domain[i] if i < len(domain) else ["", ""]
        lines.append(f"| `{f}` | {units[i] if i < len(units) else ''} | {float(d[0]):g} to {float(d[1]):g} |")
    lines += ["", "## Training data", "",
              f"- Dataset: `{train.get('data', '')}`, manifest SHA-256 `{meta.get('training_manifest_sha256', '')}` "
              f"(rendered by `torchskin generate`: anny bodies with Kubelka-Munk + microfacet skin, eq 3.1.1, "
              f"reference panels, earthlib confusers, sensor noise, ELM calibration).",
              f"- {train.get('rows', 'n/a')} skin pixels ({', '.join(train.get('light_classes', ['sunlit']))}); "
              f"method `{train.get('method', 'n/a')}` ({', '.join(f'{k}={v}' for k, v in sorted(opts.items()))})"
              + (f"; frames `{train['frames']}` ({FRAMES_TEXT.get(train['frames'], '')})" if train.get("frames")
                 else "") + ".",
              _false_alarm_line(train), ""]
    if evaluation:
        lines += _metrics_section(evaluation, meta.get("checkpoint", train.get("checkpoint", "")))
    else:
        lines += ["## Evaluation", "", "No evaluation was attached (`torchskin export --metrics EVAL.json`).", ""]
    lines += ["## Limits", "",
              "- Trained on simulated images only: a calibrated 9-layer Kubelka-Munk skin model with a Gaussian "
              "microfacet lobe, not on measured imagery; real skin, make-up, sweat, hair and clothing edges are "
              "not represented beyond what the renderer models.",
              "- Confusers are earthlib's Lambertian laboratory spectra; glossy or fluorescent materials, skin-like "
              "fabrics and leather are not in the library.",
              ("- Sunlit and shadowed skin drove the training (Pd is reported for each). " if "shadow" in
               train.get("light_classes", []) else "- Sunlit skin drove the training; shadowed skin is reported but "
               "was not optimised for. ") + "Skin seen at grazing local incidence or in a glint carries a spectrally flat surface reflection that pulls NDGRI "
              "and NDSI towards 0; the part of it below the box's NDSI floor is missed (it would meet soils).",
              "- The visible/NIR rule (NDVN >= d1) was set from the rendered skin population (Fitzpatrick I-VI of the "
              "calibrated model); skin darker in the visible than that (or heavily made-up) would be rejected.",
              f"- The {_COUNT.get(len(centres), str(len(centres)))} band centres and widths must match the training "
              "sensor (Gaussian bands, see metadata).",
              "- Configurations outside the feature domain above are flagged, never silently extrapolated.",
              "- Reflectance must be finite and non-negative: the onboard runtime refuses NaN always and negative "
              "values unless asked to clip them to 0 (`negative=\"clip\"`, `torchskin detect --clip-negative`), as "
              "ELM leaves noise around 0 on dark pixels such as sky. The indices of such pixels are ratios of noise: "
              "`min_reflectance` (`--min-reflectance`) rejects pixels whose mean reflectance is below a floor.", ""]
    return "\n".join(lines)


__all__ = ["model_card"]

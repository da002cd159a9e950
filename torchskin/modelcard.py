"""Model cards (Markdown) for the exported boundary models: what the model is, intended use, training data,
held-out metrics from ``torchskin evaluate`` and limits."""

from __future__ import annotations

import json

from . import __version__

_INPUTS = {
    "boundaries": ("`config` float32 (N, k): configuration features in the order and units below",
                   "`boxes` float32 (N, 4): (b1, b2, c1, c2) = NDGRI min, NDGRI max, NDSI min, NDSI max"),
    "detector": ("`cube` float32 (B, 4, H, W): ELM-calibrated reflectance at 544, 633, 1080, 1580 nm (bands on "
                 "axis 1, values in [0, 1]); `config` float32 (B, k): the frame's configuration features",
                 "`mask` bool (B, H, W): skin; `score` float32 (B, H, W): the smallest margin to a box edge in "
                 "index units times the band-pair sum (g + r or n + s), positive inside"),
}


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


def _metrics_section(ev: dict) -> list[str]:
    out = ["## Evaluation (held-out configurations)", ""]
    if ev.get("data"):
        out += [f"Held-out dataset: `{ev['data']}` (manifest SHA-256 `{ev.get('data_manifest_sha256', '')}`).", ""]
    out += ["| | learned | static box (thesis) |", "|---|---|---|"]
    rows = [("Pd, sunlit skin", "pd_sunlit"), ("Pd, sunlit skin, mean over configurations", "pd_sunlit_mean_over_configs"),
            ("Pd, shadowed skin", "pd_shadow"), ("Pd, all skin", "pd"),
            ("Pfa, earthlib test spectra", "pfa"), ("Pfa, scene non-skin pixels", "pfa_scene")]
    for label, k in rows:
        out.append(f"| {label} | {_f(ev['learned'].get(k))} | {_f(ev['static'].get(k))} |")
    hi = ev.get("sun_zenith_ge_60")
    if hi:
        out.append(f"| Pd sunlit, sun zenith >= 60 deg, mean over configurations | "
                   f"{_f(hi['learned'].get('pd_sunlit_mean_over_configs'))} | "
                   f"{_f(hi['static'].get('pd_sunlit_mean_over_configs'))} |")
    if ev.get("bins"):
        out += ["", "Per configuration bin (Pd sunlit skin, learned / static; Pfa earthlib test, learned):", "",
                "| sun zenith (deg) | camera zenith (deg) | Pd learned | Pd static | Pfa learned | skin pixels |",
                "|---|---|---|---|---|---|"]
        for b in ev["bins"]:
            out.append(f"| {b['sun_zenith_deg'][0]:g}-{b['sun_zenith_deg'][1]:g} | "
                       f"{b['camera_zenith_deg'][0]:g}-{b['camera_zenith_deg'][1]:g} | {_f(b['learned']['pd_sunlit'])} | "
                       f"{_f(b['static']['pd_sunlit'])} | {_f(b['learned']['pfa'])} | {b['learned']['skin_pixels']} |")
    out.append("")
    return out


def model_card(kind: str, meta: dict[str, str], train: dict, evaluation: dict | None = None) -> str:
    """Markdown card for ``kind`` in ("boundaries", "detector"). ``meta``: the ONNX metadata properties;
    ``train``: the checkpoint's training summary; ``evaluation``: the ``torchskin evaluate`` result."""
    if kind not in _INPUTS:
        raise ValueError(f"kind must be one of {tuple(_INPUTS)}, got {kind!r}")
    features = json.loads(meta.get("features", "[]"))
    units = json.loads(meta.get("feature_units", "[]"))
    domain = json.loads(meta.get("feature_domain", "[]"))
    inp, outp = _INPUTS[kind]
    opts = train.get("options", {})
    lines = [
        f"# torchskin {kind}.onnx: configuration-dependent skin-detector boundaries", "",
        f"torchskin {meta.get('torchskin_version', __version__)}, ONNX opset 17. Inputs: {inp}. Outputs: {outp}.", "",
        "## Intended use", "",
        "Onboard skin detection in 4-band (544, 633, 1080, 1580 nm) reflectance imagery with the NDGRI/NDSI rules "
        "detector of the thesis (eq 2.5.10), with the rules box chosen for the frame's sun and camera geometry "
        "instead of the fixed diffuse-model box. Run it with `torchskin.onboard` or `torchskin detect` (numpy + "
        "onnxruntime only). Reflectance must be calibrated (empirical line with reference panels) first.", "",
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
              f"- {train.get('rows', 'n/a')} sunlit skin pixels; method `{train.get('method', 'n/a')}` "
              f"({', '.join(f'{k}={v}' for k, v in sorted(opts.items()))}).",
              f"- False alarms: the boxes were shrunk by {_f(train.get('scale'))} so that at most "
              f"{_f(train.get('pfa_budget'))} of the earthlib *train* spectra fall inside any box over "
              f"{train.get('calibration_configs', 'n/a')} configurations (worst case after calibration: "
              f"{_f(train.get('pfa_train_worst'))}). The earthlib *test* partition (SHA-256 of the spectrum name) "
              f"was never used in training.", ""]
    if evaluation:
        lines += _metrics_section(evaluation)
    else:
        lines += ["## Evaluation", "", "No evaluation was attached (`torchskin export --metrics EVAL.json`).", ""]
    lines += ["## Limits", "",
              "- Trained on simulated images only: a calibrated 9-layer Kubelka-Munk skin model with a Gaussian "
              "microfacet lobe, not on measured imagery; real skin, make-up, sweat, hair and clothing edges are "
              "not represented beyond what the renderer models.",
              "- Confusers are earthlib's Lambertian laboratory spectra; glossy or fluorescent materials, skin-like "
              "fabrics and leather are not in the library.",
              "- Sunlit skin drove the boxes; shadowed skin is reported but was not optimised for. Glints that push "
              "NDGRI towards 0 are missed by design (they overlap vegetation and soils).",
              "- The four band centres and widths must match the training sensor (Gaussian bands, see metadata).",
              "- Configurations outside the feature domain above are flagged, never silently extrapolated.",
              "- Reflectance must be finite and non-negative: the onboard runtime refuses NaN always and negative "
              "values unless asked to clip them to 0 (`negative=\"clip\"`, `torchskin detect --clip-negative`), as "
              "ELM leaves noise around 0 on dark pixels such as sky. The indices of such pixels are ratios of noise: "
              "`min_reflectance` (`--min-reflectance`) rejects pixels whose mean reflectance is below a floor.", ""]
    return "\n".join(lines)


__all__ = ["model_card"]

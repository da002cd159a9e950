"""Model choice: which evaluated model to ship as ``detector.onnx`` (``select_detector``), from an evaluation
result, under the false-alarm budgets and the onboard cost."""

from __future__ import annotations

from ..detectors import registry

#: the model kinds whose detector graph meets the onboard budget (a 1 MP frame in a few times the time of reading
#: it), as registered when this module loads (each kind's ``onboard_selectable``; ``registry.onboard_kinds``, which
#: ``select_detector`` reads at each call, so that a kind registered later counts): the box models' five edge forms
#: (~2-4 ms per 1024² frame on 2 cores) and the lookup table (~1.2x the boxes); the others (each kind's
#: ``onboard_cost`` says why) are evaluated and reported, not shipped
ONBOARD_KINDS = registry.onboard_kinds()


def select_detector(result: dict, pfa_budget: float = 1e-3, scene_budget: float = 1e-4,
                    tolerance: float = 0.005, onboard_kinds: tuple[str, ...] | None = None) -> tuple[str, str]:
    """The model to ship as ``detector.onnx``: among the evaluated models (not the static box) of a kind that meets
    the onboard budget (``onboard_kinds``; any model when none does) whose held-out Pfa is within ``pfa_budget``
    on the earthlib test spectra and ``scene_budget`` on scene non-skin pixels, those within ``tolerance`` of
    the highest sunlit Pd; of these a box model (auditable rules, the cheaper graph) before a model of another kind, then
    the smallest mean decision-region area (at equal Pd, less false-alarm exposure than earthlib can show).
    ``onboard_kinds`` default: the registered kinds that meet the onboard budget (``registry.onboard_kinds``); a box
    model is one of a box kind (``registry.box_kinds``) or an exported ``boundaries.onnx``.
    Returns (model name, the reason in words; it names the models left out for their onboard cost)."""
    onboard_kinds = registry.onboard_kinds() if onboard_kinds is None else onboard_kinds
    box_kinds = {*registry.box_kinds(), registry.LEGACY_KIND}  # LEGACY_KIND: boundaries.onnx candidates
    every = [m for m in result["models"] if m["kind"] != "static"]
    if not every:
        raise ValueError("no model to choose from")
    models = [m for m in every if m["kind"] in onboard_kinds] or every
    costly = [m for m in every if m not in models]

    def ok(m):
        return m["overall"]["pfa"] <= pfa_budget and m["overall"]["pfa_scene"] <= scene_budget

    eligible = [m for m in models if ok(m)] or models
    best = max(m["overall"]["pd_sunlit"] for m in eligible)
    near = [m for m in eligible if m["overall"]["pd_sunlit"] >= best - tolerance]
    pick = min(near, key=lambda m: (m["kind"] not in box_kinds, m["area"]["mean"]))
    figures = "; ".join(f"{m['name']}: Pd sunlit {m['overall']['pd_sunlit']:.3f}, Pfa earthlib "
                        f"{m['overall']['pfa']:.1e}, scene {m['overall']['pfa_scene']:.1e}, mean area "
                        f"{m['area']['mean']:.3f}" for m in every)
    why = (f"within {tolerance:g} of the highest held-out sunlit Pd among the models inside the false-alarm budgets "
           f"(earthlib test <= {pfa_budget:g}, scene non-skin <= {scene_budget:g}), a box model first, then the "
           "smallest decision region" if ok(pick) else
           "no model met the false-alarm budgets on the held-out set; highest sunlit Pd")
    if costly:
        why += "; not eligible for their onboard cost: " + ", ".join(
            f"{m['name']} ({registry.onboard_cost(m['kind'])})" for m in costly)
    return pick["name"], f"{why}. Held-out ({result.get('data', '')}): {figures}."


__all__ = ["ONBOARD_KINDS", "select_detector"]

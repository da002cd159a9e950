"""Fit the models to measurements: skin parameters to reflectance spectra (eq 2.4.14), microfacet σ² and ρ0
to goniometric BRDF data (section 3.3.3). Batched over spectra / bands, with autograd.

Skin fits: every free parameter is bounded through a sigmoid; starts come from a look-up table of model
spectra across the Fitzpatrick ranges (a multi-start: the best few per spectrum), then Adam on all starts,
then L-BFGS on the best start of each spectrum. Parameters the data cannot determine are flagged rather than
reported as if measured: those the Fisher information at the solution gives a large uncertainty (e.g. the
NIR-only parameters of a visible-only spectrum) and those in the null space of the Jacobian (a design with
fewer wavelengths than parameters, or parameters whose effects the wavelengths cannot tell apart), whose
uncertainty is infinite.
"""

from __future__ import annotations

import math
import os
import time
from dataclasses import dataclass

import torch

from . import tissue
from ._checks import Numeric, TensorLike, as_tensor, check_range
from .optics import combined_brdf_cos, cosines_from_angles, half_angle_cos, microfacet_brdf_cos, schlick_cos

#: search range of each skin parameter (inside tissue.PARAM_BOUNDS)
FIT_BOUNDS: dict[str, tuple[float, float]] = {
    "melanosome": (0.002, 0.6),
    "blood": (0.01, 2.5),
    "oxygenation": (0.0, 1.0),
    "reticular_depth": (0.03, 0.5),
    "collagen": (0.2, 1.0),
    "subcutaneous_scale": (0.05, 1.0),
}
NAMES = tissue.PARAM_NAMES


def _bounds(dtype, device):
    lo = torch.tensor([FIT_BOUNDS[k][0] for k in NAMES], dtype=dtype, device=device)
    hi = torch.tensor([FIT_BOUNDS[k][1] for k in NAMES], dtype=dtype, device=device)
    return lo, hi


def _to_params(z: torch.Tensor, lo, hi) -> torch.Tensor:
    return lo + (hi - lo) * torch.sigmoid(z)


def _to_z(p: torch.Tensor, lo, hi) -> torch.Tensor:
    u = ((p - lo) / (hi - lo)).clamp(1e-4, 1 - 1e-4)
    return torch.log(u / (1 - u))


def _skins(p: torch.Tensor) -> tissue.SkinParams:
    """``SkinParams`` from parameters ``(..., 6)`` in ``tissue.PARAM_NAMES`` order."""
    melanosome, blood, oxygenation, reticular_depth, collagen, subcutaneous_scale = p.unbind(-1)
    return tissue.SkinParams(melanosome, blood, oxygenation, reticular_depth, collagen, subcutaneous_scale)


def _model(p: torch.Tensor, wl: torch.Tensor, r0: float) -> torch.Tensor:
    return tissue.total_reflectance(_skins(p), wl, r0=r0)


def rmse(model: torch.Tensor, measured: torch.Tensor) -> torch.Tensor:
    """Eq 2.4.14: sqrt(mean over the N bands of (ρ_model - ρ_measured)²), per spectrum."""
    return torch.sqrt(((model - measured) ** 2).mean(-1))


def check_spectra(reflectance: TensorLike, wavelengths: TensorLike) -> tuple[torch.Tensor, torch.Tensor]:
    """Validate measured spectra ``(n, W)`` and their wavelengths ``(W,)``; errors name the row and column."""
    R = as_tensor(reflectance)
    wl = as_tensor(wavelengths, like=R)
    if R.dim() == 1:
        R = R[None]
    if R.dim() != 2:
        raise ValueError(f"reflectance must be (n_spectra, n_wavelengths), got shape {tuple(R.shape)}")
    if wl.dim() != 1 or wl.numel() != R.shape[1]:
        raise ValueError(f"wavelengths ({wl.numel()} values) must match the spectra's {R.shape[1]} columns")
    bad_wl = (wl < tissue.MODEL_RANGE_NM[0]) | (wl > tissue.MODEL_RANGE_NM[1]) | torch.isnan(wl)
    if bool(bad_wl.any()):
        j = int(bad_wl.nonzero()[0])
        raise ValueError(f"column {j}: wavelength {float(wl[j]):g} nm lies outside the tables' "
                         f"{tissue.MODEL_RANGE_NM[0]:g}-{tissue.MODEL_RANGE_NM[1]:g} nm")
    if wl.numel() > 1 and bool((torch.diff(wl) <= 0).any()):
        raise ValueError("wavelengths must be strictly increasing")
    bad = ~torch.isfinite(R) | (R < 0) | (R > 1)
    if bool(bad.any()):
        i, j = (int(x) for x in bad.nonzero()[0])
        raise ValueError(f"row {i}, column {j} ({float(wl[j]):g} nm): reflectance {float(R[i, j]):g} is NaN or "
                         "outside [0, 1]")
    if R.numel() == 0:
        raise ValueError("no spectra to fit: need at least one spectrum at one wavelength")
    dead = ((R == 0) | (R == 1)).all(1)  # dark or saturated readings: no skin reflects 0 or 100 % everywhere
    if bool(dead.any()):
        i = int(dead.nonzero()[0])
        raise ValueError(f"row {i}: every reflectance is 0 or 1 (a dark or saturated measurement); nothing to fit")
    return R, wl


@dataclass
class SkinFit:
    """Result of ``fit_skin`` for n spectra."""

    params: tissue.SkinParams  # (n,) best-fit values (also where undetermined: see ``identifiable``)
    rmse: torch.Tensor  # (n,) eq 2.4.14
    fitted: torch.Tensor  # (n, W) model spectra
    converged: torch.Tensor  # (n,) bool
    identifiable: torch.Tensor  # (n, 6) bool, parameter order tissue.PARAM_NAMES
    std: torch.Tensor  # (n, 6) 1-sigma uncertainty from the Fisher information (inf: in the Jacobian's null
    #                    space, NaN: the Jacobian is not finite)
    seconds: float

    def reported(self) -> list[dict[str, float | None]]:
        """Per spectrum: parameter -> value, or None where the data cannot determine it."""
        vals = self.params.expand().as_dict()
        out = []
        for i in range(self.rmse.numel()):
            out.append({k: (vals[k][i] if bool(self.identifiable[i, j]) else None) for j, k in enumerate(NAMES)})
        return out


def _lut(wl, r0, n, dtype, device):
    skins, _ = tissue.sample(n, 12345, dtype=dtype, device=device)
    lo, hi = _bounds(dtype, device)
    p = torch.stack([getattr(skins, k) for k in NAMES], -1).clamp(lo, hi)
    with torch.no_grad():
        R = _model(p, wl, r0)
    return p, R


def _jacobian(p: torch.Tensor, wl, r0) -> torch.Tensor:
    """d model / d params, (n, W, 6), by central differences in float64 (steps inside the bounds)."""
    lo, hi = _bounds(torch.float64, p.device)
    p = p.double()
    cols = []
    with torch.no_grad():
        for k in range(p.shape[-1]):
            h = 1e-4 * (hi[k] - lo[k])
            up, dn = p.clone(), p.clone()
            up[:, k] = (p[:, k] + h).clamp(max=tissue.PARAM_BOUNDS[NAMES[k]][1])
            dn[:, k] = (p[:, k] - h).clamp(min=0.0)
            cols.append((_model(up, wl.double(), r0) - _model(dn, wl.double(), r0)) / (up[:, k] - dn[:, k])[:, None])
    return torch.stack(cols, -1)


#: singular values of the range-scaled Jacobian below this fraction of the largest count as zero (the
#: central-difference Jacobian is accurate to ~1e-9 relative; the smallest genuine ratio seen, a visible-only
#: spectrum's, is ~3e-4)
RANK_RTOL = 1e-6
#: a parameter whose unit vector has more than this squared share in the null space is undetermined
NULL_SHARE = 1e-6


def fisher_std(J: torch.Tensor, sigma: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
    """1-sigma uncertainties ``(n, k)`` of least-squares parameters from the Jacobian ``J`` ``(n, W, k)`` of
    the model and the measurement noise ``sigma`` ``(n,)``; ``scale`` ``(k,)`` are the parameters' natural
    ranges (the rank test works on the Jacobian in those units).

    The Fisher information J^T J / σ² is not inverted blindly: from the SVD of the scaled Jacobian, singular
    values below ``RANK_RTOL`` of the largest are zero, and a parameter with a share above ``NULL_SHARE`` in
    that null space (which W < k wavelengths always leave) gets an infinite uncertainty; the others get the
    pseudo-inverse's. Spectra whose Jacobian is not finite get NaN.
    """
    n, W, k = J.shape
    Js = J.double() * scale.double() / sigma.double()[:, None, None]
    finite = torch.isfinite(Js).all(-1).all(-1)
    Js = torch.where(finite[:, None, None], Js, torch.zeros_like(Js))
    _, S, Vh = torch.linalg.svd(Js, full_matrices=True)  # S (n, min(W, k)), Vh (n, k, k)
    S = torch.cat([S, S.new_zeros(n, k - S.shape[1])], 1)
    live = S > RANK_RTOL * S[:, :1]
    inv_s2 = torch.where(live, 1.0 / torch.where(live, S, torch.ones_like(S)) ** 2, torch.zeros_like(S))
    V2 = Vh.transpose(1, 2) ** 2  # (n, k params, k directions)
    var = (V2 * inv_s2[:, None, :]).sum(-1)
    null = (V2 * (~live)[:, None, :].to(V2.dtype)).sum(-1)
    std = torch.sqrt(var) * scale.double()
    std = torch.where(null > NULL_SHARE, torch.full_like(std, math.inf), std)
    return torch.where(finite[:, None], std, torch.full_like(std, math.nan))


def fit_skin(
    reflectance: TensorLike,
    wavelengths: TensorLike,
    *,
    r0: float = 0.04,
    starts: int = 2,
    lut_size: int = 3000,
    adam_steps: int = 40,
    lbfgs_steps: int = 20,
    gn_steps: int = 15,
    noise: float | None = None,
    rel_tol: float = 0.05,
    dtype: torch.dtype = torch.float64,
    device: torch.device | str | None = None,
) -> SkinFit:
    """Fit the six free skin parameters to measured total reflectance spectra (normal incidence, front
    surface ``r0``), minimising the RMSE of eq 2.4.14 for every spectrum independently.

    Stages: look-up-table multi-start, Adam on all starts, L-BFGS on the best start of every spectrum (one
    joint problem), then per-spectrum Levenberg-Marquardt. A spectrum has *converged* when the Gauss-Newton
    decrement left (the loss a further Newton step would still remove) is below 1e-3 of its loss; degenerate
    spectra (a singular Gauss-Newton system) are reported as not converged. A parameter is *identifiable*
    when its 3-sigma uncertainty is within ``rel_tol`` of its value; parameters in the null space of the
    Jacobian (always some of them with fewer wavelengths than the six parameters) have an infinite
    uncertainty (``fisher_std``).

    Args:
        reflectance: measured total reflectance in [0, 1] (``check_spectra`` validates it).
        wavelengths: in nm, strictly increasing, anywhere in 400-1700 nm.
        r0: front-surface reflectance of the model (``tissue.total_reflectance``).
        starts: look-up-table starts per spectrum; lut_size: model skins in the table (``tissue.sample``).
        adam_steps, lbfgs_steps, gn_steps: iterations of the three optimisation stages.
        noise: measurement noise (reflectance units) for the uncertainty estimate; default: the fit's own
            RMSE (at least 0.002).
        rel_tol: relative 3-sigma uncertainty below which a parameter counts as identifiable.
        dtype, device: where the fit runs (default float64, the spectra's device).

    Shape:
        ``reflectance`` (n, W) (or (W,) for one spectrum), ``wavelengths`` (W,).

    Returns:
        A ``SkinFit``: parameters (n,), RMSE (n,), fitted spectra (n, W), converged (n,), identifiable and
        std (n, 6).

    >>> from torchskin import tissue
    >>> wl = tissue.wavelength_grid(450, 1600, 50, dtype=torch.float64)
    >>> R = tissue.total_reflectance(tissue.preset(["I-II", "V-VI"], dtype=torch.float64), wl)
    >>> res = fit_skin(R, wl, lut_size=500)
    >>> tuple(res.fitted.shape), [round(x, 3) for x in res.params.melanosome.tolist()], res.converged.tolist()
    ((2, 24), [0.035, 0.4], [True, True])
    """
    t0 = time.perf_counter()
    check_range("r0 (front-surface reflectance)", r0, 0.0, 1.0, hi_open=True)
    if noise is not None:
        check_range("noise", noise, 0.0, math.inf, lo_open=True, hi_open=True)
    R, wl = check_spectra(reflectance, wavelengths)
    device = device or R.device
    R = R.to(device=device, dtype=dtype)
    wl = wl.to(device=device, dtype=dtype)
    n = R.shape[0]
    lo, hi = _bounds(dtype, device)
    # multi-start: the best `starts` look-up-table spectra per measurement
    lut_p, lut_R = _lut(wl, r0, lut_size, dtype, device)
    d2 = (R * R).sum(1, keepdim=True) - 2 * R @ lut_R.T + (lut_R * lut_R).sum(1)[None]
    best = d2.topk(min(starts, lut_size), dim=1, largest=False).indices  # (n, starts)
    z = _to_z(lut_p[best.reshape(-1)], lo, hi).detach().requires_grad_(True)  # (n * starts, 6)
    target = R.repeat_interleave(best.shape[1], 0)
    opt = torch.optim.Adam([z], lr=0.08)
    for _ in range(adam_steps):
        opt.zero_grad()
        loss = ((_model(_to_params(z, lo, hi), wl, r0) - target) ** 2).mean(-1).sum()
        loss.backward()
        opt.step()
    with torch.no_grad():
        err = ((_model(_to_params(z, lo, hi), wl, r0) - target) ** 2).mean(-1).reshape(n, -1)
        pick = err.argmin(1)
        z_best = z.detach().reshape(n, -1, 6)[torch.arange(n, device=device), pick]
    z_fit = _lbfgs(z_best, R, wl, r0, lo, hi, lbfgs_steps) if lbfgs_steps > 0 else z_best
    z_fit, converged = _gauss_newton(z_fit, R, wl, r0, lo, hi, gn_steps)
    with torch.no_grad():
        p = _to_params(z_fit, lo, hi)
        fitted = _model(p, wl, r0)
        e = rmse(fitted, R)
        J = _jacobian(p, wl, r0)  # (n, W, 6)
        sigma = torch.full_like(e, noise) if noise is not None else e.clamp_min(0.002)
        std = fisher_std(J, sigma, hi - lo).to(dtype)
        identifiable = torch.isfinite(std) & (3 * std <= rel_tol * p.abs())
    return SkinFit(_skins(p.detach()), e, fitted, converged, identifiable, std, time.perf_counter() - t0)


def _lbfgs(z0, R, wl, r0, lo, hi, steps):
    z = z0.detach().clone().requires_grad_(True)
    opt = torch.optim.LBFGS([z], lr=1.0, max_iter=steps, history_size=20, tolerance_grad=1e-12,
                            tolerance_change=1e-15, line_search_fn="strong_wolfe")

    def closure():
        opt.zero_grad()
        loss = ((_model(_to_params(z, lo, hi), wl, r0) - R) ** 2).mean(-1).sum() * 1e3
        loss.backward()
        return loss

    opt.step(closure)
    return z.detach()


def _jacobian_z(z, base, wl, r0, lo, hi):
    """d model / d z (n, W, 6) by forward differences in z (the working dtype)."""
    h = 1e-3 if z.dtype == torch.float32 else 1e-5
    cols = []
    for k in range(z.shape[-1]):
        zk = z.clone()
        zk[:, k] += h
        cols.append((_model(_to_params(zk, lo, hi), wl, r0) - base) / h)
    return torch.stack(cols, -1)


def _gauss_newton(z, R, wl, r0, lo, hi, steps):
    """Levenberg-Marquardt on every spectrum independently (second order: the Gauss-Newton Hessian
    J^T J of each spectrum's least-squares problem). Returns (z, converged) where converged means the
    Gauss-Newton decrement (the loss a further Newton step would still remove) is below 1e-3 of the loss."""
    n, W = R.shape
    lam = torch.full((n,), 1e-3, dtype=z.dtype, device=z.device)
    eye = torch.eye(z.shape[-1], dtype=z.dtype, device=z.device)
    converged = torch.zeros(n, dtype=torch.bool, device=z.device)
    with torch.no_grad():
        for _ in range(steps + 1):
            base = _model(_to_params(z, lo, hi), wl, r0)
            r = base - R
            loss = (r * r).mean(-1)
            J = _jacobian_z(z, base, wl, r0, lo, hi)
            g = (J.transpose(1, 2) @ r[..., None])  # (n, 6, 1)
            H = J.transpose(1, 2) @ J
            damp = torch.diagonal(H, dim1=1, dim2=2).mean(-1)[:, None, None] * 1e-6 * eye  # flat directions
            # solve_ex: a degenerate spectrum (a singular or non-finite system) must not stop the others
            sol, info = torch.linalg.solve_ex(H + damp, g)
            decrement = (g.transpose(1, 2) @ sol).reshape(-1) / (2 * W)
            converged = torch.isfinite(loss) & (info == 0) & (decrement <= 1e-3 * loss + 1e-14)
            if bool(converged.all()) or _ == steps:
                break
            diag = torch.diagonal(H, dim1=1, dim2=2)
            A = H + lam[:, None, None] * torch.diag_embed(diag + 1e-12)
            sol, info = torch.linalg.solve_ex(A, g)
            ok = (info == 0) & torch.isfinite(sol).all(1).squeeze(-1)
            step = torch.where(ok[:, None], -sol.squeeze(-1), torch.zeros_like(z))
            z_try = z + step
            r_try = _model(_to_params(z_try, lo, hi), wl, r0) - R
            better = torch.isfinite(r_try).all(-1) & ((r_try * r_try).mean(-1) < loss)
            z = torch.where(better[:, None], z_try, z)
            lam = torch.where(better, lam / 3, lam * 4).clamp(1e-9, 1e9)
    return z, converged


# ------------------------------------------------------------------------------------------------- BRDF fit
@dataclass
class BrdfFit:
    sigma2: torch.Tensor  # (B,)
    rho0: torch.Tensor  # (B,)
    rho_d: torch.Tensor  # (B,) diffuse reflectance (0 when not fitted)
    rmse: torch.Tensor  # (B,) eq 2.4.14 on the BRDF values
    converged: torch.Tensor  # (B,)


SIGMA2_BOUNDS = (1e-4, 0.5)
RHO0_BOUNDS = (1e-3, 0.3)


def brdf_model(cos_i: torch.Tensor, cos_r: torch.Tensor, cos_2b: torch.Tensor, sigma2: Numeric, rho0: Numeric,
               rho_d: Numeric | None = None) -> torch.Tensor:
    """The model ``fit_brdf`` fits: the microfacet lobe (eq 2.3.4, ``optics.microfacet_brdf_cos``), or with
    ``rho_d`` the combined BRDF of eq 3.1.1, lobe + (1 - F(β)) ρ_d / π (``optics.combined_brdf_cos``, which is
    0 below the horizon). Cosines as ``optics.cosines_from_angles`` gives them; all inputs broadcast."""
    if rho_d is None:
        return microfacet_brdf_cos(cos_i, cos_r, cos_2b, sigma2, rho0)
    return combined_brdf_cos(cos_i, cos_r, cos_2b, rho_d, sigma2, rho0)


def fit_brdf(theta_i: TensorLike, theta_r: TensorLike, delta_phi: TensorLike, brdf: TensorLike, *,
             diffuse: bool = True, steps: int = 200) -> BrdfFit:
    """Fit the microfacet σ² and ρ0 (and a diffuse reflectance ρ_d with ``diffuse=True``) per band to BRDF
    samples (section 3.3.3): least squares on the BRDF values (eq 2.4.14) of ``brdf_model``, from a grid of
    starts, then L-BFGS, independently per band.

    Args:
        theta_i, theta_r: incidence and view angles from the normal, rad, in [0, π/2].
        delta_phi: relative azimuth, rad (Δφ = π the forward plane).
        brdf: measured BRDF values, sr^-1 (finite, >= 0).
        diffuse: fit ρ_d too (the combined BRDF of eq 3.1.1), else the lobe alone.
        steps: L-BFGS iterations.

    Shape:
        Angles (M,) or (M, B), ``brdf`` (M, B) (a 1-D ``brdf`` is one band); results (B,).

    Returns:
        A ``BrdfFit`` (σ², ρ0, ρ_d, RMSE, converged per band).

    >>> from torchskin import optics
    >>> ti = torch.linspace(0.1, 1.2, 12, dtype=torch.float64).repeat_interleave(12)
    >>> tr = torch.linspace(0.0, 1.2, 12, dtype=torch.float64).repeat(12)
    >>> dp = torch.full_like(ti, math.pi)
    >>> res = fit_brdf(ti, tr, dp, optics.combined_brdf(ti, tr, dp, 0.3, 0.02, 0.045))
    >>> [round(float(x[0]), 4) for x in (res.sigma2, res.rho0, res.rho_d)]
    [0.02, 0.045, 0.3]
    """
    f = as_tensor(brdf, dtype=torch.float64)
    if f.dim() == 1:
        f = f[:, None]
    ti, tr, dp = (as_tensor(x, dtype=torch.float64) for x in (theta_i, theta_r, delta_phi))
    ti, tr, dp = (x[:, None] if x.dim() == 1 else x for x in (ti, tr, dp))
    try:
        ti, tr, dp, f = torch.broadcast_tensors(ti, tr, dp, f)
    except RuntimeError:
        raise ValueError(f"angles {tuple(ti.shape)} and brdf {tuple(f.shape)} must have matching rows") from None
    bad = ~torch.isfinite(f) | (f < 0)
    if bool(bad.any()):
        i, j = (int(x) for x in bad.nonzero()[0])
        raise ValueError(f"row {i}, column {j}: BRDF value {float(f[i, j]):g} is NaN or negative")
    for name, x in (("theta_i", ti), ("theta_r", tr)):
        badang = ~torch.isfinite(x) | (x < 0) | (x > math.pi / 2)
        if bool(badang.any()):
            i, j = (int(v) for v in badang.nonzero()[0])
            raise ValueError(f"row {i}: {name} {math.degrees(float(x[i, j])):g} deg must lie in [0, 90] degrees")
    ci, cr, c2b = cosines_from_angles(ti, tr, dp)
    B = f.shape[1]
    # grid of starts per band: log σ² x ρ0 (x ρ_d), pick the best per band
    s_grid = torch.logspace(math.log10(0.003), math.log10(0.2), 12, dtype=torch.float64)
    r_grid = torch.linspace(0.01, 0.12, 8, dtype=torch.float64)
    S, Rg = torch.meshgrid(s_grid, r_grid, indexing="ij")
    S, Rg = S.reshape(-1, 1, 1), Rg.reshape(-1, 1, 1)
    if diffuse:
        # best diffuse level for each (σ², ρ0) start by linear least squares on the residual
        fs = brdf_model(ci, cr, c2b, S, Rg)
        basis = (1 - schlick_cos(Rg, half_angle_cos(c2b))) / math.pi  # the diffuse term of eq 3.1.1 per unit ρ_d
        d0 = (((f - fs) * basis).sum(1, keepdim=True) / (basis * basis).sum(1, keepdim=True)).clamp(0.0, 1.0)
        pred = fs + basis * d0
    else:
        d0 = None
        pred = brdf_model(ci, cr, c2b, S, Rg)
    err = ((pred - f) ** 2).mean(1)  # (G, B)
    g = err.argmin(0)
    cols = torch.arange(B)

    def logit(x, lo, hi):
        u = ((x - lo) / (hi - lo)).clamp(1e-6, 1 - 1e-6)
        return torch.log(u / (1 - u))

    def sig(z, lo, hi):
        return lo + (hi - lo) * torch.sigmoid(z)

    zs = logit(S.reshape(-1)[g], *SIGMA2_BOUNDS).clone().requires_grad_(True)
    zr = logit(Rg.reshape(-1)[g], *RHO0_BOUNDS).clone().requires_grad_(True)
    params = [zs, zr]
    if diffuse:
        zd = logit(d0.reshape(d0.shape[0], -1)[g, cols], 0.0, 1.0).clone().requires_grad_(True)
        params.append(zd)
    scale = 1.0 / f.abs().amax(0).clamp_min(1e-12)  # per-band normalisation of the loss

    def predict():
        s2, r0 = sig(zs, *SIGMA2_BOUNDS), sig(zr, *RHO0_BOUNDS)
        rd = sig(zd, 0.0, 1.0) if diffuse else None
        return brdf_model(ci, cr, c2b, s2, r0, rd)

    opt = torch.optim.LBFGS(params, lr=1.0, max_iter=steps, history_size=20, tolerance_grad=1e-14,
                            tolerance_change=1e-16, line_search_fn="strong_wolfe")

    def closure():
        opt.zero_grad()
        loss = (((predict() - f) * scale) ** 2).mean(0).sum()
        loss.backward()
        return loss

    opt.step(closure)
    for p in params:
        p.grad = None
    loss = (((predict() - f) * scale) ** 2).mean(0)
    loss.sum().backward()
    with torch.no_grad():
        gn = torch.sqrt(sum(p.grad**2 for p in params))
        pred = predict()
        e = torch.sqrt(((pred - f) ** 2).mean(0))
        return BrdfFit(sig(zs, *SIGMA2_BOUNDS), sig(zr, *RHO0_BOUNDS),
                       sig(zd, 0.0, 1.0) if diffuse else torch.zeros(B, dtype=torch.float64), e,
                       torch.isfinite(e) & (gn <= 1e-6 + 1e-3 * loss.detach()))


__all__ = ["BrdfFit", "FIT_BOUNDS", "SkinFit", "brdf_model", "check_spectra", "fit_brdf", "fit_skin", "rmse"]


# ------------------------------------------------------------------------------------------------- file I/O
def _csv_rows(path: str | os.PathLike[str], what: str) -> tuple[str, list[list[str]]]:
    import csv
    from pathlib import Path

    p = Path(path)
    if not p.is_file():
        raise ValueError(f"{what} file {str(p)!r} does not exist")
    try:
        with open(p, newline="", encoding="utf-8") as fh:
            return p.name, [r for r in csv.reader(fh) if r and any(c.strip() for c in r)]
    except (UnicodeDecodeError, csv.Error) as e:
        raise ValueError(f"{p.name}: not a readable CSV text file ({e})") from None


def _numbers(fname: str, i: int, cells: list[str], n: int) -> list[float]:
    """Row ``i`` of a CSV as floats; errors name the file, row and column."""
    if len(cells) != n:
        raise ValueError(f"{fname}: row {i} has {len(cells)} values for {n} columns")
    out = []
    for j, c in enumerate(cells):
        try:
            out.append(float(c))
        except ValueError:
            raise ValueError(f"{fname}: row {i}, column {j}: {c!r} is not a number") from None
    return out


def read_spectra_csv(path: str | os.PathLike[str],
                     min_wavelengths: int = 1) -> tuple[list[str], torch.Tensor, torch.Tensor]:
    """Spectra CSV: header row = wavelengths in nm (optionally a first non-numeric column of names), one
    spectrum per row. Returns (names, reflectance (n, W), wavelengths (W,)), validated as ``check_spectra``
    does; errors name the file, row and column. At least ``min_wavelengths`` wavelengths (default 1: with fewer
    wavelengths than skin parameters some can never be determined, and ``fit_skin`` reports them undetermined,
    e.g. a 4-band camera's 544, 633, 1080 and 1580 nm)."""
    fname, rows = _csv_rows(path, "spectra")
    if len(rows) < 2:
        raise ValueError(f"{fname}: needs a header row of wavelengths and at least one spectrum")
    head = [c.strip() for c in rows[0]]
    named = not _is_float(head[0])
    if named:
        head = head[1:]
    if not head:
        raise ValueError(f"{fname}: the header holds no wavelength columns (wavelengths in nm expected)")
    bad = [j for j, c in enumerate(head) if not _is_float(c)]
    if bad:
        raise ValueError(f"{fname}: the header must hold wavelengths in nm; column {bad[0]} is "
                         f"{head[bad[0]][:40]!r} ({len(bad)} of {len(head)} columns not numbers)")
    wl = [float(c) for c in head]
    names = [r[0].strip() if named else str(i) for i, r in enumerate(rows[1:])]
    vals = [_numbers(fname, i, r[1:] if named else r, len(wl)) for i, r in enumerate(rows[1:])]
    try:
        R, w = check_spectra(torch.tensor(vals, dtype=torch.float64), torch.tensor(wl, dtype=torch.float64))
    except ValueError as e:
        raise ValueError(f"{fname}: {e}") from None
    if len(wl) < min_wavelengths:
        raise ValueError(f"{fname}: {len(wl)} wavelength(s) cannot determine the {len(NAMES)} skin parameters; "
                         f"need at least {min_wavelengths} wavelengths in 400-1700 nm")
    return names, R, w


def _is_float(c: str) -> bool:
    try:
        float(c)
        return True
    except ValueError:
        return False


def write_params_csv(path: str | os.PathLike[str], names: list[str], res: SkinFit) -> None:
    """Write a ``SkinFit`` as CSV: name, the six parameters (empty where not identifiable), their 1-sigma
    uncertainties, the RMSE and whether the fit converged, one row per spectrum."""
    from .io import write_text

    lines = [",".join(["name", *NAMES, *(f"std_{k}" for k in NAMES), "rmse", "converged"])]
    rep = res.reported()
    for i, n in enumerate(names):
        vals = ["" if rep[i][k] is None else f"{rep[i][k]:.6g}" for k in NAMES]
        std = [f"{float(x):.3g}" for x in res.std[i]]
        lines.append(",".join([n, *vals, *std, f"{float(res.rmse[i]):.6g}", str(bool(res.converged[i])).lower()]))
    write_text(path, "\n".join(lines) + "\n")


def read_brdf_csv(path: str | os.PathLike[str]) -> tuple[tuple[torch.Tensor, ...], torch.Tensor, list[float]]:
    """BRDF CSV: columns theta_i_deg, theta_r_deg, delta_phi_deg, then one column per band named by its
    wavelength in nm (values in sr^-1). Returns (angles in radians (3 tensors), brdf (M, B), bands_nm)."""
    fname, rows = _csv_rows(path, "BRDF")
    head = [c.strip() for c in rows[0]] if rows else []
    if head[:3] != ["theta_i_deg", "theta_r_deg", "delta_phi_deg"] or len(head) < 4:
        raise ValueError(f"{fname}: header must start theta_i_deg,theta_r_deg,delta_phi_deg then band columns")
    bad = [j for j, c in enumerate(head[3:], 3) if not (_is_float(c) and 0 < float(c) < math.inf)]
    if bad:
        raise ValueError(f"{fname}: band columns must be named by wavelength in nm; column {bad[0]} is "
                         f"{head[bad[0]][:40]!r}")
    data = [_numbers(fname, i, r, len(head)) for i, r in enumerate(rows[1:])]
    if not data:
        raise ValueError(f"{fname}: no data rows")
    a = torch.tensor(data, dtype=torch.float64)
    for j, (name, lo, hi) in enumerate((("theta_i_deg", 0.0, 90.0), ("theta_r_deg", 0.0, 90.0),
                                        ("delta_phi_deg", -math.inf, math.inf))):
        badr = ~torch.isfinite(a[:, j]) | (a[:, j] < lo) | (a[:, j] > hi)
        if bool(badr.any()):
            i = int(badr.nonzero()[0])
            raise ValueError(f"{fname}: row {i}, column {j} ({name}): {float(a[i, j]):g} must be a finite angle"
                             + (f" in [{lo:g}, {hi:g}] degrees" if math.isfinite(lo) else " in degrees"))
    f = a[:, 3:]
    badv = ~torch.isfinite(f) | (f < 0)
    if bool(badv.any()):
        i, j = (int(x) for x in badv.nonzero()[0])
        raise ValueError(f"{fname}: row {i}, column {j + 3} ({head[j + 3]} nm): BRDF value {float(f[i, j]):g} is "
                         "NaN, infinite or negative")
    dead = (f == 0).all(0)
    if bool(dead.any()):
        j = int(dead.nonzero()[0])
        raise ValueError(f"{fname}: column {j + 3} ({head[j + 3]} nm): every BRDF value is 0; nothing to fit")
    deg = math.pi / 180
    return (a[:, 0] * deg, a[:, 1] * deg, a[:, 2] * deg), a[:, 3:], [float(c) for c in head[3:]]

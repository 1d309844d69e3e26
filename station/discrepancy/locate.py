"""Where a model and the measurement disagree: significant residual structure, by step and component.

In the basis (from the coefficient residuals of a fit and their marginal covariance): per step and
component group (force fundamental, force harmonic k, force offset/drift polynomial, mains line h) the
chi^2 of its rows; a component counts when its chi^2 summed over steps has p < ``ALPHA`` (2 dof
per step and sinusoid, 3 for the polynomial), and the steps named are those with p < 1e-3.
Outside the basis (from the LS residual of each step): significant spectral lines, grouped across steps
by their frequency relative to the crank frequency (sidebands, non-integer harmonics) or by absolute
frequency; and broadband excess of the residual over the robust noise floor.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.special import chdtrc

from station.discrepancy.data import RigData
from station.discrepancy.decompose import FLAT_TOP, K_MAX
from station.discrepancy.eiv import force_cov
from station.discrepancy.fit import ModelFit
from station.discrepancy.spectrum import Line, significant_lines

ALPHA = 1e-6


@dataclass(frozen=True)
class Finding:
    """One located disagreement: channel ('force' or 'displacement'), component, steps (recording step
    indices), size (largest per-step magnitude, in ``unit``), chi2 over the steps, and a sentence."""

    channel: str
    component: str
    steps: tuple[int, ...]
    size: float
    unit: str
    chi2: float
    text: str


def step_span(steps: tuple[int, ...] | list[int]) -> str:
    """'step 3', 'steps 3-6' or 'steps 1, 4, 7'."""
    s = sorted(set(steps))
    if len(s) == 1:
        return f"step {s[0]}"
    if s == list(range(s[0], s[-1] + 1)):
        return f"steps {s[0]}–{s[-1]}"
    return "steps " + ", ".join(str(x) for x in s)


def _groups(n_mains: int) -> list[tuple[str, str, list[int], str]]:
    g = [("force", "fundamental", [0, 1], "V")]
    g += [("force", f"harmonic {k}", [2 * k - 2, 2 * k - 1], "V") for k in range(2, K_MAX + 1)]
    g += [("force", "offset and drift", [2 * K_MAX, 2 * K_MAX + 1, 2 * K_MAX + 2], "V")]
    g += [("force", f"mains line {h}", [2 * K_MAX + 1 + 2 * h, 2 * K_MAX + 2 + 2 * h], "V")
          for h in range(1, n_mains + 1)]
    return g


def _marginal_chi2(R: np.ndarray, sigma: float, e: np.ndarray, cols: list[int],
                   extra: np.ndarray | None = None) -> float:
    """e_g^T C_gg^-1 e_g for the columns ``cols`` of one step, C = sigma^2 (R^T R)^-1 over the valid
    slots (+ ``extra`` (2, 2) on the group): the group's own significance, not smeared by the
    correlation with other columns as the rows of the triangular whitening are."""
    valid = np.nonzero(np.any(R != 0, axis=0))[0]
    if not set(cols) <= set(valid.tolist()):
        return float("nan")
    Rv = R[np.ix_(valid, valid)]
    Ci = np.linalg.inv(Rv.T @ Rv)
    pos = [int(np.nonzero(valid == c)[0][0]) for c in cols]
    C = sigma**2 * Ci[np.ix_(pos, pos)]
    if extra is not None:
        C = C + extra
    eg = e[cols]
    return float(eg @ np.linalg.solve(C, eg))


def in_basis(data: RigData, fit: ModelFit) -> list[Finding]:
    """Significant force coefficient residuals of ``fit`` (see module docstring), each component tested
    on its own marginal covariance, the noise of the measured motion that drives the model included
    (``eiv.force_cov``).  The displacement channel is the model's input: ``drive`` checks it."""
    out: list[Finding] = []
    idx = [s.index for s in data.steps]
    resid = data.cf - fit.m_f
    fcov = force_cov(data)
    n = data.n_steps
    for channel, comp, cols, unit in _groups(data.n_mains):
        k = cols[1] // 2 + 1 if comp.startswith(("fundamental", "harmonic")) else 0
        c2 = np.array([_marginal_chi2(data.Rf[i], data.sigma_f[i], resid[i], cols,
                                      fcov[i, k - 1] if k else None) for i in range(n)])
        valid = np.isfinite(c2)
        _report(out, channel, comp, cols, unit, np.nan_to_num(c2), valid, resid, data, idx)
    return out


def _report(out: list[Finding], channel: str, comp: str, cols: list[int], unit: str, c2: np.ndarray,
            valid: np.ndarray, resid: np.ndarray, data: RigData, idx: list[int]) -> None:
    if not np.any(valid):
        return
    dof = len(cols)
    total = float(c2[valid].sum())
    if chdtrc(dof * int(valid.sum()), max(total, 0.0)) >= ALPHA:  # chi2.sf: 1 at total <= 0
        return
    sig = valid & (chdtrc(dof, c2) < 1e-3)
    steps = tuple(idx[i] for i in np.nonzero(sig)[0]) or tuple(idx[i] for i in np.nonzero(valid)[0])
    if comp == "offset and drift":
        mags = np.abs(resid[:, cols[0]]) + np.abs(resid[:, cols[1]]) + np.abs(resid[:, cols[2]])
        what = "offset/drift (DC, slope, curvature over each window)"
    else:
        mags = np.hypot(resid[:, cols[0]], resid[:, cols[1]])
        what = comp
    size = float(np.max(mags[valid]))
    extra = ""
    if channel == "force" and comp == "fundamental":
        extra = _fundamental_text(data, resid, sig if np.any(sig) else valid)
    sel = [i for i, s in enumerate(data.steps) if s.index in steps]
    t0 = float(np.min(data.t_mid_s[sel] - data.half_s[sel]))
    t1 = float(np.max(data.t_mid_s[sel] + data.half_s[sel]))
    out.append(Finding(channel, comp, steps, size, unit, total,
                       f"{channel} {what}: up to {size:.3g} {unit} in {step_span(steps)} (t = {t0:.3g}–{t1:.3g} s)"
                       f" (chi2 {total:.3g} for {dof * int(valid.sum())} dof){extra}"))


def fundamental_table(data: RigData, fit: ModelFit) -> tuple[tuple[float, float, float, float], ...]:
    """Per step (f in Hz, gain error in %, phase error in mrad, z): measured force fundamental against
    the model's, relative to the model's; z = sqrt of its marginal chi^2 (2 dof, displacement noise
    included)."""
    V1 = data.cf[:, 0] - 1j * data.cf[:, 1]
    M1 = fit.m_f[:, 0] - 1j * fit.m_f[:, 1]
    rel = V1 / np.where(M1 == 0, 1.0, M1) - 1.0
    eiv = force_cov(data)[:, 0]
    z = np.sqrt([_marginal_chi2(data.Rf[i], data.sigma_f[i], data.cf[i] - fit.m_f[i], [0, 1], eiv[i])
                 for i in range(data.n_steps)])
    return tuple((float(f), float(100 * r.real), float(1e3 * r.imag), float(q))
                 for f, r, q in zip(data.f_hz, rel, z, strict=True))


def _fundamental_text(data: RigData, resid: np.ndarray, sel: np.ndarray) -> str:
    V1 = data.cf[:, 0] - 1j * data.cf[:, 1]
    dV = resid[:, 0] - 1j * resid[:, 1]
    rel = dV / V1
    parts = [f"{data.f_hz[i]:.3g} Hz: gain {100 * rel[i].real:+.3g} %, phase {1e3 * rel[i].imag:+.3g} mrad"
             for i in np.nonzero(sel)[0][:4]]
    return "; " + "; ".join(parts)


def out_of_basis(data: RigData, alpha: float = 1e-4) -> list[Finding]:
    """Lines outside the basis (force channel), grouped across steps, broadband excess, clipping."""
    fs = data.sample_rate_hz
    lines: list[Line] = []
    fmap = {s.index: s.f_hz for s in data.steps}
    out: list[Finding] = []
    for i, why in data.excluded:
        if "clipped" in why:  # the others (too short) are notes, not findings about the rig
            out.append(Finding("force", "clipping", (i,), float("nan"), "", float("nan"), f"step {i}: {why}"))
    clipped = [s.index for s in data.steps if s.flat_top >= FLAT_TOP]
    if clipped:  # kept because fewer than 2 steps would remain
        out.append(Finding("force", "clipping", tuple(clipped), float(max(s.flat_top for s in data.steps)),
                           "samples", float("nan"),
                           f"force signal clipped (flat tops up to {max(s.flat_top for s in data.steps)} "
                           f"samples at the window extreme) in {step_span(clipped)}"))
    for s in data.steps:
        # lines fitted as nuisance columns (found in the first pass) and any left in the residual
        lines += [Line(s.index, f, a, float("nan")) for f, a in zip(s.extra_hz, s.extra_amp, strict=True)]
        ls = significant_lines(s.force.residual, s.force.sigma, fs, s.index, alpha)
        lines += ls
        excess = s.force.ssr / s.n_samples - s.force.sigma**2 - sum(ln.amplitude**2 / 2 for ln in ls)
        if excess > 0.25 * s.force.sigma**2:
            rms = math.sqrt(excess)
            out.append(Finding("force", "broadband", (s.index,), rms, "V", float("nan"),
                               f"force broadband residual {rms:.3g} V RMS above the noise floor "
                               f"{s.force.sigma:.3g} V in step {s.index}"))
    used: set[int] = set()
    # integer crank harmonics above the modelled K (e.g. a distorted or clipped force): one finding
    high = [j for j, ln in enumerate(lines)
            if abs(ln.frequency_hz / fmap[ln.step] - round(ln.frequency_hz / fmap[ln.step])) < 0.01
            and round(ln.frequency_hz / fmap[ln.step]) > K_MAX]
    if high:
        ks = sorted({round(lines[j].frequency_hz / fmap[lines[j].step]) for j in high})
        steps = sorted({lines[j].step for j in high})
        amp = max(lines[j].amplitude for j in high)
        used.update(high)
        out.append(Finding("force", "high harmonics", tuple(steps), amp, "V", float("nan"),
                           f"force crank harmonics {ks[0]}–{ks[-1]} ({len(ks)} lines, above the modelled "
                           f"{K_MAX}): up to {amp:.3g} V in {step_span(steps)}"))
    # group by frequency relative to the crank frequency (rounded to 0.02 f)
    rel: dict[float, list[int]] = {}
    for j, ln in enumerate(lines):
        rel.setdefault(round(ln.frequency_hz / fmap[ln.step] / 0.02) * 0.02, []).append(j)
    for ratio, members in sorted(rel.items(), key=lambda kv: -len(kv[1])):
        js = [j for j in members if j not in used]
        steps = sorted({lines[j].step for j in js})
        if len(steps) < 2 or not js:
            continue
        used.update(js)
        amp = max(lines[j].amplitude for j in js)
        k = round(ratio)
        where = f"{ratio:.2f} f" if k == 0 else f"{k} f {'+' if ratio >= k else '-'} {abs(ratio - k):.2f} f"
        out.append(Finding("force", f"line at {ratio:.2f} f", tuple(steps), amp, "V", float("nan"),
                           f"force line at {where} (not a crank harmonic): up to {amp:.3g} V in "
                           f"{step_span(steps)}"))
    out = _pair_sidebands(out)
    # group the rest by absolute frequency (0.5 Hz)
    absf: dict[float, list[int]] = {}
    for j, ln in enumerate(lines):
        if j not in used:
            absf.setdefault(round(ln.frequency_hz / 0.5) * 0.5, []).append(j)
    for nu, js in sorted(absf.items()):
        steps = sorted({lines[j].step for j in js})
        amp = max(lines[j].amplitude for j in js)
        ratios = ", ".join(f"{lines[j].frequency_hz / fmap[lines[j].step]:.2f} f" for j in js[:3])
        out.append(Finding("force", f"line at {nu:g} Hz", tuple(steps), amp, "V", float("nan"),
                           f"force line at {nu:g} Hz ({ratios}): up to {amp:.3g} V in {step_span(steps)}"))
    return out


def _pair_sidebands(found: list[Finding]) -> list[Finding]:
    """Merge lines at (k - d) f and (k + d) f seen in common steps into one sideband finding."""
    rel = [f for f in found if f.component.startswith("line at") and f.component.endswith(" f")]
    ratio = {id(f): float(f.component.split()[2]) for f in rel}
    merged: list[Finding] = []
    done: set[int] = set()
    for a in rel:
        for b in rel:
            if id(a) in done or id(b) in done or ratio[id(b)] <= ratio[id(a)]:
                continue
            centre = (ratio[id(a)] + ratio[id(b)]) / 2
            k = round(centre)
            if k < 1 or abs(centre - k) > 0.011 or not set(a.steps) & set(b.steps):
                continue
            d = (ratio[id(b)] - ratio[id(a)]) / 2
            steps = tuple(sorted(set(a.steps) | set(b.steps)))
            amp = max(a.size, b.size)
            kf = "f" if k == 1 else f"{k} f"
            merged.append(Finding("force", f"sidebands at {kf} ± {d:.2f} f", steps, amp, "V", float("nan"),
                                  f"force sidebands at {kf} ± {d:.2f} f: up to {amp:.3g} V in "
                                  f"{step_span(steps)}"))
            done.update({id(a), id(b)})
    return [f for f in found if id(f) not in done] + merged

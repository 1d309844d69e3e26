"""The rig as the model describes it, evaluated in the harmonic domain for every step at once.

Per step (crank frequency f, w = 2 pi f, harmonics k = 1..K, Omega_k = k w), from the measured
displacement fundamental X_1 (phasor, m):

1. frame motion  D_k (k = 1..K): the displacement channel's harmonics as recorded (``eiv``), whatever
   their origin; the slider crank x(phi) = r sin phi - kappa r^2 cos^2 phi / (1 + sqrt(1 - kappa^2 r^2
   cos^2 phi)), kappa = 1/L, r = |X_1|, phi = w tau + angle(j X_1) is only a check of the drive
   (``drive``), not part of the force model;
2. frame motion at the force sample instants  x_k = D_k exp(j Omega_k Delta)  (``channel_delay``),
   and ``clock_skew`` (the converters' clocks differ: the displacement sample at t is taken e t later,
   x_k = D_k exp(-j Omega_k e t), t the step's mid time), divided by the displacement sensor's own
   response H_s(j Omega_k) (``displacement_resonance``,
   ``drivers.rig.params.DisplacementResonance``: the recorded motion is H_s times the frame's);
3. spring force  F_k = G(Omega_k) x_k,  G = k_f Z2 / X_b = s^2 * (paper Eq. 9, or Eq. 8 with
   ``coupling_compliance``) in N/m;  F(t) = -M g + sum Re(F_k e^{j k w tau});
4. transducer output  v = S F (1 + q F/C + c (F/C)^2)  (``transducer_nonlinearity``; else S F), taken
   to harmonics on a grid of 64 points per period;
5. conditioner low-pass  V_k <- V_k B(j Omega_k)  (analogue Butterworth, unit DC gain);
6. force channel  = V + offset + drift (rho t + beta t^2, ``zero_drift``) + mains lines
   sum_h Re(Q_h e^{j h w_m t}) (``mains_interference``, t absolute time).  Without a common clock
   (steps with their own time origins) the drift is each step's own offset, slope and curvature, and
   the mains lines each step's own phasors.

Output: model coefficients in the force slots (n, n_f) and displacement-harmonic slots (n, n_d) of
``RigData``, and the fundamental ratio V_1 / X_1 (V/m) used for the errors-in-variables weights.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from functools import lru_cache
from typing import TypeVar

import numpy as np
from numpy.typing import NDArray

from drivers.rig.model import Laplace, spring_response
from drivers.rig.params import DisplacementResonance
from station.discrepancy.data import G, RigData, per_data_set
from station.discrepancy.decompose import K_MAX
from station.discrepancy.eiv import measured_motion

FloatArray = NDArray[np.float64]
ComplexArray = NDArray[np.complex128]
N_GRID = 64
_K = TypeVar("_K")
_V = TypeVar("_V")  # a kept stage: an array or a tuple of arrays


def crank_displacement_harmonics(x1: ComplexArray, kappa: float, K: int) -> ComplexArray:
    """Phasors D_k (k = 1..K) of the slider-crank displacement, shape (n, K), m."""
    r = np.abs(x1)[:, None]
    phi0 = np.angle(1j * x1)
    phi = 2 * np.pi * np.arange(N_GRID) / N_GRID
    rc2 = (r * np.cos(phi)) ** 2
    x = r * np.sin(phi) - kappa * rc2 / (1.0 + np.sqrt(np.maximum(1.0 - kappa**2 * rc2, 0.0)))
    c = 2.0 * np.fft.fft(x, axis=1)[:, 1 : K + 1] / N_GRID
    return c * np.exp(1j * np.arange(1, K + 1)[None, :] * phi0[:, None])


def butterworth(order: int, cutoff_hz: float, s: ComplexArray) -> ComplexArray:
    """Analogue Butterworth low-pass B(s) = prod_k 1 / (1 - s / p_k), poles
    p_k = w_c exp(j pi (2k + n - 1) / (2n)), k = 1..n (unit DC gain, -3 dB at cutoff_hz)."""
    k = np.arange(1, order + 1)
    poles = 2 * np.pi * cutoff_hz * np.exp(1j * np.pi * (2 * k + order - 1) / (2 * order))
    out = np.ones_like(s)
    for p in poles:
        out = out / (1.0 - s / p)
    return out


def _nonlinear_output(F0: float, Fk: ComplexArray, S: float, q: float, c: float, C: float,
                      K: int) -> tuple[FloatArray, ComplexArray]:
    """(V_0 (n,), V_k (n, K)) of v = S F (1 + q F/C + c (F/C)^2) for F = F0 + sum Re(F_k e^{j k theta})."""
    n = Fk.shape[0]
    spec = np.zeros((n, N_GRID // 2 + 1), dtype=complex)
    spec[:, 1 : K + 1] = Fk * (N_GRID / 2)
    spec[:, 0] = F0 * N_GRID
    F = np.fft.irfft(spec, N_GRID, axis=1)
    x = F / C
    v = S * F * (1.0 + q * x + c * x * x)
    V = np.fft.rfft(v, axis=1)
    return V[:, 0].real / N_GRID, 2.0 * V[:, 1 : K + 1] / N_GRID


@dataclass(frozen=True)
class _Drive:
    """What ``predict`` needs of a data set that no parameter changes: harmonic frequencies f_k (Hz)
    and Om (rad/s), s = j Om, s^2 (n, K_MAX), the measured motion D (n, K_MAX) and its displacement
    slots md (n, n_d)."""

    f: FloatArray
    Om: FloatArray
    s: ComplexArray
    s2: ComplexArray
    D: ComplexArray
    md: FloatArray


@per_data_set(4)
def _drive(data: RigData) -> _Drive:
    """``_Drive`` once per data set."""
    Om = 2 * np.pi * data.f_hz[:, None] * np.arange(1, K_MAX + 1)[None, :]
    s = np.asarray(1j * Om, dtype=np.complex128)
    D = measured_motion(data)  # the frame motion as recorded drives the model (``eiv``)
    md = np.zeros((data.n_steps, 2 * (K_MAX - 1)))
    md[:, 0::2], md[:, 1::2] = D[:, 1:].real, -D[:, 1:].imag
    out = _Drive(Om / (2 * np.pi), Om, s, s * s, D, md)
    for a in (out.f, out.Om, out.s, out.s2, out.D, out.md):
        a.flags.writeable = False
    return out


_MOTION_EFFECTS = frozenset(("channel_delay", "clock_skew", "displacement_resonance"))
_KEEP = 32  # stage values kept per stage and model (the oldest are dropped first)


@dataclass(frozen=True)
class _Plan:
    """What ``predict`` needs of one model (``effects``) on one data set that no parameter changes,
    and the stages of its evaluations that depend on a few parameters, kept for those parameters'
    values: a Jacobian's forward differences change one parameter at a time, so most stages of each
    of its points are those of the point it is taken at (a kept value is exactly the one computed
    anew, read-only).  x: motion (n, K) by (delay, skew, resonance, damping); G: G s^2 (n, K) by
    (k_f, b_f[, k_c, b_c]); V: the nonlinear output (V_0 (n,), V_k (n, K)) by (x key, G key, S,
    quadratic, cubic); B: the low-pass (n, K) by cut-off."""

    data: RigData
    dr: _Drive
    effects: dict[str, int]
    moved: bool
    coupled: bool
    nonlinear: bool
    lowpass: bool
    order: int
    mains: bool
    drift: bool
    merges: tuple[tuple[int, int, int], ...]  # (step, mains line, crank harmonic index - 1) of merged lines
    F0: float
    lp: Laplace
    kmask: ComplexArray  # the data set's harmonics mask as 1 + 0j / 0 (what a product with it casts it to)
    x: dict[tuple[object, ...], ComplexArray] = field(default_factory=dict)
    G: dict[tuple[float, ...], ComplexArray] = field(default_factory=dict)
    V: dict[tuple[object, ...], tuple[FloatArray, ComplexArray]] = field(default_factory=dict)
    B: dict[float, ComplexArray] = field(default_factory=dict)


_PLANS: dict[tuple[int, tuple[tuple[str, int], ...]], _Plan] = {}


def plan(data: RigData, effects: Mapping[str, int]) -> _Plan:
    """``_Plan`` of the model ``effects`` on ``data``, made once (the most recent 64 are kept; a
    ``fit.Problem`` holds its own)."""
    ident = tuple(effects.items())
    key = (id(data), ident)
    hit = _PLANS.get(key)
    if hit is not None and hit.data is data:
        return hit
    coupled = "coupling_compliance" in effects
    lowpass = "conditioner_lowpass" in effects
    pl = _Plan(data=data, dr=_drive(data), effects=dict(effects),
               moved=bool(_MOTION_EFFECTS.intersection(effects)), coupled=coupled,
               nonlinear="transducer_nonlinearity" in effects, lowpass=lowpass,
               order=int(effects["conditioner_lowpass"]) if lowpass else 0,
               mains="mains_interference" in effects and data.n_mains > 0, drift="zero_drift" in effects,
               merges=tuple((int(i), int(h), int(data.merge[i, h]) - 1)
                            for i, h in zip(*np.nonzero(data.merge), strict=True)),
               F0=-data.total_mass_kg * G, lp=_laplace(data), kmask=_complex_mask(data))
    if len(_PLANS) >= 64:
        del _PLANS[next(iter(_PLANS))]  # the oldest
    _PLANS[key] = pl
    return pl


@per_data_set(4)
def _laplace(data: RigData) -> Laplace:
    """s = j 2 pi f_k and its powers up to s^4 at the harmonic frequencies of ``data``
    (``spring_response``; the stiff model uses s and s^2 of them), once per data set."""
    out = Laplace.at(_drive(data).f, coupled=True)
    for a in (out.s, out.s2, out.s3, out.s4):
        if a is not None:
            a.flags.writeable = False
    return out


@per_data_set(4)
def _complex_mask(data: RigData) -> ComplexArray:
    """``data.kmask`` (n, K) as complex numbers, once per data set."""
    out = data.kmask.astype(np.complex128)
    out.flags.writeable = False
    return out


def _keep(kept: dict[_K, _V], key: _K, value: _V) -> _V:
    """Keep a stage's ``value`` (an array or a tuple of arrays, made read-only) under ``key``, dropping
    the oldest beyond ``_KEEP``."""
    for a in value if isinstance(value, tuple) else (value,):
        if isinstance(a, np.ndarray):
            a.flags.writeable = False
    if len(kept) >= _KEEP:
        del kept[next(iter(kept))]
    kept[key] = value
    return value


def _motion(data: RigData, dr: _Drive, p: Mapping[str, float], effects: Mapping[str, int]) -> ComplexArray:
    """The frame motion at the force sample instants, x_k (n, K) m (steps 1-2 of the module)."""
    Om, x = dr.Om, dr.D
    if "channel_delay" in effects:
        x = x * np.exp(1j * Om * p["delay_s"])
    if "clock_skew" in effects:  # the displacement sample taken clock_skew * t after the force sample at t
        x = x * np.exp(-1j * Om * p["clock_skew"] * data.t_mid_s[:, None])
    if "displacement_resonance" in effects:  # the recorded motion is H_s x_b: the frame's is D / H_s
        x = x / DisplacementResonance(p["sensor_resonance_hz"], p["sensor_damping"]).response(dr.f)
    return x


def _spring(pl: _Plan, p: Mapping[str, float]) -> ComplexArray:
    """G(Omega_k) s^2 (n, K) N/m (step 3), S not involved."""
    data = pl.data
    G_k = spring_response(pl.lp, p["k_f"], p["b_f"], data.end_mass_kg, data.load_mass_kg,
                          (p["k_c"], p["b_c"]) if pl.coupled else None)
    return np.asarray(G_k * pl.dr.s2, dtype=np.complex128)


def _outputs(pl: _Plan, ps: Sequence[Mapping[str, float]]) -> tuple[FloatArray, ComplexArray]:
    """The transducer output after the conditioner for P parameter sets, V_0 (P, n) V and V_k (P, n, K)
    (steps 1-5 of the module).  The stages that depend on the parameters are kept for the inputs they
    depend on (``_Plan``) and looked up per set; the products that join them are taken for all sets
    together (element by element the same arithmetic as for one set)."""
    data, dr = pl.data, pl.dr
    xs, Gs, V0s, Vks, Bs = [], [], [], [], []
    kept_x, kept_G, kept_V, kept_B = pl.x, pl.G, pl.V, pl.B
    xkey: tuple[object, ...] = ()
    x = dr.D  # the recorded motion itself when no effect changes it
    for p in ps:
        if pl.moved:
            xkey = (p.get("delay_s"), p.get("clock_skew"), p.get("sensor_resonance_hz"), p.get("sensor_damping"))
            hit = kept_x.get(xkey)
            x = _keep(kept_x, xkey, _motion(data, dr, p, pl.effects)) if hit is None else hit
            xs.append(x)
        gkey = (p["k_f"], p["b_f"], p["k_c"], p["b_c"]) if pl.coupled else (p["k_f"], p["b_f"])
        Gk = kept_G.get(gkey)
        if Gk is None:
            Gk = _keep(kept_G, gkey, _spring(pl, p))
        if pl.nonlinear:
            vkey = (xkey, gkey, p["S"], p["quadratic"], p["cubic"])
            V = kept_V.get(vkey)
            if V is None:
                V = _keep(kept_V, vkey, _nonlinear_output(pl.F0, Gk * x, p["S"], p["quadratic"], p["cubic"],
                                                          data.capacity_N, K_MAX))
            V0s.append(V[0])
            Vks.append(V[1])
        else:
            Gs.append(Gk)
        if pl.lowpass:
            fc = p["cutoff_hz"]
            B = kept_B.get(fc)
            Bs.append(_keep(kept_B, fc, butterworth(pl.order, fc, dr.s)) if B is None else B)
    one = len(ps) == 1  # a single set: its arrays as views (P = 1) rather than stacked copies
    if pl.nonlinear:
        V0a, Vka = (V0s[0][None], Vks[0][None]) if one else (np.array(V0s), np.array(Vks))
    else:
        S = np.array([p["S"] for p in ps])
        V0a = np.repeat((S * pl.F0)[:, None], data.n_steps, axis=1)
        Fk = (Gs[0][None] if one else np.array(Gs)) * ((xs[0][None] if one else np.array(xs)) if pl.moved else dr.D)
        Vka = S[:, None, None] * Fk
    if pl.lowpass:
        Vka = Vka * (Bs[0][None] if one else np.array(Bs))
    return V0a, Vka * pl.kmask


@lru_cache(maxsize=16)
def _step_names(n: int, nm: int) -> tuple[tuple[str, ...], ...]:
    """The names of the per-step parameters of a recording without a common clock (``catalogue``):
    the mains phasors' real and imaginary parts (step by step, line by line), the offsets of steps
    1..n-1, the slopes and the curvatures."""
    return (tuple(f"re_{h}_s{i}" for i in range(n) for h in range(1, nm + 1)),
            tuple(f"im_{h}_s{i}" for i in range(n) for h in range(1, nm + 1)),
            tuple(f"dc_s{i}" for i in range(1, n)), tuple(f"slope_s{i}" for i in range(n)),
            tuple(f"curv_s{i}" for i in range(n)))


def _channel(pl: _Plan, ps: Sequence[Mapping[str, float]], V0: FloatArray, Vk: ComplexArray) -> FloatArray:
    """The force channel's coefficients (P, n, n_f) for P parameter sets ``ps`` from their outputs V0
    (P, n) and V_k (P, n, K) (step 6 of the module, evaluated for all P at once: element by element
    the same arithmetic as for one; ``Vk`` is not changed)."""
    data = pl.data
    n, K, P = data.n_steps, K_MAX, len(ps)

    def col(name: str) -> FloatArray:  # a parameter over the P sets, (P, 1)
        return np.array([q[name] for q in ps])[:, None]

    nm = data.n_mains
    m = np.zeros((P, n, 2 * K + 3 + 2 * nm))
    if pl.mains:
        hh = np.arange(1, nm + 1)[None, None, :]
        if data.common_clock:
            Q = np.array([[complex(q[f"re_{h}"], q[f"im_{h}"]) for h in range(1, nm + 1)] for q in ps])[:, None, :]
            W = Q * np.exp(1j * hh * 2 * np.pi * col("frequency_hz")[:, :, None] * data.t_mid_s[None, :, None])
        else:  # steps with their own time origins: a phasor per step and line
            re, im = _step_names(n, nm)[:2]  # (a planned step of a proposal: no line of its own yet: 0)
            W = np.empty((P, n, nm), dtype=complex)
            W.real = np.array([[q.get(k, 0.0) for k in re] for q in ps]).reshape(P, n, nm)
            W.imag = np.array([[q.get(k, 0.0) for k in im] for q in ps]).reshape(P, n, nm)
        if pl.merges:
            Vk = Vk.copy()
        for i, line, k in pl.merges:
            Vk[:, i, k] += W[:, i, line]
            W[:, i, line] = 0.0
        m[:, :, 2 * K + 3 :: 2], m[:, :, 2 * K + 4 :: 2] = W.real, -W.imag
    else:  # no lines: -0.0 in the imaginary parts' slots, as -Im of a zero phasor
        m[:, :, 2 * K + 4 :: 2] = -0.0
    m[:, :, 0 : 2 * K : 2], m[:, :, 1 : 2 * K : 2] = Vk.real, -Vk.imag
    dc = V0 + col("offset_V")
    if pl.drift and not data.common_clock:  # per step: offset (step 0: offset_V), slope, curvature
        # (a planned step of a proposal has no drift of its own yet: 0)
        dcs, slopes, curvs = _step_names(n, nm)[2:]
        dc = dc + np.array([[0.0] + [q.get(k, 0.0) for k in dcs] for q in ps])
        m[:, :, 2 * K + 1] = np.array([[q.get(k, 0.0) for k in slopes] for q in ps])
        m[:, :, 2 * K + 2] = np.array([[q.get(k, 0.0) for k in curvs] for q in ps])
    elif pl.drift:
        rho, beta, tm, h = col("rate_V_per_s"), col("quadratic_V_per_s2"), data.t_mid_s, data.half_s
        dc = dc + rho * tm + beta * tm**2
        m[:, :, 2 * K + 1] = (rho + 2 * beta * tm) * h
        m[:, :, 2 * K + 2] = beta * h**2
    m[:, :, 2 * K] = dc  # (without drift the slope and curvature slots stay 0)
    return m


def predict(data: RigData, p: Mapping[str, float], effects: Mapping[str, int]
            ) -> tuple[FloatArray, FloatArray, ComplexArray]:
    """Model coefficients (force (n, n_f), displacement harmonics (n, n_d)) and V_1/X_1 (n,).

    p: physical parameters by name (S V/N, k_f N/m, b_f N s/m, offset_V V, and the effects' own);
    effects: names of the effects switched on (value: the low-pass order, else ignored)."""
    pl = plan(data, effects)
    V0, Vk = _outputs(pl, (p,))
    m = _channel(pl, (p,), V0, Vk)[0]
    return m, pl.dr.md, Vk[0, :, 0] / data.x1


def forces(pl: _Plan, ps: Sequence[Mapping[str, float]]) -> FloatArray:
    """The force coefficients of ``predict`` for P parameter sets at once on the model and data set of
    ``pl`` (``plan``), (P, n, n_f): the same values (a Jacobian's forward differences, each of which
    changes one parameter: most stages are shared, ``_Plan``, and the force channel is evaluated for
    all sets together)."""
    return _channel(pl, ps, *_outputs(pl, ps))

"""What a catalogue effect's fitted parameters may be on a real rig (``implausible``): a fit outside
these bounds is not what the effect's name means, so the name is not given for it and its model is
not a possible truth (``plausible`` withdraws such names, ``ties`` leaves such models out of the
average, the selection never names one while a physical explanation fits as well).

* transducer nonlinearity above 5 % of capacity;
* a channel delay longer than a millisecond, or *negative* (the force sampled after the
  displacement) by more than one sample interval: ``channel_delay`` is the skew of a multiplexed ADC
  (``drivers.rig.params.ChannelDelay``), and a force channel that lags by more than a sample is the
  group delay of something in the force path (a low-pass, a coupling), which the catalogue models
  as such;
* a coupling softer than a tenth of the transducer (no adapter is);
* a conditioner cut-off below 10 Hz; a mains line more than 2 % off 50 or 60 Hz.
"""

from __future__ import annotations

from station.discrepancy.data import RigData
from station.discrepancy.fit import ModelFit

NONLINEARITY_MAX = 0.05  # |q|, |c| (relative to capacity)
DELAY_MAX_S = 1e-3
COUPLING_MIN = 0.1  # k_c / k_f
MAINS_REL = 0.02  # relative distance from 50 or 60 Hz
CUTOFF_MIN_HZ = 10.0


def implausible(name: str, fit: ModelFit, data: RigData) -> str:
    """Why the effect's fitted parameters are not physically plausible, or ''."""
    v = fit.values
    if name == "transducer_nonlinearity":
        big = [k for k in ("quadratic", "cubic") if abs(v[k]) > NONLINEARITY_MAX]
        if big:
            return (f"{', '.join(f'{k} = {v[k]:.3g}' for k in big)}: a nonlinearity above "
                    f"{100 * NONLINEARITY_MAX:g} % of capacity is not a transducer's")
    if name == "channel_delay" and abs(v["delay_s"]) > DELAY_MAX_S:
        return f"delay {v['delay_s']:.3g} s is beyond {DELAY_MAX_S:g} s"
    if name == "channel_delay" and v["delay_s"] < -1.0 / data.sample_rate_hz:
        return (f"delay {1e6 * v['delay_s']:.4g} us is negative (force sampled after the displacement) and longer "
                f"than one sample interval ({1e6 / data.sample_rate_hz:.3g} us): not an ADC skew but the group "
                "delay of something in the force path")
    if name == "coupling_compliance" and v["k_c"] < COUPLING_MIN * v["k_f"]:
        return f"k_c = {v['k_c']:.3g} N/m is below {COUPLING_MIN:g} k_f"
    if name == "conditioner_lowpass" and v["cutoff_hz"] < CUTOFF_MIN_HZ:
        return f"cut-off {v['cutoff_hz']:.3g} Hz is below {CUTOFF_MIN_HZ:g} Hz"
    if name == "mains_interference" and "frequency_hz" in v:
        f = v["frequency_hz"]
        if min(abs(f / 50 - 1), abs(f / 60 - 1)) > MAINS_REL:
            return f"frequency {f:.4g} Hz is not within {100 * MAINS_REL:g} % of 50 or 60 Hz"
    return ""



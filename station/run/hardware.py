"""The configuration against what the connected DAQ bridge reports of itself (``HW?``).

Checked at connect, before the motor is enabled: a configuration that disagrees with the bridge is
refused with one message naming the configuration's value and the bridge's, rather than recording
with a quantisation step, channel order or link the hardware does not have.  The run then takes the
bridge's own figures (its resolution for the LSB; the recording stores them as ``daq_*`` attributes).
"""

from __future__ import annotations

from drivers.daq.bridge import DaqHardware
from drivers.daq.protocol import CHANNELS
from station.config import StationConfig
from station.errors import HardwareMismatchError


def _mismatch(field: str, configured: object, reported: object, what: str) -> HardwareMismatchError:
    return HardwareMismatchError(
        f"{field} is {configured} but the DAQ bridge reports {what} (HW?); the configuration must describe "
        "the connected hardware: nothing was moved", field=field, configured=configured, reported=reported,
        device="daq")


def check_daq_hardware(cfg: StationConfig, hw: DaqHardware) -> None:
    """Raise :class:`HardwareMismatchError` at the first disagreement of ``cfg`` with the bridge's
    ``hw``: the resolution of its codes (``daq.adc_bits``: the converter's, at most the 16 bits the
    frames carry), the channels the station streams (displacement and
    force), the link kind (``devices.daq_link``) and the sample rate (``daq.sample_rate_hz`` within
    the bridge's ``rate_min``..``rate_max``)."""
    if cfg.daq.adc_bits != hw.code_bits:
        wider = f", codes rounded to {hw.code_bits} bits" if hw.code_bits != hw.adc_bits else ""
        raise _mismatch("daq.adc_bits", cfg.daq.adc_bits, hw.code_bits, f"bits={hw.adc_bits} ({hw.adc}{wider})")
    missing = [c for c in CHANNELS if c not in hw.channels]
    if missing:
        raise _mismatch("channels", ",".join(CHANNELS), ",".join(hw.channels),
                        f"channels={','.join(hw.channels)} (without {','.join(missing)})")
    if cfg.devices.daq_link != hw.link:
        raise _mismatch("devices.daq_link", cfg.devices.daq_link, hw.link, f"link={hw.link}")
    rate = cfg.daq.sample_rate_hz
    if not hw.rate_min_hz <= rate <= hw.rate_max_hz:
        raise _mismatch("daq.sample_rate_hz", f"{rate:g} Hz", (hw.rate_min_hz, hw.rate_max_hz),
                        f"rate_min={hw.rate_min_hz:g} rate_max={hw.rate_max_hz:g} Hz")

"""``station compensate design|apply`` end to end in process, the calibration table's fit, and bad
input: one clear message and exit code 2 for each."""

from __future__ import annotations

import json
from pathlib import Path

import h5py
import numpy as np
import pytest
from scipy import signal as dsp

from station.cli import main
from station.compensate.apply import Noise, compensate
from station.compensate.design import DesignSpec, design_filter
from station.compensate.sensor import RESPONSES, fit_table, read_table
from station.compensate.signals import read_signal
from station.errors import BadInputError
from station.ident.identify import identify_recording, store_result
from station.recording.reader import read_recording

S0, F0, DELTA = 0.124, 36e3, 0.0055  # PyDynamic's FIR example: V/N, Hz, 1
FS = 500e3


def table_text(rel_u: float = 1e-3, seed: int = 0, n: int = 40) -> str:
    """Sinusoidal calibration values of the second-order system up to 60 kHz with relative noise."""
    f = np.linspace(1e3, 60e3, n)
    H = S0 / (1 - (f / F0) ** 2 + 2j * DELTA * f / F0)
    rng = np.random.default_rng(seed)
    mag = np.abs(H) * (1 + rel_u * rng.standard_normal(n))
    ph = np.degrees(np.angle(H)) + np.degrees(rel_u) * rng.standard_normal(n)
    rows = "\n".join(f"{a:.6f},{b:.9g},{c:.9g},{rel_u * b:.3g},{np.degrees(rel_u):.3g}"
                     for a, b, c in zip(f, mag, ph, strict=True))
    return "frequency_hz,magnitude,phase_deg,u_magnitude,u_phase_deg\n" + rows + "\n"


def test_table_fit_recovers_the_system_within_its_uncertainty() -> None:
    zs = []
    for seed in range(5):
        s = fit_table(read_table(table_text(seed=seed)))
        zs.append((s.theta_array - [S0, F0, DELTA]) / np.sqrt(np.diag(s.cov_array)))
    assert np.all(np.abs(zs) < 4), zs
    assert 0.2 < np.std(zs) < 2.5  # the stated covariance is of the scatter's size
    assert s.fit["weighted"] and len(s.fit["residual_rel"]) == 40


def test_table_without_uncertainties_says_so() -> None:
    text = "\n".join(",".join(r.split(",")[:3]) for r in table_text().splitlines())
    s = fit_table(read_table(text))
    assert [c.name for c in s.findings] == ["table_without_uncertainty"]


@pytest.mark.parametrize(("text", "says"), [
    ("frequency_hz,magnitude\n1,2\n", "phase_deg or phase_rad"),
    ("frequency_hz,magnitude,phase_deg\n1,2,0\n2,2,nan\n3,2,0\n4,2,0\n", "line 3"),
    ("frequency_hz,magnitude,phase_deg\n1,2,0\n2,2,0\n", "at least 4"),
    ("frequency_hz,magnitude,phase_deg\n1,2,0\n1,2,0\n2,2,0\n3,2,0\n", "distinct"),
])
def test_bad_tables_are_refused(text: str, says: str) -> None:
    with pytest.raises(BadInputError, match=says):
        read_table(text)


def test_table_design_compensates_pydynamics_example_signal() -> None:
    """The second-order system of PyDynamic's example simulated here by scipy's bilinear transform:
    the compensated Gaussian shock within its u, and the uncompensated far off."""
    s = fit_table(read_table(table_text()))
    filt = design_filter(s, DesignSpec(FS, (0.0, 50e3), 60e3, taps=64, lowpass_order=4, allow_extrapolation=True))
    w0 = 2 * np.pi * F0
    b, a = dsp.bilinear([S0 * w0**2], [1, 2 * DELTA * w0, w0**2], FS)
    t = np.arange(2000) / FS
    x = 0.8 * np.exp(-((t - 2e-3) ** 2) / (2 * 1e-5**2))  # PyDynamic's shocklikeGaussian is similar
    y = dsp.lfilter(b, a, x) + np.random.default_rng(10).normal(0, 1e-3, t.size)
    est, _ = compensate(filt, y, Noise.white(1e-3))
    ref = np.interp(t - filt.delay_s, t, x)
    assert np.max(np.abs(est - ref)) < 0.05 * 0.8
    assert np.max(np.abs(y / S0 - x)) > 0.3


@pytest.fixture(scope="module")
def identified(sim_recording: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    import shutil

    d = tmp_path_factory.mktemp("comp")
    p = Path(shutil.copy(sim_recording, d / sim_recording.name))
    store_result(p, identify_recording(read_recording(p), method="fd", model="sdof"))
    return p


@pytest.mark.slow
def test_design_and_apply_end_to_end(identified: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    f = tmp_path / "filter.json"
    rc = main(["compensate", "design", "--recording", str(identified), "--mass", "1.0", "--sample-rate", "50000",
               "--band", "0", "4000", "--allow-extrapolation", "-o", str(f), "--plot", str(tmp_path / "bode.png"),
               "--json"])
    assert rc == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["format"] == "sinecal-compensation-filter" and doc["taps"] == 64 and doc["stable"]
    assert {c["name"] for c in doc["findings"]} >= {"extrapolation"}
    assert (tmp_path / "bode.png").read_bytes()[:4] == b"\x89PNG"
    t = np.arange(2000) / 50000
    x = 2e-3 * 500 * np.exp(-((t - 0.02) / 1e-3) ** 2)
    sig = tmp_path / "sig.csv"
    np.savetxt(sig, np.column_stack([t, x]), delimiter=",", header="time_s,force_V", comments="")
    out = tmp_path / "est.h5"
    rc = main(["compensate", "apply", str(f), str(sig), "--noise-std", "1e-4", "-o", str(out), "--plot",
               str(tmp_path / "sig.png"), "--monte-carlo", "50", "--json"])
    assert rc == 0
    summ = json.loads(capsys.readouterr().out)
    assert summ["samples"] == 2000 and summ["delay_removed"] and summ["monte_carlo"]["max_rel_diff_u"] < 0.5
    with h5py.File(out) as h:
        assert h["estimate"].attrs["unit"] == "N" and h["time"].attrs["unit"] == "s"
        np.testing.assert_allclose(h["time"][:], t - doc["delay_s"], atol=1e-12)
        assert np.all(h["u"][:] > 0)
        from station.commands.compensate import load_filter

        y, u = compensate(load_filter(f), x, Noise.white(1e-4))
        np.testing.assert_allclose(h["estimate"][:], y, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(h["u"][:], u, rtol=1e-12)
    # .npy needs a stated rate; a wrong one is refused against the filter's
    np.save(tmp_path / "sig.npy", x)
    assert main(["compensate", "apply", str(f), str(tmp_path / "sig.npy"), "-o", str(tmp_path / "o.csv"),
                 "--sample-rate", "20000"]) == 2
    assert "designed for 50000 Hz" in capsys.readouterr().err
    assert main(["compensate", "apply", str(f), str(tmp_path / "sig.npy"), "-o", str(tmp_path / "o.csv"),
                 "--sample-rate", "50000"]) == 0
    head = (tmp_path / "o.csv").read_text().splitlines()
    assert any(ln.startswith("time_s,estimate_N,u_N") for ln in head[:20])


def test_band_beyond_calibration_is_refused_without_consent(identified: Path, tmp_path: Path,
                                                           capsys: pytest.CaptureFixture[str]) -> None:
    rc = main(["compensate", "design", "--recording", str(identified), "--mass", "1.0", "--sample-rate", "50000",
               "--band", "0", "4000", "-o", str(tmp_path / "f.json")])
    assert rc == 2 and "beyond the calibrated range 4 to 100 Hz" in capsys.readouterr().err
    assert not (tmp_path / "f.json").exists()
    assert main(["compensate", "design", "--recording", str(identified), "--sample-rate", "50000",
                 "--band", "0", "40", "-o", str(tmp_path / "f.json")]) == 2
    assert "needs --mass" in capsys.readouterr().err


def test_bad_signals_get_one_clear_message(tmp_path: Path) -> None:
    p = tmp_path / "nan.npy"
    x = np.zeros(100)
    x[37] = np.nan
    np.save(p, x)
    with pytest.raises(BadInputError, match=r"NaN or infinite .* at sample 37"):
        read_signal(p, 1000.0)
    big = tmp_path / "big.npy"
    np.save(big, np.zeros(2000))
    with pytest.raises(BadInputError, match="above the limit"):
        read_signal(big, 1000.0, max_bytes=1000)
    c = tmp_path / "jitter.csv"
    c.write_text("time_s,v\n0,1\n0.001,1\n0.0025,1\n0.003,1\n")
    with pytest.raises(BadInputError, match="not uniformly sampled"):
        read_signal(c)
    with pytest.raises(BadInputError, match="no time column and no sample rate"):
        read_signal(big)
    h = tmp_path / "two.h5"
    with h5py.File(h, "w") as f:
        f["a"] = np.zeros(3)
        f["b"] = np.zeros(3)
    with pytest.raises(BadInputError, match="name one with --dataset"):
        read_signal(h, 1000.0)


def test_second_order_static_gain() -> None:
    assert abs(RESPONSES["second_order"]([S0, F0, DELTA], [0.0])[0] - S0) < 1e-15

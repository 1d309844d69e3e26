"""``station paper --quick``: the report's structure, its measured claims and the figures.

The reproduction is computed once, through the command (``station paper --quick --json``), and
every test reads that one report."""

import contextlib
import io
import json
from pathlib import Path

import pytest

from station.cli import main

pytestmark = [pytest.mark.slow, pytest.mark.xdist_group("paper")]  # the quick paper reproduction alone takes ~7 s


@pytest.fixture(scope="module")
def report(tmp_path_factory: pytest.TempPathFactory) -> tuple[dict, Path]:
    out = tmp_path_factory.mktemp("paper")
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        assert main(["paper", "--quick", "--json", "--out", str(out)]) == 0
    return json.loads(printed.getvalue()), out


def test_report_has_the_paper_sections_side_by_side(report) -> None:
    rep, _ = report
    assert set(rep["table1"]) == {"I", "II"}
    for case in ("I", "II"):
        assert {"pso", "pso+"} <= set(rep["table1"][case]["median"])
        assert rep["table1"][case]["paper"]["pso_mse"] > 0
    assert [r["snr_db"] for r in rep["noise_study"]] == [10, 20, 30, 40, 50]
    assert set(rep["section5"]) == {"5kN", "12.5kN"}
    json.dumps(rep)  # JSON-safe


def test_noise_study_paper_figures_are_called_unexplained_with_the_numbers(report) -> None:
    """The Case I filter's output power cannot reach what the paper's MSEs imply (independent check:
    the filter's gain on a dense grid, and the output power of a long sine at its worst frequency)."""
    import numpy as np
    from scipy.signal import lfilter

    from station.paper import CASES, PAPER_NOISE
    rep, _ = report
    b, a, _, _ = CASES["I"]
    w = np.linspace(0, np.pi, 4001)
    z = np.exp(-1j * w)
    gain = np.abs((b[0] + b[1] * z + b[2] * z**2) / (a[0] + a[1] * z + a[2] * z**2))
    y = lfilter(b, a, 5 * np.sin(w[np.argmax(gain)] * np.arange(20000)))
    assert np.mean(y[1000:] ** 2) < 16.7 < min(m * 10 ** (s / 10) for s, m in PAPER_NOISE.items()) / 40
    p = rep["noise_output_power"]
    assert p["max_gain"] == pytest.approx(gain.max(), rel=1e-4) and p["bound"] == pytest.approx(16.61, abs=0.01)
    text = next(e for e in rep["explanations"] if e.startswith("Noise study"))
    implied = [m * 10 ** (s / 10) for s, m in sorted(PAPER_NOISE.items())]
    assert p["paper_implied"] == pytest.approx(implied)
    assert "unexplained" in text and f"{p['bound']:.3g}" in text
    assert f"output power of {min(implied):.0f}-{max(implied):.0f}" in text


def test_noise_study_mse_is_the_noise_variance(report) -> None:
    rep, _ = report
    for r in rep["noise_study"]:
        if r["snr_db"] >= 30:
            assert 0.7 < r["mse_over_noise_variance"] < 1.3


def test_section5_expert_beats_the_protocol_and_flags_the_4hz_step(report) -> None:
    rep, _ = report
    for name in ("5kN", "12.5kN"):
        r = rep["section5"][name]
        assert abs(r["expert_rel_err"]["k_f"]) < 1e-3 and abs(r["expert_rel_err"]["b_f"]) < 0.02
        assert r["expert_single_4Hz"]["b_f"]["identifiable"] is False
        assert r["expert_single_4Hz"]["b_f"]["value"] is None
        case = "III" if name == "5kN" else "V"
        assert r[f"pso+_{case}"]["identifiable"]["b_f"] is False


def test_figures_are_written(report) -> None:
    rep, out = report
    assert len(rep["figures"]) >= 5
    for f in rep["figures"]:
        p = Path(f)
        assert p.parent == out and p.stat().st_size > 5000 and p.read_bytes()[:4] == b"\x89PNG"


def test_explanations_quote_measured_numbers(report) -> None:
    """Every number the explanations give is the one measured in this run (formatted as the text does)."""
    import numpy as np

    rep, _ = report
    text = " ".join(rep["explanations"])
    first = rep["table1"]["I"]["runs"][0]
    assert f"up to iteration {first['first_difference']};" in text
    assert f"differs from the MSE's own at iteration {first['first_tie']}:" in text
    pp, ps = first["pso+"], first["pso"]
    assert f"stops improving at MSE {pp['mse']:.3g} (iteration {pp['iterations_to_converge']})" in text
    assert f"PSO goes on to {ps['mse']:.3g} (iteration {ps['iterations_to_converge']})" in text
    ratios = ", ".join(f"{r['mse_over_noise_variance']:.2f}" for r in rep["noise_study"])
    assert f"(ratios {ratios} for 10..50 dB)" in text
    r5 = rep["section5"]["5kN"]
    assert f"testing MSE is {r5['rls_III']['testing_mse_V2']:.3g} V^2" in text
    ratio = r5["rls_III"]["testing_mse_V2"] / np.median(r5["pso+_III"]["testing_mse_V2"])
    assert f"ours is {ratio:.3g}x" in text
    power = rep["noise_output_power"]
    assert f"(ours: {power['ours']:.3g})" in text and f"largest gain is {power['max_gain']:.4g}" in text


def test_cli_paper_quick_json(report) -> None:
    doc, out = report  # printed by `station paper --quick --json`
    assert "table1" in doc and (out / "noise_study.png").exists()

"""Calibration report and result plots (station.report): PNGs of the stated size that depend on the
data, stored results preferred over computing, the identified values and uncertainties in the HTML
exactly as the identification gives them, identifiability, the discrepancy workflow's effects, PDF."""

from __future__ import annotations

import base64
import copy
import re
import shutil
import struct
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import pytest

from station.config import default_config_path, load_config, parse_config
from station.errors import RecordingFormatError
from station.ident.coverage import coverage
from station.ident.identify import identify_recording
from station.ident.paper.protocol import SwarmSize
from station.recording import read_recording, write_result
from station.report import PLOT_NAMES, render_plot, render_report, render_report_pdf
from station.report.data import load_run
from station.report.plots import FIG_SIZE_PX
from station.report.quantities import fmt_unc, fmt_value
from station.run.processing import process_recording
from station.simulate import simulate_run
from tests.conftest import fast_dict

pytestmark = pytest.mark.xdist_group("report")  # its module fixture is built once: the module's tests on one worker

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


@pytest.fixture(scope="module")
def full_recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The shipped 5-step plan (its 4 Hz step is long enough for the paper's PSO+ protocol); read-only."""
    return simulate_run(load_config(default_config_path()), tmp_path_factory.mktemp("full"), seed=3)


def _copy(src: Path, tmp_path: Path) -> Path:
    dst = tmp_path / src.name
    shutil.copy(src, dst)
    return dst


def _png_size(png: bytes) -> tuple[int, int]:
    assert png[:8] == PNG_MAGIC, "not a PNG"
    assert png[12:16] == b"IHDR"
    return struct.unpack(">II", png[16:24])


def _cell(page: str, key: str) -> tuple[str, float | None]:
    """Displayed text and data-value of the table cell with data-key=key."""
    m = re.search(rf'<td[^>]*data-key="{re.escape(key)}"[^>]*>([^<]*)</td>', page)
    assert m, f"no cell {key!r} in the report"
    v = re.search(r'data-value="([^"]+)"', m.group(0))
    return m.group(1), (float(v.group(1)) if v else None)


# -- plots -------------------------------------------------------------------------------------------

@pytest.mark.slow
def test_plots_are_pngs_of_the_stated_size_deterministic_and_drawn_once(sim_recording: Path) -> None:
    """Each plot a PNG of the stated size; drawn again from the file, the same bytes; the recording is
    read and fitted once for all plots, and each plot drawn once while the recording and its results
    are unchanged (render times are measured in bench/, not asserted here)."""
    from station.report.data import cached_run_data
    from station.report.plots import cached_png

    for name in PLOT_NAMES:
        png = render_plot(sim_recording, name)
        assert _png_size(png) == FIG_SIZE_PX, name
        assert len(png) > 10_000, f"{name}: suspiciously small PNG"
    first = {n: render_plot(sim_recording, n) for n in PLOT_NAMES}
    cached_run_data.cache_clear()  # render again from the file: same bytes, the file read once
    cached_png.cache_clear()
    assert {n: render_plot(sim_recording, n) for n in PLOT_NAMES} == first
    assert (cached_run_data.cache_info().misses, cached_run_data.cache_info().hits) == (1, len(PLOT_NAMES) - 1)
    assert cached_png.cache_info().misses == len(PLOT_NAMES)
    assert len(set(first.values())) == len(PLOT_NAMES), "two plots gave the same image"
    # drawn on a canvas of its own (a new renderer, nothing measured before): the same bytes as with the
    # renderer the thread's plots share
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    from station.report.plots import make_figure, png

    fig = make_figure(load_run(sim_recording), "residuals")
    FigureCanvasAgg(fig)
    assert png(fig) == first["residuals"]
    for name in PLOT_NAMES:  # asked again: the same PNGs, not drawn again
        assert render_plot(sim_recording, name) == first[name]
    assert cached_png.cache_info().hits == len(PLOT_NAMES) and cached_run_data.cache_info().misses == 1


@pytest.mark.slow
def test_plots_differ_between_recordings(sim_recording: Path, sim_recording_one_radius: Path) -> None:
    for name in ("bode", "timefit", "residuals"):
        assert render_plot(sim_recording, name) != render_plot(sim_recording_one_radius, name), name


def test_unknown_plot_and_unusable_recordings(sim_recording: Path, tmp_path: Path) -> None:
    with pytest.raises(KeyError, match="unknown plot 'nyquist'"):
        render_plot(sim_recording, "nyquist")
    with pytest.raises(RecordingFormatError, match="no such recording"):
        render_plot(tmp_path / "missing.h5", "bode")
    bad = _copy(sim_recording, tmp_path)
    with h5py.File(bad, "r+") as f:  # every step lost samples: nothing can be identified
        f["steps/lost_in_window"][...] = 5
    with pytest.raises(RecordingFormatError, match="no identification results stored"):
        render_plot(bad, "bode")
    with pytest.raises(RecordingFormatError, match="no identification results stored"):
        render_report(bad)


@pytest.mark.slow
def test_convergence_shows_a_stored_pso_history(full_recording: Path, tmp_path: Path) -> None:
    rec_path = _copy(full_recording, tmp_path)
    placeholder = render_plot(rec_path, "convergence")
    # a swarm of 24 particles x 120 iterations (the paper's 200 x 1000 is what the shipped configuration
    # runs; the plot shows whatever history is stored)
    res = identify_recording(read_recording(rec_path), "pso+", seed=1, swarm=SwarmSize(24, 120))
    assert len(res.extra["mse_history"]) > 100
    write_result(rec_path, f"identify_{res.method}_{res.model}", res.to_dict())
    shown = render_plot(rec_path, "convergence")
    assert _png_size(shown) == FIG_SIZE_PX
    assert shown != placeholder
    page = render_report(rec_path)  # the only stored identification is the one shown, its history plotted
    assert f"results/identify_pso+_{res.model}" in page
    assert base64.b64encode(shown).decode("ascii") in page
    assert base64.b64encode(placeholder).decode("ascii") not in page


# -- HTML report -------------------------------------------------------------------------------------

@pytest.mark.slow
def test_report_shows_the_stored_identification_with_u_and_U(sim_recording: Path, tmp_path: Path) -> None:
    rec_path = _copy(sim_recording, tmp_path)
    res = identify_recording(read_recording(rec_path))
    write_result(rec_path, f"identify_{res.method}_{res.model}", res.to_dict())
    page = render_report(rec_path)
    assert page.startswith("<!DOCTYPE html>") and page.rstrip().endswith("</html>")
    assert f"results/identify_fd_{res.model}" in page
    for name in ("S", "k_f", "b_f"):
        p = res.parameter(name)
        text, value = _cell(page, f"param.{name}")
        assert value == p.value and text == fmt_value(p.value, p.std)
        text, u = _cell(page, f"param.{name}.u")
        assert u == p.std and text == fmt_unc(p.std)
        _, big_u = _cell(page, f"param.{name}.U")
        k = coverage(res.budget[name]).k  # 1.96: no term with few degrees of freedom in this run
        assert _cell(page, f"param.{name}.k")[1] == k and big_u == pytest.approx(k * p.std, rel=1e-12)
    assert "N/m" in page and "N*s/m" in page and "V/N" in page and "Hz" in page
    rec = read_recording(rec_path)
    for text in (rec.transducer_id, rec.run_id, "completed", "25.717 kg", "0 in 0 gap(s)", rec.software_version):
        assert text in page
    # self-contained: every image inline, nothing fetched
    assert not re.search(r'(src|href)="(?!data:)', page)
    imgs = re.findall(r'src="data:image/png;base64,([A-Za-z0-9+/=]+)"', page)
    assert len(imgs) == len(PLOT_NAMES)
    assert all(base64.b64decode(b)[:8] == PNG_MAGIC for b in imgs)


@pytest.mark.slow
def test_report_prefers_a_stored_result_and_processed_steps(sim_recording: Path, tmp_path: Path) -> None:
    rec_path = _copy(sim_recording, tmp_path)
    payload = identify_recording(read_recording(rec_path)).to_dict()
    payload["parameters"]["k_f"].update(value=1.2345e7, std=3.1e3)  # not what the data give: proves use
    write_result(rec_path, "identify_fd_sdof", payload)
    steps = process_recording(rec_path)
    page = render_report(rec_path)
    assert _cell(page, "param.k_f")[1] == 1.2345e7
    assert _cell(page, "param.k_f.u")[1] == 3.1e3
    assert "Measured points from processed/steps" in page
    M = load_run(rec_path).mass_kg
    for i, st in enumerate(steps):
        assert _cell(page, f"sdyn.{i}")[1] == pytest.approx(abs(st.H) / M, rel=1e-12)
        assert _cell(page, f"phase.{i}")[1] == pytest.approx(np.degrees(np.angle(-st.H)), abs=1e-9)


@pytest.mark.slow
def test_single_frequency_says_not_identifiable(tmp_path: Path) -> None:
    d = fast_dict()
    d["plan"]["steps"] = [{"crank_frequency_hz": 20.0, "crank_radius_m": 0.001}]
    rec_path = simulate_run(parse_config(d, "one-step"), tmp_path)
    res = identify_recording(read_recording(rec_path))
    assert not res.parameter("k_f").identifiable
    page = render_report(rec_path)
    assert f"not identifiable: {res.parameter('k_f').reason}"[:60] in page
    text, value = _cell(page, "param.k_f")
    assert value is None and text.startswith("not identifiable: ")  # a reason, no digits for k_f
    assert 'data-key="param.k_f.u"' not in page
    assert "Model curve not drawn" in page
    for name in PLOT_NAMES:
        assert _png_size(render_plot(rec_path, name)) == FIG_SIZE_PX


def _discrepancy_payload() -> dict[str, Any]:
    est = {"value": 1.0e9, "std": 2.0e7, "unit": "N/m", "identifiable": True}
    return {"base_gap": 0.0123, "final_gap": 0.00051, "noise_floor_V": 0.0005,
            "effects": [{"name": "coupling_compliance",
                         "params": {"k_c": est, "b_c": {"value": None, "std": None, "unit": "N*s/m",
                                                        "identifiable": False, "reason": "b_c at its bound"}},
                         "gap_after": 0.0021, "evidence": "Delta chi2 = 5000 <script>alert(1)</script>"},
                        {"name": "channel_delay", "params": {"delay_s": {"value": 2.5e-5, "std": 1e-6, "unit": "s",
                                                                         "identifiable": True}},
                         "gap_after": 0.00051, "evidence": "p = 1e-30"}],
            "parameters_before": {"k_f": {"value": 2.8e7, "std": 1e3, "unit": "N/m", "identifiable": True}},
            "parameters_after": {"k_f": {"value": 2.91e7, "std": 1.1e3, "unit": "N/m", "identifiable": True}},
            "unexplained": ["a line at 137 Hz in step 2"],
            "ties": [{"kind": "tie", "message": "coupling_compliance / channel_delay explain the data equally well",
                      "candidates": [
                          {"effects": ["coupling_compliance"], "chi2": 101.4,
                           "k_f": {"value": 2.9e7, "std": 3e3, "unit": "N/m"},
                           "b_f": {"value": 17136.0, "std": 4.0, "unit": "N*s/m"}},
                          {"effects": ["channel_delay"], "chi2": 101.9,
                           "k_f": {"value": 3.4e7, "std": 6e4, "unit": "N/m"},
                           "b_f": {"value": 33541.0, "std": 64.0, "unit": "N*s/m"}}]}]}


@pytest.mark.slow
def test_report_names_the_discrepancy_effects(sim_recording: Path, tmp_path: Path) -> None:
    rec_path = _copy(sim_recording, tmp_path)
    from station.report.plots import cached_png

    assert "has not been run on this recording" in render_report(rec_path)
    drawn = cached_png.cache_info().misses
    write_result(rec_path, "discrepancy", copy.deepcopy(_discrepancy_payload()))
    page = render_report(rec_path)
    assert cached_png.cache_info().misses == drawn, "no plot reads the analysis: none is drawn again"
    for text in ("coupling_compliance", "channel_delay", "a line at 137 Hz in step 2", "0.012 V", "5.1e-04 V",
                 "not identifiable: b_c at its bound", "2.50e-05 ± 1.0e-06 s", "Ties: explanations the data do not",
                 "coupling_compliance / channel_delay explain the data equally well"):
        assert text in page, text
    assert "<script>" not in page and "&lt;script&gt;" in page
    assert _cell(page, "disc.before.k_f")[1] == 2.8e7
    assert _cell(page, "disc.after.k_f.u")[1] == 1.1e3


@pytest.mark.slow
@pytest.mark.slow
def test_pdf_report_is_the_html_and_cuts_no_budget_line(sim_recording: Path) -> None:
    """WeasyPrint (a few s): the PDF read back holds every budget row whole on one line, the
    parameters with their k, and one page image per plot."""
    import io

    from pypdf import PdfReader

    pdf = render_report_pdf(sim_recording)
    assert pdf.startswith(b"%PDF")
    reader = PdfReader(io.BytesIO(pdf))
    page_texts = [p.extract_text() for p in reader.pages]  # read back once (pypdf: about 0.3 s a page)
    text = "\n".join(page_texts)
    lines = text.splitlines()
    ident = load_run(sim_recording).ident
    assert ident.budget
    for name, b in ident.budget.items():
        cells = [fmt_unc(v) if v is not None else "conditional" for v in b.stds.values()]
        want = " ".join([name, *cells, fmt_unc(b.combined), b.unit])
        assert want in lines, (want, [ln for ln in lines if ln.startswith(name + " ")])
    assert "combined" in text and "Uncertainty statement" in text
    images = sum(len(p.images) for p in reader.pages)
    assert images >= len(PLOT_NAMES)
    n = len(reader.pages)
    run_id = read_recording(sim_recording).run_id
    for i, page_text in enumerate(page_texts, 1):  # the run and "page i of n" on every page
        flat = " ".join(page_text.split())
        assert f"page {i} of {n}" in flat and run_id in flat, i


@pytest.mark.slow  # WeasyPrint
def test_a_page_is_laid_out_once() -> None:
    """The same HTML asked again is the PDF already made (a draft certificate served twice); another
    page is laid out anew."""
    import io

    from pypdf import PdfReader

    from station.report.render import cached_pdf, html_to_pdf

    page = "<html><body><p>run 4711: S = 2.0 mV/N</p></body></html>"
    first = html_to_pdf(page)
    hits = cached_pdf.cache_info().hits
    assert html_to_pdf(page) is first and cached_pdf.cache_info().hits == hits + 1
    other = html_to_pdf(page.replace("4711", "4712"))
    assert "run 4712" in PdfReader(io.BytesIO(other)).pages[0].extract_text()
    assert "run 4711" in PdfReader(io.BytesIO(first)).pages[0].extract_text()


@pytest.mark.slow
def test_report_of_an_imported_run(sim_recording_one_radius: Path, tmp_path: Path) -> None:
    from station.interchange import export_run, import_run

    rec_path = import_run(export_run(sim_recording_one_radius, tmp_path / "csv"), tmp_path / "imported")
    page = render_report(rec_path)
    assert "import" in page and "not recorded separately" in page  # RUN.yaml has no rig section
    res = identify_recording(read_recording(rec_path))
    assert _cell(page, "param.k_f")[1] == res.parameter("k_f").value


# -- what the report reads: stored results, labelled by recording step ------------------------------

def test_traces_keep_their_step_numbers_when_the_gate_drops_a_step(sim_recording: Path, tmp_path: Path,
                                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    import station.report.data as data
    from station.ident.identify import store_result

    rec_path = _copy(sim_recording, tmp_path)
    first = read_recording(rec_path).steps[0]
    with h5py.File(rec_path, "r+") as f:  # a dead force channel in step 0: the plausibility gate drops it
        f["raw/force"][first.start_sample:first.end_sample] = f["raw/force"][first.start_sample]
    rec = read_recording(rec_path)
    kept = [s for s in rec.steps if s.index != first.index]

    def shown(d: data.RunData) -> None:
        assert [t.index for t in d.traces] == list(d.response.step_index) == [s.index for s in kept]
        for t, s in zip(d.traces, kept, strict=True):  # each trace is the data of the step it is labelled with
            assert t.f_hz == pytest.approx(s.crank_frequency_hz, rel=1e-3)
            assert t.t_s.size == s.end_sample - s.start_sample

    data.cached_run_data.cache_clear()
    shown(load_run(rec_path))  # nothing stored: computed once from the raw windows
    process_recording(rec_path)
    res = identify_recording(rec)
    store_result(rec_path, res)
    monkeypatch.setattr(data, "checked_response", lambda *a, **k: pytest.fail("the report re-fitted the raw windows"))
    d = load_run(rec_path)
    shown(d)
    assert d.ident == res and d.response.source == "processed/steps"
    assert d.curve is not None and d.curve.cov is not None
    names = list(d.curve.model.names)
    assert res.covariance is not None
    i = [res.covariance.names.index(n) for n in names]
    np.testing.assert_array_equal(d.curve.cov, res.covariance.array[np.ix_(i, i)])  # the stored one, not rebuilt

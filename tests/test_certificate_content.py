"""What a certificate states, read back: the measuring chain it calibrates (title, unit, budget),
what the data determined and what was assumed (the end mass and its share of u²(S)), identify's
flags beside their values, S_dyn(f) with every source of the budget (against an independent
computation), one coverage convention."""

from __future__ import annotations

import io
import math
import re
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from station.certificate.content import Approval, certificate_content
from station.certificate.dcc import build_dcc
from station.certificate.render import certificate_html
from station.config import MeasurementChain
from station.ident.identify import identify_recording
from station.ident.response.checked import checked_response
from station.recording import read_recording, write_result
from station.report.render import html_to_pdf
from tests.ident_support import R, sim


def _pdf(pdf: bytes) -> Any:
    """The PDF read back (pypdf, imported where a test reads one: 0.4 s of every worker's collection)."""
    from pypdf import PdfReader

    return PdfReader(io.BytesIO(pdf))


# its module fixture is built once: the module's tests on one worker
pytestmark = pytest.mark.xdist_group("certificate_content")

ISSUED = Approval("issued", "SC-2026-0042", "T. Technician", "A. Approver", "approver", "2026-11-24T12:00:00+00:00")
REFERENCE = {"calibrated": "transducer", "gain_rel_std": 2e-4, "excitation_V": 5.0, "excitation_rel_std": 1e-4}


def _stored(folder: Path, conditioner: dict[str, Any] | None = None) -> Path:
    def edit(d: dict[str, Any]) -> None:
        if conditioner:
            d["conditioner"] = {**d.get("conditioner", {}), **conditioner}

    rec = sim(folder, edit=edit)
    res = identify_recording(read_recording(rec))
    write_result(rec, f"identify_{res.method}_{res.model}", res.to_dict())
    return rec


@pytest.fixture(scope="module")
def chain_rec(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _stored(tmp_path_factory.mktemp("chain"))


@pytest.fixture(scope="module")
def transducer_rec(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _stored(tmp_path_factory.mktemp("transducer"), REFERENCE)


def _row(c: dict[str, Any], name: str) -> dict[str, Any]:
    return next(r for r in c["results"] if r["name"] == name)


def _page_texts(pdf: bytes) -> list[str]:
    """Each page's text, read back once (pypdf: most of a second for a certificate)."""
    return [p.extract_text() for p in _pdf(pdf).pages]


def _pdf_text(pdf: bytes | list[str]) -> str:
    return re.sub(r"\s+", " ", "\n".join(_page_texts(pdf) if isinstance(pdf, bytes) else pdf))


@pytest.mark.slow
def test_the_chain_kind_changes_title_unit_and_budget(chain_rec: Path, transducer_rec: Path) -> None:
    """The same transducer on the same (simulated) rig: as one chain S is in V/N with the conditioner's
    gain inside; with a reference conditioner (gain 1000 V/V, 5 V excitation) S is the transducer's in
    mV/V per N = S_chain / (G E) · 10³, and the conditioner's gain and excitation enter u(S), not u(k_f)."""
    a, b = certificate_content(chain_rec), certificate_content(transducer_rec)
    assert "measuring chain" in a["title"] and "measuring chain" not in b["title"]
    assert "force transducer" in b["title"] and "reference conditioner" in b["item"]["text"]
    assert "calibrated as one chain" in a["item"]["text"]
    sa, sb = _row(a, "S"), _row(b, "S")
    assert sa["unit"] == "V/N" and sb["unit"] == "mV/V/N" and sb["unit_text"] == "mV/(V·N)"
    assert sb["value"] == pytest.approx(sa["value"] / (1000.0 * 5.0) * 1e3, rel=1e-3)
    # the budget: a conditioner column in the transducer's certificate only, with u = S_tr · sqrt(2e-4² + 1e-4²)
    assert "conditioner_gain" not in a["budget"]["sources"] and "conditioner_gain" in b["budget"]["sources"]
    assert b["coverage"]["S"]["u"] > a["coverage"]["S"]["u"] / 5.0  # rescaled, and larger relatively
    rel_a = a["coverage"]["S"]["u"] / sa["value"]
    rel_b = b["coverage"]["S"]["u"] / sb["value"]
    assert rel_b == pytest.approx(math.hypot(rel_a, math.hypot(2e-4, 1e-4)), rel=0.05)
    assert b["coverage"]["k_f"]["u"] == pytest.approx(a["coverage"]["k_f"]["u"], rel=0.05)
    assert any("reference conditioner's gain" in s for s in b["statement"])
    # the S_dyn table in the item's unit, its U including the conditioner
    assert b["response_unit"] == "mV/V/N"
    assert b["response"][0]["magnitude"] == pytest.approx(a["response"][0]["magnitude"] / 5.0, rel=1e-3)
    html_a, html_b = certificate_html(a), certificate_html(b)
    assert "mV/(V·N)" in html_b and "mV/(V·N)" not in html_a


def test_a_reference_conditioner_needs_its_uncertainty(tmp_path: Path) -> None:
    from station.config import ConditionerConfig

    with pytest.raises(ValueError, match="gain_rel_std"):
        ConditionerConfig.model_validate({"calibrated": "transducer"})
    with pytest.raises(ValueError, match="excitation_rel_std"):
        ConditionerConfig.model_validate({"calibrated": "transducer", "gain_rel_std": 1e-4, "excitation_V": 5.0})


def test_sdyn_u_equals_an_independent_propagation_of_the_budget(chain_rec: Path) -> None:
    """Each S_dyn point's u, recomputed here from the stored H(f), its covariance, the stated chain and
    the masses by numerical differentiation (not the code under test's delta method)."""
    c = certificate_content(chain_rec)
    ident = identify_recording(read_recording(chain_rec))
    a = ident.assumptions.to_dict()
    ch = MeasurementChain.model_validate(a["measurement_chain"])
    M = a["end_mass_kg"]["value"] + a["load_mass_kg"]["value"]
    uM = math.hypot(a["end_mass_kg"]["std"], a["load_mass_kg"]["std"])
    frf = checked_response(read_recording(chain_rec)).frf  # the H(f) the certificate shows (no processed/steps)
    H, cov, f = frf.H, frf.cov, frf.f_hz
    assert len(c["response"]) == len(f)
    for i, p in enumerate(c["response"]):
        z = -complex(H[i]) / M
        h = 1e-6 * abs(z)
        grads = []
        for fn in (abs, lambda w: math.atan2(w.imag, w.real)):
            grads.append(np.array([(fn(z + h) - fn(z - h)) / (2 * h), (fn(z + 1j * h) - fn(z - 1j * h)) / (2 * h)]))
        c2 = cov[i] / M**2
        u_mag = math.sqrt(grads[0] @ c2 @ grads[0] + abs(z) ** 2 * (ch.gain_rel_std**2 + ch.flatness_rel_std**2
                                                                     + (uM / M) ** 2))
        u_ph = math.sqrt(grads[1] @ c2 @ grads[1] + math.radians(ch.phase_offset_std_deg) ** 2
                         + math.radians(ch.phase_std_deg) ** 2 + (2 * math.pi * f[i] * ch.delay_std_s) ** 2)
        assert p["U_magnitude"] == pytest.approx(2 * u_mag, rel=1e-4)
        assert p["U_phase_deg"] == pytest.approx(2 * math.degrees(u_ph), rel=1e-4)
        # the chain's phase terms are there: U(phase) at least 2 sqrt(2) 0.005°
        assert p["U_phase_deg"] >= 2 * math.hypot(ch.phase_offset_std_deg, ch.phase_std_deg)
    assert c["response_k"] == 2.0 and all(r["k"] == 2.0 for r in c["results"] if r["k"] is not None)


def _with_flags(rec: Path, edit: Any) -> Path:
    ident = identify_recording(read_recording(rec))
    d = ident.to_dict()
    edit(d)
    write_result(rec, f"identify_{ident.method}_{ident.model}", d)
    return rec


@pytest.mark.slow
def test_flags_stand_beside_their_values_and_a_contradicted_assumption_is_not_certified(tmp_path: Path) -> None:
    """identify's flags (as a stored result carries them) on the certificate: a conditional b_f is
    marked beside its value; k_f withheld says why; when the structure the values rest on is
    contradicted by the data, a value conditional on it is not certified (no number, not in the DCC)."""
    rec = _stored(tmp_path)

    def conditional(d: dict[str, Any]) -> None:
        d["parameters"]["b_f"]["flag"] = "conditional"
        d["parameters"]["b_f"]["reason"] = "conditional on a stiff coupling (a suspected coupling's damping is in it)"

    c = certificate_content(_with_flags(rec, conditional))
    b = _row(c, "b_f")
    assert b["status"] == "conditional" and b["value"] is not None and "stiff coupling" in b["note"]
    html = certificate_html(c)
    assert re.search(r'data-key="b_f" data-status="conditional">.*?<b>conditional</b>: conditional on a stiff', html,
                     re.S)

    def contradicted(d: dict[str, Any]) -> None:
        d["parameters"]["k_f"] = {"value": None, "std": None, "unit": "N/m", "identifiable": False,
                                  "reason": "k_f of the transducer alone is not determined: the data contradict it"}
        d["parameters"]["b_f"]["flag"] = "conditional"
        d["parameters"]["b_f"]["reason"] = ("conditional on a stiff coupling, which the data contradict "
                                            "(coupling_suspected)")
        d["assumptions"]["structure"]["coupling"]["contradicted_by_the_data"] = True

    c = certificate_content(_with_flags(rec, contradicted), ISSUED)
    k, b = _row(c, "k_f"), _row(c, "b_f")
    assert k["status"] == "withheld" and k["value"] is None and "not determined" in k["note"]
    assert b["status"] == "not certified" and b["value"] is None and b["U"] is None
    assert "which the data contradict" in b["note"]
    xml = build_dcc(c).decode()
    assert "<si:label>b_f</si:label>" not in xml and "<si:label>k_f</si:label>" not in xml
    assert "not certified" in xml and "<si:label>S</si:label>" in xml


@pytest.mark.slow
def test_a_single_mass_certificate_states_the_assumed_end_mass_in_pdf_and_dcc(chain_rec: Path) -> None:
    """The end mass a single run cannot determine: its value, source, share of u²(S) and the campaign
    as the remedy, read back from the PDF (pypdf) and the DCC; U to two significant digits with the
    value at the same decimal place; k = 2 with its probability."""
    c = certificate_content(chain_rec, ISSUED)
    em = c["end_mass"]
    assert em["status"] == "assumed" and em["value"] == 0.12 and 0.3 < em["share_of_u2_S"] < 0.95
    pages = _page_texts(html_to_pdf(certificate_html(c)))
    text = _pdf_text(pages)
    share = f"{100 * em['share_of_u2_S']:.0f} % of u²(S)"
    for want in ("The end mass m_e is not determined by this run", "0.12 kg", share, "campaign",
                 "not supported by a certificate", "coverage factor k = 2", "95.45 %", "N·s/m"):
        assert want in text, want
    assert "N*s/m" not in text and "e+0" not in text
    s = _row(c, "S")
    decimals = len(s["U_text"].split(".")[1])
    assert len(s["text"].split(".")[1]) == decimals
    assert len(s["U_text"].replace(".", "").lstrip("0")) == 2
    xml = build_dcc(c).decode()
    assert "The end mass m_e is not determined by this run" in xml and share in xml
    # the range of validity from the plan (4 to 100 Hz), the model's, the method cited, no internal names
    v = c["validity"]
    assert v["f_min_hz"] == pytest.approx(4.0, rel=1e-3) and v["f_max_hz"] == pytest.approx(100.0, rel=1e-3)
    M = c["assumptions"]["M_kg"]
    assert v["force_max_N"] == pytest.approx(M * (2 * math.pi * 100.0) ** 2 * R, rel=1e-3)  # M ω² r at 100 Hz
    assert v["force_min_N"] == pytest.approx(M * (2 * math.pi * 4.0) ** 2 * R, rel=1e-3)
    for want in ("valid for sinusoidal forces of frequency 4 Hz to 100 Hz", "no statement is made outside",
                 "The plan supports it for a coupling stiffness k_c >", "J. Lu", "Journal of Vibroengineering",
                 "[1] Eq. 9"):
        assert want in text, want
    assert "doi.org/10.21595/jve.2017.17744" in text.replace(" ", "")  # the PDF may break the address
    assert "results/identify" not in text and "S_times_M" not in text and "paper Eq" not in text
    # the Bode plot: embedded, its model drawn only within the plan's range
    assert 'id="bode"' in certificate_html(c)
    f_model = c["bode_model"]["f_hz"]
    assert f_model[0] >= v["f_min_hz"] * (1 - 1e-9) and f_model[-1] <= v["f_max_hz"] * (1 + 1e-9)
    # the number and "page i of n" on every page
    for i, page in enumerate(pages, 1):
        assert f"SC-2026-0042 · page {i} of {len(pages)}" in " ".join(page.split()), i


@pytest.mark.slow
def test_a_campaign_certificate_carries_the_determined_end_mass(tmp_path: Path) -> None:
    """Three top masses on the simulated rig, the campaign stored beside each run: the certificate of
    any of them states m_e as determined (within 3 u of the configured truth), with its covariance,
    no assumed end mass, and S_dyn with M = m_e + m_l of that run; read back from PDF and DCC."""
    from station.ident.campaign.identify import RESULT_NAME, identify_campaign
    from station.simulate import simulate_run
    from tests.conftest import station_config

    paths = []
    for i, top in enumerate((5.0, 15.0, 25.717)):
        cfg = station_config(settle_s=0.2, record_s=0.5, acceleration_hz_per_s=200.0, pre_roll_s=0.1,
                             steps=((4.0, 0.01), (20.0, 0.002), (50.0, 6e-4), (100.0, 1.5e-4)),
                             rig={"top_mass_kg": top}, transducer={"end_mass_kg": 0.12})
        p = simulate_run(cfg, tmp_path, seed=40 + i)
        res = identify_recording(read_recording(p))
        write_result(p, f"identify_{res.method}_{res.model}", res.to_dict())
        paths.append(p)
    camp = identify_campaign([read_recording(p) for p in paths])
    assert camp.status == "separated"
    for p in paths:
        write_result(p, RESULT_NAME, camp.to_dict())
    c = certificate_content(paths[0], ISSUED)
    em = c["end_mass"]
    assert em["status"] == "determined" and em["source"] == "campaign"
    me = _row(c, "m_e")
    assert me["status"] == "certified" and abs(me["value"] - 0.12) < 3 * me["u"]
    assert me["u"] < 0.006  # smaller than the 5 % data-sheet default it replaces
    assert "end_mass" not in c["budget"]["sources"]
    assert c["correlation"]["names"] == ["S", "m_e", "k_f", "b_f"] and em["correlation_with_S"] is not None
    m_l = camp.to_dict()["assumptions"]["load_mass_kg"][0]["value"]
    assert c["assumptions"]["M_kg"] == pytest.approx(me["value"] + m_l)
    text = _pdf_text(html_to_pdf(certificate_html(c)))
    for want in ("The end mass m_e is determined by the data", "a campaign of 3 runs", "correlation coefficients",
                 "end mass of the transducer", me["text"], me["U_text"]):
        assert want in text, want
    assert "not determined by this run" not in text and "jointly with the other parameters" in text
    xml = build_dcc(c).decode()
    assert "<si:label>m_e</si:label>" in xml and "The end mass m_e is determined by the data" in xml
    assert "covariance matrix of (S, m_e, k_f, b_f)" in xml


def test_the_runs_standards_feed_its_budget_and_its_certificate(tmp_path: Path) -> None:
    """The register's standards a run uses (seeded once from the configuration): their certificates'
    uncertainties replace the station's defaults in the configuration the run records, so the budget
    rests on them; the certificate lists what the run recorded and what each does in the budget; a
    standard past its due date refuses the run."""
    from station.config import parse_config
    from station.lab import register
    from station.lab.store import Store
    from station.simulate import simulate_run
    from tests.conftest import station_dict

    standards = [
        {"id": "MASS-1", "kind": "masses", "certificate_id": "M-88", "issuer": "PTB", "due_date": "2099-01-31",
         "uncertainty": 5e-5, "uncertainty_unit": "kg"},
        {"id": "DAQ-1", "kind": "daq", "certificate_id": "D-7", "issuer": "DKD lab", "due_date": "2099-01-31",
         "uncertainty": 3e-4, "uncertainty_unit": "relative"},
        {"id": "LVDT-1", "kind": "displacement_sensor", "certificate_id": "L-1", "issuer": "DKD lab",
         "due_date": "2099-01-31", "uncertainty": 2e-7, "uncertainty_unit": "m"}]
    data = station_dict(settle_s=0.3, record_s=1.0, steps=((4.0, R), (30.0, R), (100.0, R)),
                        acceleration_hz_per_s=200.0, pre_roll_s=0.1)
    data["lab"] = {"standards": standards}
    cfg = parse_config(data)
    store = Store(tmp_path / "station.db")
    try:
        assert {"MASS-1", "DAQ-1", "LVDT-1"} <= set(register.seed(store, cfg))
        setup = register.run_setup(store, cfg, cfg.transducer.id, None)
        late = {**standards[1], "id": "DAQ-OLD", "due_date": "2020-01-31"}
        register.put_standard(store, register.Standard(**late), "admin")
        with pytest.raises(register.OverdueStandardError, match=r"DAQ-OLD.*2020-01-31"):
            register.run_setup(store, cfg, cfg.transducer.id, ["MASS-1", "DAQ-OLD"])
    finally:
        store.close()
    run_cfg = setup.config(cfg)
    assert run_cfg.rig.load_mass_std_kg == 5e-5 and run_cfg.identification.chain.gain_rel_std == 3e-4
    rec = simulate_run(run_cfg, tmp_path / "rec", seed=5)
    res = identify_recording(read_recording(rec))
    write_result(rec, f"identify_{res.method}_{res.model}", res.to_dict())
    assert res.assumptions.load_mass.std == 5e-5
    assert res.assumptions.measurement_chain["gain_rel_std"] == 3e-4
    c = certificate_content(rec, register={"standards": [s.to_dict() for s in setup.standards]})
    by_id = {s["id"]: s for s in c["standards"]}
    assert by_id["MASS-1"]["budget"] == "in the budget as the load mass's standard uncertainty"
    assert by_id["DAQ-1"]["budget"].endswith("gain ratio of the force and displacement chains")
    assert "enters no budget term" in by_id["LVDT-1"]["budget"]
    chain = c["assumptions"]["chain"]
    assert any(x.startswith("gain ratio") and "default" not in x for x in chain)
    assert any(x.startswith("gain flatness") and "the station's default" in x for x in chain)
    # without the register's record, the configuration's list is marked as not recorded with the run
    assert all(not s["recorded"] and "not recorded with the run" in s["budget"]
               for s in certificate_content(rec)["standards"])

"""The Digital Calibration Certificate: built from the issued certificate's content, PTB's own
Schematron rules (dcclib, offline), D-SI unit strings (dsiunits), the values and expanded
uncertainties of the certificate, and a configured XML Schema that refuses an invalid DCC."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
from lxml import etree

from station.certificate.content import Approval, certificate_content
from station.certificate.dcc import DCC_NS, DSI_UNITS, SI_NS, build_dcc, validate
from station.ident.identify import identify_recording
from station.lab.issued import CertificateError
from station.recording import read_recording, write_result
from tests.ident_support import sim

NS = {"dcc": DCC_NS, "si": SI_NS}


@pytest.fixture(scope="module")
def issued_content(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    rec = sim(Path(tmp_path_factory.mktemp("dcc")))
    res = identify_recording(read_recording(rec))
    write_result(rec, f"identify_{res.method}_{res.model}", res.to_dict())
    return certificate_content(rec, Approval("issued", "SC-2026-0042", "T. Technician", "A. Approver", "approver",
                                             "2026-11-24T12:00:00+00:00"))


@pytest.mark.slow
def test_dcc_passes_ptbs_schematron_and_carries_the_results(issued_content: dict[str, Any]) -> None:
    from dcclib.validation.schematron import SchematronValidator
    from dsi_unit import DsiUnit

    xml = build_dcc(issued_content)
    result = SchematronValidator.for_dcc().validate_str(xml.decode())
    assert result.is_valid, [(f.location, f.text) for f in result.failed_assertions]
    doc = etree.fromstring(xml)
    assert doc.get("schemaVersion") == "3.3.0"
    assert doc.findtext(".//dcc:coreData/dcc:uniqueIdentifier", namespaces=NS) == "SC-2026-0042"
    assert doc.find(".//dcc:respPerson[dcc:mainSigner='true']/dcc:person/dcc:name/dcc:content",
                    NS).text == "A. Approver"
    for u in {e.text for e in doc.iterfind(".//si:unit", NS)} | {e.text for e in doc.iterfind(".//si:unitXMLList", NS)}:
        assert u in DSI_UNITS.values() and DsiUnit(u).valid, u
    by_label = {r.findtext("si:label", namespaces=NS): r for r in doc.iterfind(".//dcc:result//si:real", NS)}
    for r in issued_content["results"]:
        if r.get("U") is None:
            continue
        e = by_label[r["name"]]
        assert float(e.findtext("si:value", namespaces=NS)) == r["value"]
        mu = e.find("si:measurementUncertaintyUnivariate/si:expandedMU", NS)
        assert float(mu.findtext("si:valueExpandedMU", namespaces=NS)) == pytest.approx(r["k"] * r["u"])
        assert float(mu.findtext("si:coverageProbability", namespaces=NS)) == r["p"] == 0.9545
    assert {"S", "k_f", "b_f", "natural_frequency_hz", "series_stiffness"} <= set(by_label)
    mags = doc.find(".//dcc:list/dcc:quantity/si:realListXMLList[si:labelXMLList='magnitude']", NS)
    assert len(mags.findtext("si:valueXMLList", namespaces=NS).split()) == len(issued_content["response"])
    temp = doc.find(".//dcc:influenceCondition//si:real", NS)
    assert float(temp.findtext("si:value", namespaces=NS)) == issued_content["environment"]["temperature_c"]


def test_a_configured_schema_refuses_an_invalid_dcc(issued_content: dict[str, Any], tmp_path: Path) -> None:
    """The lab's own XSD (here a minimal one for the root element and its schemaVersion): a DCC that
    does not meet it is refused with the schema's message."""
    xsd = tmp_path / "dcc.xsd"
    xsd.write_text(f"""<xs:schema xmlns:xs="http://www.w3.org/2001/XMLSchema" targetNamespace="{DCC_NS}"
  elementFormDefault="qualified"><xs:element name="digitalCalibrationCertificate"><xs:complexType><xs:sequence>
  <xs:any processContents="skip" minOccurs="0" maxOccurs="unbounded"/></xs:sequence>
  <xs:attribute name="schemaVersion" type="xs:string" fixed="3.3.0" use="required"/>
  <xs:anyAttribute namespace="##other" processContents="skip"/></xs:complexType></xs:element></xs:schema>""")
    xml = build_dcc(issued_content)
    validate(xml, xsd)  # passes
    bad = xml.replace(b'schemaVersion="3.3.0"', b'schemaVersion="3.2.0"')
    with pytest.raises(CertificateError, match="does not validate"):
        validate(bad, xsd)
    with pytest.raises(CertificateError, match="cannot be used"):
        validate(xml, tmp_path / "missing.xsd")


def test_software_contacts_and_country_come_from_the_station_and_its_configuration(
        issued_content: dict[str, Any]) -> None:
    """usedSoftware (name, version) silences PTB's Schematron reports about undeclared software; the
    laboratory's and the customer's e-mail and country are the configuration's (no fixed country)."""
    from dcclib.validation.schematron import SchematronValidator

    xml = build_dcc(issued_content)
    result = SchematronValidator.for_dcc().validate_str(xml.decode())
    assert result.is_valid
    assert not [r for r in result.successful_reports if "software" in r.text and "NEITHER" in r.text]
    assert [r for r in result.successful_reports if "software used during measuring process is global" in r.text]
    doc = etree.fromstring(xml)
    sw = doc.find(".//dcc:measurementResult/dcc:usedSoftware/dcc:software", NS)
    assert sw is not None and sw.findtext("dcc:release", namespaces=NS).startswith("v")
    assert doc.findtext(".//dcc:coreData/dcc:countryCodeISO3166_1", namespaces=NS) == "DE"
    lab = doc.find(".//dcc:calibrationLaboratory/dcc:contact", NS)
    assert lab.findtext("dcc:eMail", namespaces=NS) == "calibration@example.org"
    cust = doc.find(".//dcc:customer", NS)
    assert cust.findtext("dcc:eMail", namespaces=NS) == "metrology@example.com"
    assert cust.findtext("dcc:location/dcc:countryCode", namespaces=NS) == "AT"
    other = {**issued_content, "laboratory": {**issued_content["laboratory"], "country": "CH"}}
    assert etree.fromstring(build_dcc(other)).findtext(".//dcc:countryCodeISO3166_1", namespaces=NS) == "CH"
    with pytest.raises(CertificateError, match=r"certificate\.laboratory\.country"):
        build_dcc({**issued_content, "laboratory": {**issued_content["laboratory"], "country": ""}})


def test_a_draft_dcc_is_marked_as_a_draft(issued_content: dict[str, Any]) -> None:
    from dcclib.validation.schematron import SchematronValidator

    draft = {**issued_content, "approval": Approval(prepared_by="T. Technician").__dict__}
    xml = build_dcc(draft)
    assert SchematronValidator.for_dcc().validate_str(xml.decode()).is_valid
    doc = etree.fromstring(xml)
    assert doc.findtext(".//dcc:coreData/dcc:uniqueIdentifier", namespaces=NS).startswith("DRAFT-")
    first = doc.find(".//dcc:statements/dcc:statement/dcc:declaration/dcc:content", NS).text
    assert first.startswith("DRAFT: not issued")
    assert doc.find(".//dcc:respPerson[dcc:mainSigner='true']", NS) is None

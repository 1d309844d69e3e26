"""The issued certificate as a PTB Digital Calibration Certificate (DCC, XML, schema 3.3.0).

Built from the same content as the HTML and PDF (``content.certificate_content``), never from a new
computation.  Mapping (docs/certificate.md): administrativeData: dccSoftware (sinecal and its
version), coreData (country, language, the certificate number as uniqueIdentifier, the run's begin
and end, the place, the issue date), items (the transducer, its id as the customer's identification),
calibrationLaboratory, respPersons (who prepared it; the approver as main signer), customer,
statements (the results relate only to the item; the assumptions; the uncertainty statement);
measurementResults/measurementResult: usedMethods (stepped sine on a crank rig, model, estimator),
measuringEquipments (the reference standards with their certificates and due dates),
influenceConditions (temperature and humidity), results: each identified parameter and each
determined quantity as ``si:real`` with ``si:expandedMU`` (U, k, p), and H(f) as a list of
``si:realListXMLList`` quantities (frequency, |S_dyn| and phase with their U).  Units in D-SI syntax
(``DSI_UNITS``).  ``validate`` checks a DCC against an XML Schema (``certificate.dcc_schema``).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from station import __version__
from station.lab.issued import CertificateError

DCC_NS = "https://ptb.de/dcc"
SI_NS = "https://ptb.de/si"
XSI_NS = "http://www.w3.org/2001/XMLSchema-instance"
SCHEMA_VERSION = "3.3.0"
LANG = "en"
DSI_UNITS = {"V/N": r"\volt\newton\tothe{-1}", "N/m": r"\newton\metre\tothe{-1}",
             "N*s/m": r"\newton\second\metre\tothe{-1}", "kg": r"\kilogram", "Hz": r"\hertz", "1": r"\one",
             "V*s^2/m": r"\volt\second\tothe{2}\metre\tothe{-1}", "deg": r"\degree", "degC": r"\degreecelsius",
             "%": r"\percent", "m": r"\metre", "mV/V/N": r"\milli\volt\volt\tothe{-1}\newton\tothe{-1}",
             "mV/V*s^2/m": r"\milli\volt\volt\tothe{-1}\second\tothe{2}\metre\tothe{-1}",
             "pC/N": r"\pico\coulomb\newton\tothe{-1}", "pC*s^2/m": r"\pico\coulomb\second\tothe{2}\metre\tothe{-1}"}


DRAFT = "DRAFT: not issued, not valid as a calibration certificate (no number, not approved)."


def dsi(unit: str) -> str:
    """The D-SI form of a station unit string (CertificateError for one without a mapping)."""
    try:
        return DSI_UNITS[unit]
    except KeyError:
        raise CertificateError(f"no D-SI unit for {unit!r}") from None


def _num(x: float) -> str:
    return repr(float(x))


def signature_declaration(approval: dict[str, Any]) -> list[str]:
    """The lab's detached signature of an issued certificate (``station.lab.signing``), as a
    statement: the file that holds it and the key's fingerprint ([] unsigned)."""
    sig = approval.get("signature")
    if not sig:
        return []
    return [f"Signed by the laboratory: {sig['algorithm']} signature in the file {sig['file']} (detached; it "
            f"covers this DCC, the PDF and the HTML forms), key fingerprint {sig['key_fingerprint']}"]


class _Xml:
    """The DCC's element builders (lxml, imported on first use)."""

    D, S = f"{{{DCC_NS}}}", f"{{{SI_NS}}}"

    def __init__(self) -> None:
        from lxml import etree

        self.etree = etree

    def el(self, parent: Any, tag: str, text: str | None = None, **attrib: str) -> Any:
        e = self.etree.SubElement(parent, tag, attrib)
        if text is not None:
            e.text = text
        return e

    def text_block(self, parent: Any, tag: str, *lines: str) -> Any:
        e = self.el(parent, self.D + tag)
        for line in lines:
            self.el(e, self.D + "content", line, lang=LANG)
        return e

    def contact(self, parent: Any, party: dict[str, Any]) -> None:
        D = self.D
        self.text_block(parent, "name", party["name"])
        if party.get("email"):
            self.el(parent, D + "eMail", party["email"])
        loc = self.el(parent, D + "location")
        if party.get("country"):
            self.el(loc, D + "countryCode", party["country"])
        self.text_block(loc, "further", *(party.get("address") or ["not stated"]))

    def real(self, parent: Any, value: float, unit: str, U: float | None = None, k: float | None = None,
             p: float | None = None, label: str | None = None) -> None:
        el, S = self.el, self.S
        r = el(parent, S + "real")
        if label:
            el(r, S + "label", label)
        el(r, S + "value", _num(value))
        el(r, S + "unit", dsi(unit))
        if U is not None and k is not None and p is not None:
            mu = el(el(r, S + "measurementUncertaintyUnivariate"), S + "expandedMU")
            el(mu, S + "valueExpandedMU", _num(U))
            el(mu, S + "coverageFactor", _num(k))
            el(mu, S + "coverageProbability", _num(p))

    def real_list(self, parent: Any, values: list[float], unit: str, U: list[float] | None, k: float, p: float,
                  label: str) -> None:
        """A list quantity; with ``U`` None, values only (no uncertainty)."""
        el, S = self.el, self.S
        r = el(parent, S + "realListXMLList")
        el(r, S + "labelXMLList", label)
        el(r, S + "valueXMLList", " ".join(_num(v) for v in values))
        el(r, S + "unitXMLList", dsi(unit))
        if U is None:
            return
        mu = el(el(r, S + "measurementUncertaintyUnivariateXMLList"), S + "expandedMUXMLList")
        el(mu, S + "valueExpandedMUXMLList", " ".join(_num(u) for u in U))
        el(mu, S + "coverageFactorXMLList", _num(k))
        el(mu, S + "coverageProbabilityXMLList", _num(p))


def build_dcc(content: dict[str, Any]) -> bytes:
    """The DCC of a certificate's content (UTF-8 XML bytes): an issued one, or a draft marked as such
    (uniqueIdentifier DRAFT-<run>, the draft statement first, no approver); CertificateError without
    the laboratory's country."""
    a = content["approval"]
    issued = a["status"] == "issued" and bool(a["number"])
    country = content["laboratory"].get("country")
    if not country:
        raise CertificateError("the DCC needs the laboratory's country: set certificate.laboratory.country "
                               "(ISO 3166-1 alpha-2, e.g. DE) in the configuration")
    x = _Xml()
    D = x.D
    root = x.etree.Element(D + "digitalCalibrationCertificate", nsmap={"dcc": DCC_NS, "si": SI_NS, "xsi": XSI_NS})
    root.set("schemaVersion", SCHEMA_VERSION)
    root.set(f"{{{XSI_NS}}}schemaLocation", f"{DCC_NS} {DCC_NS}/v{SCHEMA_VERSION}/dcc.xsd")
    _administrative_data(x, x.el(root, D + "administrativeData"), content, issued, country)
    mr = x.el(x.el(root, D + "measurementResults"), D + "measurementResult")
    _method_and_equipment(x, mr, content)
    _influence_conditions(x, mr, content["environment"])
    _results(x, x.el(mr, D + "results"), content)
    return bytes(x.etree.tostring(root, xml_declaration=True, encoding="UTF-8", pretty_print=True))


def _administrative_data(x: _Xml, adm: Any, content: dict[str, Any], issued: bool, country: str) -> None:
    """dccSoftware, coreData, items, calibrationLaboratory, respPersons, customer, statements."""
    el, text_block, D = x.el, x.text_block, x.D
    a, run, item = content["approval"], content["run"], content["item"]
    sw = el(el(adm, D + "dccSoftware"), D + "software")
    text_block(sw, "name", "sinecal calibration station")
    el(sw, D + "release", f"v{__version__}")  # the DCC rules want a letter before the version
    el(sw, D + "type", "application")
    core = el(adm, D + "coreData")
    el(core, D + "countryCodeISO3166_1", country)
    el(core, D + "usedLangCodeISO639_1", LANG)
    el(core, D + "mandatoryLangCodeISO639_1", LANG)
    el(core, D + "uniqueIdentifier", a["number"] if issued else f"DRAFT-{run['run_id']}")
    el(core, D + "beginPerformanceDate", run["start_time"][:10])
    el(core, D + "endPerformanceDate", (run["end_time"] or run["start_time"])[:10])
    el(core, D + "performanceLocation", "laboratory")
    el(core, D + "issueDate", a["issued_at"][:10] if issued else (run["end_time"] or run["start_time"])[:10])
    it = el(el(adm, D + "items"), D + "item")
    text_block(it, "name", f"{content['title'].removeprefix('Calibration certificate for a ')} "
                           f"{item['transducer_id']}")
    text_block(el(it, D + "manufacturer"), "name", "not stated")
    ident = el(el(it, D + "identifications"), D + "identification")
    el(ident, D + "issuer", "customer")
    el(ident, D + "value", item["transducer_id"])
    text_block(ident, "name", "transducer id")
    x.contact(el(el(adm, D + "calibrationLaboratory"), D + "contact"), content["laboratory"])
    persons = el(adm, D + "respPersons")
    signers = ((a["prepared_by"] or "not stated", "prepared", False),
               *(((a["approved_by"], a["approver_role"], True),) if issued else ()))
    for name, role, main in signers:
        rp = el(persons, D + "respPerson")
        text_block(el(rp, D + "person"), "name", name)
        el(rp, D + "role", role)
        if main:
            el(rp, D + "mainSigner", "true")
    cust = el(adm, D + "customer")
    x.contact(cust, content["customer"] or {"name": "not stated", "address": []})
    statements = el(adm, D + "statements")
    for d in [*declarations(content, issued), *signature_declaration(a)]:
        text_block(el(statements, D + "statement"), "declaration", d)


def declarations(content: dict[str, Any], issued: bool) -> list[str]:
    """The DCC's statements before the signature: the draft mark, what the results relate to, the
    item, the uncertainty statement, the assumptions, the notes and findings, the correlation, the
    model structure, a replaced certificate."""
    a, item = content["approval"], content["item"]
    masses = content["assumptions"]["masses"]
    out = [*(() if issued else (DRAFT,)), content["relates_only"], f"item calibrated: {item['text']}",
           *content["statement"],
           *(f"assumption: {m['name']} = {m['value']} kg ({m['source']})" for m in masses),
           content["end_mass"]["text"],
           *(f"{r['meaning']} ({r['name']}): {r['note']}" for r in content["results"]
             if r["status"] != "certified" and r["note"]),
           *(f"finding ({f['severity']}) {f['name']}: {f['message']}" for f in content["checks"])]
    corr = content.get("correlation")
    if corr:
        out.append(f"covariance matrix of ({', '.join(corr['names'])}) in ({', '.join(corr['units'])}): "
                   + "; ".join(" ".join(_num(v) for v in row) for row in corr["matrix"]))
    if content["assumptions"]["structure"]:
        out.append("model structure: " + content["assumptions"]["structure"])
    if a.get("replaces"):
        out.append(f"This certificate replaces certificate {a['replaces']}, which is withdrawn: {a['reason']}")
    return out


def _method_and_equipment(x: _Xml, mr: Any, content: dict[str, Any]) -> None:
    """usedMethods, usedSoftware and the reference standards as measuringEquipments."""
    el, text_block, D = x.el, x.text_block, x.D
    run = content["run"]
    text_block(mr, "name", "dynamic calibration of a force transducer")
    um = el(el(mr, D + "usedMethods"), D + "usedMethod")
    m = content["method"]
    text_block(um, "name", m["name"])
    text_block(um, "description", f"model {m['model']}: {m['model_text']}",
               f"estimator {m['estimator']}: {m['estimator_text']}")
    used = el(el(mr, D + "usedSoftware"), D + "software")
    text_block(used, "name", "sinecal calibration station (acquisition, identification, uncertainty budget)")
    el(used, D + "release", f"v{run.get('software_version') or __version__}")
    el(used, D + "type", "application")
    if content["standards"]:
        eqs = el(mr, D + "measuringEquipments")
        for s in content["standards"]:
            eq = el(eqs, D + "measuringEquipment")
            text_block(eq, "name", s["name"])
            trace = f"; {s['traceability']}" if s["traceability"] else ""
            text_block(eq, "description", f"kind {s['kind']}; calibration certificate {s['certificate_id']}, "
                                           f"due {s['due_date']}{trace}")
            eid = el(el(eq, D + "identifications"), D + "identification")
            el(eid, D + "issuer", "calibrationLaboratory")
            el(eid, D + "value", s["id"])


def _influence_conditions(x: _Xml, mr: Any, env: dict[str, Any] | None) -> None:
    """The room's temperature and humidity with U (k = 2), those known."""
    if not env:
        return
    el, text_block, D = x.el, x.text_block, x.D
    infl = el(mr, D + "influenceConditions")
    for key, std, unit, name in (("temperature_c", "temperature_std_c", "degC", "air temperature"),
                                 ("relative_humidity_pct", "relative_humidity_std_pct", "%", "relative humidity")):
        if env.get(key) is None:
            continue
        ic = el(infl, D + "influenceCondition")
        text_block(ic, "name", name)
        text_block(ic, "description", str(env.get("source", "")))
        q = el(el(ic, D + "data"), D + "quantity")
        x.real(q, env[key], unit, 2 * env[std], 2.0, 0.95)


def _results(x: _Xml, results: Any, content: dict[str, Any]) -> None:
    """Each parameter and determined quantity with its U, then S_dyn(f) as lists."""
    el, text_block, D = x.el, x.text_block, x.D
    for r in content["results"]:
        if r.get("U") is None:
            continue
        res = el(results, D + "result")
        text_block(res, "name", f"{r['name']}: {r['meaning']}")
        q = el(el(res, D + "data"), D + "quantity", refType=f"sinecal_{r['name']}")
        x.real(q, r["value"], r["unit"], r["U"], r["k"], r["p"], label=r["name"])
    pts = content["response"]
    if not pts:
        return
    res = el(results, D + "result")
    text_block(res, "name", "dynamic sensitivity S_dyn(f) = -H(f)/M")
    lst = el(el(res, D + "data"), D + "list")
    k, p = float(content["response_k"]), float(content["response_p"])
    for label, key, unit, ukey in (("frequency", "f_hz", "Hz", None),
                                   ("magnitude", "magnitude", content["response_unit"], "U_magnitude"),
                                   ("phase", "phase_deg", "deg", "U_phase_deg")):
        q = el(lst, D + "quantity")
        text_block(q, "name", label)
        x.real_list(q, [pt[key] for pt in pts], unit, None if ukey is None else [pt[ukey] for pt in pts], k, p, label)


def validate(xml: bytes, schema_path: str | Path) -> None:
    """Validate a DCC against the XML Schema at ``schema_path`` (lxml); CertificateError naming the
    first problems when it is invalid or the schema cannot be read."""
    from lxml import etree

    try:
        schema = etree.XMLSchema(etree.parse(str(schema_path)))
    except (OSError, etree.XMLSchemaParseError, etree.XMLSyntaxError) as e:
        raise CertificateError(f"the DCC schema {schema_path} cannot be used: {e}") from None
    doc = etree.fromstring(xml)
    if not schema.validate(doc):
        errs = "; ".join(f"line {e.line}: {e.message}" for e in list(schema.error_log)[:3])
        raise CertificateError(f"the DCC does not validate against {Path(schema_path).name}: {errs}")

"""The isolation fault matrix: one test per row of the station's isolation findings that concern
its edges (bad bodies, imports, secrets, the database at start, a second daemon, orphaned workers,
a full disk while identifying).  The row is quoted in each docstring.  The daemon's app runs
in-process (``tests.test_fault_matrix_service.station``) wherever a process boundary is not what is
tested; a second daemon and a killed daemon are real processes (marked slow)."""

from __future__ import annotations

import asyncio
import json
from pathlib import Path

import httpx
import pytest

from station.bounded import MAX_YAML_NODES
from station.cli import main
from station.errors import BadInputError, ConfigError, RecordingFormatError
from tests.test_fault_matrix_service import station
from tests.test_service_support import daemon_config, run_body

# --------------------------------------------------------------------------------------- bad bodies
POSTS = ("/runs", "/runs/no-such-run/abort", "/stop/acknowledge", "/campaigns")
NOT_JSON = {  # content type: body
    "application/octet-stream": b"\xff\xfe\x00binary",
    "text/plain": json.dumps(run_body()).encode(),  # JSON text sent as text/plain: a cross-site "simple" request
    "application/x-www-form-urlencoded": b"transducer_id=TX5K-0001&top_mass_kg=25",
    "multipart/form-data; boundary=xx": b'--xx\r\nContent-Disposition: form-data; name="a"\r\n\r\n\xff\r\n--xx--\r\n',
    "text/html; charset=utf-8": b"<p>\xe9</p>",
}
BAD_JSON = {  # name: body sent as application/json
    "not UTF-8": b'{"transducer_id": "\xff\xfe"}',
    "an array": b"[1, 2, 3]",
    "a string": b'"runs"',
    "null": b"null",
    "empty": b"",
    "truncated": b'{"runs": [',
    "NaN": b'{"transducer_id": "TX5K-0001", "top_mass_kg": NaN, "operator": NaN, "runs": NaN}',
    "Infinity": b'{"top_mass_kg": Infinity, "runs": [1e999]}',
    "a 5000-digit number": b'{"top_mass_kg": ' + b"9" * 5000 + b"}",
    "nested 100000 deep": b"[" * 100_000 + b"]" * 100_000,
    "a 300 kB string": b'{"transducer_id": "' + b"x" * 300_000 + b'", "operator": "' + b"y" * 300_000 + b'"}',
}


def _assert_clear_4xx(r: httpx.Response, expected: tuple[int, ...], what: str) -> None:
    assert r.status_code in expected, (what, r.status_code, r.text[:500])
    assert r.headers["content-type"].startswith("application/json"), what
    assert "Traceback" not in r.text and 'File "' not in r.text, what
    assert len(r.content) < 3000, (what, len(r.content))  # the input is quoted within a few hundred characters
    assert r.json()["detail"], what


def test_every_bad_body_on_every_post_endpoint_is_a_clear_4xx(tmp_path: Path) -> None:
    """| non-UTF-8 bodies | 500 with a 5.4 kB traceback on `POST /runs`, `/stop/acknowledge`,
    `/campaigns` for every non-JSON content type (octet-stream, text/plain, form, multipart) |"""

    async def go() -> None:
        async with station(tmp_path / "rec") as (m, c):
            for path in POSTS:
                for ctype, body in NOT_JSON.items():
                    r = await c.post(path, content=body, headers={"Content-Type": ctype})
                    _assert_clear_4xx(r, (415,), f"{path} {ctype}")
                    assert "application/json" in r.json()["detail"]
                for name, body in BAD_JSON.items():
                    r = await c.post(path, content=body, headers={"Content-Type": "application/json"})
                    # 404: the abort of an unknown run reads no body; 413: over service.max_body_bytes
                    _assert_clear_4xx(r, (404, 413, 422) if "abort" in path else (413, 422), f"{path} {name}")
                # without the token: 401 before anything is read, whatever the type
                for ctype in ("application/json", "text/plain"):
                    r = await c.post(path, content=b"{}", headers={"Content-Type": ctype, "Authorization": ""})
                    _assert_clear_4xx(r, (401,), f"{path} anonymous {ctype}")
            # the emergency stop takes any body (it never reads it) and still stops
            r = await c.post("/stop", content=b"\xff", headers={"Content-Type": "application/octet-stream"})
            assert r.status_code == 200 and r.json()["motor_stopped"] is True
            assert m.store.list_runs() == []  # nothing started
    asyncio.run(go())


def test_campaigns_need_the_token_even_on_loopback(tmp_path: Path) -> None:
    """| non-UTF-8 bodies | `/campaigns` needs no token and accepts cross-site text/plain |"""

    async def go() -> None:
        async with station(tmp_path / "rec") as (_, c):
            anon = {"Authorization": "", "Content-Type": "text/plain", "Origin": "http://evil.example",
                    "Sec-Fetch-Site": "cross-site"}
            r = await c.post("/campaigns", content=json.dumps({"runs": ["x"]}).encode(), headers=anon)
            assert r.status_code == 401
            r = await c.post("/campaigns", json={"runs": ["x"]}, headers={"Authorization": ""})
            assert r.status_code == 401
            r = await c.post("/campaigns", json={"runs": ["no-such-run"]})  # with the token: reaches the route
            assert r.status_code == 404
            info = (await c.get("/station")).json()
            assert "POST /campaigns" in info["token_required"]
    asyncio.run(go())


# --------------------------------------------------------------------------------------- imports
def _alias_bomb(levels: int = 9) -> str:
    """A few hundred bytes that expand to 9**levels nodes (the billion laughs)."""
    lines = ['a0: &a0 ["lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol"]']
    lines += [f"a{i}: &a{i} [{', '.join([f'*a{i - 1}'] * 9)}]" for i in range(1, levels + 1)]
    return "\n".join(lines) + "\n"


def test_import_bounds_yaml_aliases_file_sizes_and_quotes(tmp_path: Path) -> None:
    """| import amplification | a 685-byte YAML with nested aliases -> a 351 MB error message and 1.4 GB
    of memory; step files are read whole with no size limit (512 MB sparse file -> 6.9 GB RSS) |"""
    import resource

    from station.interchange import MAX_STEP_FILE_BYTES, import_run

    out = tmp_path / "out"
    src = tmp_path / "run"
    src.mkdir()
    bomb = _alias_bomb()
    assert len(bomb) < 700 and MAX_YAML_NODES < 9 ** 9
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    for text in (bomb, "format: sinecal-csv\nformat_version: 1\ntransducer:\n  " + bomb.replace("\n", "\n  ")):
        (src / "RUN.yaml").write_text(text)
        with pytest.raises(RecordingFormatError) as exc:
            import_run(src / "RUN.yaml", out)
        assert len(str(exc.value)) < 1000, len(str(exc.value))
    assert "expands to more than" in str(exc.value)
    # a RUN.yaml that is right but for a huge value: quoted within a few hundred characters
    run = {"format": "sinecal-csv", "format_version": 1, "sample_rate_hz": 20000, "crank_radius_m": 0.001,
           "top_mass_kg": 25.0, "transducer": {"id": "T" * 100_000, "capacity_N": 5000, "sensitivity_V_per_N": 1e-3},
           "steps": [{"file": "s.csv", "crank_frequency_hz": 10}]}
    (src / "RUN.yaml").write_text(json.dumps(run))
    with pytest.raises(RecordingFormatError) as exc:
        import_run(src / "RUN.yaml", out)
    assert "transducer.id" in str(exc.value) and len(str(exc.value)) < 1000
    # a step file over the limit (sparse: no disk used) is refused by its size, unread
    run["transducer"]["id"] = "T1"  # type: ignore[index]
    (src / "RUN.yaml").write_text(json.dumps(run))
    with (src / "s.csv").open("wb") as f:
        f.write(b"t_s,displacement_m,force_V\n")
        f.truncate(MAX_STEP_FILE_BYTES + 1)
    with pytest.raises(RecordingFormatError) as exc:
        import_run(src / "RUN.yaml", out)
    assert f"exceeds the limit of {MAX_STEP_FILE_BYTES} bytes" in str(exc.value)
    assert (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - rss0) < 200 * 1024  # kB: nothing read whole
    assert not out.exists() or not any(out.iterdir())  # nothing written


def test_configuration_yaml_is_bounded_the_same_way(tmp_path: Path) -> None:
    """| import amplification | (the station configuration goes through the same loader) |"""
    from station.config import load_config

    p = tmp_path / "station.yaml"
    p.write_text(_alias_bomb())
    with pytest.raises(ConfigError) as exc:
        load_config(p)
    assert "expands to more than" in str(exc.value) and len(str(exc.value)) < 1000
    p.write_text("rig: [" * 50_000)
    with pytest.raises(ConfigError) as exc2:
        load_config(p)
    assert len(str(exc2.value)) < 1000
    with p.open("wb") as f:
        f.truncate(2 << 20)
    with pytest.raises(ConfigError, match="exceeds the limit"):
        load_config(p)
    # shared aliases of a small document still load (YAML as users write it)
    from station.bounded import load_yaml

    assert load_yaml("a: &x [1, 2]\nb: *x\nc: {d: *x}\n", "t") == {"a": [1, 2], "b": [1, 2], "c": {"d": [1, 2]}}
    with pytest.raises(BadInputError):
        load_yaml(_alias_bomb(6), "t", max_nodes=9 ** 6)


# --------------------------------------------------------------------------------------- secrets
def test_an_invalid_token_is_never_printed(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                           monkeypatch: pytest.MonkeyPatch) -> None:
    """| token echoed | an invalid configured token (e.g. with spaces) is printed in the start-up error |"""
    import yaml

    secrets = ["my zq-secret passphrase", "zqshort", "zqtab\tzqsecret-9876", "ümlaut-zqsecret-1234"]
    for secret in secrets:
        d = daemon_config(tmp_path / "rec")
        d["service"] = {"token": secret}
        cfg = tmp_path / "station.yaml"
        cfg.write_text(yaml.safe_dump(d))
        monkeypatch.delenv("STATION_TOKEN", raising=False)
        assert main(["serve", "--config", str(cfg)]) == 2
        monkeypatch.setenv("STATION_TOKEN", secret)
        assert main(["serve", "--sim", "--config", str(cfg)]) == 2
        d["service"] = {"tokn": secret}  # a misspelt key
        cfg.write_text(yaml.safe_dump(d))
        assert main(["serve", "--sim", "--config", str(cfg)]) == 2
        out = capsys.readouterr()
        text = out.out + out.err
        assert "service.token" in text and "service.tokn: unknown key" in text
        for part in secret.split():
            assert part not in text, (secret, text)

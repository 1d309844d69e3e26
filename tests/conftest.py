"""Shared fixtures of the foundation tests: small, fast configurations derived from
config/sim-5kN.yaml and simulated recordings made once per session.

Session-scoped recordings are shared: tests must not modify them (copy them into tmp_path first).
"""

from __future__ import annotations

import copy
import functools
import gc
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

import pytest
import yaml

from station.config import StationConfig, default_config_path, parse_config
from station.simulate import simulate_run

REPO = Path(__file__).resolve().parent.parent
CONFIG_DIR = REPO / "config"


Steps = Sequence[tuple[float, float]]  # (crank frequency in Hz, crank radius in m) per step

MULTI_RADIUS: Steps = ((4.0, 0.01), (30.0, 0.001), (100.0, 0.00015))  # each radius change stops the crank
ONE_RADIUS: Steps = ((5.0, 0.0004), (20.0, 0.0004), (60.0, 0.0004))  # sinecal-csv v1 exports only these


def pytest_configure(config: pytest.Config) -> None:
    """Once per run, before the xdist workers start: the simulated rig's compiled synthesis is read from
    numba's cache, or compiled into it (tens of seconds of CPU on a fresh clone), so that workers and the
    daemons the tests start do not all compile it at once while a test waits for them."""
    if hasattr(config, "workerinput"):
        return
    from drivers.rig.presets import paper_5kN_physics
    from drivers.sim.daq_source import RigSource

    RigSource(paper_5kN_physics(), seed=0, crank_radius_m=1e-3).configure(20_000.0, 10.0, 10.0)


def pytest_collection_finish(session: pytest.Session) -> None:
    """In each test process, once its modules are imported and its tests collected: the objects made so far
    (the modules of numpy, SciPy, matplotlib, FastAPI and the station, a few hundred thousand) are moved out
    of the cyclic garbage collector's reach (``gc.freeze``), and the collector runs after 50 000 new
    container objects instead of 700.  Every full collection walked all of them again: 4 % of a test
    process's CPU (2.8 s of 65 s over five test files), 1.2 % with these.  Garbage is still collected; a
    test that needs it collected at once calls ``gc.collect()``."""
    gc.freeze()
    gc.set_threshold(50_000, 20, 10)


def _module_rank(item: pytest.Item) -> int:
    """0: the module keeps tests together on one worker (``xdist_group``: a daemon, a browser, a shared
    analysis, 15-50 s each) or has a test that mostly waits (``waits``: a kill and restart, a run over
    the wire, 5-20 s of wall time); 1: it has slow tests; 2: only fast ones."""
    if item.get_closest_marker("xdist_group") is not None or item.get_closest_marker("waits") is not None:
        return 0
    return 1 if item.get_closest_marker("slow") is not None else 2


def _weight(item: pytest.Item) -> float:
    """A test's rough length for spreading the waits: a slow test takes seconds, the others a tenth or so."""
    return 10.0 if item.get_closest_marker("slow") is not None else 1.0


WAITS_SPREAD = 0.75  # the waits are spread over this leading share of the other tests of slow modules


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """The order in which pytest-xdist hands out the tests that are not kept together (``--dist
    loadgroup`` hands out every ``xdist_group`` first, the largest first, then each other test on its
    own in this order): longest work first, and the waits spread among the CPU's work.

    - Modules are ranked by their longest unit (``_module_rank``: a module's rank is its best item's)
      and keep their place within a rank and their tests' order (a stable sort).  The alphabetical
      order put the browser and daemon modules last, where a worker still running one left the
      others idle.
    - A test that mostly waits in real time (``waits``, on it or its module) is spread evenly, by
      rough length (``_weight``), over the first ``WAITS_SPREAD`` of the other tests of the modules
      with slow tests.  Handed out together, as they were, the four workers all waited at once: in
      one run 12.5 of the run's 24 core-seconds of idle time fell in the 20 s they took.  Spread, one
      or two wait at a time while the others compute; none is left for the end, where the fast
      tests even out the workers' finishing times."""
    rank: dict[str, int] = {}
    for it in items:
        key = it.nodeid.split("::", 1)[0]
        rank[key] = min(rank.get(key, 2), _module_rank(it))
    items.sort(key=lambda it: rank[it.nodeid.split("::", 1)[0]])  # stable: file and test order kept
    grouped = [it for it in items if it.get_closest_marker("xdist_group") is not None]
    single = [it for it in items if it.get_closest_marker("xdist_group") is None]
    waits = [it for it in single if it.get_closest_marker("waits") is not None]
    work = [it for it in single if it.get_closest_marker("waits") is None and rank[it.nodeid.split("::", 1)[0]] < 2]
    fast = [it for it in single if it.get_closest_marker("waits") is None and rank[it.nodeid.split("::", 1)[0]] == 2]
    # spread by a rough length (``_weight``): many of the waits are protocol checks of a tenth of a second,
    # and spread by count they bunched the long ones together as before
    due = sum(map(_weight, waits)) / max(WAITS_SPREAD * sum(map(_weight, work)), 1e-9)  # waits per unit of work
    spread: list[pytest.Item] = []
    k, done, placed = 0, 0.0, 0.0  # waits placed, work handed out, waits handed out (in _weight)
    for it in work:
        spread.append(it)
        done += _weight(it)
        while k < len(waits) and placed <= done * due:
            spread.append(waits[k])
            placed += _weight(waits[k])
            k += 1
    items[:] = grouped + spread + waits[k:] + fast


@functools.cache
def _shipped() -> dict[str, Any]:
    """The shipped configuration as parsed YAML, read once per process (callers copy it)."""
    data = yaml.load(default_config_path().read_text(encoding="utf-8"), Loader=yaml.CSafeLoader)
    assert isinstance(data, dict)
    return data


def station_dict(*, steps: Steps | None = None, settle_s: float | None = None, record_s: float | None = None,
                 acceleration_hz_per_s: float | None = None, pre_roll_s: float | None = None,
                 effects: dict[str, Any] | None = None, recordings_dir: Path | None = None,
                 service: dict[str, Any] | None = None, **sections: dict[str, Any]) -> dict[str, Any]:
    """The tests' one configuration builder: config/sim-5kN.yaml as parsed YAML with the given changes
    (None: as shipped).  ``steps`` replaces the plan's steps; ``sections`` update a section's keys
    (e.g. ``rig={"top_mass_kg": 5.0}``); ``service`` replaces the service section."""
    d = copy.deepcopy(_shipped())
    plan = {"settle_s": settle_s, "record_s": record_s,
            "steps": None if steps is None else [{"crank_frequency_hz": f, "crank_radius_m": r} for f, r in steps]}
    d["plan"].update({k: v for k, v in plan.items() if v is not None})
    if acceleration_hz_per_s is not None:
        d["rig"]["acceleration_hz_per_s"] = acceleration_hz_per_s
    if pre_roll_s is not None:
        d["simulation"]["pre_roll_s"] = pre_roll_s
    if effects is not None:
        d["simulation"]["effects"] = effects
    if recordings_dir is not None:
        d["station"]["recordings_dir"] = str(recordings_dir)
    if service:
        d["service"] = service
    d.setdefault("identification", {})["swarm"] = dict(TEST_SWARM)  # the paper's methods beside fd stay quick
    for name, values in sections.items():
        d.setdefault(name, {}).update(values)
    return d


# The tests' swarm (PSO/PSO+ beside fd on every run): small enough to be quick; the shipped
# configuration keeps the paper's (Section 5.1, 200 particles x 1000 iterations).
TEST_SWARM = {"n_particles": 24, "n_iterations": 60}


FAST = {"settle_s": 0.2, "record_s": 0.5, "acceleration_hz_per_s": 100.0, "pre_roll_s": 0.2, "steps": MULTI_RADIUS}


def fast_dict(**changes: Any) -> dict[str, Any]:
    """:func:`station_dict` with short settle/record/pre-roll times and a fast crank ramp (3 steps,
    3 radii) unless ``changes`` say otherwise."""
    return station_dict(**{**FAST, **changes})


def station_config(**changes: Any) -> StationConfig:
    """:func:`station_dict` parsed (``fast=True``: over :data:`FAST`)."""
    fast = changes.pop("fast", False)
    return parse_config(fast_dict(**changes) if fast else station_dict(**changes), "test")


def write_yaml(path: Path, data: Any) -> Path:
    path.write_text(yaml.safe_dump(data, sort_keys=False), encoding="utf-8")
    return path


@pytest.fixture
def base_config_dict() -> dict[str, Any]:
    """A fresh, mutable copy of config/sim-5kN.yaml as parsed YAML."""
    return station_dict()


@pytest.fixture
def fast_config_dict() -> dict[str, Any]:
    return fast_dict()


@pytest.fixture
def fast_config() -> StationConfig:
    return parse_config(fast_dict(), "fast")


@pytest.fixture
def fast_config_file(tmp_path: Path) -> Path:
    """The fast (multi-radius) configuration as a YAML file."""
    return write_yaml(tmp_path / "fast.yaml", fast_dict())


@pytest.fixture
def one_radius_config_file(tmp_path: Path) -> Path:
    return write_yaml(tmp_path / "one-radius.yaml", fast_dict(steps=ONE_RADIUS))


@pytest.fixture
def write_config(tmp_path: Path) -> Callable[[dict[str, Any], str], Path]:
    """Write a configuration mapping as YAML into tmp_path; returns the file's path."""

    def write(data: dict[str, Any], name: str = "station.yaml") -> Path:
        return write_yaml(tmp_path / name, data)

    return write


@pytest.fixture(scope="session")
def sim_recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A completed simulated recording of the fast multi-radius plan (read-only: do not modify)."""
    out = tmp_path_factory.mktemp("sim")
    return simulate_run(parse_config(fast_dict(), "fast"), out)


@pytest.fixture(scope="session")
def sim_recording_one_radius(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A completed simulated recording with a single crank radius (read-only: do not modify)."""
    out = tmp_path_factory.mktemp("sim1r")
    return simulate_run(parse_config(fast_dict(steps=ONE_RADIUS), "fast-1r"), out, seed=7)


def coupling_tie_config() -> StationConfig:
    """The 5 kN preset (``station.discrepancy.scenarios``) with a coupling k_c = 2 k_f, b_c = 0.5 b_f of
    its true transducer and 6 steps at 3-40 Hz: a run whose model gap ties the coupling, a low-pass and
    a (negative, so unphysical) delay."""
    from station.discrepancy.scenarios import plan_steps, scenario_config

    sim = scenario_config({}, seed=COUPLING_TIE_SEED).simulation
    assert sim is not None
    t = sim.truth
    cfg = scenario_config({"coupling_compliance": {"k_c": 2.0 * t.k_f, "b_c": 0.5 * t.b_f}}, seed=COUPLING_TIE_SEED)
    d = cfg.model_dump(exclude_none=True)
    d["plan"]["steps"] = plan_steps(cfg, 6, 3.0, 40.0)
    return parse_config(d)


COUPLING_TIE_SEED = 2  # its noise seed too: a draw whose 3-40 Hz run ties coupling, low-pass and delay


@pytest.fixture(scope="session")
def coupling_tie_recording(tmp_path_factory: pytest.TempPathFactory) -> tuple[StationConfig, Path]:
    """(configuration, recording) of :func:`coupling_tie_config`, simulated once per session (read-only)."""
    cfg = coupling_tie_config()
    return cfg, simulate_run(cfg, tmp_path_factory.mktemp("tie"), seed=COUPLING_TIE_SEED)


@pytest.fixture(scope="session")
def coupling_tie(coupling_tie_recording: tuple[StationConfig, Path]) -> tuple[StationConfig, Path, Any]:
    """(configuration, recording, its model-gap analysis) of the coupling tie run: one analysis per
    worker shared by the tests that read it (mark them ``xdist_group("coupling_2kf")`` so that they
    share one worker; the analysis is frozen)."""
    from station.discrepancy import analyse_recording

    cfg, rec = coupling_tie_recording
    return cfg, rec, analyse_recording(rec)


@pytest.fixture(scope="module")
def browser() -> Iterator[Any]:
    """Debian's headless Chromium driven by Playwright, one per test module (``tests/web_support.py``;
    the page tests import it, which skips them where it says)."""
    from tests.web_support import chromium

    with chromium() as b:
        yield b

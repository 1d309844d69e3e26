"""A transducer's history page in a real headless Chromium against a real daemon: the control charts
of each parameter with their limits, the out-of-control points of a stepped sensitivity in red, the
as-found comparison and the recommended intervals (a recommendation, never a number made up)."""

from __future__ import annotations

from pathlib import Path

import pytest

from station.lab import policy
from station.lab.store import Store
from tests.history_support import TX, add_runs, add_transducer
from tests.station_support import Daemon
from tests.web_support import open_page

pytestmark = pytest.mark.slow  # a real daemon and a browser


def test_history_page_shows_the_charts_and_their_out_of_control_points(browser: object, tmp_path: Path) -> None:
    d = Daemon(tmp_path)
    d.data_dir.mkdir(parents=True)
    store = Store(d.data_dir / "station.db")
    add_transducer(store)
    ids = add_runs(store, d.data_dir, 16, step_at=10, step_u=4.0)
    policy.put_policy(store, policy.Policy(TX, {"S": 0.005}, 30.0, True), "admin")
    store.close()
    with d, open_page(browser, d.url + f"/#/transducers/{TX}") as page:
        page.wait_for_selector("#hist-trends svg", timeout=20_000)
        text = page.inner_text("#hist-trends")
        assert "check transducer" in text and "sensitivity S" in text and "natural frequency f_0" in text
        assert "EWMA (λ 0.2, limits ±3 s)" in text and "as found in run015" in text
        assert "recommended intervals (for a person to decide)" in text
        # the stepped runs are red on the S charts, and no k_f point is
        red = page.eval_on_selector_all("#hist-trends svg[aria-label='S control chart'] circle[fill='#c00'] title",
                                        "els => els.map(e => e.textContent)")
        assert red and all(t.split(":")[0] in ids[10:] for t in red)
        assert page.eval_on_selector_all("#hist-trends svg[aria-label='k_f control chart'] circle[fill='#c00']",
                                         "els => els.length") == 0

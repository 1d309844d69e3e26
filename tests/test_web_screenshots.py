"""docs/web.md shows the page's main views at 1280 and 390 CSS px: each screenshot is referenced, present,
as wide as its name says, and small (``docs/screenshots.py`` takes them from the page)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
from PIL import Image

DOCS = Path(__file__).resolve().parents[1] / "docs"
VIEWS = ("main", "run", "results", "certificate")
WIDTHS = (1280, 390)


@pytest.mark.parametrize("view", VIEWS)
@pytest.mark.parametrize("width", WIDTHS)
def test_web_md_shows_each_view_at_each_width(view: str, width: int) -> None:
    name = f"img/web-{view}-{width}.png"
    text = (DOCS / "web.md").read_text(encoding="utf-8")
    assert re.search(rf"!\[[^\]]+\]\({re.escape(name)}\)", text), f"docs/web.md does not show {name}"
    path = DOCS / name
    with Image.open(path) as im:
        assert im.format == "PNG" and im.width == width, (im.format, im.size)
        assert im.height <= 2600 and im.mode == "P", (im.size, im.mode)  # capped and palette: small files
    assert path.stat().st_size < 300_000, path.stat().st_size

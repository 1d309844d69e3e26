"""The station's shipped YAML (installed as the package ``sinecal_config``).

``config/`` of the source tree is this package: setuptools maps it to ``sinecal_config`` (see
``setup.py``), so a wheel carries the files and both ``drivers`` and ``station`` find them through
:mod:`importlib.resources` wherever the package is installed, never through paths relative to
their own source files.  It imports nothing of either.
"""

from __future__ import annotations

from importlib.resources import files
from pathlib import Path

__all__ = ["config_file"]


def config_file(name: str) -> Path:
    """Path of a shipped file, e.g. ``config_file("sim-5kN.yaml")``.

    Raises FileNotFoundError naming the file and the package folder when it is not shipped.
    """
    res = files(__name__) / name
    if not res.is_file():
        have = sorted(p.name for p in files(__name__).iterdir() if p.name.endswith(".yaml"))
        raise FileNotFoundError(f"{name!r} is not among the shipped configuration files ({', '.join(have)}) "
                                f"in {files(__name__)}")
    return Path(str(res))

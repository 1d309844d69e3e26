"""Package layout only (the metadata is in pyproject.toml): ``station`` and ``drivers`` as found,
plus ``config/`` installed as the data package ``sinecal_config`` (pyproject.toml cannot map a
folder to a package under another name while also finding packages)."""

from setuptools import find_packages, setup

setup(
    packages=[*find_packages(include=["station", "station.*", "drivers", "drivers.*"]), "sinecal_config"],
    package_dir={"sinecal_config": "config"},
)

"""sinecal: calibration-station daemon for force transducers on a sine-mechanism rig."""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("sinecal")
except PackageNotFoundError:  # running from a source tree without installation
    __version__ = "0.0.0+unknown"

"""topseg: real-time segmentation of top-view depth frames (see docs/index.md)."""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("topseg")
except PackageNotFoundError:  # running from a source tree that is not installed
    __version__ = "0.0.0+unknown"

"""alignd: camera-based alignment of a sample onto a turntable's rotation axis."""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("alignd")
except PackageNotFoundError:  # running from a source tree without installing
    __version__ = "0.0.0+src"

"""The acquisition daemon, operator tools and the ``mls`` CLI."""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("marine-mls")
except PackageNotFoundError:  # running from a source tree that is not installed
    __version__ = "0.0.0+source"

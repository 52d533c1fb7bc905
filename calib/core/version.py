"""The software name and version written into the files the project makes (LAZ headers,
result.json): ``"marine-mls <version>"``, the installed distribution's version, else
``0.0.0+source`` when running from a source tree that is not installed."""

from __future__ import annotations


def software_version() -> str:
    """``"marine-mls <version>"``."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return f"marine-mls {version('marine-mls')}"
    except PackageNotFoundError:
        return "marine-mls 0.0.0+source"

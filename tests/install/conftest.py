"""One real wheelhouse per test session (``make wheelhouse``'s build: the project's wheel and its
dependencies' through pip, whose cache makes it quick after the first time), for the slow tests
that install it offline. Under pytest-xdist those tests share the group ``wheelhouse``, so one
worker builds it once."""

from __future__ import annotations

import pytest

from tests.install.helpers import load


@pytest.fixture(scope="session")
def real_wheelhouse(tmp_path_factory):
    """``(directory, archive, manifest)`` of the wheelhouse built from this tree and .venv."""
    return load("wheelhouse").build(tmp_path_factory.mktemp("dist"))

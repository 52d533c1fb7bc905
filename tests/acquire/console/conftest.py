"""Fixtures of the console tests: the ``browser`` mark (registered here: the pyproject's marker
list is not this unit's to change), and Debian's Chromium under Playwright (never a browser
Playwright downloads)."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from tests.acquire.console.chromium import CHROMIUM, CHROMIUM_ARGS


def pytest_configure(config) -> None:
    config.addinivalue_line(
        "markers", "browser: drives Debian's Chromium with Playwright (installed by .ci/run)"
    )


@pytest.fixture(scope="module")
def chromium(tmp_path_factory):
    """A Playwright Chromium (Debian's; Playwright gives each launch a fresh temporary profile);
    the test fails without it."""
    from playwright.sync_api import sync_playwright

    assert shutil.which(CHROMIUM) or Path(CHROMIUM).exists(), f"{CHROMIUM} missing: .ci/run installs it"
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        yield browser
        browser.close()

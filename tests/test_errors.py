"""One error tree (docs/architecture.md §9): every exception class of the source packages derives
from :class:`~calib.core.errors.MlsError` through its layer's base, and the CLI reports an
``MlsError`` that escapes a command in one line on stderr, never a traceback.
"""

from __future__ import annotations

import importlib
import pkgutil
import subprocess
import sys

import pytest
from typer.testing import CliRunner

from acquire.errors import AcquireError
from calib.core.errors import CalibError, ConfigError, MlsError
from drivers.base import DriverError
from sim_devices.errors import SimDevicesError
from tests.conftest import PROJECT_ROOT

PACKAGES = ("calib", "drivers", "sim_devices", "acquire", "office", "cli")

#: Exception classes that are not errors, and why.
NOT_ERRORS = {
    # A control-flow signal, not an error: Ctrl-C, SIGTERM or SIGHUP while the demo runs; the
    # demo catches it to stop its processes and exit with the signal's status.
    "office.jobs.demo.Interrupted",
}

#: The base each package's errors derive from (ConfigError, for every configuration file, is the
#: other root every layer may use: site and scenario, vessel config, fault timeline).
LAYER_BASES = {
    "calib": (CalibError, ConfigError),
    "drivers": (DriverError,),
    "sim_devices": (SimDevicesError, ConfigError),
    "acquire": (AcquireError, ConfigError),
    "office": (AcquireError, ConfigError),  # the office's jobs are acquire's batch side
    "cli": (MlsError,),
}


def _reraise(name: str) -> None:
    raise  # pkgutil calls this inside its `except`: the import error itself, not a silent skip


def _exception_classes() -> dict[str, type[BaseException]]:
    """``module.Class`` → class, for every exception class defined at module level in the packages."""
    found = {}
    for pkg in PACKAGES:
        root = importlib.import_module(pkg)
        names = [pkg] + [m.name for m in pkgutil.walk_packages(root.__path__, f"{pkg}.", onerror=_reraise)]
        for name in names:
            module = importlib.import_module(name)
            for obj in vars(module).values():
                if isinstance(obj, type) and issubclass(obj, BaseException) and obj.__module__ == name:
                    found[f"{name}.{obj.__qualname__}"] = obj
    return found


CLASSES = _exception_classes()


def test_the_walk_finds_the_error_classes_and_the_allow_list_is_current():
    assert len(CLASSES) >= 30, sorted(CLASSES)
    assert NOT_ERRORS <= set(CLASSES), NOT_ERRORS - set(CLASSES)


@pytest.mark.parametrize("name", sorted(set(CLASSES) - NOT_ERRORS))
def test_every_error_class_derives_from_its_layer_base(name):
    cls = CLASSES[name]
    assert issubclass(cls, MlsError), f"{name} does not derive from MlsError (docs/architecture.md §9)"
    bases = LAYER_BASES[name.split(".")[0]]
    assert cls is MlsError or issubclass(cls, bases), (
        f"{name}: expected a subclass of {' or '.join(b.__name__ for b in bases)}"
    )


def test_the_layer_bases_keep_the_builtins_callers_catch():
    assert issubclass(ConfigError, ValueError) and issubclass(DriverError, ValueError)
    assert issubclass(SimDevicesError, RuntimeError)
    from acquire.log.session import LogError
    from calib.io.bundle import BundleError
    from calib.io.configfile import ConfigError as ConfigfileError

    assert ConfigfileError is ConfigError  # one ConfigError, re-exported by calib.io.configfile
    assert issubclass(BundleError, ValueError) and issubclass(LogError, RuntimeError)


@pytest.mark.parametrize(
    "error",
    [
        CalibError("bundle/points.csv:3:1: injected calibration error"),
        ConfigError("site.yaml:2:1: injected: got 1, expected 2"),
        DriverError("injected driver error"),
        AcquireError("injected acquisition error"),
        SimDevicesError("injected emulator error"),
    ],
    ids=lambda e: type(e).__name__,
)
def test_an_mls_error_escaping_a_command_is_one_line_on_stderr(monkeypatch, tmp_path, error):
    """``mls calib georef`` has no handler of its own: cli.app reports what escapes it."""
    import calib.io.georef_bundle
    from cli.app import EXIT_ERROR, app

    def fail(*args, **kwargs):
        raise error

    monkeypatch.setattr(calib.io.georef_bundle, "georeference_bundle", fail)
    res = CliRunner().invoke(app, ["calib", "georef", str(tmp_path), "--out", str(tmp_path / "out")])
    assert res.exit_code == EXIT_ERROR != 0, res.output
    assert isinstance(res.exception, SystemExit)  # typer.Exit, not the MlsError itself
    assert res.stderr.splitlines() == [f"error: {error}"]
    assert "Traceback" not in res.output


def test_the_console_entry_point_prints_no_traceback(tmp_path):
    """Through ``main()`` in a process of its own: a BundleError (no such bundle directory)."""
    res = subprocess.run(
        [
            sys.executable,
            "-m",
            "cli.app",
            "calib",
            "georef",
            str(tmp_path / "nowhere"),
            "--out",
            str(tmp_path),
        ],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=PROJECT_ROOT,
    )
    assert res.returncode == 1, res.stderr
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and "nowhere: not a directory" in lines[0], (
        lines
    )
    assert "Traceback" not in res.stderr + res.stdout

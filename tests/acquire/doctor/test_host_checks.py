"""The doctor's checks of the host, each passing and failing: the UDP receive buffer (a real file
read where /proc/sys/net/core/rmem_max would be), the clock discipline (chronyc and timedatectl
played by a runner; the real runner on this machine), the leap-second table (a real
leap-seconds.list file), the disk (real directories and modes, the free space through the
seam) and the config's ports (what mls acquire --check found)."""

from __future__ import annotations

import datetime as _dt
import os

import pytest

from acquire.doctor.access import DaemonUser, daemon_user
from acquire.doctor.clock import clock_check, parse_tracking, run_command
from acquire.doctor.configcheck import AcquireCheck, config_result, ports_result
from acquire.doctor.disk import disk_check, log_rate_bytes_per_s
from acquire.doctor.host import leap_check, udp_buffer_check
from acquire.doctor.result import (
    EXIT_NOT_READY,
    EXIT_READY,
    EXIT_WARNINGS,
    Status,
    exit_code,
    fail,
    ok,
    skip,
    warn,
)
from acquire.guidance.prechecks import DEFAULT_LOG_RATE_BYTES_S
from calib.core.gpstime import BUILTIN, NTP_EPOCH_DATE
from tests.acquire.doctor.helpers import NOBODY, config

UDP_PPS = "{type: udp, host: 127.0.0.1, port: 9}"


# -- UDP receive buffer ----------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("value", "status"),
    [(33554432, Status.OK), (67108864, Status.OK), (4194304, Status.WARN), (212992, Status.FAIL)],
)
def test_udp_buffer_against_32_mib(tmp_path, value, status):
    path = tmp_path / "rmem_max"
    path.write_text(f"{value}\n")
    r = udp_buffer_check(path)
    assert r.status == status and r.data["rmem_max_bytes"] == value
    assert (r.advice == "") == (status == Status.OK)
    if status != Status.OK:
        assert "90-mls-net.conf" in r.advice


def test_udp_buffer_unreadable_is_a_warning(tmp_path):
    r = udp_buffer_check(tmp_path / "missing")
    assert r.status == Status.WARN and "cannot be read" in r.message


def test_udp_buffer_of_this_machine_is_read():
    assert udp_buffer_check().data.get("rmem_max_bytes", 0) > 0


# -- clock discipline --------------------------------------------------------------------------

TRACKING = """Reference ID    : 50505300 (PPS)
Stratum         : 1
Ref time (UTC)  : Fri Dec 04 22:30:47 2026
System time     : {offset} seconds {side} of NTP time
Last offset     : -0.000000120 seconds
Leap status     : {leap}
"""


def runner(answers: dict[str, tuple[int, str] | None]):
    calls = []

    def run(cmd: list[str]):
        calls.append(cmd)
        return answers.get(cmd[0])

    run.calls = calls
    return run


def test_parse_tracking():
    t = parse_tracking(TRACKING.format(offset="0.000012000", side="slow", leap="Normal"))
    assert t == {"leap_status": "Normal", "reference": "PPS", "stratum": 1, "offset_s": -12e-6}


@pytest.mark.parametrize(
    ("offset", "side", "leap", "status"),
    [
        ("0.000012000", "fast", "Normal", Status.OK),
        ("0.020000000", "slow", "Normal", Status.WARN),
        ("2.500000000", "fast", "Normal", Status.FAIL),
        ("0.000012000", "fast", "Not synchronised", Status.WARN),
    ],
)
def test_chrony_tracking(offset, side, leap, status):
    r = clock_check(runner({"chronyc": (0, TRACKING.format(offset=offset, side=side, leap=leap))}), 1.0)
    assert r.status == status and r.data["source"] == "chrony" and r.data["reference"] == "PPS"


def test_chronyd_not_running_is_a_warning():
    r = clock_check(runner({"chronyc": (1, "506 Cannot talk to daemon")}))
    assert r.status == Status.WARN and "Cannot talk" in r.message and "chrony" in r.advice


@pytest.mark.parametrize(("synced", "status"), [("yes", Status.OK), ("no", Status.WARN)])
def test_timedatectl_without_chrony(synced, status):
    run = runner({"timedatectl": (0, f"NTP=yes\nNTPSynchronized={synced}\n")})
    r = clock_check(run)
    assert r.status == status and r.data["source"] == "timedatectl"
    assert [c[0] for c in run.calls] == ["chronyc", "timedatectl"]


def test_no_clock_tool_is_unknown_with_advice():
    r = clock_check(runner({}))
    assert r.status == Status.WARN and r.message.startswith("unknown") and "chrony" in r.advice


def test_the_real_runner_on_this_machine():
    assert run_command(["/nonexistent/chronyc"]) is None
    assert run_command(["true"]) == (0, "")
    assert clock_check().name == "clock"  # whatever this machine runs: a result, no exception


# -- leap-second table -------------------------------------------------------------------------


def leap_list(path, expires: _dt.date):
    """An IERS-style leap-seconds.list with the built-in steps and another expiry."""

    def ntp(d: _dt.date) -> int:
        return (d - NTP_EPOCH_DATE).days * 86400

    lines = [
        "#$ " + str(ntp(_dt.date(2026, 7, 1))),
        "#@ " + str(ntp(expires)),
        f"{ntp(_dt.date(1972, 1, 1))} 10",
    ]
    lines += [f"{ntp(day)} {n + 19}" for day, n in BUILTIN.steps]
    path.write_text("\n".join(lines) + "\n")
    return path


def test_leap_table_fresh_expiring_and_expired(tmp_path):
    none = tmp_path / "missing.list"
    assert leap_check(BUILTIN.expires - _dt.timedelta(days=200), none).status == Status.OK
    soon = leap_check(BUILTIN.expires - _dt.timedelta(days=10), none)
    assert soon.status == Status.WARN and "expires in 10 days" in soon.message and "tzdata" in soon.advice
    gone = leap_check(BUILTIN.expires + _dt.timedelta(days=1), none)
    assert gone.status == Status.WARN and "leap_table_stale" in gone.message
    assert gone.data["gps_minus_utc_s"] == 18 and "not used" in gone.data["system_list"]


def test_a_newer_system_leap_list_is_the_one_judged(tmp_path):
    newer = leap_list(tmp_path / "leap-seconds.list", BUILTIN.expires + _dt.timedelta(days=180))
    r = leap_check(BUILTIN.expires + _dt.timedelta(days=1), newer)
    assert r.status == Status.OK and r.data["expires"] == str(BUILTIN.expires + _dt.timedelta(days=180))
    older = leap_list(tmp_path / "old.list", BUILTIN.expires - _dt.timedelta(days=180))
    assert leap_check(BUILTIN.expires + _dt.timedelta(days=1), older).status == Status.WARN


# -- disk ----------------------------------------------------------------------------------------


def test_log_rate_at_the_defaults_is_the_daemons_estimate(tmp_path):
    cfg = config(tmp_path, pps=UDP_PPS)
    assert log_rate_bytes_per_s(cfg) == pytest.approx(DEFAULT_LOG_RATE_BYTES_S)


@pytest.mark.parametrize(
    ("free_gib", "hours", "status"),
    [(400, 8, Status.OK), (190, 8, Status.WARN), (100, 8, Status.FAIL), (100, 0, Status.OK)],
)
def test_disk_free_against_the_hours_planned(tmp_path, free_gib, hours, status):
    cfg = config(tmp_path, pps=UDP_PPS)
    r = disk_check(cfg, hours, daemon_user(), lambda path: free_gib * 2**30)
    assert r.status == status, r.message
    need = hours * 3600 * DEFAULT_LOG_RATE_BYTES_S
    assert r.data["need_bytes"] == pytest.approx(need, abs=1)
    assert r.data["hours_possible"] == pytest.approx(
        (free_gib - 2) * 2**30 / DEFAULT_LOG_RATE_BYTES_S / 3600, abs=0.1
    )


def test_disk_real_free_space_of_the_session_directorys_parent(tmp_path):
    r = disk_check(config(tmp_path, pps=UDP_PPS), 0.001, daemon_user())
    assert r.data["free_bytes"] > 0 and r.status != Status.FAIL, r.message


def test_disk_not_writable_by_the_daemons_user(tmp_path):
    cfg = config(tmp_path, pps=UDP_PPS)
    (tmp_path / "sessions").mkdir(mode=0o755)
    os.chmod(tmp_path / "sessions", 0o755)
    r = disk_check(cfg, 1, NOBODY, lambda path: 10**15)
    assert r.status == Status.FAIL and "may not write" in r.message and "chown mls:mls" in r.advice
    own = DaemonUser(name="mls", uid=os.stat(tmp_path / "sessions").st_uid, gids=frozenset(), installed=True)
    assert disk_check(cfg, 1, own, lambda path: 10**15).status == Status.OK


def test_disk_free_space_unknown_is_a_warning(tmp_path):
    r = disk_check(config(tmp_path, pps=UDP_PPS), 1, daemon_user(), lambda path: None)
    assert r.status == Status.WARN and "unknown" in r.message


# -- config and ports (what mls acquire --check found) -----------------------------------------

BUSY = "v.yaml: device 'profiler': cannot bind udp 0.0.0.0:3000 (Address already in use): another process ..."


def test_config_and_ports_from_acquire_check():
    good = AcquireCheck(exit_code=0, output=["guidance: 6 passes around 2 targets"])
    assert config_result(good, "v.yaml").status == Status.OK
    assert config_result(good, "v.yaml").data["notes"] == ["guidance: 6 passes around 2 targets"]
    assert ports_result(good, None).status == Status.OK
    bad = AcquireCheck(
        exit_code=2, errors=["v.yaml:3:5: devices[0].kind: got 'x'", "mls acquire: v.yaml: 1 error"]
    )
    r = config_result(bad, "v.yaml")
    assert r.status == Status.FAIL and r.data["errors"][0].startswith("v.yaml:3:5") and r.advice
    assert ports_result(bad, None).status == Status.SKIP
    busy = AcquireCheck(exit_code=1, errors=[BUSY, "mls acquire: v.yaml: 1 port(s) cannot be bound"])
    assert config_result(busy, "v.yaml").status == Status.OK
    r = ports_result(busy, None)
    assert r.status == Status.FAIL and r.data["busy"] == [BUSY] and "ss -lunp" in r.advice
    held = ports_result(busy, 4242)
    assert held.status == Status.OK and "pid 4242" in held.message


def test_exit_code_is_the_worst_status():
    assert exit_code([ok("a", "x")]) == EXIT_READY
    assert exit_code([ok("a", "x"), warn("b", "y", "z")]) == EXIT_WARNINGS
    assert exit_code([skip("s", "n"), fail("c", "x", "y"), warn("b", "y", "z")]) == EXIT_NOT_READY
    assert exit_code([skip("s", "n")]) == EXIT_READY

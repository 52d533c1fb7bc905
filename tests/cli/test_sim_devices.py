"""``mls sim devices`` as a user runs it: where each device is, a vessel config ``acquire``
validates, and a clean stop — Ctrl-C (SIGINT to the process group), SIGTERM, even ``kill -9`` of
the command — leaves no emulator process and no INS link behind; bad input exits 2 with a
located message."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from acquire.daemon.config import load_vessel_config
from calib.core.errors import MlsError
from sim_devices.runner import free_udp_port
from tests.sim_devices.harness import SHORT_PASSES
from tests.waiting import wait_until

pytestmark = [pytest.mark.integration, pytest.mark.xdist_group("sim_devices_live")]


def start_cli(run_dir: Path, *extra: str) -> subprocess.Popen:
    sets = [a for s in SHORT_PASSES for a in ("--set", s)]
    cmd = [
        sys.executable,
        "-m",
        "cli.app",
        "sim",
        "devices",
        "-s",
        "montreal",
        *sets,
        "--start",
        "2.5",
        "--duration",
        "60",
        "--run-dir",
        str(run_dir),
        "--can-port",
        str(free_udp_port()),
        *extra,
    ]
    return subprocess.Popen(
        cmd,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
        env={**os.environ, "COLUMNS": "200"},
    )


def wait_running(proc: subprocess.Popen, run_dir: Path, timeout_s: float = 60.0) -> dict:
    def emitting() -> dict | None:
        try:
            info = json.loads((run_dir / "devices.json").read_text())
        except (OSError, ValueError):  # not written yet, or being written
            return None
        return info if time.monotonic_ns() > info["window"]["start_host_ns"] + 200_000_000 else None

    def still_running() -> None:
        if proc.poll() is not None:
            out, err = proc.communicate()
            pytest.fail(f"mls sim devices ended early ({proc.returncode}):\n{out}\n{err}")

    info = wait_until(emitting, timeout_s, "devices.json", interval_s=0.05, between=still_running, fail=False)
    if not info:
        proc.kill()
        pytest.fail(f"mls sim devices wrote no devices.json within {timeout_s} s")
    return info


def alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (FileNotFoundError, ProcessLookupError):
        return False
    return state not in ("Z", "X")  # a zombie waiting for init to reap it has ended


def wait_gone(pids, timeout_s: float = 5.0) -> list[int]:
    wait_until(lambda: not any(alive(p) for p in pids), timeout_s, "the processes to end", fail=False)
    return [p for p in pids if alive(p)]


def test_devices_say_where_they_are_write_a_valid_config_and_stop_on_ctrl_c(tmp_path):
    run_dir = tmp_path / "run"
    proc = start_cli(run_dir, "--write-config", str(tmp_path / "vessel.yaml"), "--speed", "1")
    info = wait_running(proc, run_dir)
    link = run_dir / "ins"
    pty = info["devices"]["ins"]["pty"]
    assert link.is_symlink() and os.readlink(link) == pty and pty.startswith("/dev/pts/")

    def written():  # (written in place: it may be read while it is being written)
        try:
            return load_vessel_config(tmp_path / "vessel.yaml")
        except (OSError, ValueError, MlsError):
            return None

    cfg = wait_until(written, 30, "a complete vessel.yaml", interval_s=0.05)
    assert cfg.vessel == "sim-montreal" and cfg.session_dir == run_dir.resolve() / "sessions"
    assert cfg.device("ins").transport.port == str(run_dir.resolve() / "ins")
    assert cfg.device("profiler").transport.port == info["devices"]["profiler"]["address"][1]
    assert cfg.device("pps").source.udp_port == info["devices"]["pps"]["address"][1]
    assert cfg.device("pps").time_device == "ins" and cfg.device("pps").time_messages == ("ZDA",)
    assert cfg.device("marks").transport.interface == "udp_multicast"
    assert cfg.mount.lever_arm_m == (0.35, 0.85, -1.65) and cfg.site_file.name == "vessel.site.yaml"
    truth = json.loads((run_dir / "truth_clock.json").read_text())
    assert truth["speed"] == 1.0 and truth["window"]["duration_s"] == 60.0
    os.killpg(proc.pid, signal.SIGINT)  # what a terminal's Ctrl-C does: the whole process group
    out, err = proc.communicate(timeout=30)
    assert proc.returncode == 0, out + err
    out = " ".join(out.split())
    assert f"{link} → {pty}" in out
    for name in ("profiler", "pps"):
        assert f"udp 127.0.0.1:{info['devices'][name]['address'][1]}" in out
    assert "udp_multicast 239.74.163.2" in out and "emulators (stopped)" in out
    assert wait_gone(info["processes"].values()) == []
    assert not link.exists() and not link.is_symlink()
    stats = {p.stem: json.loads(p.read_text()) for p in (run_dir / "stats").glob("*.json")}
    assert {n: s["status"] for n, s in stats.items()} == dict.fromkeys(
        ("ins", "profiler", "pps", "can"), "stopped"
    )


def test_sigterm_stops_the_emulators(tmp_path):
    run_dir = tmp_path / "run"
    proc = start_cli(run_dir, "--devices", "ins,pps")
    info = wait_running(proc, run_dir)
    proc.send_signal(signal.SIGTERM)
    out, err = proc.communicate(timeout=30)
    assert proc.returncode == 0, out + err
    assert set(info["processes"]) == {"ins", "pps"}
    assert wait_gone(info["processes"].values()) == []
    assert not (run_dir / "ins").is_symlink()


def test_kill_9_of_the_command_takes_the_emulators_with_it(tmp_path):
    run_dir = tmp_path / "run"
    proc = start_cli(run_dir, "--devices", "ins,profiler")
    info = wait_running(proc, run_dir)
    proc.kill()
    proc.communicate(timeout=30)
    assert wait_gone(info["processes"].values()) == []  # PR_SET_PDEATHSIG


@pytest.mark.parametrize(
    ("faults", "args", "message"),
    [
        (
            "faults:\n  - {at_s: 1, kind: udp_loss, duration_s: 1}\n",
            (),
            "faults.yaml:2:5: faults[0]: a udp_loss fault needs 'device' (one of profiler, pps)",
        ),
        (
            "faults:\n  - {at_s: 99, kind: pps_loss}\n",
            ("--duration", "2"),
            "faults[0].at_s: got 99, expected < 2 (the run window's length in scenario seconds)",
        ),
        (None, ("--start", "pass:7"), "start 'pass:7': expected pass:N with N one of [1, 2, 3, 4, 5, 6]"),
        (
            None,
            ("--ins-rate", "3"),
            "INS rate 3 Hz: expected a rate whose period is a whole number of nanoseconds",
        ),
    ],
)
def test_bad_input_exits_2_with_a_located_message(tmp_path, faults, args, message):
    extra = list(args)
    if faults is not None:
        (tmp_path / "faults.yaml").write_text(faults)
        extra += ["--faults", str(tmp_path / "faults.yaml")]
    sets = [a for s in SHORT_PASSES for a in ("--set", s)]
    cmd = [
        sys.executable,
        "-m",
        "cli.app",
        "sim",
        "devices",
        "-s",
        "montreal",
        *sets,
        "--run-dir",
        str(tmp_path / "r"),
        *extra,
    ]
    proc = subprocess.run(
        cmd, capture_output=True, text=True, timeout=60, env={**os.environ, "COLUMNS": "300"}
    )
    assert proc.returncode == 2, proc.stdout + proc.stderr
    assert message in " ".join(proc.stdout.split())
    assert not (tmp_path / "r" / "devices.json").exists()


def test_point_rate_scale_thins_the_profiler_to_that_fraction_of_its_points(tmp_path):
    """``--point-rate-scale 0.1`` sends about a tenth of the points of a run at 1.0 over the same
    2 scenario seconds (√0.1 on the profile rate and on the points per profile), read from the
    emulator's own stats (packets, bytes) and the layout it announced in devices.json."""
    sets = [a for s in SHORT_PASSES for a in ("--set", s)]
    points, infos = {}, {}
    for scale in ("1.0", "0.1"):
        run_dir = tmp_path / f"run-{scale}"
        cmd = [
            sys.executable,
            "-m",
            "cli.app",
            "sim",
            "devices",
            "-s",
            "montreal",
            *sets,
            "--start",
            "2.5",
            "--duration",
            "2",
            "--devices",
            "profiler",
            "--point-rate-scale",
            scale,
            "--run-dir",
            str(run_dir),
        ]
        proc = subprocess.run(
            cmd, capture_output=True, text=True, timeout=180, env={**os.environ, "COLUMNS": "200"}
        )
        assert proc.returncode == 0, proc.stdout + proc.stderr
        info = json.loads((run_dir / "devices.json").read_text())["devices"]["profiler"]
        result = json.loads((run_dir / "stats" / "profiler.json").read_text())
        assert result["status"] == "finished", result
        st = result["stats"]
        assert st["packets"] == st["datagrams_sent"] > 0 and st["lost"] == 0
        # every ZFP1 datagram: 40-byte header, 6 bytes a point, CRC-32
        from_bytes = (st["bytes_sent"] - st["packets"] * (40 + 4)) / 6
        assert from_bytes == st["profiles"] * info["points_per_profile"]
        assert st["profiles"] == pytest.approx(2.0 * info["profile_rate_hz"], abs=2)  # 2 scenario seconds
        points[scale], infos[scale] = from_bytes, info
    assert infos["1.0"]["profile_rate_hz"] == 200.0 and infos["1.0"]["points_per_360"] == 5080  # the Z+F rate
    assert infos["0.1"]["profile_rate_hz"] == pytest.approx(200.0 * 0.1**0.5)
    assert points["0.1"] / points["1.0"] == pytest.approx(0.1, rel=0.1)

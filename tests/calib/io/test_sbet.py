"""calib.io.sbet: Applanix SBET / SMRMSG records, GPS week handling, trajectories."""

from __future__ import annotations

import numpy as np
import pytest

from calib.core import frames
from calib.io import sbet
from calib.io.sbet import SbetError

WEEK = 2171  # 2021-08-15 … 2021-08-21
W_S = 604_800


def random_sbet(n, rng, t0_sow=345_600.0):
    rec = np.zeros(n, sbet.SBET_DTYPE)
    for name in sbet.SBET_FIELDS:
        rec[name] = rng.normal(size=n)
    rec["time_sow"] = t0_sow + np.arange(n) * 0.005
    rec["lat_rad"] = np.radians(45.5) + rng.normal(size=n) * 1e-6
    rec["lon_rad"] = np.radians(-73.55) + rng.normal(size=n) * 1e-6
    return rec


def test_record_layout_is_17_and_10_little_endian_doubles():
    assert sbet.SBET_DTYPE.itemsize == 136 and len(sbet.SBET_FIELDS) == 17
    assert sbet.SMRMSG_DTYPE.itemsize == 80 and len(sbet.SMRMSG_FIELDS) == 10
    rec = np.zeros(1, sbet.SBET_DTYPE)
    rec["time_sow"], rec["lat_rad"], rec["platform_heading_rad"] = 1.5, 0.25, -0.5
    raw = rec.tobytes()
    assert np.frombuffer(raw, "<f8").tolist()[:10] == [1.5, 0.25, 0, 0, 0, 0, 0, 0, 0, -0.5]


def test_sbet_write_read_round_trip_is_exact(tmp_path):
    rec = random_sbet(1000, np.random.default_rng(1))
    sbet.write_sbet(tmp_path / "a.sbet", rec)
    assert (tmp_path / "a.sbet").stat().st_size == 136_000
    back = sbet.read_sbet(tmp_path / "a.sbet")
    assert back.tobytes() == rec.tobytes()


def test_smrmsg_write_read_round_trip_is_exact_and_keeps_file_order(tmp_path):
    rng = np.random.default_rng(2)
    rec = np.zeros(300, sbet.SMRMSG_DTYPE)
    for name in sbet.SMRMSG_FIELDS:
        rec[name] = rng.uniform(0.0, 3.0, 300)
    rec["time_sow"] = rng.permutation(345_600.0 + np.arange(300))  # unordered, as POSPac may
    sbet.write_smrmsg(tmp_path / "a.smrmsg", rec)
    assert (tmp_path / "a.smrmsg").stat().st_size == 24_000
    assert sbet.read_smrmsg(tmp_path / "a.smrmsg").tobytes() == rec.tobytes()


@pytest.mark.parametrize(
    ("reader", "size", "record"), [(sbet.read_sbet, 136 * 3 + 7, 136), (sbet.read_smrmsg, 80 * 2 + 1, 80)]
)
def test_size_not_a_multiple_of_the_record_is_an_error_naming_file_and_size(tmp_path, reader, size, record):
    path = tmp_path / "cut.out"
    path.write_bytes(b"\0" * size)
    with pytest.raises(
        SbetError,
        match=rf"cut\.out: size {size} bytes is not a multiple of "
        rf"the .* record size \({record} bytes",
    ):
        reader(path)


def test_bad_records_are_named(tmp_path):
    rec = random_sbet(5, np.random.default_rng(3))
    rec["roll_rad"][3] = np.nan
    sbet.write_sbet(tmp_path / "nan.sbet", rec)
    with pytest.raises(SbetError, match=r"nan\.sbet: record 3 \(byte 408\): roll_rad is nan"):
        sbet.read_sbet(tmp_path / "nan.sbet")
    rec = random_sbet(5, np.random.default_rng(3))
    rec["time_sow"][2] = 1e7
    sbet.write_sbet(tmp_path / "t.sbet", rec)
    with pytest.raises(SbetError, match="record 2: time 10000000.0 s is not a GPS second of the"):
        sbet.read_sbet(tmp_path / "t.sbet")
    rec = random_sbet(5, np.random.default_rng(3))
    rec["lat_rad"][1] = 2.0
    sbet.write_sbet(tmp_path / "lat.sbet", rec)
    with pytest.raises(SbetError, match="record 1: latitude 2.0 rad, longitude .* rad are out of"):
        sbet.read_sbet(tmp_path / "lat.sbet")
    with pytest.raises(SbetError, match="missing.sbet: file not found"):
        sbet.read_sbet(tmp_path / "missing.sbet")
    rec = np.zeros(2, sbet.SMRMSG_DTYPE)
    rec["sigma_pitch_arcmin"][1] = -1.0
    sbet.write_smrmsg(tmp_path / "neg.smrmsg", rec)
    with pytest.raises(SbetError, match=r"record 1: sigma_pitch_arcmin is -1\.0, expected ≥ 0"):
        sbet.read_smrmsg(tmp_path / "neg.smrmsg")


def test_trajectory_round_trip_through_sbet_and_smrmsg(tmp_path, wave_trajectory):
    traj = wave_trajectory(duration_s=3.0, rate_hz=200.0, sigmas=True, t0=WEEK * W_S + 345_600.0)
    rec, week = sbet.sbet_records(traj, wander_rad=np.radians(12.5))
    assert week == WEEK
    sbet.write_sbet(tmp_path / "t.sbet", rec)
    sbet.write_smrmsg(tmp_path / "t.smrmsg", sbet.smrmsg_records(traj)[::-1])  # reversed order
    back = sbet.read_sbet_trajectory(
        tmp_path / "t.sbet", traj.frame, week=WEEK, smrmsg_path=tmp_path / "t.smrmsg"
    )
    np.testing.assert_array_equal(back.t_gps_s, traj.t_gps_s)
    assert np.abs(back.p_lgf_m - traj.p_lgf_m).max() < 1e-6
    assert np.abs(frames.wrap_pi(back.rpy_rad - traj.rpy_rad)).max() < 1e-14
    np.testing.assert_allclose(back.sigma_p_m, traj.sigma_p_m, rtol=1e-14)
    np.testing.assert_allclose(back.sigma_rpy_rad, traj.sigma_rpy_rad, rtol=1e-14)
    # the file holds the platform heading; heading = platform heading − wander angle
    raw = sbet.read_sbet(tmp_path / "t.sbet")
    np.testing.assert_allclose(
        frames.wrap_pi(raw["platform_heading_rad"] - raw["wander_rad"] - traj.rpy_rad[:, 2]), 0.0, atol=1e-14
    )
    assert np.all(raw["wander_rad"] == np.radians(12.5))


def test_smrmsg_is_sorted_and_interpolated_to_sbet_epochs(tmp_path, wave_trajectory):
    traj = wave_trajectory(duration_s=4.0, rate_hz=100.0, t0=WEEK * W_S + 1000.0)
    rec, _ = sbet.sbet_records(traj)
    sbet.write_sbet(tmp_path / "t.sbet", rec)
    acc = np.zeros(5, sbet.SMRMSG_DTYPE)  # 1 Hz, out of order
    acc["time_sow"] = [1003.0, 1000.0, 1002.0, 1001.0, 1004.0]
    acc["sigma_north_m"] = [0.05, 0.02, 0.04, 0.03, 0.06]
    acc["sigma_heading_arcmin"] = [4.0, 1.0, 3.0, 2.0, 5.0]
    sbet.write_smrmsg(tmp_path / "t.smrmsg", acc)
    back = sbet.read_sbet_trajectory(tmp_path / "t.sbet", week=WEEK, smrmsg_path=tmp_path / "t.smrmsg")
    s = back.t_gps_s - (WEEK * W_S + 1000.0)
    np.testing.assert_allclose(back.sigma_p_m[:, 0], 0.02 + 0.01 * s, atol=1e-12)
    arcmin = np.pi / (180 * 60)
    np.testing.assert_allclose(back.sigma_rpy_rad[:, 2], (1.0 + s) * arcmin, rtol=1e-12)
    # an SMRMSG that stops 2 s early does not cover the SBET
    sbet.write_smrmsg(tmp_path / "short.smrmsg", acc[[1, 3, 2]])  # 1000 … 1002 s
    with pytest.raises(
        SbetError,
        match=r"short\.smrmsg: covers .* SBET epochs are more than 1 s "
        r"outside it",
    ):
        sbet.read_sbet_trajectory(tmp_path / "t.sbet", week=WEEK, smrmsg_path=tmp_path / "short.smrmsg")


def test_crossing_the_end_of_the_week_keeps_time_continuous(tmp_path, wave_trajectory):
    t0 = WEEK * W_S + W_S - 1.0  # one second before the week ends
    traj = wave_trajectory(duration_s=2.0, rate_hz=50.0, t0=t0)
    rec, week = sbet.sbet_records(traj)
    assert rec["time_sow"][0] == W_S - 1.0 and rec["time_sow"][-1] == pytest.approx(1.0)
    sbet.write_sbet(tmp_path / "wrap.sbet", rec)
    back = sbet.read_sbet_trajectory(tmp_path / "wrap.sbet", traj.frame, week=week)
    np.testing.assert_array_equal(back.t_gps_s, traj.t_gps_s)


@pytest.mark.parametrize(
    ("first_sow", "near", "week"),
    [
        (345_600.0, WEEK * W_S + 345_700.0, WEEK),  # same week
        (604_000.0, (WEEK + 1) * W_S + 100.0, WEEK),  # file starts in the week before the points
        (100.0, WEEK * W_S + 604_700.0, WEEK + 1),  # points at the end of the week before the file
    ],
)
def test_infer_week(first_sow, near, week):
    assert sbet.infer_week(first_sow, near) == week


def test_week_must_be_given_or_inferable(tmp_path, wave_trajectory):
    traj = wave_trajectory(duration_s=1.0, t0=WEEK * W_S + 604_000.0)
    sbet.write_sbet(tmp_path / "t.sbet", sbet.sbet_records(traj)[0])
    with pytest.raises(SbetError, match="seconds of the GPS week; give the week"):
        sbet.read_sbet_trajectory(tmp_path / "t.sbet")
    back = sbet.read_sbet_trajectory(tmp_path / "t.sbet", near_gps_s=(WEEK + 1) * W_S + 10.0)
    np.testing.assert_array_equal(back.t_gps_s, traj.t_gps_s)


def test_non_increasing_sbet_times_name_the_file(tmp_path, wave_trajectory):
    rec, week = sbet.sbet_records(wave_trajectory(duration_s=1.0, t0=WEEK * W_S + 10.0))
    rec["time_sow"][7] = rec["time_sow"][6]
    sbet.write_sbet(tmp_path / "dup.sbet", rec)
    with pytest.raises(SbetError, match=r"dup\.sbet: times must increase strictly; epoch 7"):
        sbet.read_sbet_trajectory(tmp_path / "dup.sbet", week=week)
    sbet.write_sbet(tmp_path / "one.sbet", rec[:1])
    with pytest.raises(SbetError, match="1 records, a trajectory needs at least 2"):
        sbet.read_sbet_trajectory(tmp_path / "one.sbet", week=week)

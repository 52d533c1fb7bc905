"""Calibration history (calib.assess.history): result validation, bundle fingerprints, the SQLite store
and the test for a moved mount."""

from __future__ import annotations

import copy
import datetime as dt
import json
import sqlite3
from contextlib import closing

import numpy as np
import pytest

from calib.assess.history import (
    HistoryError,
    ResultFormatError,
    bundle_fingerprint,
    compare,
    default_db_path,
    get_result,
    list_results,
    load_result,
    record_result,
    records_of_bundle,
    validate_result,
)
from calib.core import frames
from calib.core.georef import Mount
from calib.io.site import Site

ANGLES = ("roll", "pitch", "yaw")


def make_result(boresight, sigma_scaled, sigma_realistic=None, n_points=1300, version="0.1.0"):
    """A result.json as docs/architecture.md §4 describes it (degrees)."""
    b = dict(zip(ANGLES, map(float, boresight)))
    s = dict(zip(ANGLES, map(float, sigma_scaled)))
    return {
        "boresight_deg": b,
        "sigma_deg": {k: v / 1.1 for k, v in s.items()},
        "sigma_scaled_deg": s,
        "sigma_realistic_deg": None
        if sigma_realistic is None
        else dict(zip(ANGLES, map(float, sigma_realistic))),
        "correlation": [[1.0, -0.0034, 0.0], [-0.0034, 1.0, 0.003], [0.0, 0.003, 1.0]],
        "sigma0_squared": 1.21,
        "chi2_test": {"df": 1297, "lower": 1198.0, "upper": 1399.0, "passed": True},
        "iterations": 4,
        "converged": True,
        "planes": [],
        "passes": [],
        "n_points": n_points,
        "n_outliers": 0,
        "runtime_s": 1.5,
        "apriori_deg": {"roll": 0.0, "pitch": 0.0, "yaw": 0.0},
        "software_version": version,
    }


def make_bundle(path, gps_s=None, vessel="survey-1", points="1,0.0,15.0,90.0,0.9\n"):
    path.mkdir(parents=True)
    Site(mount=Mount(), targets=(), vessel=vessel).dump(path / "site.yaml")
    gps_s = gps_s if gps_s is not None else 1_246_665_618.0
    (path / "trajectory.csv").write_text(
        "gps_time,lat_deg,lon_deg,height_m,roll_deg,pitch_deg,heading_deg\n"
        f"{gps_s:.3f},45.5,-73.55,0.0,0.1,0.2,90.0\n{gps_s + 1:.3f},45.5,-73.55,0.0,0.1,0.2,90.0\n"
    )
    (path / "points.csv").write_text("pass_id,gps_time,range_m,scan_angle_deg,intensity\n" + points)
    return path


@pytest.fixture
def db(tmp_path):
    return tmp_path / "history.sqlite"


# -- result.json validation -----------------------------------------------------------------


def test_a_complete_result_validates_and_lists_are_accepted_for_angles():
    r = make_result([0.208, 1.245, 0.149], [0.001, 0.0118, 0.0008])
    v = validate_result(r)
    assert v["boresight_deg"] == {"roll": 0.208, "pitch": 1.245, "yaw": 0.149}
    assert v["sigma_realistic_deg"] is None
    r["sigma_realistic_deg"] = [0.03, 0.05, 0.04]  # roll, pitch, yaw order
    assert validate_result(r)["sigma_realistic_deg"] == {"roll": 0.03, "pitch": 0.05, "yaw": 0.04}


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda r: r.pop("boresight_deg"), "required field 'boresight_deg' is missing"),
        (lambda r: r.pop("sigma_scaled_deg"), "required field 'sigma_scaled_deg' is missing"),
        (lambda r: r.pop("software_version"), "required field 'software_version' is missing"),
        (lambda r: r["boresight_deg"].pop("pitch"), "boresight_deg.pitch is missing"),
        (
            lambda r: r["boresight_deg"].update(yaw="0.1"),
            "boresight_deg.yaw is '0.1', expected a finite number",
        ),
        (lambda r: r["sigma_deg"].update(roll=0.0), "sigma_deg.roll is 0.0, expected a positive sigma"),
        (
            lambda r: r.update(sigma_realistic_deg={"roll": 1, "pitch": -1, "yaw": 1}),
            "sigma_realistic_deg.pitch is -1, expected a positive sigma",
        ),
        (lambda r: r.update(correlation=[[1, 0], [0, 1]]), "correlation is [[1, 0], [0, 1]], expected a 3×3"),
        (lambda r: r["correlation"][0].__setitem__(1, 0.5), "correlation is not symmetric"),
        (lambda r: r["correlation"][2].__setitem__(2, 0.9), "correlation[2][2] is 0.9, expected 1"),
        (lambda r: r.update(sigma0_squared=-1.0), "sigma0_squared is -1.0, expected a finite number ≥ 0"),
        (lambda r: r.update(n_points=12.5), "n_points is 12.5, expected an integer ≥ 0"),
        (lambda r: r.update(boresight_deg="0,0,0"), "boresight_deg is '0,0,0', expected an object"),
    ],
)
def test_validation_names_the_bad_field(edit, message):
    r = make_result([0.2, 1.2, 0.1], [0.001, 0.01, 0.001])
    edit(r)
    with pytest.raises(ResultFormatError) as e:
        validate_result(r, "run1/result.json")
    assert str(e.value).startswith("run1/result.json: ")
    assert message in str(e.value)


def test_load_result_reports_json_errors_with_position(tmp_path):
    p = tmp_path / "result.json"
    p.write_text('{"boresight_deg": {"roll": 1,}')
    with pytest.raises(ResultFormatError, match=r"result.json:1:\d+: not valid JSON"):
        load_result(p)
    p.write_text(json.dumps(make_result([0.2, 1.2, 0.1], [0.001, 0.01, 0.001])))
    assert load_result(tmp_path)["n_points"] == 1300  # a directory means its result.json
    with pytest.raises(ResultFormatError, match="file not found"):
        load_result(tmp_path / "nothing.json")


# -- bundle fingerprint ---------------------------------------------------------------------


def test_fingerprint_covers_inputs_only(tmp_path):
    a = make_bundle(tmp_path / "a")
    b = make_bundle(tmp_path / "b")
    fa = bundle_fingerprint(a)
    assert len(fa) == 64 and fa == bundle_fingerprint(b)  # same inputs, another directory
    (a / "truth.json").write_text('{"boresight_deg": [1, 2, 3]}')
    (a / "result.json").write_text("{}")
    assert bundle_fingerprint(a) == fa  # truth and outputs are not inputs
    c = make_bundle(tmp_path / "c", points="1,0.0,15.0,90.0,0.8\n")
    assert bundle_fingerprint(c) != fa
    (b / "trajectory.csv").unlink()
    with pytest.raises(HistoryError, match="no trajectory.csv or trajectory.sbet"):
        bundle_fingerprint(b)
    with pytest.raises(HistoryError, match="not a bundle directory"):
        bundle_fingerprint(tmp_path / "nowhere")


# -- the database ---------------------------------------------------------------------------


def test_record_list_and_reruns(tmp_path, db):
    july = frames.gps_ns_to_seconds(frames.utc_to_gps_ns(dt.datetime(2019, 7, 9, 14, 30, tzinfo=dt.UTC)))
    october = frames.gps_ns_to_seconds(frames.utc_to_gps_ns(dt.datetime(2019, 10, 2, 9, 0, tzinfo=dt.UTC)))
    b_oct = make_bundle(tmp_path / "oct", gps_s=october, points="2,0,15,90,0.9\n")
    b_jul = make_bundle(tmp_path / "jul", gps_s=july)
    r_oct = make_result([0.341, 0.805, 0.032], [0.0014, 0.0110, 0.0006])
    r_jul = make_result([0.208, 1.245, 0.149], [0.0010, 0.0118, 0.0008])
    id_oct = record_result(r_oct, b_oct, "survey-1", "bracket-A", db=db)
    id_jul = record_result(r_jul, b_jul, None, "bracket-A", db=db)  # vessel from site.yaml
    other = record_result(r_jul, b_jul, "survey-2", "pole", db=db)
    assert len({id_oct, id_jul, other}) == 3
    recs = list_results(db=db)
    assert [r.id for r in recs] == [id_jul, other, id_oct]  # oldest survey first
    jul = get_result(id_jul, db=db)
    assert jul.vessel == "survey-1" and jul.mount_id == "bracket-A"
    assert jul.survey_utc == "2019-07-09T14:30:00Z" and jul.date_utc.startswith("2019-07-09")
    assert jul.boresight_deg == {"roll": 0.208, "pitch": 1.245, "yaw": 0.149}
    assert jul.result == r_jul and jul.n_points == 1300 and jul.sigma0_squared == 1.21
    assert jul.bundle_fingerprint == bundle_fingerprint(b_jul)
    with closing(sqlite3.connect(db)) as con:  # plain columns for anyone reading the database directly
        row = con.execute(
            "SELECT pitch_deg, sigma_pitch_deg, sigma_scaled_pitch_deg, "
            "sigma_realistic_pitch_deg, correlation_json FROM calibrations "
            "WHERE id = ?",
            (id_jul,),
        ).fetchone()
    assert row[:4] == (1.245, 0.0118 / 1.1, 0.0118, None)
    assert json.loads(row[4])[0][1] == -0.0034
    assert [r.id for r in list_results("survey-2", db=db)] == [other]
    assert [r.id for r in list_results(db=db, mount_id="bracket-A")] == [id_jul, id_oct]
    # the same result of the same bundle is recognised; a new result of it is a new row
    assert record_result(r_jul, b_jul, "survey-1", "bracket-A", db=db) == id_jul
    r_new = make_result([0.209, 1.244, 0.149], [0.0010, 0.0118, 0.0008], version="0.2.0")
    id_new = record_result(r_new, b_jul, "survey-1", "bracket-A", db=db)
    assert id_new not in (id_jul, other, id_oct)
    assert [r.id for r in records_of_bundle(bundle_fingerprint(b_jul), db=db)] == [id_jul, other, id_new]
    with pytest.raises(HistoryError, match="no calibration #999"):
        get_result(999, db=db)


def test_record_rejects_bad_input(tmp_path, db):
    b = make_bundle(tmp_path / "b")
    r = make_result([0.2, 1.2, 0.1], [0.001, 0.01, 0.001])
    with pytest.raises(HistoryError, match="mount id ''"):
        record_result(r, b, "v", "", db=db)
    bad = copy.deepcopy(r)
    del bad["correlation"]
    with pytest.raises(ResultFormatError, match="'correlation' is missing"):
        record_result(bad, b, "v", "m", db=db)
    assert list_results(db=db) == []


def test_database_location_and_bad_databases(tmp_path, monkeypatch):
    monkeypatch.delenv("MLS_HISTORY_DB", raising=False)
    monkeypatch.setenv("XDG_DATA_HOME", str(tmp_path / "xdg"))
    assert default_db_path() == tmp_path / "xdg" / "marine-mls" / "history.sqlite"
    monkeypatch.setenv("MLS_HISTORY_DB", str(tmp_path / "env.sqlite"))
    assert default_db_path() == tmp_path / "env.sqlite"
    assert list_results() == [] and records_of_bundle("0" * 64) == []
    assert not (tmp_path / "env.sqlite").exists()  # reading creates no database
    with pytest.raises(HistoryError, match="no calibration #1: no history database at"):
        get_result(1)
    b = make_bundle(tmp_path / "b")
    rid = record_result(make_result([0.2, 1.2, 0.1], [0.001, 0.01, 0.001]), b, "v", "m")
    assert (tmp_path / "env.sqlite").exists() and get_result(rid).vessel == "v"
    (tmp_path / "junk.sqlite").write_bytes(b"this is not a database" * 100)
    with pytest.raises(HistoryError, match="junk.sqlite: not a usable history database"):
        list_results(db=tmp_path / "junk.sqlite")
    with closing(sqlite3.connect(tmp_path / "new.sqlite")) as con:  # (a PRAGMA needs no commit)
        con.execute("PRAGMA user_version = 99")
    with pytest.raises(HistoryError, match="schema version 99 is newer"):
        list_results(db=tmp_path / "new.sqlite")


# -- comparing calibrations -----------------------------------------------------------------


def test_a_mount_change_is_flagged_in_words():
    a = make_result([0.208, 1.245, 0.149], [0.001, 0.012, 0.001], sigma_realistic=[0.011, 0.0155563, 0.011])
    b = make_result([0.210, 1.685, 0.151], [0.001, 0.012, 0.001], sigma_realistic=[0.011, 0.0155563, 0.011])
    c = compare(a, b)
    assert c.changed and c.sigma_kind_a == c.sigma_kind_b == "realistic"
    p = c.angle("pitch")
    assert p.difference_deg == pytest.approx(0.44)
    assert p.sigma_combined_deg == pytest.approx(0.022, rel=1e-5)
    assert p.n_sigma == pytest.approx(20.0, rel=1e-4) and p.changed
    assert not c.angle("roll").changed and not c.angle("yaw").changed
    assert c.message == (
        "pitch changed by 0.440°, 20σ: the mount has moved; recalibrate after each re-installation"
    )


def test_two_results_within_their_sigma_are_not_flagged():
    a = make_result([0.208, 1.245, 0.149], [0.001, 0.012, 0.001], sigma_realistic=[0.01, 0.02, 0.01])
    b = make_result([0.2193, 1.260, 0.140], [0.001, 0.012, 0.001], sigma_realistic=[0.01, 0.02, 0.01])
    c = compare(a, b)
    assert not c.changed
    assert c.angle("roll").n_sigma == pytest.approx(0.0113 / np.hypot(0.01, 0.01))  # 0.8σ
    assert c.message == "no angle changed beyond 3σ (largest: roll 0.8σ)"


def test_scaled_sigma_is_used_without_a_realistic_one_and_the_verdict_warns():
    """The thesis's two Montreal calibrations (Table 4.5, canonical signs) with only formal-type
    σ: every angle differs by dozens of σ."""
    july = make_result([0.208, 1.245, 0.149], [0.0010, 0.0118, 0.0008])
    october = make_result([0.341, 0.805, 0.032], [0.0014, 0.0110, 0.0006])
    c = compare(july, october, a_label="July", b_label="October")
    assert c.sigma_kind_a == c.sigma_kind_b == "scaled"
    assert [a.changed for a in c.angles] == [True, True, True]
    assert c.angle("yaw").n_sigma == pytest.approx(0.117 / 0.001, rel=1e-6)
    assert c.message.startswith(
        "roll changed by 0.133°, 77σ, pitch changed by -0.440°, 27σ, "
        "yaw changed by -0.117°, 117σ: the mount has moved"
    )
    assert "scaled σ (no realistic σ in July and October) is optimistic" in c.message
    # with realistic σ in one of them, each side uses its own best σ
    october["sigma_realistic_deg"] = {"roll": 0.05, "pitch": 0.05, "yaw": 0.05}
    c2 = compare(july, october)
    assert (c2.sigma_kind_a, c2.sigma_kind_b) == ("scaled", "realistic")
    assert c2.angle("roll").sigma_combined_deg == pytest.approx(np.hypot(0.0010, 0.05))
    with pytest.raises(ValueError, match="k_sigma"):
        compare(july, october, k_sigma=0)


def test_false_alarms_and_detections_over_many_simulated_pairs():
    """Pairs of results drawn around one truth with their realistic σ are flagged at the 3σ rate
    (three angles: 1 − (1 − 0.0027)³ ≈ 0.8 %); pairs whose truth differs by 6 combined σ in one
    angle are flagged almost always (the |Δ| > 3σ probability for a 6σ shift is 99.9 %)."""
    rng = np.random.default_rng(20)
    sig = np.array([0.01, 0.03, 0.015])
    truth = np.array([0.2, 1.2, 0.15])
    same = moved = 0
    n = 2000
    shift = np.array([0.0, 6.0 * np.hypot(sig[1], sig[1]), 0.0])
    for _ in range(n):
        a = make_result(truth + rng.normal(0, sig), sig / 5, sigma_realistic=sig)
        b = make_result(truth + rng.normal(0, sig), sig / 5, sigma_realistic=sig)
        m = make_result(truth + shift + rng.normal(0, sig), sig / 5, sigma_realistic=sig)
        same += compare(a, b).changed
        moved += compare(a, m).angle("pitch").changed
    assert same / n < 0.02
    assert moved / n > 0.99


def test_comparing_history_records_knows_a_rerun_of_the_same_bundle(tmp_path, db):
    b = make_bundle(tmp_path / "b")
    r1 = make_result([0.2, 1.2, 0.1], [0.001, 0.01, 0.001])
    r2 = make_result([0.2001, 1.2, 0.1], [0.001, 0.01, 0.001], version="0.2.0")
    i1 = record_result(r1, b, "v", "m", db=db)
    i2 = record_result(r2, b, "v", "m", db=db)
    c = compare(get_result(i1, db=db), get_result(i2, db=db))
    assert c.same_bundle is True and not c.changed
    assert c.a_label == f"#{i1} (v/m, 2019-07-09)"
    assert c.message.endswith("; both results come from the same bundle")
    assert compare(r1, r2).same_bundle is None


# =============================================================================================
# Real simulated bundles and calibration results (added with calib.assess.comparison)
# =============================================================================================
# Calibrations of bundles simulated with the same true mount are not flagged; a calibration
# after the mount moved is. The bundles are the shipped `tower` scenario (Gauss–Markov POS
# errors, 2 cm / 20 s and 0.012° / 10 s) written to disk, calibrated by the pipeline
# (calib.boresight.pipeline.calibrate_bundle) and recorded in a history database, so the fingerprints,
# the realistic σ (≈ 0.05°, 0.16°, 0.06° here) and the comparison are the real ones.

JULY_DEG = "[0.208, 1.245, 0.149]"  # the thesis's Montreal mount (canonical signs)
#: after a re-installation: roll +0.5°, pitch −0.8°, yaw +0.5° (≈ 7σ, 3.6σ, 6σ of the combined
#: realistic σ). The thesis's own July→October change (0.13°, −0.44°, −0.12°) is below 3σ of
#: this scenario's realistic σ and would not be flagged from one calibration each.
MOVED_DEG = "[0.708, 0.445, 0.649]"


@pytest.fixture(scope="module")
def simulated_history(tmp_path_factory):
    from calib.boresight.pipeline import calibrate_bundle
    from calib.sim.simulate import simulate

    d = tmp_path_factory.mktemp("history")
    db = d / "history.sqlite"
    ids, docs = {}, {}
    for label, truth, seed in (
        ("same-1", JULY_DEG, 21),
        ("same-2", JULY_DEG, 22),
        ("same-3", JULY_DEG, 23),
        ("moved", MOVED_DEG, 24),
    ):
        simulate("tower", seed, overrides=[f"truth.boresight_deg={truth}"]).write(d / label)
        docs[label] = calibrate_bundle(d / label).doc
        ids[label] = record_result(docs[label], d / label, None, "bracket-A", db=db)
    return db, ids, docs


def test_calibrations_of_the_same_simulated_mount_are_not_flagged(simulated_history):
    db, ids, docs = simulated_history
    recs = {k: get_result(i, db=db) for k, i in ids.items()}
    assert len({r.bundle_fingerprint for r in recs.values()}) == 4
    assert [r.vessel for r in list_results(db=db)] == ["sim-montreal"] * 4  # from site.yaml
    truth = dict(zip(ANGLES, (0.208, 1.245, 0.149)))
    for label in ("same-1", "same-2", "same-3"):  # each estimate within 3 realistic σ
        for a in ANGLES:
            sig = docs[label]["sigma_realistic_deg"][a]
            assert abs(docs[label]["boresight_deg"][a] - truth[a]) < 3 * sig
    for a, b in (("same-1", "same-2"), ("same-1", "same-3"), ("same-2", "same-3")):
        c = compare(recs[a], recs[b])
        assert not c.changed, c.message
        assert (c.sigma_kind_a, c.sigma_kind_b, c.same_bundle) == ("realistic", "realistic", False)
        assert c.message.startswith("no angle changed beyond 3σ")


def test_a_simulated_mount_change_is_flagged(simulated_history):
    from typer.testing import CliRunner

    from cli.app import app

    db, ids, _ = simulated_history
    recs = {k: get_result(i, db=db) for k, i in ids.items()}
    for label in ("same-1", "same-2", "same-3"):
        c = compare(recs[label], recs["moved"])
        assert c.changed and c.message.endswith("the mount has moved; recalibrate after each re-installation")
        assert c.angle("roll").changed and c.angle("yaw").changed
        for angle, delta in (("roll", 0.5), ("pitch", -0.8), ("yaw", 0.5)):
            ch = c.angle(angle)
            assert ch.difference_deg == pytest.approx(delta, abs=3 * ch.sigma_combined_deg)
    r = CliRunner().invoke(
        app,
        ["calib", "compare", str(ids["same-1"]), str(ids["moved"]), "--db", str(db)],
        env={"COLUMNS": "200"},
    )
    assert r.exit_code == 0, r.output
    assert "CHANGED" in r.output and "the mount has moved" in r.output

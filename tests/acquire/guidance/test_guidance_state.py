"""The guidance state: the state machine on constructed tracks (rejection, resail, abort); and a
whole simulated survey: six passes accepted, live hits close to the truth, the predicted σ (the
GLS estimator's, the calibration's default) never rising and agreeing with the adjustment's own,
and the guidance consumer publishing it."""

from __future__ import annotations

import asyncio
import math

import numpy as np
import pytest

from acquire.daemon.consumers import ChecklistPublisher, Tap
from acquire.guidance.acceptance import AcceptanceTolerances
from acquire.guidance.consumer import GuidanceConsumer
from acquire.guidance.state import SCHEMA, Guidance, sigma_rises
from calib.design.passpredict import ObservationModel, SigmaPrediction, predict_sigma, weakest_angle
from calib.sim.scenariofile import load_scenario
from calib.survey.passplan import PlannedPass, plan_site
from drivers.hydrins.nav import NavRecord, status_words
from drivers.zf.codec import Profile
from tests.acquire.guidance_sim import adjust_simulated, nav_records, profiles, run_survey
from tests.waiting import wait_until_async

# -- the state machine on constructed tracks ------------------------------------------------------


class Sailor:
    """Sails constructed tracks along a plan's lines: INS records at 20 Hz and no-return
    profiles at 50 Hz (gaps only where asked)."""

    def __init__(self, g: Guidance, t0: float = 1.3e9):
        self.g, self.t = g, t0

    def sail(
        self,
        line: PlannedPass,
        along_from: float,
        along_to: float,
        xte=0.0,
        heading_offset_deg=0.0,
        speed=2.0,
        profiles=True,
        then_s=30.0,
    ) -> None:
        """Sail from ``along_from`` to ``along_to``, then wait ``then_s`` (no records)."""
        h = line.heading_rad
        u = np.array([math.cos(h), math.sin(h), 0.0])
        s = np.array([-math.sin(h), math.cos(h), 0.0])
        n = int((along_to - along_from) / speed * 20)
        frame = self.g.frame
        alg, sys_ = status_words(
            navigation=True,
            fine_alignment=True,
            gps_valid=True,
            gps_received=True,
            utc_detected=True,
            pps_detected=True,
        )
        for k in range(n):
            t = self.t + k / 20
            a = along_from + speed * k / 20
            x = xte(a) if callable(xte) else xte
            p = line.start_lgf_m + a * u + x * s
            lat, lon, hh = frame.to_geodetic(p[None])
            v = speed * u
            self.g.on_nav(
                NavRecord(
                    "nmea",
                    gps_ns=int(round(t * 1e9)),
                    lat_deg=float(lat[0]),
                    lon_deg=float(lon[0]),
                    height_m=float(hh[0]),
                    roll_rad=0.0,
                    pitch_rad=0.0,
                    heading_rad=(h + math.radians(heading_offset_deg)) % (2 * math.pi),
                    v_north_m_s=v[0],
                    v_east_m_s=v[1],
                    algorithm_status=alg,
                    system_status=sys_,
                )
            )
            if profiles:
                for j in range(k * 5 // 2, (k + 1) * 5 // 2):
                    tp = self.t + j / 50
                    self.g.on_profile(
                        Profile(
                            j,
                            np.array([int(round(tp * 1e9))]),
                            np.array([0.1]),
                            np.array([np.nan]),
                            np.zeros(1, np.uint16),
                            True,
                            True,
                            1,
                            1,
                        )
                    )
            if k % 4 == 3:
                self.g.update(predict=False)
        self.t += n / 20 + then_s
        self.g.update(predict=False)


@pytest.fixture(scope="module")
def montreal():
    site = load_scenario("montreal").site()
    return site, plan_site(site)


def _sailed(montreal) -> tuple[Guidance, Sailor]:
    """A guidance that asks for no target points (the sailor's profiles have no returns)."""
    g = Guidance(*montreal, tolerances=AcceptanceTolerances(min_points_per_target=0))
    g.on_clock("LOCKED")
    return g, Sailor(g)


def test_reject_then_resail_then_accept(montreal):
    g, sailor = _sailed(montreal)
    line = montreal[1].by_id(2)
    assert g.active_pass_id() == 1  # nothing sailed: the first of the plan
    g.select_pass(2)
    assert g.active_pass_id() == 2
    mid = 0.5 * (line.capture_start_m + line.capture_end_m)
    sailor.sail(line, -20.0, line.length_m, xte=lambda a: 2.6 if a > mid else 0.4)
    rec = g.passes[2]
    assert rec.status == "rejected" and len(rec.verdicts) == 1
    assert rec.verdicts[0].reasons[0].startswith("cross-track error up to 2.60 m")
    msg = g.message()
    assert msg["schema"] == SCHEMA
    p2 = next(p for p in msg["passes"] if p["id"] == 2)
    assert p2["status"] == "rejected" and p2["attempts"] == 1
    assert p2["reasons"][0].startswith("cross-track error up to 2.60 m")
    sailor.sail(line, -20.0, line.length_m, xte=0.5, heading_offset_deg=-3.0)
    assert rec.status == "accepted" and len(rec.verdicts) == 2
    v = rec.verdicts[-1]
    assert v.attempt == 2 and v.stats["max_xte_m"] == pytest.approx(0.5, abs=1e-3)
    assert v.stats["max_heading_error_deg"] == pytest.approx(3.0, abs=1e-6)
    assert v.stats["n_profiles"] == pytest.approx(50 * (line.capture_end_m - line.capture_start_m) / 2, abs=3)
    assert g.accepted_ids == [2]
    assert g.active_pass_id() == 1


def test_turning_away_ends_the_capture_early_and_clock_holdover_rejects(montreal):
    g, sailor = _sailed(montreal)
    line = montreal[1].by_id(1)
    mid = 0.5 * (line.capture_start_m + line.capture_end_m)
    sailor.sail(line, -10.0, mid, then_s=0.0)
    assert g.passes[1].status == "capturing"
    assert g.message()["active"]["state"] == "capture"
    # the vessel swings 60° off the line
    sailor.sail(line, mid, line.length_m, heading_offset_deg=60.0)
    v = g.passes[1].verdicts[-1]
    assert not v.accepted
    assert v.reasons[0].startswith("capture window not completed: turned away (heading error +60°)")
    # the next attempt sees the clock fall to HOLDOVER in the window
    sailor.sail(line, -10.0, mid, then_s=0.0)
    g.on_clock("HOLDOVER")
    g.on_clock("LOCKED")
    sailor.sail(line, mid, line.length_m)
    v = g.passes[1].verdicts[-1]
    assert v.reasons == ("clock HOLDOVER during the window (must stay LOCKED)",)
    # the profiler silent over the first half of the window
    g2, s2 = _sailed(montreal)
    s2.sail(line, -10.0, mid, profiles=False, then_s=0.0)
    s2.sail(line, mid, line.length_m)
    v = g2.passes[1].verdicts[-1]
    assert len(v.reasons) == 1 and v.reasons[0].startswith("profiler data gap of ")
    # from the window's entry (the first INS epoch inside, ≤ 0.05 s late) to the first profile
    gap_s = float(v.reasons[0].split()[4])
    assert gap_s == pytest.approx((mid - line.capture_start_m) / 2.0, abs=0.06)


# -- the simulated survey ------------------------------------------------------------------------


@pytest.fixture(scope="module")
def survey():
    return run_survey(3)


def test_simulated_survey_accepts_the_six_passes_in_order(survey):
    assert [(v.pass_id, v.accepted) for v in survey.verdicts] == [(i, True) for i in range(1, 7)]
    assert [name for name, _ in survey.stages] == ["start"] + [
        f"pass-{i}-{stage}" for i in range(1, 7) for stage in ("capture", "accepted")
    ]
    for v in survey.verdicts:
        assert v.stats["max_xte_m"] < 0.1 and v.stats["max_nav_gap_s"] < 0.05
    final = survey.stages[-1][1]
    assert final["accepted"] == 6 and final["calibration_ready"]
    assert all(p["status"] == "accepted" for p in final["passes"])


def test_live_hits_are_close_to_the_simulator_truth(survey):
    """Hits found live with the a-priori mount (boresight 0°, truth 0.2°/1.2°/0.15°) against the
    simulator's labels of the same returns."""
    truth = survey.sim.point_counts()
    got = {v.pass_id: v.stats["hits"] for v in survey.verdicts}
    total_t = total_g = 0
    for pid, row in truth.items():
        for name in ("T1", "T2"):
            ratio = got[pid][name] / row[name]
            assert 0.7 < ratio < 1.5, (pid, name, got[pid][name], row[name])
            total_t += row[name]
            total_g += got[pid][name]
    assert abs(total_g / total_t - 1) < 0.08
    c = survey.guidance.counters
    assert c["points_gated"] < 0.6 * c["points_seen"]  # the gate spares most georeferencing
    assert c["profiles_dropped"] == 0 and c["points_uncovered"] == 0


def test_predicted_sigma_never_rises_pass_by_pass_and_matches_the_adjustment(survey):
    hist = survey.guidance.sigma_history  # before any pass, then after each accepted pass
    assert survey.guidance.obs_model.estimator == "gls"  # the default
    assert [h["passes"] for h in hist] == [list(range(1, k + 1)) for k in range(7)]
    determined = [sum(h["observable"].values()) for h in hist]
    assert determined == sorted(determined) and determined[-1] == 3
    worst = [h["worst_deg"] if h["worst_deg"] is not None else math.inf for h in hist]
    finite = [w for w in worst if math.isfinite(w)]
    assert len(finite) >= 3
    assert all(b <= a for a, b in zip(worst, worst[1:]))  # never grows
    assert all(b < a for a, b in zip(finite, finite[1:]))  # shrinks once all are determined
    # GLS: every accepted pass adds information, so no angle's σ rises (and nothing is marked ↑)
    for before, after in zip(hist, hist[1:]):
        for a in ("roll", "pitch", "yaw"):
            if before["realistic_deg"][a] is not None:
                assert after["realistic_deg"][a] is not None, a
                assert after["realistic_deg"][a] <= before["realistic_deg"][a] * (1 + 1e-12), (
                    after["passes"],
                    a,
                )
        assert after["rose"] == []
    # each stage recommends a pass not sailed yet; the last has nothing left to recommend
    for name, msg in survey.stages:
        if name.endswith("accepted"):
            nb = msg["sigma"]["next_best"]
            done = {p["id"] for p in msg["passes"] if p["status"] == "accepted"}
            assert (nb is None) == (len(done) == 6)
            if nb is not None:
                assert nb["pass_id"] not in done
                weak = msg["sigma"]["weakest"]
                assert weak["angle"] in ("roll", "pitch", "yaw") and weak["best_pass"] not in done
            assert msg["sigma"]["current"]["rose"] == []
    # the prediction from the live hits agrees with the GLS adjustment of the labelled returns
    # under the same model (the site's sigmas)
    predicted = np.radians([hist[-1]["realistic_deg"][a] for a in ("roll", "pitch", "yaw")])
    # the GLS adjustment under the model the prediction assumes: the site's sigmas with its
    # beam divergence and correlation times, no roughness estimated
    ratio = predicted / adjust_simulated(survey.sim, beam=True, roughness="none").sigma_realistic_rad
    assert np.all((ratio > 0.8) & (ratio < 1.25)), ratio
    # and with the calibration's defaults (GLS; each target's roughness estimated from its
    # residuals, which finds the beam footprint that these observations do not model)
    ratio = predicted / adjust_simulated(survey.sim).sigma_realistic_rad
    assert np.all((ratio > 0.75) & (ratio < 1.33)), ratio


def test_the_thesis_estimators_live_sigma_is_larger_than_the_gls_one(survey):
    """The accepted passes predicted for the thesis estimator (``Guidance(estimator="thesis")``,
    where a rise is possible and marked ↑): the same white formal σ, a realistic σ no smaller
    than GLS's on every angle."""
    g = survey.guidance
    accepted = [g._accepted[i] for i in g.accepted_ids]
    thesis = ObservationModel.from_site(g.site, "thesis")
    for k in range(3, len(accepted) + 1):
        a = predict_sigma(accepted[:k], g.scene.rectangles, g.mount, g.obs_model, thin_step=g.thin_step)
        b = predict_sigma(accepted[:k], g.scene.rectangles, g.mount, thesis, thin_step=g.thin_step)
        np.testing.assert_array_equal(a.formal_rad, b.formal_rad)
        ok = a.observable
        assert np.all(a.realistic_rad[ok] <= b.realistic_rad[ok]), k
    assert Guidance(g.site, g.plan, estimator="thesis").obs_model.estimator == "thesis"


def test_a_realistic_sigma_that_rose_with_the_last_pass_is_named():
    def pred(passes, realistic_deg, formal_deg=(0.002, 0.004, 0.003)):
        return SigmaPrediction(
            tuple(passes), np.radians(formal_deg), np.radians(realistic_deg), np.eye(3), 1000
        )

    hist = [
        pred([], [np.nan] * 3, [np.nan] * 3).as_dict(),
        pred([1, 2], [0.043, 1.0, 1.0], [0.0015, 1.0, 1.0]).as_dict(),
    ]  # pitch, yaw n/o
    assert hist[1]["realistic_deg"]["pitch"] is None
    assert sigma_rises(hist[:1], pred([1, 2], [0.043, 1.0, 1.0])) == ()  # nothing to compare
    three = pred([1, 2, 3], [0.062, 0.04, 0.03])
    assert sigma_rises(hist, three) == ("roll",)  # pitch and yaw were not determined before
    hist.append(three.as_dict())
    assert sigma_rises(hist, pred([1, 2, 3], [0.07, 0.05, 0.04])) == ("roll",)  # vs passes 1, 2
    assert sigma_rises(hist, pred([1, 2, 3, 4], [0.056, 0.041, 0.03])) == ("pitch",)
    assert sigma_rises(hist, pred([1, 2, 3, 4], [0.05, 0.03, 0.02])) == ()


def test_the_weakest_angle_names_the_pass_that_sharpens_it_most():
    def pred(passes, realistic_deg, formal_deg=(0.002, 0.004, 0.003)):
        return SigmaPrediction(
            tuple(passes), np.radians(formal_deg), np.radians(realistic_deg), np.eye(3), 10
        )

    assert weakest_angle(pred([], [np.nan] * 3, [np.nan] * 3), []) is None
    now = pred([1, 2], [0.01, 0.02, 0.04])
    ranking = [(3, pred([1, 2, 3], [0.005, 0.01, 0.035])), (7, pred([1, 2, 7], [0.009, 0.019, 0.02]))]
    # the best pass overall (3) is not the one that helps the weakest angle (yaw) most
    w = weakest_angle(now, ranking)
    assert w == {
        "angle": "yaw",
        "realistic_deg": pytest.approx(0.04),
        "best_pass": 7,
        "best_deg": pytest.approx(0.02),
    }
    # an angle not determined yet is the weakest, and a pass that determines it beats a sharper one that does not
    undetermined = pred([1], [0.01, 0.02, 1.0], [0.002, 0.004, 1.0])
    ranking = [
        (4, pred([1, 4], [0.01, 0.02, 1.0], [0.002, 0.004, 0.5])),
        (5, pred([1, 5], [0.01, 0.02, 0.045])),
    ]
    assert weakest_angle(undetermined, ranking) == {
        "angle": "yaw",
        "realistic_deg": None,
        "best_pass": 5,
        "best_deg": pytest.approx(0.045),
    }
    assert weakest_angle(now, [])["best_pass"] is None


def test_guidance_consumer_publishes_the_guidance_section(survey):
    """The daemon's consumer protocol: records through a real Tap, the message as the
    ``guidance`` section of the ``checklist`` topic (the first pass of the simulated survey)."""
    sim = survey.sim
    navs = nav_records(sim)
    profs = profiles(sim)
    l0, l1 = sim.truth["passes"][0]["line_gps_s"]
    navs = [r for r in navs if r.gps_ns * 1e-9 <= l1 + 1]
    profs = [p for p in profs if p.gps_ns[-1] * 1e-9 <= l1 + 1]
    sc = sim.scenario
    g = Guidance(
        sim.site,
        plan_site(sim.site, track_down_m=1.65, capture_margin_m=2.0),
        scanner=sc.scanner,
        tolerances=AcceptanceTolerances(min_points_per_target=50),
    )
    published = []
    pub = ChecklistPublisher(lambda topic, data: published.append((topic, data)))
    consumer = GuidanceConsumer(g, clock_state=lambda: "LOCKED", period_s=0.01)

    async def main():
        tap = Tap("guidance", GuidanceConsumer.kinds, maxsize=100000)
        task = asyncio.create_task(consumer.run(tap, pub))
        items = sorted(
            [(r.gps_ns, "nav", r) for r in navs] + [(int(p.gps_ns[-1]), "profile", p) for p in profs],
            key=lambda x: x[0],
        )
        tap.offer("event", {"event": "pass_start", "pass_id": 1}, None)
        for i in range(0, len(items), 500):
            for gps_ns, kind, rec in items[i : i + 500]:
                tap.offer(kind, rec, gps_ns)
            n = 1 + min(i + 500, len(items))
            await wait_until_async(lambda n=n: consumer.records >= n, 30, f"the consumer to take {n} records")
        await wait_until_async(
            lambda: g.sigma is not None and g.sigma.current.pass_ids == (1,), 10, "pass 1 in the estimate"
        )

        def published_passes():
            sigma = published[-1][1]["guidance"].get("sigma") or {} if published else {}
            return (sigma.get("current") or {}).get("passes")

        await wait_until_async(  # and published
            lambda: published_passes() == [1], 10, "the guidance message with pass 1 in the estimate"
        )
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)

    asyncio.run(main())
    assert tap_ok(published)
    last = published[-1][1]["guidance"]
    assert [p["status"] for p in last["passes"]][:2] == ["accepted", "pending"]
    assert last["sigma"]["current"]["passes"] == [1]
    assert consumer.records == len(navs) + len(profs) + 1


def tap_ok(published) -> bool:
    return bool(published) and all(t == "checklist" and set(d) == {"guidance"} for t, d in published)

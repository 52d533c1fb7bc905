"""The line guidance inside the daemon (docs/architecture.md §8): when the vessel config names a site file,
``mls acquire`` runs a :class:`~acquire.guidance.consumer.GuidanceConsumer` next to the devices.

- :func:`make_guidance` builds the :class:`~acquire.guidance.state.Guidance` of a vessel config:
  the site's targets and its six-fold plan (:func:`calib.survey.passplan.plan_site`), the vessel
  config's mount (what is installed; else the site's), the acceptance tolerances and the
  profiler settings of the config's ``guidance`` section
  (:class:`acquire.daemon.configschema.GuidanceConfig`).
- :func:`guidance_consumer` wires it to a :class:`~acquire.daemon.supervisor.Supervisor`: the clock
  model's state for the acceptance, and the pre-survey checks
  (:func:`acquire.guidance.prechecks.prechecks`) from the supervisor's devices that are not
  connected, latest navigation, clock status, latency statistics, free disk and configuration. The consumer publishes the guidance message
  as the ``guidance`` section of the retained ``checklist`` topic (status socket and MQTT), next
  to the supervisor's own ``presurvey`` section.
"""

from __future__ import annotations

import math
import time
from pathlib import Path

from acquire.daemon.config import site_of
from acquire.daemon.configschema import GuidanceConfig, VesselConfig
from acquire.errors import AcquireError
from acquire.guidance.acceptance import AcceptanceTolerances
from acquire.guidance.consumer import GuidanceConsumer
from acquire.guidance.prechecks import Check, disk_needed_bytes, prechecks
from acquire.guidance.state import Guidance

MS = 1_000_000


class GuidanceSetupError(AcquireError, ValueError):
    """The guidance cannot be built from the vessel config's site file (the message says why)."""


def tolerances(g: GuidanceConfig) -> AcceptanceTolerances:
    return AcceptanceTolerances(
        max_xte_m=g.max_xte_m,
        max_heading_error_rad=math.radians(g.max_heading_error_deg),
        max_speed_error_mps=g.max_speed_error_mps,
        min_points_per_target=g.min_points_per_target,
        max_gap_s=g.max_gap_s,
    )


def make_guidance(cfg: VesselConfig) -> Guidance:
    """The guidance of a vessel config with a ``site_file`` (see the module docstring)."""
    from calib.sim.scenario import ScannerModel
    from calib.survey.passplan import PassPlanError, plan_site

    if cfg.site_file is None:
        raise GuidanceSetupError(
            f"{cfg.source}: no site_file: the guidance needs the site's targets and pass plan"
        )
    path = Path(cfg.site_file)
    site, frame, mount = site_of(cfg, GuidanceSetupError)
    if frame is None:
        raise GuidanceSetupError(f"site_file {path}: neither a reference point nor a target: no LGF")
    try:
        plan = plan_site(site, frame)
    except PassPlanError as e:
        raise GuidanceSetupError(f"site_file {path}: no pass plan: {e}") from None
    g = cfg.guidance
    scanner = ScannerModel(profile_rate_hz=g.profile_rate_hz, points_per_360=g.points_per_360)
    return Guidance(site, plan, frame=frame, mount=mount, tolerances=tolerances(g), scanner=scanner)


def daemon_checks(sup, guidance: Guidance, needed_bytes: int) -> list[Check]:
    """The pre-survey checks from the supervisor's state now."""
    cfg = sup.config
    now = time.monotonic_ns()
    latency = {name: sup.monitor.stats(name).as_dict() for name in sup.monitor.devices}
    bands = {
        d.name: (d.latency.band_ns[0] / MS, d.latency.band_ns[1] / MS)
        for d in cfg.devices
        if d.name in latency
    }
    free = sup.writer.stats().free_bytes if sup.writer is not None else None
    return prechecks(
        guidance.last_nav,
        sup.clock.status(now).as_dict(),
        latency,
        bands,
        free_bytes=free,
        needed_bytes=needed_bytes,
        mount_configured=cfg.mount is not None,
        n_targets=len(guidance.target_names),
        devices={name: sup.device_error(dev) for name, dev in sup.devices.items()},
    )


def guidance_consumer(cfg: VesselConfig, sup) -> GuidanceConsumer | None:
    """The daemon's guidance consumer for ``sup`` (None without a site file, or when the
    config's ``guidance.enabled`` is false); :class:`GuidanceSetupError` when the site file
    gives no plan."""
    if cfg.site_file is None or not cfg.guidance.enabled:
        return None
    g = make_guidance(cfg)
    gc = cfg.guidance  # the log's data rate at the configured profiler settings (as the default)
    needed = disk_needed_bytes(g.plan, gc.profile_rate_hz * gc.points_per_360 * 6 * 1.1 + 200 * 300)
    return GuidanceConsumer(
        g,
        clock_state=lambda: sup.clock.state_at(time.monotonic_ns()).value,
        checks=lambda: daemon_checks(sup, g, needed),
        period_s=cfg.guidance.period_s,
    )

"""The daemon's wiring of the mount watch: when the vessel config's ``watch`` section names the
calibrated mount (``watch.calibration``, a calibration ``result.json``), ``mls acquire`` runs a
:class:`~acquire.watch.consumer.MountWatchConsumer` next to the devices (and the guidance).

- :func:`watch_model` builds what every block is estimated with: the site file's LGF (its
  reference, else the targets' mean centre, as the guidance takes it), wall azimuth,
  observation sigmas (:func:`calib.watch.block.site_sigmas`) and POS error model
  (:func:`calib.watch.block.site_error_model`: the site's correlation times); and the
  **calibrated mount**: the vessel config's mount (what is installed; else the site's) with the
  result's boresight and extras applied (:func:`calib.assess.mounts.mount_from_result`, as
  ``mls georef --calibration`` applies them).
- :func:`mount_watch_consumer` wires it to a :class:`~acquire.daemon.supervisor.Supervisor`:
  the status bus (topic ``mount``), the alarm book (``mount_shift``) and ``/events``.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from acquire.daemon.config import site_of
from acquire.daemon.configschema import VesselConfig
from acquire.errors import AcquireError
from acquire.watch.blockjob import WatchModel
from acquire.watch.consumer import MountWatchConsumer
from calib.watch.sequential import WatchDesign


class WatchSetupError(AcquireError, ValueError):
    """The mount watch cannot be built from the vessel config (the message says why)."""


def watch_model(cfg: VesselConfig) -> tuple[WatchModel, dict]:
    """The :class:`WatchModel` of a vessel config with ``watch.calibration`` and ``site_file``,
    and what the ``mount`` topic says of the calibration."""
    from calib.assess.history import load_result
    from calib.assess.mounts import mount_from_result
    from calib.core.errors import CalibError
    from calib.watch.block import site_error_model, site_sigmas

    w = cfg.watch
    if w.calibration is None or cfg.site_file is None:
        raise WatchSetupError(
            f"{cfg.source}: the mount watch needs watch.calibration (the calibrated mount) and site_file"
        )
    path = Path(cfg.site_file)
    site, frame, installed = site_of(cfg, WatchSetupError)
    if frame is None:
        raise WatchSetupError(
            f"site_file {path}: the mount watch needs the site's reference point (LGF origin)"
        )
    apriori = site.mount if installed is None else installed
    try:
        result = load_result(w.calibration)
        mount, notes = mount_from_result(apriori, result, str(w.calibration))
    except (CalibError, OSError) as e:
        raise WatchSetupError(f"watch.calibration {w.calibration}: {e}") from None
    model = WatchModel(
        mount=mount,
        frame=frame,
        wall_azimuth_rad=float(site.wall_azimuth_rad),
        sigmas=site_sigmas(site),
        error_model=site_error_model(site),
    )
    info = {
        "result": str(w.calibration),
        "boresight_deg": [float(x) for x in np.degrees(mount.boresight_rad)],
        "software_version": result.get("software_version"),
        "notes": notes,
    }
    return model, info


def design_of(cfg: VesselConfig) -> WatchDesign:
    return WatchDesign(
        shift_rad=math.radians(cfg.watch.shift_deg),
        false_alarms_per_hour=cfg.watch.false_alarms_per_hour,
    )


def mount_watch_consumer(cfg: VesselConfig, sup) -> MountWatchConsumer | None:
    """The daemon's mount watch for ``sup`` (None unless the config's ``watch`` section names
    the calibration and is enabled); :class:`WatchSetupError` when it cannot be built."""
    if not cfg.watch.active or cfg.site_file is None:
        return None
    model, info = watch_model(cfg)
    w = cfg.watch
    return MountWatchConsumer(
        model,
        design_of(cfg),
        max_points_per_s=w.max_points_per_s,
        min_line_s=w.min_line_s,
        max_line_s=w.max_line_s,
        publish=sup.bus.publish,
        alarms=sup.alarms,
        log_event=sup.log_event,
        info=info,
    )

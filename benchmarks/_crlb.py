"""Shared by the calibration benchmarks (accuracy.py, honesty.py): angles of truth.json and
result.json as radian vectors, and the Cramér–Rao bound of the targets alone at the truth.

CRLB: ``calib.boresight.covariance.predict_covariance(..., estimator="gls")`` (=
``calib.boresight.gls.gls_information``, equal to the dense oracle ``oracle.dense_gls``) on a
run's targets-only observations (``CalibrationOptions(tie_patches="off")``), linearized at the
truth (truth.json: boresight, lever arm, target planes) with the true Gauss–Markov error model.
"""

from __future__ import annotations

import numpy as np

ANGLES = ("roll", "pitch", "yaw")


def angles_rad(v) -> np.ndarray:
    """(3,) radians of a ``{"roll", "pitch", "yaw"}`` mapping or a 3-list, in degrees."""
    return np.radians([v[a] for a in ANGLES] if isinstance(v, dict) else list(v))


def true_correlation_time_s(truth: dict) -> tuple[float, ...]:
    """The six POS correlation times (north, east, down, roll, pitch, heading) the simulator
    drew its Gauss–Markov errors with (truth.json ``settings.noise.pos``)."""
    pos = truth["settings"]["noise"]["pos"]
    return tuple(float(x) for x in [*pos["tau_position_s"], *pos["tau_attitude_s"]])


def targets_only_crlb_rad(truth: dict, observations, correlation_time_s) -> np.ndarray:
    """(3,) the CRLB σ (rad) of roll, pitch, yaw from the targets' ``observations`` at the
    truth, under a Gauss–Markov model with ``correlation_time_s``."""
    from calib.boresight.covariance import predict_covariance
    from calib.boresight.errormodel import ErrorModel
    from calib.core.georef import Mount

    planes = {p["name"]: (np.asarray(p["normal"], float), float(p["d"])) for p in truth["targets"]}
    mount = Mount(
        lever_arm_m=np.asarray(truth["lever_arm_m"], float),
        nominal_rad=np.radians(truth["nominal_deg"]),
        boresight_rad=angles_rad(truth["boresight_deg"]),
    )
    model = ErrorModel("gauss_markov", correlation_time_s)
    cov = predict_covariance(
        observations,
        mount,
        [planes[n] for n in observations.plane_names],
        model=model,
        estimator="gls",
    )
    return np.sqrt(np.diag(cov["realistic"]))

"""A session's navigation without a bundle: what ``mls georef`` and the Foxglove export need to
georeference a session (the site with the session's mount, the /ins/nav trajectory, the passes
marked in /events), read exactly as :func:`office.jobs.export.export_session` reads them."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from acquire.log.read import SessionReadError, session_summary
from office.jobs.export import ExportError, ExportOptions, PassWindow, passes_from_events
from office.jobs.sessionread import Mapper, read_navigation

if TYPE_CHECKING:
    from calib.core.trajectory import Trajectory
    from calib.io.site import Site


@dataclass(frozen=True)
class SessionNavigation:
    """What a session says of where the vessel was: for the jobs that georeference a session
    without writing a bundle (``mls georef``, the Foxglove export)."""

    site: Site  # with the mount of the session's vessel config
    site_path: Path
    trajectory: Trajectory  # of /ins/nav (LGF of the site)
    passes: list[PassWindow]  # from the /events marks (empty when the session has none)
    warnings: list[str]


#: the export options of a caller that gives none
DEFAULT_OPTIONS = ExportOptions()


def session_navigation(
    session_dir: str | Path, options: ExportOptions = DEFAULT_OPTIONS, mapper: Mapper | None = None
) -> SessionNavigation:
    """The site, the /ins/nav trajectory (with its sigmas when at least half the epochs carry
    them) and the passes marked in /events of a session, read as :func:`export_session` does
    (``mapper``: the messages decoded in pieces by it, :func:`office.jobs.sessionread.read_nav_and_events`)."""
    from acquire.log.read import session_losses

    session = Path(session_dir)
    try:
        summary = session_summary(session)
        warnings = [loss.describe() for loss in session_losses(session)]
    except SessionReadError as e:
        raise ExportError(str(e)) from None
    nv = read_navigation(session, options, summary, None, mapper)
    if nv.filled:
        warnings.append(f"{nv.filled} of {nv.nav.t_ns.size} INS epochs had no sigmas: interpolated")
    windows, w = passes_from_events(nv.events, int(nv.nav.t_ns[-1]))
    return SessionNavigation(nv.site, nv.site_path, nv.trajectory, windows, warnings + w)

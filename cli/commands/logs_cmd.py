"""``mls logs``: inspect and salvage session logs (docs/architecture.md §4)."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from cli.options import SessionDir, json_option, session_argument

if TYPE_CHECKING:
    from rich.table import Table

    from acquire.log.recover import SegmentInfo, SessionInfo

app = typer.Typer(
    help="Session logs: summary (info) and salvage of torn segments (recover).", no_args_is_help=True
)


def _utc(gps_ns: int | None) -> str:
    if gps_ns is None:
        return "-"
    from calib.core.frames import gps_ns_to_utc

    return gps_ns_to_utc(gps_ns).strftime("%Y-%m-%d %H:%M:%S.%f")[:-3]


def _session_arg(session: Path) -> Path:
    if not session.is_dir():
        typer.echo(f"mls logs: {session}: no such session directory", err=True)
        raise typer.Exit(2)
    return session


@app.command("info")
def info(
    session: SessionDir,
    gap_s: Annotated[
        float,
        typer.Option(
            "--gap", help="Report pauses longer than this (s) and than 5 × the channel's typical period."
        ),
    ] = 1.0,
    as_json: Annotated[bool, json_option("Print the summary as JSON.")] = False,
) -> None:
    """Segments, channels, message counts, time span, gaps and sequence continuity of a session.

    Times are GPS (the clock model's log time); messages stamped before the PPS lock carry the
    host's clock instead: they are counted ("before lock") and left out of the span and gaps.

    Exit status 0 when every segment is complete and every sequence contiguous, 1 otherwise.
    """
    import json

    from rich.console import Console
    from rich.progress import Progress

    from acquire.log.recover import session_info

    session = _session_arg(session)
    with Progress(transient=True, disable=as_json) as progress:
        task = progress.add_task(f"reading {session.name}", total=None)
        info_ = session_info(
            session, gap_s, progress=lambda done, total: progress.update(task, completed=done, total=total)
        )
    bad_segments = [s for s in info_.segments if s.state != "complete"]
    discontinuous = [c for c in info_.channels.values() if c.missing or c.duplicates or c.backwards]
    if as_json:
        typer.echo(json.dumps(info_.as_dict(), indent=2))
        raise typer.Exit(1 if bad_segments or discontinuous else 0)
    con = Console()
    con.print(_segments_table(session, info_))
    con.print(_channels_table(info_))
    for line in _info_summary(session, info_, bad_segments):
        con.print(line)
    raise typer.Exit(1 if bad_segments or discontinuous else 0)


def _segment_note(s: SegmentInfo) -> str:
    """What is to know about a segment beyond its state: torn tail, problem, recovery, end."""
    note = []
    if s.torn_bytes:
        note.append(f"torn tail {s.torn_bytes} B")
    if s.problem:
        note.append(s.problem)
    if s.recovery:
        note.append(f"recovered (torn {s.recovery.get('torn_bytes')} B)")
    if s.end_reason:
        note.append(s.end_reason)
    if s.host_time:
        note.append(f"{s.host_time} before the PPS lock (host time)")
    return "; ".join(note)


def _segments_table(session: Path, info_: SessionInfo) -> Table:
    """One row per segment: state, size, messages, first and last log time, note."""
    from rich.table import Table

    st = Table(title=f"{session.name}: segments")
    for col in ("segment", "state", "MiB", "messages", "first (UTC, GPS log time)", "last", "note"):
        st.add_column(col, justify="right" if col in ("MiB", "messages") else "left")
    for s in info_.segments:
        st.add_row(
            s.name,
            s.state,
            f"{s.bytes / 2**20:.2f}",
            str(s.messages),
            _utc(s.first_log_ns),
            _utc(s.last_log_ns),
            _segment_note(s),
        )
    return st


def _channels_table(info_: SessionInfo) -> Table:
    """One row per channel: messages, sequence range and its holes, gaps, unlocked stamps."""
    from rich.table import Table

    ct = Table(title="channels")
    for col in (
        "channel",
        "messages",
        "seq",
        "missing",
        "dup",
        "gaps",
        "longest gap s",
        "unlocked",
        "before lock",
    ):
        ct.add_column(col, justify="left" if col == "channel" else "right")
    for t, c in sorted(info_.channels.items()):
        longest = max((g[1] for g in c.gaps), default=0.0)
        ct.add_row(
            t,
            str(c.messages),
            f"{c.seq_first}–{c.seq_last}",
            str(c.missing),
            str(c.duplicates + c.backwards),
            str(len(c.gaps)),
            f"{longest:.2f}" if c.gaps else "-",
            str(c.unlocked),
            str(c.host_time),
        )
    return ct


def _info_summary(session: Path, info_: SessionInfo, bad_segments: list[SegmentInfo]) -> list[str]:
    """The lines under the tables: totals and span, host-time messages, missing sequence
    numbers (five ranges per channel), the advice to recover."""
    lines = []
    first, last = info_.span_ns
    span = (last - first) / 1e9 if first is not None and last is not None else 0.0
    lines.append(
        f"{len(info_.segments)} segments, {info_.messages} messages, {_utc(first)} → "
        f"{_utc(last)} UTC ({span:.1f} s of GPS time); {len(bad_segments)} segment(s) not complete, "
        f"{sum(c.missing for c in info_.channels.values())} sequence number(s) missing"
    )
    if info_.host_time_messages:
        lines.append(
            f"{info_.host_time_messages} message(s) stamped before the PPS lock carry the host's "
            "clock, not GPS time: counted, left out of the span and the gaps"
        )
    for c in info_.channels.values():
        for a, b in c.missing_ranges[:5]:
            lines.append(f"  {c.topic}: sequence {a}–{b} missing")
    if bad_segments and any(s.state == "unfinished" for s in bad_segments):
        lines.append(f"run `mls logs recover {session}` to salvage the unfinished segment(s)")
    return lines


@app.command("recover")
def recover(
    session: Annotated[Path, session_argument("Session directory to salvage.")],
    keep_torn: Annotated[
        bool,
        typer.Option(
            "--keep-torn/--delete-torn", help="Keep each original torn segment as seg-NNNNNN.mcap.torn."
        ),
    ] = True,
) -> None:
    """Rewrite every unfinished segment as a valid MCAP with all its complete messages.

    The torn tail (a half-written chunk after a crash or a full disk) is reported, never
    guessed at. The recovered file keeps the original's mode (and owner and group, as root).
    Refuses a session that a running daemon is writing.
    """
    from rich.console import Console
    from rich.table import Table

    from acquire.log.recover import salvage_session
    from acquire.log.session import LogError

    session = _session_arg(session)
    try:
        reports = salvage_session(session, keep_original=keep_torn)
    except LogError as e:
        typer.echo(f"mls logs recover: {e}", err=True)
        raise typer.Exit(1) from None
    if not reports:
        typer.echo(f"{session.name}: every segment is complete; nothing to recover")
        return
    t = Table(title=f"{session.name}: recovered segments")
    for c in ("segment", "messages", "kept bytes", "torn bytes", "why it stopped", "original"):
        t.add_column(c)
    for r in reports:
        t.add_row(
            r.segment,
            str(r.messages),
            str(r.good_bytes),
            str(r.torn_bytes),
            r.problem or "no footer (clean end of file)",
            r.original or "deleted",
        )
    Console().print(t)

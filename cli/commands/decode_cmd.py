"""``mls decode``: decode a recorded device file (INS NMEA/STDBIN, ZFP1 profiles, pcapng captures)."""

from __future__ import annotations

import json
import sys
from array import array
from dataclasses import dataclass, field
from enum import Enum
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from cli.options import json_option

if TYPE_CHECKING:
    from rich.console import Console
    from rich.table import Table

    from drivers.capture.files import FileDecoder


class Format(str, Enum):
    nmea = "nmea"
    stdbin = "stdbin"
    zfp = "zfp"
    pcapng = "pcapng"


class Payload(str, Enum):
    stdbin = "stdbin"
    nmea = "nmea"
    zfp = "zfp"
    pps = "pps"


def decode(
    file: Annotated[
        Path, typer.Argument(help="The recorded file: a raw stream, a stamped log or a packet capture.")
    ],
    fmt: Annotated[
        Format, typer.Option("--format", "-f", help="What the file holds: nmea, stdbin, zfp or pcapng.")
    ],
    payload: Annotated[
        Payload, typer.Option("--payload", help="pcapng only: the protocol carried in the UDP payloads.")
    ] = Payload.stdbin,
    port: Annotated[
        int | None, typer.Option("--port", help="pcapng only: keep UDP datagrams to or from this port.")
    ] = None,
    as_json: Annotated[bool, json_option("Print one JSON object per record (summary on stderr).")] = False,
    nav: Annotated[
        bool,
        typer.Option(
            "--nav", help="INS formats: print canonical navigation records (radians → degrees, NED, FRD)."
        ),
    ] = False,
    timing: Annotated[
        bool,
        typer.Option(
            "--timing", help="Fit the device time tags against the receive stamps: drift, offset, jitter."
        ),
    ] = False,
    date: Annotated[
        str | None,
        typer.Option(
            "--date",
            help="UTC date YYYY-MM-DD for time tags when the file carries none (no ZDA/system date).",
        ),
    ] = None,
) -> None:
    """Decode a recorded device file; end with a summary: records, bytes, rejected frames and why.

    The file is streamed (bounded memory, whatever its size). Exit status 2 when it cannot be
    read or when it gives no valid record (the message says what was skipped instead)."""
    from rich.console import Console
    from rich.markup import escape

    from drivers.base import DriverError
    from drivers.capture.files import FileDecoder

    err = Console(stderr=True, emoji=False)  # ":100:" of file:line:column is no emoji
    out = Console()
    try:
        fd = FileDecoder(file, fmt.value, payload.value, port, nav, date)
    except DriverError as exc:
        err.print(f"[red]error:[/red] {exc}")
        raise typer.Exit(2) from exc

    decoded = _decode_records(fd, as_json, timing, err)
    if not as_json:
        out.print(_counts_table(decoded.counts, file, fmt, payload))
    if timing:
        _print_timing(decoded.host_ns, decoded.device_ns, out if not as_json else err)
    (err if as_json else out).print(_summary(fd), highlight=False, soft_wrap=True)
    if not decoded.counts:
        err.print(f"[red]error:[/red] {escape(fd.no_record_message())}", highlight=False, soft_wrap=True)
        raise typer.Exit(2)


@dataclass
class _Decoded:
    """What the pass over the file gathered: records per type, and the time-tag samples of
    ``--timing`` (16 bytes per time-tagged record)."""

    counts: dict[str, int] = field(default_factory=dict)
    host_ns: array = field(default_factory=lambda: array("q"))
    device_ns: array = field(default_factory=lambda: array("q"))


def _decode_records(fd: FileDecoder, as_json: bool, timing: bool, err: Console) -> _Decoded:
    """Stream the file once: count the records by type, keep the time samples of ``--timing``,
    print each record with ``--json``; a progress bar on a terminal's stderr. Exit status 2
    when the file cannot be read, 0 when stdout's reader leaves (``| head``)."""
    from rich.progress import BarColumn, Progress, TextColumn

    from calib.core.errors import MlsError
    from drivers.capture.files import json_default, record_to_dict, record_type, time_sample

    decoded = _Decoded()
    counts = decoded.counts
    try:
        with Progress(
            TextColumn("decoding"),
            BarColumn(),
            TextColumn("{task.percentage:>3.0f}%"),
            console=err,
            transient=True,
            disable=as_json or not err.is_terminal,
        ) as progress:
            task = progress.add_task("decode", total=max(fd.size, 1))
            for rec in fd:
                d = record_to_dict(rec) if as_json else None
                kind = d["type"] if d is not None else record_type(rec)
                counts[kind] = counts.get(kind, 0) + 1
                if timing:
                    sample = time_sample(rec)
                    if sample is not None:
                        decoded.host_ns.append(sample[0])
                        decoded.device_ns.append(sample[1])
                if as_json:
                    _write_json_line(json.dumps(d, default=json_default))
                progress.update(task, completed=fd.bytes_done)
    except (MlsError, OSError) as exc:
        err.print(f"[red]error:[/red] {exc}")
        raise typer.Exit(2) from exc
    return decoded


def _write_json_line(line: str) -> None:
    """One ``--json`` record on stdout; exit 0 when its reader has gone (``mls decode ... --json | head``)."""
    try:
        sys.stdout.write(line + "\n")
    except BrokenPipeError:
        sys.stdout = None  # nothing more goes to the closed pipe (not even at exit)
        raise typer.Exit(0) from None


def _summary(fd: FileDecoder) -> str:
    """The summary line: the decoder's statistics, and for a capture what it held and skipped."""
    summary = f"summary: {fd.stats.summary()}"
    if fd.capture_stats is not None:
        assert fd.udp_stats is not None  # a capture has both its packet and its UDP statistics
        summary += (
            f"; capture: {fd.capture_stats.records} packets, {fd.udp_stats.records} UDP datagrams decoded"
        )
        skipped = {**fd.capture_stats.rejected, **fd.udp_stats.events}
        if skipped:
            summary += " (skipped " + ", ".join(f"{k}: {v}" for k, v in sorted(skipped.items())) + ")"
    return summary


def _counts_table(counts: dict[str, int], file: Path, fmt: Format, payload: Payload) -> Table:
    """Records per type, by type name."""
    from rich.table import Table

    table = Table(title=f"{file.name} ({fmt.value}{'/' + payload.value if fmt is Format.pcapng else ''})")
    table.add_column("record type")
    table.add_column("count", justify="right")
    for kind, n in sorted(counts.items()):
        table.add_row(kind, str(n))
    return table


def _print_timing(host_ns: array, device_ns: array, console: Console) -> None:
    from rich.table import Table

    from drivers.timing import fit_clock, signed_time_of_day_offset_s, unwrap_time_of_day_ns

    if len(host_ns) < 3:
        console.print("timing: fewer than 3 time-tagged records with receive stamps, nothing to fit")
        return
    fit = fit_clock(host_ns, unwrap_time_of_day_ns(device_ns))
    table = Table(title="device clock vs receive stamps")
    table.add_column("quantity")
    table.add_column("value", justify="right")
    table.add_row("samples (outliers)", f"{fit.n} ({fit.n_outliers})")
    table.add_row("span_s", f"{fit.span_s:.3f}")
    table.add_row("drift_ppm (host vs device)", f"{fit.drift_ppm:+.2f}")
    offset_s = signed_time_of_day_offset_s(fit.offset_s)  # the date out, the sign kept
    table.add_row("offset_s (latency + clock offset, signed)", f"{offset_s:+.6f}")
    table.add_row("jitter_rms_ms", f"{fit.jitter_rms_s * 1e3:.3f}")
    table.add_row("jitter_max_ms", f"{fit.jitter_max_s * 1e3:.3f}")
    table.add_row("jitter_p2p_ms", f"{fit.jitter_p2p_s * 1e3:.3f}")
    console.print(table)

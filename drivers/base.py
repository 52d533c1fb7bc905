"""What every protocol codec in :mod:`drivers` shares (docs/architecture.md §5).

A *decoder* is sans-I/O: ``feed(data: bytes, host_ns: int | None = None) -> list[record]``.
It keeps its own buffer (a record may be split across reads), resynchronizes after garbage,
never raises on bad bytes and counts what it rejected in :class:`DecoderStats`. ``host_ns`` is
the host receive stamp (``time.monotonic_ns()``) of the chunk; the decoder copies it into the
records completed by that chunk. ``flush()`` ends the stream (a file's last line without a line
terminator, a half-assembled epoch) and returns what can still be decoded.

An *encoder* does the reverse (records → bytes) and is used by the simulated devices.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any, Protocol

from calib.core.errors import MlsError


class DriverError(MlsError, ValueError):
    """Bad input handed to a driver function that is not a stream decoder (a datagram, a config)."""


@dataclass
class DecoderStats:
    """Counters of one decoder; all monotonically increasing.

    ``rejected`` counts frames/sentences/packets thrown away, by reason (``bad_checksum``,
    ``missing_checksum``, ``bad_field``, ``size_mismatch``, ``unknown_version``, ...).
    ``events`` counts things that are observed but not errors of the bytes (``duplicate``,
    ``reordered``, ``packets_lost``, ``profiles_lost``, ``unknown_block``, ...).
    """

    bytes_in: int = 0
    records: int = 0
    skipped_bytes: int = 0
    rejected: Counter = field(default_factory=Counter)
    events: Counter = field(default_factory=Counter)

    @property
    def rejected_total(self) -> int:
        return sum(self.rejected.values())

    def as_dict(self) -> dict[str, Any]:
        return {
            "bytes_in": self.bytes_in,
            "records": self.records,
            "skipped_bytes": self.skipped_bytes,
            "rejected": dict(self.rejected),
            "events": dict(self.events),
        }

    def summary(self) -> str:
        """One line for logs and the end of ``mls decode``."""
        parts = [f"{self.records} records", f"{self.bytes_in} bytes"]
        if self.rejected:
            why = ", ".join(f"{k}: {v}" for k, v in sorted(self.rejected.items()))
            parts.append(f"{self.rejected_total} rejected ({why})")
        else:
            parts.append("0 rejected")
        if self.skipped_bytes:
            parts.append(f"{self.skipped_bytes} bytes skipped")
        if self.events:
            parts.append(", ".join(f"{k}: {v}" for k, v in sorted(self.events.items())))
        return "; ".join(parts)


class Decoder(Protocol):
    """The shape of every stream decoder in :mod:`drivers`."""

    stats: DecoderStats

    def feed(self, data: bytes, host_ns: int | None = None) -> list[Any]: ...

    def flush(self) -> list[Any]: ...


class Registry(dict):
    """Device classes by the config's ``kind`` (python-can's interface registry is the model).

    ``@REGISTRY.register("serial")`` on a class files it (and sets ``cls.kind``);
    ``REGISTRY.create({"kind": "serial", ...}, **extra)`` builds one from a config mapping, with a
    :class:`DriverError` naming the section, the kind and what was expected when it cannot.
    """

    def __init__(self, section: str) -> None:
        super().__init__()
        self.section = section

    def register(self, kind: str):
        def deco(cls):
            cls.kind = kind
            self[kind] = cls
            return cls

        return deco

    def create(self, config: dict[str, Any], **extra: Any):
        return create_from_config(self.section, self, config, None, **extra)


def create_from_config(
    section: str,
    kinds: Mapping[str, Any],
    config: Mapping[str, Any],
    load: Callable[[Any], Any] | None = None,
    /,
    **extra: Any,
):
    """The object ``config['kind']`` names: ``kinds[kind]`` (turned into a class by ``load`` when
    the table holds something else, e.g. where to import it from) called with ``extra`` and the
    config's other keys. A :class:`DriverError` names the section, the kind and what was expected
    when it cannot."""
    cfg = dict(config)
    kind = cfg.pop("kind", None)
    entry = kinds.get(kind)
    if entry is None:
        raise DriverError(f"{section}.kind {kind!r}: expected one of {sorted(kinds)}")
    cls = entry if load is None else load(entry)
    try:
        return cls(**extra, **cfg)
    except TypeError as exc:  # an unknown or missing key
        raise DriverError(f"{section} ({kind}): {exc}") from exc

"""MQTT operator commands: strict validation of the payloads, and rate limits per command kind.

A command is a message on ``<base>/cmd/<name>`` whose payload is a JSON object (an empty
payload is ``{}``). :func:`parse_command` accepts exactly this set and refuses everything else
with a reason (:class:`CommandRefused`) — never an exception of another kind, whatever the bytes::

    mark        {"text": str}        1 … 200 characters, no control characters
    pass_start  {"pass_id": int}     1 … 2⁵³ − 1 (an integer every JSON reader keeps exactly;
    pass_end    {"pass_id": int}     the bundle and the LAS export store it as int64)
    rotate      {}                   start a new log segment

Every command may carry an ``"id"`` (a string of ≤ 64 characters or an int64) echoed in the
reply. Unknown fields, duplicate keys, NaN/Infinity, floats where an integer is expected,
booleans, payloads over :data:`MAX_PAYLOAD_BYTES` are refused.

:class:`CommandLimiter` holds one token bucket per command kind (``rotate`` far stricter: each
one closes a segment) and one for the replies to refused commands, so that a flood of bad
messages can neither fill the log with events nor the link with replies.
"""

from __future__ import annotations

import json
import time
import unicodedata
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from acquire.errors import AcquireError

MAX_PAYLOAD_BYTES = 1024
MAX_TEXT_CHARS = 200
MAX_ID_CHARS = 64
MAX_PASS_ID = 2**53 - 1  # JSON-safe; export and georef keep pass ids as int64 (calib.io.bundle)
INT64 = (-(2**63), 2**63 - 1)
COMMANDS: dict[str, dict[str, type]] = {
    "mark": {"text": str},
    "pass_start": {"pass_id": int},
    "pass_end": {"pass_id": int},
    "rotate": {},
}


class CommandRefused(AcquireError, ValueError):
    """A command message that is not accepted; ``str()`` is the reason sent back."""


@dataclass(frozen=True)
class Command:
    name: str
    args: dict[str, Any]  # validated arguments (without "id")
    id: str | int | None = None


def parse_command(name: str, payload: bytes) -> Command:
    """The command ``name`` with its JSON ``payload``, validated; :class:`CommandRefused` else."""
    if name not in COMMANDS:
        raise CommandRefused(f"unknown command {name[:40]!r}; accepted: {', '.join(COMMANDS)}")
    if len(payload) > MAX_PAYLOAD_BYTES:
        raise CommandRefused(f"{name}: payload of {len(payload)} bytes; at most {MAX_PAYLOAD_BYTES}")
    doc = strict_json(name, payload or b"{}")
    reason = check_command(name, doc)
    if reason is not None:
        raise CommandRefused(reason)
    return Command(name, {k: v for k, v in doc.items() if k != "id"}, doc.get("id"))


def check_command(name: str, args: Any) -> str | None:
    """None when ``name``/``args`` (a decoded payload) form a valid command, else the reason."""
    spec = COMMANDS.get(name)
    if spec is None:
        return f"unknown command {name[:40]!r}; accepted: {', '.join(COMMANDS)}"
    if not isinstance(args, dict):
        return f"{name}: payload must be a JSON object"
    unknown = sorted(str(k)[:40] for k in set(args) - set(spec) - {"id"})
    if unknown:
        return f"{name}: unknown argument(s) {', '.join(unknown)}; accepted: {', '.join(spec) or 'none'}"
    for key, typ in spec.items():
        value = args.get(key)
        if not isinstance(value, typ) or isinstance(value, bool):
            return f"{name}: argument {key!r} must be {typ.__name__}, got {_short(value)}"
        reason = _CHECKS[key](value)
        if reason is not None:
            return f"{name}: argument {key!r} {reason}"
    if "id" in args:
        reason = _check_id(args["id"])
        if reason is not None:
            return f"{name}: 'id' {reason}"
    return None


def command_id(payload: bytes) -> str | int | None:
    """The valid ``"id"`` of a payload, best effort (to answer a refused command), else None."""
    try:
        doc = strict_json("", payload) if len(payload) <= MAX_PAYLOAD_BYTES else None
    except CommandRefused:
        return None
    value = doc.get("id") if isinstance(doc, dict) else None
    return value if value is not None and _check_id(value) is None else None


def strict_json(name: str, payload: bytes) -> Any:
    """``payload``'s JSON, or :class:`CommandRefused` naming the command ``name`` when it is not
    JSON or has duplicate keys, NaN/Infinity or an integer beyond 64 bits."""
    try:
        return json.loads(
            payload,
            object_pairs_hook=_no_duplicates,
            parse_constant=_no_constant,
            parse_int=_bounded_int,
        )
    except CommandRefused as e:
        raise CommandRefused(f"{name}: {e}") from None
    except (ValueError, RecursionError) as e:  # UnicodeDecodeError, JSONDecodeError are ValueErrors
        raise CommandRefused(f"{name}: payload is not JSON ({type(e).__name__})") from None


def _no_duplicates(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    doc = dict(pairs)
    if len(doc) != len(pairs):
        raise CommandRefused("duplicate keys in the payload")
    return doc


def _no_constant(token: str) -> Any:
    raise CommandRefused(f"{token} is not a JSON number")


def _bounded_int(token: str) -> int:
    if len(token.lstrip("-")) > 19:
        raise CommandRefused(f"integer {token[:24]}… out of the int64 range")
    return int(token)


def _check_pass_id(value: int) -> str | None:
    if not 1 <= value <= MAX_PASS_ID:
        return f"must be in 1 … {MAX_PASS_ID} (2**53 - 1), got {_short(value)}"
    return None


def _check_text(value: str) -> str | None:
    if not 1 <= len(value) <= MAX_TEXT_CHARS:
        return f"must have 1 … {MAX_TEXT_CHARS} characters, got {len(value)}"
    bad = next((c for c in value if unicodedata.category(c) in ("Cc", "Cs")), None)
    if bad is not None:
        return f"must not contain control characters or lone surrogates (U+{ord(bad):04X})"
    return None


def _check_id(value: Any) -> str | None:
    if isinstance(value, bool) or not isinstance(value, str | int):
        return f"must be a string or an integer, got {_short(value)}"
    if isinstance(value, int) and not INT64[0] <= value <= INT64[1]:
        return "must be an int64"
    if isinstance(value, str):
        return _check_text(value) if len(value) <= MAX_ID_CHARS else f"must have ≤ {MAX_ID_CHARS} characters"
    return None


_CHECKS: dict[str, Callable[[Any], str | None]] = {"pass_id": _check_pass_id, "text": _check_text}


def _short(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 40 else text[:37] + "…"


# -- rate limits --------------------------------------------------------------------------------


@dataclass
class TokenBucket:
    """``burst`` tokens, refilled at ``rate_per_s``; :meth:`take` spends one when there is one."""

    rate_per_s: float
    burst: float
    clock: Callable[[], float] = time.monotonic
    tokens: float = field(init=False)
    stamp: float = field(init=False)

    def __post_init__(self) -> None:
        self.tokens = float(self.burst)
        self.stamp = self.clock()

    def take(self) -> bool:
        now = self.clock()
        self.tokens = min(float(self.burst), self.tokens + (now - self.stamp) * self.rate_per_s)
        self.stamp = now
        if self.tokens >= 1.0:
            self.tokens -= 1.0
            return True
        return False


# (rate per second, burst) per command kind; rotate closes a segment each time: one per 30 s
RATE_LIMITS: dict[str, tuple[float, float]] = {
    "mark": (2.0, 5.0),
    "pass_start": (2.0, 5.0),
    "pass_end": (2.0, 5.0),
    "rotate": (1 / 30, 2.0),
}
REPLY_LIMIT = (5.0, 20.0)  # replies (and session events) for refused commands


class CommandLimiter:
    """The rate limits of the commands (:data:`RATE_LIMITS`) and of the refusals' replies."""

    def __init__(
        self,
        limits: dict[str, tuple[float, float]] | None = None,
        reply_limit: tuple[float, float] = REPLY_LIMIT,
        clock: Callable[[], float] = time.monotonic,
    ):
        limits = RATE_LIMITS if limits is None else limits
        self.limits = dict(limits)
        self._buckets = {k: TokenBucket(r, b, clock) for k, (r, b) in limits.items()}
        self._replies = TokenBucket(*reply_limit, clock)

    def allow(self, name: str) -> str | None:
        """None when command ``name`` may run now, else the reason it is refused."""
        bucket = self._buckets.get(name)
        if bucket is None or bucket.take():
            return None
        rate, burst = self.limits[name]
        return f"{name}: rate limited (at most {burst:g} at once, then one every {1 / rate:g} s)"

    def may_reply(self) -> bool:
        """Whether a refusal may still be answered (and logged) now."""
        return self._replies.take()

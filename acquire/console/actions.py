"""Operator actions from the console: the bearer token, then the MQTT commands' own validation
and rate limits (:mod:`acquire.status.commands`), and the session record.

Accepted actions: ``pass_start``, ``pass_end`` and ``mark`` (exactly the MQTT commands' payloads
and checks; ``rotate`` stays an MQTT command) and ``alarm_ack`` (``{"alarm": name, "device":
name}`` of an active alarm). Each kind has the MQTT token bucket (``alarm_ack`` the marks'); a
refusal is logged as ``{"event": "command_refused", "source": "web", …}`` within the refusals'
own budget, as MQTT does. An accepted action is an ``/events`` entry with ``"source": "web"``,
as an MQTT command is one with ``"source": "mqtt"``.
"""

from __future__ import annotations

import hmac
import re
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from acquire.alarms import AlarmBook
from acquire.status.commands import (
    MAX_PAYLOAD_BYTES,
    RATE_LIMITS,
    CommandLimiter,
    CommandRefused,
    check_command,
    command_id,
    parse_command,
    strict_json,
)

ACTIONS = ("pass_start", "pass_end", "mark", "alarm_ack")
LIMITS = {**{k: v for k, v in RATE_LIMITS.items() if k != "rotate"}, "alarm_ack": RATE_LIMITS["mark"]}
_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.:/-]{0,63}")


@dataclass(frozen=True)
class ActionResult:
    """What the console answers: the HTTP status and ``{"command", "ok", "message"[, "id"]}``."""

    status: int
    command: str
    ok: bool
    message: str
    id: str | int | None = None

    def as_dict(self) -> dict:
        d: dict[str, Any] = {"command": self.command, "ok": self.ok, "message": self.message}
        if self.id is not None:
            d["id"] = self.id
        return d


def token_refusal(header: str | None, token: str | None) -> ActionResult | None:
    """None when ``header`` (``Authorization``) carries the operator ``token``; else the refusal:
    401 without a bearer token, 403 with a wrong one or when the console has none (read-only)."""
    if token is None:
        return ActionResult(403, "", False, "read-only console: no web.credentials_file in the vessel config")
    scheme, _, given = (header or "").partition(" ")
    if scheme.lower() != "bearer" or not given.strip():
        return ActionResult(401, "", False, "operator token required (Authorization: Bearer <token>)")
    if not hmac.compare_digest(given.strip().encode(), token.encode()):
        return ActionResult(403, "", False, "wrong operator token")
    return None


@dataclass
class ActionDesk:
    """Validates, rate-limits and records the console's operator actions."""

    log_event: Callable[[dict, int], None]  # the supervisor's: an /events entry at host ns
    alarms: AlarmBook
    gps_ns: Callable[[int], int | None]
    limiter: CommandLimiter = field(default_factory=lambda: CommandLimiter(LIMITS))
    counts: dict[str, int] = field(
        default_factory=lambda: {"accepted": 0, "refused": 0, "rate_limited": 0, "dropped": 0}
    )
    acked: dict[str, dict] = field(default_factory=dict)  # "name/device" → the ack of its raise

    def handle(self, name: str, payload: bytes) -> ActionResult:
        """One authorised action ``name`` with its JSON ``payload``."""
        try:
            args, cmd_id = self._parse(name, payload)
        except CommandRefused as e:
            return self._refuse(name, command_id(payload), str(e), 400, "refused")
        reason = self.limiter.allow(name)
        if reason is not None:
            return self._refuse(name, cmd_id, reason, 429, "rate_limited")
        if name == "alarm_ack":
            return self._ack(args, cmd_id)
        now = time.monotonic_ns()
        self.log_event({"event": name, "source": "web", **args}, now)
        self.counts["accepted"] += 1
        what = f"pass {args['pass_id']}" if "pass_id" in args else repr(args.get("text", ""))
        return ActionResult(200, name, True, f"{name} {what} logged at GPS {self.gps_ns(now)}", cmd_id)

    def _parse(self, name: str, payload: bytes) -> tuple[dict[str, Any], str | int | None]:
        if name not in ACTIONS:
            raise CommandRefused(f"unknown action {name[:40]!r}; accepted: {', '.join(ACTIONS)}")
        if name != "alarm_ack":
            cmd = parse_command(name, payload)
            return dict(cmd.args), cmd.id
        return ack_args(payload)

    def _ack(self, args: dict[str, Any], cmd_id: str | int | None) -> ActionResult:
        alarm, device = args["alarm"], args["device"]
        active = self.alarms.get(alarm, device)
        if active is None or not active.active:
            return self._refuse(
                "alarm_ack", cmd_id, f"alarm_ack: no active alarm {alarm}/{device}", 409, "refused"
            )
        now = time.monotonic_ns()
        self.log_event({"event": "alarm_ack", "source": "web", "alarm": alarm, "device": device}, now)
        self.acked = {  # an ack holds for the raise it acknowledged: a later raise is new
            k: v for k, v in self.acked.items() if self.alarms.is_active(v["alarm"], v["device"])
        }
        self.acked[f"{alarm}/{device}"] = {
            "alarm": alarm,
            "device": device,
            "first_host_ns": active.first_host_ns,  # which raise (the page compares it)
            "gps_ns": self.gps_ns(now),
        }
        self.counts["accepted"] += 1
        return ActionResult(200, "alarm_ack", True, f"alarm {alarm}/{device} acknowledged", cmd_id)

    def _refuse(self, name: str, cmd_id: Any, reason: str, status: int, counter: str) -> ActionResult:
        self.counts[counter] += 1
        short = name if name in ACTIONS else name[:40]
        if self.limiter.may_reply():
            event = {"event": "command_refused", "source": "web", "command": short, "reason": reason}
            self.log_event(event, time.monotonic_ns())
        else:
            self.counts["dropped"] += 1
        return ActionResult(status, short, False, reason, cmd_id)


def ack_args(payload: bytes) -> tuple[dict[str, Any], str | int | None]:
    """``alarm_ack``'s arguments ``{"alarm", "device"}`` (names), checked as strictly as a
    command's payload (JSON object, size, no duplicates or unknown keys, a valid ``id``)."""
    if len(payload) > MAX_PAYLOAD_BYTES:
        raise CommandRefused(f"alarm_ack: payload of {len(payload)} bytes; at most {MAX_PAYLOAD_BYTES}")
    doc = strict_json("alarm_ack", payload or b"{}")
    if not isinstance(doc, dict):
        raise CommandRefused("alarm_ack: payload must be a JSON object")
    unknown = sorted(str(k)[:40] for k in set(doc) - {"alarm", "device", "id"})
    if unknown:
        raise CommandRefused(f"alarm_ack: unknown argument(s) {', '.join(unknown)}; accepted: alarm, device")
    for key in ("alarm", "device"):
        value = doc.get(key)
        if not isinstance(value, str) or not _NAME.fullmatch(value):
            raise CommandRefused(f"alarm_ack: argument {key!r} must be an alarm or device name")
    reason = check_command("mark", {"text": "x", "id": doc["id"]}) if "id" in doc else None
    if reason is not None:
        raise CommandRefused(reason.replace("mark:", "alarm_ack:", 1))
    return {"alarm": doc["alarm"], "device": doc["device"]}, doc.get("id")

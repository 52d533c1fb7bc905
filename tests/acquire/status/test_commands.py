"""MQTT command payloads: strict validation (and a fuzz of it), the token buckets of the rate limit."""

from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from acquire.log.schema import dumps
from acquire.status.commands import (
    COMMANDS,
    MAX_PASS_ID,
    MAX_PAYLOAD_BYTES,
    CommandLimiter,
    CommandRefused,
    TokenBucket,
    command_id,
    parse_command,
)
from office.jobs.export import PassWindow


def refused(name: str, payload: bytes | str) -> str:
    raw = payload.encode() if isinstance(payload, str) else payload
    with pytest.raises(CommandRefused) as exc:
        parse_command(name, raw)
    return str(exc.value)


@pytest.mark.parametrize(
    ("payload", "reason"),
    [
        ('{"pass_id": 9223372036854775808}', "must be in 1 … 9007199254740991"),  # crashed export
        ('{"pass_id": 12345678901234567890123}', "out of the int64 range"),
        ('{"pass_id": 9223372036854775807}', "must be in 1 … 9007199254740991"),
        ('{"pass_id": 9007199254740992}', "must be in 1 …"),
        ('{"pass_id": -5}', "must be in 1 …"),  # made a bundle calib run refuses
        ('{"pass_id": 0}', "must be in 1 …"),
        ('{"pass_id": 3.0}', "must be int"),
        ('{"pass_id": true}', "must be int"),
        ('{"pass_id": "3"}', "must be int"),
        ('{"pass_id": NaN}', "NaN is not a JSON number"),
        ('{"pass_id": 1, "pass_id": 2}', "duplicate keys"),
        ('{"pass_id": 1, "force": true}', "unknown argument(s) force"),
        ('{"pass_id": 1, "id": 1.5}', "'id' must be a string or an integer"),
        ('{"pass_id": 1, "id": "' + "x" * 65 + '"}', "'id' must have ≤ 64 characters"),
        ("[1]", "payload must be a JSON object"),
        ("{", "payload is not JSON"),
        ("[" * 100_000, "payload is not JSON"),  # nesting: no RecursionError escapes
        ("9" * 5000, "out of the int64 range"),
        (b"\xff\xfe{", "payload is not JSON"),
    ],
)
def test_pass_start_payloads_are_refused_with_a_reason(payload, reason):
    if len(payload) > MAX_PAYLOAD_BYTES:
        assert "payload of" in refused("pass_start", payload)
        return
    assert reason in refused("pass_start", payload)


def test_valid_commands_and_their_ids():
    assert parse_command("pass_start", b'{"pass_id": 9007199254740991, "id": 7}').args == {
        "pass_id": MAX_PASS_ID
    }
    assert parse_command("pass_end", b'{"pass_id": 1, "id": "a-1"}').id == "a-1"
    assert parse_command("rotate", b"").args == {}
    assert parse_command("mark", '{"text": "bouée T1 vue"}'.encode()).args == {"text": "bouée T1 vue"}
    assert command_id(b'{"pass_id": -5, "id": 9}') == 9  # a refusal still echoes a valid id
    assert command_id(b'{"id": 1e400}') is None and command_id(b"\xff") is None


@pytest.mark.parametrize(
    ("text", "reason"),
    [
        ("", "1 … 200 characters"),
        ("x" * 201, "1 … 200 characters"),
        ("line\nbreak", "control characters"),
        ("\ud800", "lone surrogates"),
    ],
)
def test_mark_text_is_bounded_and_printable(text, reason):
    assert reason in refused("mark", json.dumps({"text": text}))


def test_unknown_commands_and_oversized_payloads():
    assert "unknown command 'reboot'" in refused("reboot", b"{}")
    assert f"at most {MAX_PAYLOAD_BYTES}" in refused("mark", b'{"text": "' + b"x" * 2000 + b'"}')
    assert "unknown argument(s) now" in refused("rotate", b'{"now": 1}')


# -- fuzz ---------------------------------------------------------------------------------------

json_scalars = (
    st.none()
    | st.booleans()
    | st.integers(min_value=-(2**70), max_value=2**70)
    | st.floats(allow_nan=True, allow_infinity=True)
    | st.text(max_size=260)
)
json_values = st.recursive(
    json_scalars,
    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=8), inner, max_size=3),
    max_leaves=8,
)
field_names = st.sampled_from(["pass_id", "text", "id", "force"]) | st.text(max_size=8)
documents = st.dictionaries(field_names, json_values, max_size=4)
names = st.sampled_from([*COMMANDS, "result", "reboot"])


def _storable(name: str, args: dict) -> None:
    """What the daemon does with an accepted command: an /events entry, and for passes the
    int64 pass ids of the export (PassWindow, the bundle's pass_id column)."""
    event = json.loads(dumps({"event": name, "source": "mqtt", **args}))
    assert event == {"event": name, "source": "mqtt", **args}
    if "pass_id" in args:
        pid = args["pass_id"]
        assert type(pid) is int and 1 <= pid <= MAX_PASS_ID
        assert int(np.array([PassWindow(pid, 0, 1, "mqtt").pass_id], dtype=np.int64)[0]) == pid
        assert float(pid) == pid  # exact in a JSON reader using doubles
    if "text" in args:
        args["text"].encode("utf-8")


@settings(max_examples=400, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(names, documents)
def test_fuzz_json_documents_never_crash_and_accepted_ones_are_storable(name, doc):
    payload = json.dumps(doc).encode()
    try:
        cmd = parse_command(name, payload)
    except CommandRefused as e:
        refusal = str(e)
    else:
        refusal = None
    if refusal is not None:
        assert refusal  # a refusal always says why
        return
    assert cmd.name == name and set(cmd.args) == set(COMMANDS[name])
    _storable(name, dict(cmd.args))


near_valid = st.one_of(
    st.tuples(
        st.sampled_from(["pass_start", "pass_end"]),
        st.fixed_dictionaries(
            {"pass_id": st.integers(min_value=-(2**64), max_value=2**64) | json_scalars},
            optional={"id": json_scalars},
        ),
    ),
    st.tuples(
        st.just("mark"), st.fixed_dictionaries({"text": st.text(max_size=260)}, optional={"id": json_scalars})
    ),
    st.tuples(st.just("rotate"), st.fixed_dictionaries({}, optional={"id": json_scalars})),
)


@settings(max_examples=600, deadline=None)
@given(near_valid)
def test_fuzz_near_valid_commands_accepted_ones_are_storable(case):
    name, doc = case
    try:
        cmd = parse_command(name, json.dumps(doc).encode())
    except CommandRefused as e:
        refusal = str(e)
    else:
        refusal = None
    if refusal is not None:
        assert refusal.startswith(f"{name}: ")  # the refusal names the command
        return
    _storable(name, dict(cmd.args))
    assert cmd.id is None or isinstance(cmd.id, str | int)


@settings(max_examples=400, deadline=None)
@given(names, st.binary(max_size=2 * MAX_PAYLOAD_BYTES))
def test_fuzz_raw_bytes_never_crash(name, payload):
    try:
        cmd = parse_command(name, payload)
    except CommandRefused:
        return
    _storable(name, dict(cmd.args))


# -- rate limits --------------------------------------------------------------------------------


class FakeClock:
    def __init__(self) -> None:
        self.t = 1000.0

    def __call__(self) -> float:
        return self.t


def test_token_bucket_spends_its_burst_then_refills_at_its_rate():
    clock = FakeClock()
    bucket = TokenBucket(2.0, 3.0, clock)
    assert [bucket.take() for _ in range(5)] == [True, True, True, False, False]
    clock.t += 0.5  # one token back
    assert [bucket.take() for _ in range(2)] == [True, False]
    clock.t += 100.0  # never more than the burst
    assert sum(bucket.take() for _ in range(10)) == 3


def test_rotate_is_limited_more_strictly_than_marks():
    clock = FakeClock()
    limiter = CommandLimiter(clock=clock)
    rotates = [limiter.allow("rotate") for _ in range(100)]  # 100 rotates at one instant
    assert rotates.count(None) == 2
    assert "rotate: rate limited" in next(r for r in rotates if r is not None)
    assert [limiter.allow("mark") for _ in range(5)] == [None] * 5
    assert limiter.allow("mark") is not None
    clock.t += 3.0  # 3 s later: marks are back, rotate not yet
    assert limiter.allow("mark") is None and limiter.allow("rotate") is not None
    clock.t += 30.0
    assert limiter.allow("rotate") is None
    assert limiter.allow("reboot") is None  # unknown kinds are refused by validation, not here


def test_replies_to_refusals_have_their_own_budget():
    clock = FakeClock()
    limiter = CommandLimiter(reply_limit=(1.0, 4.0), clock=clock)
    assert [limiter.may_reply() for _ in range(6)] == [True] * 4 + [False] * 2
    clock.t += 2.0
    assert [limiter.may_reply() for _ in range(3)] == [True, True, False]

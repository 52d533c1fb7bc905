"""Waiting in tests on the condition itself, with a deadline (not a module of tests).

A test that sleeps a fixed time and then checks hopes the machine was quick enough; on a loaded
CI machine it fails, and on a quick one it waits for nothing. :func:`wait_until` (in a thread)
and :func:`wait_until_async` (in an event loop) look at ``predicate`` until it holds and give
back its value; past ``timeout_s`` they raise an AssertionError naming ``what`` was awaited. The
deadline is a bound on a hang, not a measure of speed: make it generous.

Between two looks they wait for a notice: ``changed``, an event (or, in a thread, a condition
variable) that the code under test or the test's own tap sets (notifies) when the state may have
changed, wakes them at once; they look again at the latest after ``interval_s`` all the same (a
state may change without a notice), and that interval is all they have when nobody gives
notice (a predicate on a file, a process, a socket). Where the code under test has an event, a
pipe or a clock of its own to wait on, use that instead.
"""

from __future__ import annotations

import asyncio
import contextlib
import inspect
import threading
import time
from collections.abc import Callable
from typing import Any

Notice = threading.Event | threading.Condition


def _timed_out(timeout_s: float, what: str, detail: Callable[[], str] | None) -> AssertionError:
    text = f"timed out after {timeout_s:g} s waiting for {what}"
    if detail is not None:
        text += f"\n{detail()}"
    return AssertionError(text)


def _next_look(changed: Notice | None, wait_s: float) -> None:
    """Until ``changed`` gives notice or ``wait_s`` passes. An event is cleared once it woke us:
    what set it changed the state before, so the look that follows sees the change. A condition
    is waited on with its lock held by the caller (the look and the wait under one lock: no notice
    falls between them)."""
    if changed is None:
        threading.Event().wait(wait_s)  # nobody gives notice: the next look after wait_s
    elif isinstance(changed, threading.Condition):
        changed.wait(wait_s)
    elif changed.wait(wait_s):
        changed.clear()


def wait_until(
    predicate: Callable[[], Any],
    timeout_s: float,
    what: str,
    *,
    interval_s: float = 0.01,
    between: Callable[[], Any] | None = None,
    detail: Callable[[], str] | None = None,
    fail: bool = True,
    changed: Notice | None = None,
) -> Any:
    """``predicate()`` once it is truthy, looked at when ``changed`` gives notice (a
    ``threading.Event`` that is set, cleared here; a ``threading.Condition`` that is notified,
    the predicate then looked at under its lock) and at least every ``interval_s``;
    ``between()`` runs between looks (it may raise to give up early, e.g. when a process it
    watches has ended). At ``timeout_s`` (the predicate is looked at once more at the deadline):
    AssertionError naming ``what`` (plus ``detail()``), or the falsy value when ``fail`` is False
    (the caller goes on and lets its own assertions say what is missing)."""
    deadline = time.monotonic() + timeout_s
    held = changed if isinstance(changed, threading.Condition) else contextlib.nullcontext()
    with held:
        while True:
            value = predicate()
            if value:
                return value
            left_s = deadline - time.monotonic()
            if left_s <= 0:
                if fail:
                    raise _timed_out(timeout_s, what, detail)
                return value
            if between is not None:
                between()
            _next_look(changed, min(interval_s, left_s))


async def _next_look_async(changed: asyncio.Event | None, wait_s: float) -> None:
    """:func:`_next_look` in an event loop: until ``changed`` is set (then cleared) or ``wait_s``
    passes, the loop running meanwhile."""
    notice = asyncio.Event() if changed is None else changed  # (none: the next look after wait_s)
    try:
        async with asyncio.timeout(wait_s):
            await notice.wait()
    except TimeoutError:
        return
    notice.clear()


async def wait_until_async(
    predicate: Callable[[], Any],
    timeout_s: float,
    what: str,
    *,
    interval_s: float = 0.01,
    detail: Callable[[], str] | None = None,
    fail: bool = True,
    changed: asyncio.Event | None = None,
) -> Any:
    """:func:`wait_until` in an event loop: the loop runs between looks, which come when
    ``changed`` (an ``asyncio.Event``, cleared here) is set and at least every ``interval_s``.
    ``predicate`` may return an awaitable (a coroutine function), which is awaited."""
    deadline = time.monotonic() + timeout_s
    while True:
        value = predicate()
        if inspect.isawaitable(value):
            value = await value
        if value:
            return value
        left_s = deadline - time.monotonic()
        if left_s <= 0:
            if fail:
                raise _timed_out(timeout_s, what, detail)
            return value
        await _next_look_async(changed, min(interval_s, left_s))

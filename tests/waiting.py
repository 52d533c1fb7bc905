"""Waiting in tests on the condition itself, with a deadline (not a module of tests).

A test that sleeps a fixed time and then checks hopes the machine was quick enough; on a loaded
CI machine it fails, and on a quick one it waits for nothing. :func:`wait_until` (in a thread)
and :func:`wait_until_async` (in an event loop) look at ``predicate`` until it holds and give
back its value; past ``timeout_s`` they raise an AssertionError naming ``what`` was awaited. The
deadline is a bound on a hang, not a measure of speed: make it generous. Where the code under
test has an event, a pipe or a clock of its own to wait on, use that instead.
"""

from __future__ import annotations

import asyncio
import inspect
import time
from collections.abc import Callable
from typing import Any


def _timed_out(timeout_s: float, what: str, detail: Callable[[], str] | None) -> AssertionError:
    text = f"timed out after {timeout_s:g} s waiting for {what}"
    if detail is not None:
        text += f"\n{detail()}"
    return AssertionError(text)


def wait_until(
    predicate: Callable[[], Any],
    timeout_s: float,
    what: str,
    *,
    interval_s: float = 0.01,
    between: Callable[[], Any] | None = None,
    detail: Callable[[], str] | None = None,
    fail: bool = True,
) -> Any:
    """``predicate()`` once it is truthy, looked at every ``interval_s``; ``between()`` runs
    between looks (it may raise to give up early, e.g. when a process it watches has ended).
    After ``timeout_s`` (the predicate is looked at once more at the deadline): AssertionError
    naming ``what`` (plus ``detail()``), or the falsy value when ``fail`` is False (the caller
    goes on and lets its own assertions say what is missing)."""
    deadline = time.monotonic() + timeout_s
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() >= deadline:
            if fail:
                raise _timed_out(timeout_s, what, detail)
            return value
        if between is not None:
            between()
        time.sleep(interval_s)


async def wait_until_async(
    predicate: Callable[[], Any],
    timeout_s: float,
    what: str,
    *,
    interval_s: float = 0.01,
    detail: Callable[[], str] | None = None,
    fail: bool = True,
) -> Any:
    """:func:`wait_until` in an event loop: the loop runs between looks. ``predicate`` may
    return an awaitable (a coroutine function), which is awaited."""
    deadline = time.monotonic() + timeout_s
    while True:
        value = predicate()
        if inspect.isawaitable(value):
            value = await value
        if value:
            return value
        if time.monotonic() >= deadline:
            if fail:
                raise _timed_out(timeout_s, what, detail)
            return value
        await asyncio.sleep(interval_s)

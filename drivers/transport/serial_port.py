"""The ``serial`` transport: a serial port (or pty) read by a thread of its own, reopened after a loss.

pyserial opens and configures the port; a thread of its own reads it (:class:`_PortReader`:
``poll`` and ``os.read``, the GIL released while it waits) and stamps the bytes when they are
ready, so a busy event loop delays their decoding but neither their stamp nor their reading (a
pty or UART buffers only a few kB). When the port vanishes (EIO/EOF: a USB adapter unplugged, an
emulator's pty closed) the transport reports ``disconnected`` and reopens the same path — a
stable symlink such as ``/dev/serial/by-id/...`` or an emulator's ``<run dir>/ins`` then reaches
the new device — and reports ``connected``. Every second waited after the INS is back is a
second of navigation lost, so:

- while the path is missing the transport waits for it to appear
  (:func:`drivers.transport.pathwatch.wait_for_path`: inotify, no polling) and opens it at
  once, within milliseconds; it still looks every ``reconnect_max_s`` (0.5 s) in case the watch
  misses it (a link that comes before its target);
- while the path is there but cannot be opened (busy, permissions not yet set by udev) it backs
  off, ``reconnect_min_s`` doubling to ``reconnect_max_s``, starting over when the path
  (re)appears;
- a reopened port keeps what the device sent since it came back: pyserial's ``open`` flushes the
  input (``TCIFLUSH``), which would throw away the first epochs after a replug; only the first
  open of the transport flushes (what waited there may be from before the daemon started).

A slow consumer pauses reading (the kernel buffers) instead of losing bytes.
"""

from __future__ import annotations

import asyncio
import functools
import os
import select
import threading
import time
from collections import deque
from collections.abc import Awaitable, Callable

from drivers.base import DriverError
from drivers.transport.base import Chunk, Transport
from drivers.transport.pathwatch import wait_for_path


class _PortReader:
    """The thread that reads one open serial fd: it waits in ``poll`` (the GIL released), stamps
    the host time as soon as the bytes are ready and hands them to the event loop. A busy loop
    (a burst of profiler datagrams, the log writer holding the GIL) then delays only the
    *decoding* of serial bytes, never their reading: a UART's or pty's kernel buffer holds a few
    kB, which at 100 kB/s is tens of milliseconds. At most ``max_waiting`` chunks wait for the
    consumer; beyond that the thread stops reading (the kernel buffers) until :meth:`resume`."""

    def __init__(
        self,
        fd: int,
        loop: asyncio.AbstractEventLoop,
        deliver: Callable[[Chunk | str], None],
        waiting: Callable[[], int],
        max_waiting: int,
        name: str,
    ) -> None:
        self.fd, self.loop, self.deliver = fd, loop, deliver
        self.waiting, self.max_waiting = waiting, max_waiting
        self.incoming: deque[Chunk | str] = deque()  # appended here, taken in the loop (deque ops are atomic)
        self._wake_r, self._wake_w = os.pipe()
        self._room = threading.Event()
        self._room.set()
        self._stop = False
        self.thread = threading.Thread(target=self._run, name=f"mls-serial-{name}"[:15], daemon=True)
        self.thread.start()

    def _hand_over(self, item: Chunk | str) -> None:
        self.incoming.append(item)
        try:
            self.loop.call_soon_threadsafe(self._in_loop)
        except RuntimeError:  # the loop is closed: nobody reads any more
            self._stop = True

    def _in_loop(self) -> None:
        incoming, deliver = self.incoming, self.deliver
        while incoming:
            deliver(incoming.popleft())

    def _run(self) -> None:
        poller = select.poll()
        poller.register(self.fd, select.POLLIN | select.POLLPRI)
        poller.register(self._wake_r, select.POLLIN)
        while not self._stop:
            if self.waiting() + len(self.incoming) >= self.max_waiting:  # the consumer lags
                self._room.clear()
                if self.waiting() + len(self.incoming) >= self.max_waiting:
                    self._room.wait(0.05)
                continue
            try:
                ready = poller.poll()
            except InterruptedError:
                continue
            if self._stop:
                return
            host_ns = time.monotonic_ns()
            if not any(fd == self.fd for fd, _ in ready):
                continue
            try:
                data = os.read(self.fd, 65536)
            except BlockingIOError:
                continue
            except OSError as exc:
                self._hand_over(f"read failed: {exc.strerror or exc}")
                return
            if not data:
                self._hand_over("end of file (port closed by the other side)")
                return
            self._hand_over(Chunk(data, host_ns))

    def resume(self) -> None:
        self._room.set()

    def stop(self) -> None:
        """End the thread (it returns from ``poll`` at once) and wait for it."""
        self._stop = True
        self._room.set()
        os.write(self._wake_w, b"x")
        if self.thread is not threading.current_thread():
            self.thread.join(2.0)
        os.close(self._wake_r)
        os.close(self._wake_w)


@functools.cache
def _keep_input_port() -> type:  # (made once: pyserial is imported lazily)
    """pyserial's port whose ``open`` keeps the bytes waiting in the input (no ``TCIFLUSH``)."""
    import serial

    class KeepInputSerial(serial.Serial):
        _opening = False

        def open(self) -> None:
            self._opening = True
            try:
                super().open()
            finally:
                self._opening = False

        def _reset_input_buffer(self) -> None:  # reset_input_buffer() still flushes
            if not self._opening:
                super()._reset_input_buffer()

    return KeepInputSerial


class SerialTransport(Transport):
    """A serial port (or pty) read by a thread of its own; reopens the same path after a loss."""

    kind = "serial"

    def __init__(
        self,
        port: str,
        baudrate: int = 115200,
        bytesize: int = 8,
        parity: str = "N",
        stopbits: float = 1,
        name: str | None = None,
        *,
        path_watch: Callable[[str, float], Awaitable[bool]] = wait_for_path,
        **kwargs,
    ) -> None:
        kwargs.setdefault("reconnect_max_s", 0.5)
        super().__init__(name or port, **kwargs)
        self.port = port
        # how a missing path is awaited: (path, timeout s) → it exists (a test watches the wait)
        self.path_watch = path_watch
        self.settings = {"baudrate": baudrate, "bytesize": bytesize, "parity": parity, "stopbits": stopbits}
        self._serial = None
        self._reader: _PortReader | None = None
        self._opened = False  # opened once: a reopened port keeps what waits in its input

    def describe(self) -> str:
        s = self.settings
        return f"serial {self.port} {s['baudrate']} {s['bytesize']}{s['parity']}{s['stopbits']}"

    async def _wait_retry(self, delay_s: float) -> bool:
        """A missing path: wait for it to appear (at most ``reconnect_max_s`` between looks) and
        say so; a path that is there but failed to open: back off ``delay_s``."""
        if os.path.exists(self.port):  # noqa: ASYNC240 (a stat of a device path: no disk, no wait)
            await asyncio.sleep(delay_s)
            return False
        deadline = self._loop.time() + self.reconnect_max_s
        while not self._closing and (left := deadline - self._loop.time()) > 0:
            if await self.path_watch(self.port, left):
                return True
        return False

    async def _connect(self) -> None:
        import serial  # pyserial

        port_class = _keep_input_port() if self._opened else serial.Serial
        try:
            ser = port_class(self.port, timeout=0, exclusive=True, **self.settings)
        except serial.SerialException as exc:
            raise OSError(str(exc)) from exc
        except ValueError as exc:  # a bad setting is a configuration error, not a missing device
            raise DriverError(f"serial {self.port}: {exc}") from exc
        os.set_blocking(ser.fileno(), False)
        self._serial = ser
        self._opened = True
        reader: _PortReader | None = None

        def deliver(item: Chunk | str) -> None:
            if self._reader is not reader:
                return  # from a reader already stopped (a loss raced the thread's last read)
            if isinstance(item, str):
                self._lost(item)
            else:
                self._push(item.data, item.host_ns)

        reader = self._reader = _PortReader(
            ser.fileno(), self._loop, deliver, self._chunks.__len__, self.max_chunks, self.name
        )

    async def _disconnect(self) -> None:
        ser, reader = self._serial, self._reader
        self._serial = self._reader = None
        if reader is not None:
            reader.stop()
        if ser is not None:
            try:
                ser.close()
            except Exception:  # the device is gone; closing it can fail, that is fine
                pass

    def _resume(self) -> None:
        if self._reader is not None:
            self._reader.resume()

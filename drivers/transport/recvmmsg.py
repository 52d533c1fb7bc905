"""Many datagrams per system call: Linux ``recvmmsg(2)`` through :mod:`ctypes`, with each
datagram's kernel receive stamp (``SCM_TIMESTAMPNS``).

Python's socket module reads one datagram per ``recvmsg`` call, and on a virtual machine a
system call (with the GIL released and taken back around it) costs ~10–20 µs: at the full Z+F
rate (~4600 datagrams/s) that alone was a tenth of a core. :class:`MmsgReceiver` fills up to
``slots`` datagrams per call into one preallocated buffer (``slots`` × ``max_datagram`` bytes,
4 MiB by default) and reads the lengths, flags and time stamps of all of them with numpy.

:func:`available` says whether the C library has ``recvmmsg`` (glibc and musl on Linux do);
:mod:`drivers.transport.udp_batch` falls back to one ``recvmsg`` per datagram where it has not.
"""

from __future__ import annotations

import ctypes
import errno
import os
import socket
from collections.abc import Callable

import numpy as np

MSG_DONTWAIT = 0x40
MSG_TRUNC = 0x20
_SCM_TIMESTAMPNS = getattr(socket, "SO_TIMESTAMPNS", 35)


class _Iovec(ctypes.Structure):
    _fields_ = [("iov_base", ctypes.c_void_p), ("iov_len", ctypes.c_size_t)]


class _Msghdr(ctypes.Structure):
    _fields_ = [
        ("msg_name", ctypes.c_void_p),
        ("msg_namelen", ctypes.c_uint32),
        ("msg_iov", ctypes.POINTER(_Iovec)),
        ("msg_iovlen", ctypes.c_size_t),
        ("msg_control", ctypes.c_void_p),
        ("msg_controllen", ctypes.c_size_t),
        ("msg_flags", ctypes.c_int),
    ]


class _Mmsghdr(ctypes.Structure):
    _fields_ = [("msg_hdr", _Msghdr), ("msg_len", ctypes.c_uint)]


_CMSG_SPACE = socket.CMSG_SPACE(16)  # one struct timespec
# one control buffer per slot: struct cmsghdr (size_t len; int level; int type) + timespec
_CMSG = np.dtype(
    {
        "names": ["len", "level", "type", "sec", "nsec"],
        "formats": [np.uintp, np.int32, np.int32, np.int64, np.int64],
        "offsets": [
            0,
            ctypes.sizeof(ctypes.c_size_t),
            ctypes.sizeof(ctypes.c_size_t) + 4,
            socket.CMSG_LEN(0),
            socket.CMSG_LEN(0) + 8,
        ],
        "itemsize": _CMSG_SPACE,
    }
)
_HDR = np.dtype(
    {
        "names": ["controllen", "flags", "len"],
        "formats": [np.uintp, np.int32, np.uint32],
        "offsets": [_Msghdr.msg_controllen.offset, _Msghdr.msg_flags.offset, _Mmsghdr.msg_len.offset],
        "itemsize": ctypes.sizeof(_Mmsghdr),
    }
)

_recvmmsg: Callable[..., int] | None
try:
    _libc = ctypes.CDLL(None, use_errno=True)
    _recvmmsg = _libc.recvmmsg
    _recvmmsg.argtypes = [ctypes.c_int, ctypes.c_void_p, ctypes.c_uint, ctypes.c_int, ctypes.c_void_p]
    _recvmmsg.restype = ctypes.c_int
except (OSError, AttributeError):
    _recvmmsg = None


def available() -> bool:
    return _recvmmsg is not None


class MmsgReceiver:
    """Reads a non-blocking datagram socket ``slots`` datagrams per call."""

    def __init__(self, sock: socket.socket, slots: int = 64, max_datagram: int = 65535) -> None:
        if _recvmmsg is None:
            raise OSError(errno.ENOSYS, "recvmmsg is not available in this C library")
        self._recvmmsg = _recvmmsg
        self.fd = sock.fileno()
        self.slots, self.max_datagram = slots, max_datagram
        self._data = (ctypes.c_char * (slots * max_datagram))()
        self._ctrl = (ctypes.c_char * (slots * _CMSG_SPACE))()
        self._iov = (_Iovec * slots)()
        self._msgs = (_Mmsghdr * slots)()
        data0, ctrl0 = ctypes.addressof(self._data), ctypes.addressof(self._ctrl)
        for i in range(slots):
            self._iov[i].iov_base, self._iov[i].iov_len = data0 + i * max_datagram, max_datagram
            h = self._msgs[i].msg_hdr
            h.msg_iov, h.msg_iovlen = ctypes.pointer(self._iov[i]), 1
            h.msg_control, h.msg_controllen = ctrl0 + i * _CMSG_SPACE, _CMSG_SPACE
        self._view = memoryview(self._data).cast("B")
        # through a memoryview (the same memory): numpy's stubs do not take ctypes arrays
        self._hdr = np.frombuffer(memoryview(self._msgs), dtype=_HDR)
        self._cmsg = np.frombuffer(memoryview(self._ctrl), dtype=_CMSG)

    def receive(self, limit: int | None = None) -> tuple[list[bytes], list[int | None], int]:
        """(datagrams, kernel receive stamps in ``CLOCK_REALTIME`` ns — None where the kernel
        gave none —, how many were truncated and dropped) of what waits now, at most ``limit``
        (and ``slots``). Raises BlockingIOError when nothing waits, OSError on a socket error."""
        vlen = self.slots if limit is None else max(1, min(limit, self.slots))
        n = self._recvmmsg(self.fd, self._msgs, vlen, MSG_DONTWAIT, None)
        if n < 0:
            err = ctypes.get_errno()
            if err in (errno.EAGAIN, errno.EWOULDBLOCK):
                raise BlockingIOError(err, os.strerror(err))
            raise OSError(err, os.strerror(err))
        hdr, cm = self._hdr[:n], self._cmsg[:n]
        stamped = (
            (hdr["controllen"] >= _CMSG_SPACE)
            & (cm["level"] == socket.SOL_SOCKET)
            & (cm["type"] == _SCM_TIMESTAMPNS)
        )
        stamps = np.where(stamped, cm["sec"] * 1_000_000_000 + cm["nsec"], -1).tolist()
        lens, truncated = hdr["len"].tolist(), (hdr["flags"] & MSG_TRUNC).astype(bool).tolist()
        hdr["controllen"] = _CMSG_SPACE  # the kernel wrote the length it used
        view, size = self._view, self.max_datagram
        out, when, bad = [], [], 0
        for i in range(n):
            if truncated[i]:
                bad += 1
                continue
            out.append(bytes(view[i * size : i * size + lens[i]]))
            when.append(stamps[i] if stamps[i] >= 0 else None)
        return out, when, bad

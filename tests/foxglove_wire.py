"""Reading Foxglove's protobuf messages with the descriptors their channel carries (an MCAP
schema, or a WebSocket server's advertisement): the venv has no protobuf package."""

from __future__ import annotations

import struct
from dataclasses import dataclass

_FIXED = {1: "<d", 2: "<f", 6: "<Q", 7: "<I", 15: "<i", 16: "<q"}  # protobuf type → struct format
_ZERO = {1: bytes(8), 2: bytes(4), 6: bytes(8), 7: bytes(4), 15: bytes(4), 16: bytes(8), 9: b"", 12: b""}


def _varint(buf: bytes, i: int) -> tuple[int, int]:
    shift = value = 0
    while True:
        b, i = buf[i], i + 1
        value |= (b & 0x7F) << shift
        if not b & 0x80:
            return value, i
        shift += 7


def _wire(buf: bytes):
    """(field number, wire type, value) of a protobuf message's fields."""
    i = 0
    while i < len(buf):
        key, i = _varint(buf, i)
        num, wt = key >> 3, key & 7
        if wt == 0:
            v, i = _varint(buf, i)
        elif wt in (1, 2, 5):  # 64-bit, length-delimited, 32-bit
            n, i = _varint(buf, i) if wt == 2 else (8 if wt == 1 else 4, i)
            v, i = buf[i : i + n], i + n
        else:
            raise AssertionError(f"wire type {wt}")
        yield num, wt, v


@dataclass
class Descriptors:
    """Message and enum types of a FileDescriptorSet (the MCAP schema data of a protobuf channel)."""

    messages: dict[str, dict[int, tuple[str, int, int, str]]]  # number → (name, type, label, type name)
    enums: dict[str, dict[int, str]]

    @classmethod
    def parse(cls, fds: bytes) -> Descriptors:
        d = cls({}, {})
        for num, _, file in _wire(fds):
            parts = [(n, v) for n, _, v in _wire(file)] if num == 1 else []
            pkg = next((v.decode() for n, v in parts if n == 2), "")
            for n, v in parts:
                if n in (4, 5):  # message_type, enum_type
                    d._add(v, f".{pkg}", enum=n == 5)
        return d

    def _add(self, desc: bytes, prefix: str, enum: bool) -> None:
        parts = [(n, v) for n, _, v in _wire(desc)]
        full = f"{prefix}.{next(v.decode() for n, v in parts if n == 1)}"
        subs = [{k: x for k, _, x in _wire(v)} for n, v in parts if n == 2]  # fields or values
        if enum:
            self.enums[full] = {f.get(2, 0): f[1].decode() for f in subs}
            return
        self.messages[full] = {f[3]: (f[1].decode(), f[5], f.get(4, 1), f.get(6, b"").decode()) for f in subs}
        for n, v in parts:
            if n in (3, 4):  # nested_type, enum_type
                self._add(v, full, enum=n == 4)

    def _scalar(self, ftype: int, tname: str, v):
        if ftype in _FIXED:
            return struct.unpack(_FIXED[ftype], v)[0]
        if ftype in (9, 12):
            return v.decode() if ftype == 9 else bytes(v)
        if ftype == 14:
            return self.enums[tname].get(v, v)
        if ftype in (17, 18):  # zigzag
            return (v >> 1) ^ -(v & 1)
        if ftype in (3, 5) and v >= 1 << 63:  # a negative int64 / int32
            return v - (1 << 64)
        return bool(v) if ftype == 8 else v

    def decode(self, type_name: str, buf: bytes) -> dict:
        """A message → dict: proto3 defaults for absent scalars, None for absent messages, enums
        as their value names."""
        fields = self.messages[type_name]
        out: dict = {}
        for name, ftype, label, tname in fields.values():
            default = None if ftype == 11 else self._scalar(ftype, tname, _ZERO.get(ftype, 0))
            out[name] = [] if label == 3 else default
        for num, wt, v in _wire(buf):
            if num not in fields:
                continue
            name, ftype, label, tname = fields[num]
            if label == 3 and wt == 2 and ftype not in (9, 11, 12):  # packed
                if ftype in _FIXED:
                    size = struct.calcsize(_FIXED[ftype])
                    out[name] += [self._scalar(ftype, tname, v[i : i + size]) for i in range(0, len(v), size)]
                else:
                    i = 0
                    while i < len(v):
                        x, i = _varint(v, i)
                        out[name].append(self._scalar(ftype, tname, x))
                continue
            val = self.decode(tname, v) if ftype == 11 else self._scalar(ftype, tname, v)
            out[name] = [*out[name], val] if label == 3 else val
        return out

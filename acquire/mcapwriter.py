"""The mcap ``Writer`` with a cheaper ``add_message`` for the session log's hot path.

The library builds a ``Message`` object per record and writes it field by field (six
``struct.pack`` calls and buffer writes, ~15 µs a record on the vessel PC's class of CPU: at
the full Z+F rate, ~5000 records/s, a tenth of a core). :class:`SegmentWriter` packs the same
Message record (opcode, record length, channel id, sequence, log time, publish time, data: MCAP
spec, "Message" op 0x05) with one ``struct.pack`` into the open chunk and keeps the chunk's
message index (written with one ``struct.pack`` too), the chunk's time range and the file's
statistics exactly as the library does, so chunks, indexes and summary are byte-for-byte those
of ``Writer.add_message``.

It relies on the ``Writer`` internals of the pinned mcap version (1.6.0: the chunk builder, the
statistics and the chunk size); ``tests/acquire/test_mcapwriter.py`` writes the same records
through both and compares the files, so an upgrade that changes them fails there first. Without
chunking it falls back to the library's method.
"""

from __future__ import annotations

import struct
from itertools import chain

from mcap.opcode import Opcode
from mcap.records import MessageIndex
from mcap.writer import Writer

_MESSAGE_HEAD = struct.Struct("<BQHIQQ")  # opcode, record length, channel id, sequence, log time, publish time
_MESSAGE_FIXED = 2 + 4 + 8 + 8  # the record's bytes before the data


class _MessageIndex(MessageIndex):
    """A chunk's message index, written with one ``struct.pack`` (the library packs each entry's
    two fields separately: at chunk end, the slowest part of the writer after the messages)."""

    def write(self, stream) -> None:
        n = len(self.records)
        stream.start_record(Opcode.MESSAGE_INDEX)
        stream.write(struct.pack(f"<HI{2 * n}Q", self.channel_id, 16 * n, *chain.from_iterable(self.records)))
        stream.finish_record()


class SegmentWriter(Writer):
    def add_message(self, channel_id: int, log_time: int, data: bytes, publish_time: int, sequence: int = 0,
                    head: bytes = b"") -> None:  # fmt: skip
        """The library's ``add_message`` of ``head + data`` (``head``: a prefix written without
        joining the two first, the raw records' envelope header)."""
        chunk = self._Writer__chunk_builder
        if chunk is None:
            return super().add_message(channel_id, log_time, head + data, publish_time, sequence)
        st = self._Writer__statistics
        if st.message_count == 0 or log_time < st.message_start_time:
            st.message_start_time = log_time
        if log_time > st.message_end_time:
            st.message_end_time = log_time
        st.channel_message_counts[channel_id] += 1
        st.message_count += 1
        if chunk.num_messages == 0 or log_time < chunk.message_start_time:
            chunk.message_start_time = log_time
        if log_time > chunk.message_end_time:
            chunk.message_end_time = log_time
        index = chunk.message_indices.get(channel_id)
        if index is None:
            index = chunk.message_indices[channel_id] = _MessageIndex(channel_id=channel_id, records=[])
        buf = chunk.record_writer._buffer
        index.records.append((log_time, buf.tell()))
        chunk.num_messages += 1
        buf.write(_MESSAGE_HEAD.pack(Opcode.MESSAGE, _MESSAGE_FIXED + len(head) + len(data), channel_id, sequence,
                                     log_time, publish_time))  # fmt: skip
        if head:
            buf.write(head)
        buf.write(data)
        if buf.tell() > self._Writer__chunk_size:
            self._Writer__finalize_chunk()

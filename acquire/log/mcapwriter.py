"""The mcap ``Writer`` with a cheaper ``add_message`` for the session log's hot path.

The library builds a ``Message`` object per record and writes it field by field (six
``struct.pack`` calls and buffer writes, ~15 µs a record on the vessel PC's class of CPU: at
the full Z+F rate, ~5000 records/s, a tenth of a core). :class:`SegmentWriter` packs the same
Message record (opcode, record length, channel id, sequence, log time, publish time, data: MCAP
spec, "Message" op 0x05) with one ``struct.pack`` into the open chunk and keeps the chunk's
message index (written with one ``struct.pack`` too), the chunk's time range and the file's
statistics exactly as the library does, so chunks, indexes and summary are byte-for-byte those
of ``Writer.add_message``. :meth:`SegmentWriter.add_run` writes a run of one channel's messages
with one write and one update of the statistics and index (the session log's raw records: the
profiler's datagrams come in runs); ``add_message`` is its run of one.

It relies on the ``Writer`` internals of the pinned mcap version (1.6.0: the chunk builder, the
statistics and the chunk size); ``tests/acquire/log/test_mcapwriter.py`` writes the same records
through both and compares the files, so an upgrade that changes them fails there first. Without
chunking it falls back to the library's method.
"""

from __future__ import annotations

import struct
from collections.abc import Callable
from itertools import chain

from mcap._chunk_builder import ChunkBuilder
from mcap.opcode import Opcode
from mcap.records import MessageIndex, Statistics
from mcap.writer import Writer

_MESSAGE_HEAD = struct.Struct(
    "<BQHIQQ"
)  # opcode, record length, channel id, sequence, log time, publish time
_MESSAGE_FIXED = 2 + 4 + 8 + 8  # the record's bytes before the data
MESSAGE_RECORD_BYTES = (
    1 + 8 + _MESSAGE_FIXED
)  # a Message record without its data (opcode, length, fixed fields)


class _MessageIndex(MessageIndex):
    """A chunk's message index, written with one ``struct.pack`` (the library packs each entry's
    two fields separately: at chunk end, the slowest part of the writer after the messages)."""

    def write(self, stream) -> None:
        n = len(self.records)
        stream.start_record(Opcode.MESSAGE_INDEX)
        stream.write(struct.pack(f"<HI{2 * n}Q", self.channel_id, 16 * n, *chain.from_iterable(self.records)))
        stream.finish_record()


class SegmentWriter(Writer):
    # The ``Writer`` internals this class relies on (name-mangled private attributes of mcap
    # 1.6.0, declared here for the type checker; annotations only, nothing set at runtime).
    _Writer__chunk_builder: ChunkBuilder | None
    _Writer__chunk_size: int
    _Writer__statistics: Statistics
    _Writer__finalize_chunk: Callable[[], None]

    def add_message(
        self,
        channel_id: int,
        log_time: int,
        data: bytes,
        publish_time: int,
        sequence: int = 0,
        head: bytes = b"",
    ) -> None:
        """The library's ``add_message`` of ``head + data`` (``head``: a prefix written without
        joining the two first, the raw records' envelope header)."""
        self.add_run(channel_id, [(log_time, publish_time, sequence, head, data)])

    def chunk_room(self) -> int | None:
        """Bytes of Message records the open chunk takes before it is complete (the record that
        crosses the chunk size completes it); None without chunking."""
        chunk = self._Writer__chunk_builder
        if chunk is None:
            return None
        return self._Writer__chunk_size - chunk.record_writer._buffer.tell()

    def add_run(self, channel_id: int, messages: list[tuple[int, int, int, bytes, bytes]]) -> None:
        """:meth:`add_message` of each ``(log_time, publish_time, sequence, head, data)`` of one
        channel, in order, with one write and the statistics, time ranges and message index
        updated once: the same bytes. With chunking, only the last message may cross
        :meth:`chunk_room` (the caller cuts the run there); the chunk is then completed."""
        chunk = self._Writer__chunk_builder
        if chunk is None:
            for log_time, publish_time, sequence, head, data in messages:
                super().add_message(channel_id, log_time, head + data, publish_time, sequence)
            return
        if not messages:
            return
        times = [m[0] for m in messages]
        lo, hi, k = min(times), max(times), len(messages)
        st = self._Writer__statistics
        if st.message_count == 0 or lo < st.message_start_time:
            st.message_start_time = lo
        if hi > st.message_end_time:
            st.message_end_time = hi
        st.channel_message_counts[channel_id] += k
        st.message_count += k
        if chunk.num_messages == 0 or lo < chunk.message_start_time:
            chunk.message_start_time = lo
        if hi > chunk.message_end_time:
            chunk.message_end_time = hi
        index = chunk.message_indices.get(channel_id)
        if index is None:
            index = chunk.message_indices[channel_id] = _MessageIndex(channel_id=channel_id, records=[])
        buf = chunk.record_writer._buffer
        pos = buf.tell()
        parts: list[bytes]
        parts, entries, pack, message, fixed = (
            [],
            index.records,
            _MESSAGE_HEAD.pack,
            Opcode.MESSAGE,
            _MESSAGE_FIXED,
        )
        for log_time, publish_time, sequence, head, data in messages:
            size = fixed + len(head) + len(data)
            entries.append((log_time, pos))
            parts += (pack(message, size, channel_id, sequence, log_time, publish_time), head, data)
            pos += MESSAGE_RECORD_BYTES - fixed + size
        chunk.num_messages += k
        buf.write(b"".join(parts))
        if pos > self._Writer__chunk_size:
            self._Writer__finalize_chunk()

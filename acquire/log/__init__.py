"""The session log: crash-safe MCAP segments, their salvage, and reading them back.

- ``schema``: the message encodings of a session's channels (envelope, raw record heads).
- ``mcapwriter``: the mcap ``Writer`` with a cheaper ``add_message`` for the hot path.
- ``session``: a session directory's names, :class:`SessionOptions`, ``LogError``, ``fsync_dir``.
- ``segments``: the writer thread's segments: records in, chunks, fsync, rotation, write failures.
- ``diskspace``: the log file system's free space and the ``disk_low`` alarm, checked while writing.
- ``sessionlog``: :class:`SessionWriter`, the bounded queue and writer thread of one session.
- ``batch``: batching records from the event loop to the session writer (the hot path).
- ``recover``: scanning, salvaging and summarizing sessions (``mls logs info`` / ``recover``).
- ``read``: a session's messages read back, every segment in order, decoded; what it lost (torn segments).
- ``indexed``: a few channels of a closed segment read through its MCAP index (read's fast path).
- ``profiles``: the profiler's datagrams of a session, decoded once and timed (export, Foxglove).
"""

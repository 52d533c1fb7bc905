"""Line guidance for the calibration passes, in the daemon and to the autopilot.

- ``lines``: the guidance settings and the line geometry (pure): offsets, heading error, capture window.
- ``targethits``: the live target hits of a batch of profiles (pure).
- ``prechecks``: the pre-survey checks and the disk the planned passes need (pure).
- ``acceptance``: the acceptance of a sailed capture window, every failed condition a reason (pure).
- ``tracking``: :class:`PassTracker`, the capture windows of the lines and their verdicts.
- ``state``: :class:`Guidance`, the tracking plus the σ prediction and the checklist message.
- ``consumer``: :class:`GuidanceConsumer`, a :class:`Guidance` run on the daemon's record stream.
- ``daemon``: the guidance of a vessel config and its wiring to the supervisor.
- ``autopilot``: the autopilot sentences (``$--XTE``, ``$--APB``) for the active line.
- ``autopilot_out``: sending the autopilot sentences (``mls plan --nmea``).
"""

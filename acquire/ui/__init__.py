"""The operator's screens.

- ``checklist_app``: ``mls checklist``, the Textual screen of the calibration survey.
- ``panels``: its panels as Rich text, pure functions of the status messages and the room.
- ``fit``: fitting text to the room without cutting it (short forms, wrapping).
- ``planview``: a plan view of the active line in Unicode braille.
"""

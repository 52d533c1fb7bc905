"""The operator's screens.

- ``checklist_app``: ``mls checklist``, the Textual screen of the calibration survey.
- ``planview``: a plan view of the active line in Unicode braille.
"""

"""Assessment of a calibration (thesis §4.4.6, §4.5.4–4.5.5; docs/architecture.md §7 "Assessment"): relative
accuracy before and after it, and the history of the results.

Modules (each imports only those above it):

- ``c2c``: cloud-to-cloud distances with a local least-squares plane model (CloudCompare's C2C).
- ``history``: every boresight result in a local SQLite database, and whether two calibrations
  differ.
- ``results``: the options and the results of a relative accuracy assessment (``AssessError``).
- ``mounts``: the mounts compared, from a calibration result (*after*) and from truth.json.
- ``pairs``: the pairs of passes compared (sailed headings, reciprocal pairs, ``--pairs``).
- ``surfaces``: the surfaces compared and their returns (validation planes, automatic patches).
- ``expected``: the expected level of the C2C after a calibration (sensors' noise, POS errors,
  the result's boresight σ).
- ``comparison``: the assessment itself, the C2C of each surface and overlap before and after.
- ``summary``: the report: the summary in words, figures, ``assessment.md`` and
  ``assessment.json``.
"""

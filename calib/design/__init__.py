"""Site design (docs/architecture.md §7 "Design study"; thesis Chapters 3–4 as a tool): which targets,
inclinations, sizes and passes observe the boresight best, before and during the survey.

Modules (each imports only those above it, ``criteria`` and ``passpredict`` none of the others):

- ``criteria``: the systematic-error visibility criteria (Type I, Type II) of one target, pass
  by pass.
- ``passpredict``: the predicted boresight σ during the survey, pass by pass, and the next pass
  that helps most (the GLS estimator's σ by default).
- ``prediction``: the predicted σ of the boresight for a configuration (observation sigmas,
  observations of a simulated design scene, the six error models — GLS, the calibration's
  default estimator, gives the realistic σ); ``DesignError``.
- ``scenes``: design scenes, the targets placed on a base scenario's site.
- ``layouts``: the study's specification and its candidate target / inclination / pass layouts.
- ``study``: running the study (the rows of ``sigma.csv``, tasks in parallel processes, the
  recommendation).
- ``summary``: the study's tables, figures, findings, ``recommendation.json`` and ``summary.md``.
- ``montecarlo``: the Monte Carlo check of a prediction.
- ``sitecheck``: the Monte Carlo check of a recommendation beside the scenario's own site
  (``mls design --seeds``).
- ``whatif``: the predicted σ of a planned site config after each pass (``mls design --site``).
"""

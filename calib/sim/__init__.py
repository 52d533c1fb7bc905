"""The MLS simulator: a scenario and a seed in, a calibration bundle's content and its truth out.

Modules, each importing only modules above it:

- ``surfaceshape``: a surface's waviness and roughness, a fixed displacement field along its
  normal, and where a ray meets the displaced surface;
- ``scene``: planar rectangles (optionally shaped) and exact, vectorized ray casting against them;
- ``motion``: vessel motion along a pass plan → the true trajectory;
- ``noise``: random errors of the scanner's observations and of the POS;
- ``scenario``: a scenario (surfaces in the site frame, injected errors, scanner, motion and
  noise models) and the scene and site config that follow from it;
- ``scenariofile``: scenario YAML files (shipped ones by name, or any path), validated, with
  ``key=value`` overrides on dotted keys;
- ``simulate``: the simulation itself (profiles, observations, the observed trajectory, truth).
"""

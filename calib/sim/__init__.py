"""The MLS simulator: a scenario and a seed in, a calibration bundle's content and its truth out.

Modules, each importing only modules above it:

- ``surfaceshape``: a surface's waviness and roughness, a fixed displacement field along its
  normal, and where a ray meets the displaced surface;
- ``cylinders``: vertical cylinders (piles): where a ray enters one, and the scan-angle sector
  one occupies in a profiler's scan plane;
- ``scene``: planar rectangles (optionally shaped) and vertical cylinders, and exact, vectorized
  ray casting against them;
- ``motion``: vessel motion along a pass plan → the true trajectory;
- ``noise``: random errors of the scanner's observations and of the POS;
- ``scenario``: a scenario (surfaces and piles in the site frame, injected errors, scanner, motion and
  noise models, optionally a production survey and its mount event) and the scene and site
  config that follow from it;
- ``harbour``: the harbour front a production survey sails along (walls, piles, fenders, hulls),
  and the swell that moves its moored hulls;
- ``scenariofile``: scenario YAML files (shipped ones by name, or any path), validated, with
  ``key=value`` overrides on dotted keys;
- ``randomdraw``: the randomized calibration scenario (``random``): a geometry drawn from a
  seed (mount tilt, wall azimuth, standoff, targets, contrast, waviness, lever arm, boresight,
  POS noise, headings), read as a scenario document, its passes placed from the standoff;
- ``scanning``: the profiler's exact returns (profiles cast against the scene with the true mount);
- ``result``: what a simulation produced and how returns become observations and truth;
- ``production``: the production survey (lines along the harbour front, the mount event);
- ``simulate``: the simulation itself (passes around the targets, or a production survey).
"""

"""From raw points to what the adjustment uses: the targets of each pass and the scene's planar
tie patches.

- ``points``: raw scanner points georeferenced pass by pass;
- ``segmentation``: point-cloud building blocks (RANSAC plane, intensity split, incidence
  correction, clusters, extents);
- ``extract``: target planes extracted from each pass's points;
- ``patches``: candidate tie patches: planar cells of the scene seen from several headings;
- ``cylinders``: candidate tie cylinders: vertical piles and posts seen from several headings.
"""

"""The ``mls`` command line (:mod:`cli.app`): the top layer, the only code that imports both
``acquire`` and ``sim_devices``. It parses options, calls the libraries, prints and maps
outcomes to exit codes; the work itself lives in ``calib``, ``drivers``, ``acquire`` and
``sim_devices``."""

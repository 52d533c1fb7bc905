"""Commands on a production survey's records: ``mls export`` (bundles, Foxglove), ``mls georef``
(deliverable tiles) and ``mls watch`` (the mount watch after the fact)."""

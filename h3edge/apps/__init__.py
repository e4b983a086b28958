"""Applications on top of the service and the mapper: offline runs (``h3edge map``), the
one-machine demo (``h3edge demo``), the service daemon (``h3edge serve``) and the Rerun viewer
(``h3edge view``)."""

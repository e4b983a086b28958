"""Benchmarks: scripts that print a table and write JSON (run as python -m benchmarks.NAME).

They run the mapper as the service and the CLI do: idle OpenMP workers sleep rather than spin
(:func:`h3edge.mapping.threads.passive_environment`, set here before any benchmark loads torch; a
value already in the environment wins).
"""

from h3edge.mapping.threads import passive_environment

passive_environment()

"""Benchmarks: scripts that print a table and write JSON (run as python -m h3edge.bench.NAME)."""

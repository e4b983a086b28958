"""Serving: the map service (ingest, mapper thread, queries, checkpoints), its zenoh transport,
the query client and the simulated publisher, systemd integration."""

"""Serving: the map service (ingest, ROS 2 input, mapper thread, queries, checkpoints, live
outputs), its zenoh transport, the query client and the publishers, systemd integration."""

"""Serving: the map service (ingest, ROS 2 input, mapper thread, queries, checkpoints, live
outputs), its zenoh server (``server.py``), the typed query client (``client.py``,
``h3edge.Client``), systemd integration."""

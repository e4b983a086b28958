"""Simulated RGB-D data: a procedural textured room, its trajectory, sensor model and writer."""

"""Shared geometry: the camera model and pixel convention, pose maths, the CPU mesh ray caster."""

"""Mapping core: the H3-Mapping representation, training and extraction (issues 2/6 and 3/6)."""

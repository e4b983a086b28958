"""Mapping core: the H3-Mapping representation (voxels, priors, hash grids, texture grids), its
training and keyframes, rendering at a pose, meshes, map copies and the mapper state."""

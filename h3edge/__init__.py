"""h3edge: real-time neural RGB-D mapping (H3-Mapping) as an edge service over Eclipse Zenoh.

Packages follow the data: ``io`` (RGB-D sequences in) -> ``mapping`` (the H3-Mapping core) ->
serving (zenoh service, later issues); ``geometry`` holds the camera convention and the CPU ray
caster every stage shares, ``sim`` the simulated scene, ``eval`` the paper's metrics.
"""

__version__ = "0.1.0"

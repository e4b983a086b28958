"""h3edge: real-time neural RGB-D mapping (H3-Mapping) for edge devices, as a library and as a
service over Eclipse Zenoh.

The library is :class:`h3edge.Mapper` (``from h3edge import Mapper``; docs/python-api.md). Packages
follow the data: ``geometry`` (the camera convention, the CPU ray caster) and ``profiling`` ->
``io`` (RGB-D sequences, messages in) -> ``mapping`` (the H3-Mapping core, the map file) ->
``api`` (the :class:`Mapper` façade) -> ``serving`` (the zenoh service, :class:`Client`, its typed
client, and :class:`Fleet`, many services asked as one map) -> applications (``cli``,
``apps``); ``sim`` makes the simulated scene, ``eval`` holds the paper's metrics.
"""

__version__ = "0.1.0"
__all__ = ["Client", "Fleet", "Intrinsics", "MapSettings", "MapSnapshot", "Mapper", "__version__"]


def __getattr__(name: str):
    """The library's names, imported on first use (``import h3edge`` and ``h3edge --version`` stay
    light: no torch)."""
    if name in ("Mapper", "MapSnapshot"):
        from h3edge import api

        return getattr(api, name)
    if name == "Client":
        from h3edge.serving.client import Client

        return Client
    if name == "Fleet":
        from h3edge.serving.fleet import Fleet

        return Fleet
    if name == "MapSettings":
        from h3edge.mapping.engine import MapSettings

        return MapSettings
    if name == "Intrinsics":
        from h3edge.geometry.camera import Intrinsics

        return Intrinsics
    raise AttributeError(f"module 'h3edge' has no attribute {name!r}")

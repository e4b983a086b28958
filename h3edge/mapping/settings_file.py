"""Map settings read from files: a profile's mapping tables (TOML) or a saved map's header (JSON)
onto the typed dataclasses of :class:`~h3edge.mapping.engine.MapSettings`, every key checked.

One home for turning a table of plain values into a settings section: ``h3edge.config`` reads a
whole profile (mapping, service, evaluation, ROS tables) with the same :func:`section`, and the
library (:meth:`h3edge.MapEngine.from_profile`, :meth:`h3edge.MapEngine.load`) reads only the mapping
tables, so it needs nothing from the service layer.
"""

from __future__ import annotations

import dataclasses
import logging
import sys
import typing
from pathlib import Path

if sys.version_info >= (3, 11):
    import tomllib
else:  # JetPack 6's Python 3.10
    import tomli as tomllib

from h3edge.errors import InputError
from h3edge.mapping.engine import MapSettings
from h3edge.mapping.field import FieldConfig
from h3edge.mapping.raymarch import RenderConfig, floor_window_weight

log = logging.getLogger(__name__)

# The shipped profiles (package data); the repository's top-level profiles/ holds the same files.
PROFILES_DIR = Path(__file__).resolve().parents[1] / "profiles"
MAPPING_TABLES = frozenset(f.name for f in dataclasses.fields(MapSettings))
SAVED_FREE_FLOOR = 0.5  # truncation units: what a saved map's refused render floor is read as (x86-cpu's, D53-7)


class ProfileError(InputError):
    """An invalid profile file or saved settings: the message names the file, table and key."""


def _coerce(value, tp, where: str):
    if tp is float and isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    if tp in (int, float, str, bool) and not (isinstance(value, tp) and not (tp is int and isinstance(value, bool))):
        raise ProfileError(f"{where}: expected {tp.__name__}, got {type(value).__name__} {value!r}")
    return value


def section(cls, table: dict, where: str, unknown: str = "error"):
    """The settings dataclass ``cls`` from a table of plain values (int, float, str, bool), each
    checked against the field's type; missing keys keep the dataclass default. A key ``cls`` does
    not have is a ProfileError (``unknown="error"``) or is dropped with a warning
    (``unknown="drop"``: a file written by another version); so is a value the section's own check
    refuses (``__post_init__``)."""
    if not isinstance(table, dict):
        raise ProfileError(f"{where} must be a table")
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    kwargs = {}
    for key, value in table.items():
        if key not in names:
            if unknown == "drop":
                log.warning("%s: setting %r does not exist in this version; ignored", where, key)
                continue
            raise ProfileError(f"{where}: unknown key {key!r} (known: {', '.join(sorted(names))})")
        if hints[key] not in (int, float, str, bool):
            if unknown == "drop":  # a saved nested section (train.weights): its own table is the source
                continue
            raise ProfileError(f"{where}: {key!r} is not settable here (it has its own table)")
        kwargs[key] = _coerce(value, hints[key], f"{where}.{key}")
    try:
        return cls(**kwargs)
    except ValueError as e:  # a section's own check (__post_init__)
        raise ProfileError(f"{where}: {e}") from None


def profile_path(name_or_path: str | Path) -> Path:
    """The file of a profile: a path as given, or a bare name like ``x86-cpu`` for a shipped one."""
    p = Path(name_or_path)
    return PROFILES_DIR / f"{p.name}.toml" if not p.suffix and not p.exists() else p


def read_profile_tables(name_or_path: str | Path) -> tuple[Path, dict]:
    """(the file, its top-level tables) of a profile; ProfileError when it is missing or not TOML."""
    p = profile_path(name_or_path)
    try:
        return p, tomllib.loads(p.read_text())
    except FileNotFoundError:
        raise ProfileError(f"{p}: profile not found") from None
    except tomllib.TOMLDecodeError as e:
        raise ProfileError(f"{p}: {e}") from None


def map_settings(tables: dict, where: str, unknown: str = "error") -> MapSettings:
    """:class:`MapSettings` from its tables (``[mapper]``, ``[voxels]``, ...); tables that are not
    mapping sections are left to the caller. ``unknown`` as :func:`section`."""
    hints = typing.get_type_hints(MapSettings)
    parts = {k: section(hints[k], v, f"{where}: [{k}]", unknown) for k, v in tables.items() if k in MAPPING_TABLES}
    try:
        return MapSettings(**parts)
    except ValueError as e:
        raise ProfileError(f"{where}: {e}") from None


def map_settings_from_profile(name_or_path: str | Path) -> MapSettings:
    """The mapping settings of a profile (a shipped name such as ``x86-cpu`` or a TOML path); its
    service, evaluation and ROS tables are not read here (``h3edge.config.load_profile`` reads them)."""
    p, data = read_profile_tables(name_or_path)
    return map_settings(data, str(p))


def map_settings_from_saved(saved: dict, where: str) -> MapSettings:
    """The settings a map was saved with (``dataclasses.asdict`` of its :class:`MapSettings`); a
    setting this version no longer has is dropped with a warning, a missing one takes its default.
    A render floor this version refuses (D53-7: a map saved at 0.1) is read as the shipped
    ``SAVED_FREE_FLOOR``, with a warning: how a map renders is not what it holds."""
    render = saved.get("render")
    if isinstance(render, dict) and isinstance(saved.get("field", {}), dict):
        beta = saved.get("field", {}).get("beta", FieldConfig.beta)
        known = {f.name for f in dataclasses.fields(RenderConfig)}  # the others are warned about once, below
        cfg = section(RenderConfig, {k: v for k, v in render.items() if k in known}, f"{where}: [render]")
        if (cfg.free_floor > 0 and isinstance(beta, (int, float)) and beta > 0
                and floor_window_weight(cfg, beta) >= cfg.min_weight):
            log.warning("%s: render.free_floor = %g lets seen-free space render (D53-7); read as %g", where,
                        cfg.free_floor, SAVED_FREE_FLOOR)
            saved = {**saved, "render": {**render, "free_floor": SAVED_FREE_FLOOR}}
    return map_settings(saved, where, unknown="drop")

"""Device profiles: ``h3edge/profiles/*.toml`` (package data) loaded into typed dataclasses.

Each TOML table maps onto one dataclass section of :class:`Profile`; every key must be a field
of it (a typo is an error naming the file, table and key, not a silently ignored setting) and
values are checked against the field's type. Missing keys keep the dataclass default, which is
the paper's value where the paper has one.
"""

from __future__ import annotations

import dataclasses
import json
import sys
import typing
from dataclasses import dataclass
from pathlib import Path

if sys.version_info >= (3, 11):
    import tomllib
else:  # JetPack 6's Python 3.10
    import tomli as tomllib

from h3edge.errors import InputError
from h3edge.eval.evaluate import EvalConfig
from h3edge.io.ros import RosConfig
from h3edge.mapping.mapper import MapSettings
from h3edge.mapping.onnx_decoders import InferenceConfig
from h3edge.serving.service import ServiceConfig

# Shipped inside the package (package data); the repository's top-level profiles/ links here.
PROFILES_DIR = Path(__file__).resolve().parent / "profiles"


class ProfileError(InputError):
    """An invalid profile file: the message names the file, table and key."""


@dataclass(frozen=True)
class Profile:
    """A device profile: the mapper's settings (one TOML table per :class:`MapSettings` section:
    ``[mapper]``, ``[voxels]``, ...), plus evaluation, service and query-inference settings
    (``[eval]``, ``[service]``, ``[inference]``, ``[ros]``)."""

    name: str = "default"
    mapping: MapSettings = dataclasses.field(default_factory=MapSettings)
    eval: EvalConfig = dataclasses.field(default_factory=EvalConfig)
    service: ServiceConfig = dataclasses.field(default_factory=ServiceConfig)
    inference: InferenceConfig = dataclasses.field(default_factory=InferenceConfig)
    ros: RosConfig = dataclasses.field(default_factory=RosConfig)  # used by ``h3edge serve --ros``

    def map_settings(self) -> MapSettings:
        return self.mapping

    def with_device(self, device: str) -> Profile:
        """This profile with the mapper on ``device`` (cpu, cuda, auto)."""
        mapping = dataclasses.replace(self.mapping, mapper=dataclasses.replace(self.mapping.mapper, device=device))
        return dataclasses.replace(self, mapping=mapping)


def _coerce(value, tp, where: str):
    if tp is float and isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    if tp in (int, float, str, bool) and not (isinstance(value, tp) and not (tp is int and isinstance(value, bool))):
        raise ProfileError(f"{where}: expected {tp.__name__}, got {type(value).__name__} {value!r}")
    return value


def _section(cls, table: dict, where: str):
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    kwargs = {}
    for key, value in table.items():
        if key not in names:
            raise ProfileError(f"{where}: unknown key {key!r} (known: {', '.join(sorted(names))})")
        if hints[key] not in (int, float, str, bool):
            raise ProfileError(f"{where}: {key!r} is not settable here (it has its own table)")
        kwargs[key] = _coerce(value, hints[key], f"{where}.{key}")
    try:
        return cls(**kwargs)
    except ValueError as e:  # a section's own check (__post_init__)
        raise ProfileError(f"{where}: {e}") from None


def load_profile(path: str | Path) -> Profile:
    """Load a profile file; a bare name like ``x86-cpu`` is one of the profiles shipped in the package."""
    p = Path(path)
    if not p.suffix and not p.exists():
        p = PROFILES_DIR / f"{p.name}.toml"
    try:
        data = tomllib.loads(p.read_text())
    except FileNotFoundError:
        raise ProfileError(f"{p}: profile not found") from None
    except tomllib.TOMLDecodeError as e:
        raise ProfileError(f"{p}: {e}") from None
    own = {f.name for f in dataclasses.fields(Profile)} - {"name", "mapping"}
    mapping_sections = {f.name for f in dataclasses.fields(MapSettings)}
    kwargs: dict = {"name": data.pop("name", p.stem)}
    mapping: dict = {}
    for key, value in data.items():
        if key not in own | mapping_sections:
            raise ProfileError(f"{p}: unknown table [{key}] (known: {', '.join(sorted(own | mapping_sections))})")
        if not isinstance(value, dict):
            raise ProfileError(f"{p}: [{key}] must be a table")
        owner = Profile if key in own else MapSettings
        section = _section(typing.get_type_hints(owner)[key], value, f"{p}: [{key}]")
        (kwargs if key in own else mapping)[key] = section
    return Profile(mapping=MapSettings(**mapping), **kwargs)


def apply_overrides(settings: MapSettings, overrides: list[str]) -> MapSettings:
    """``section.key=value`` overrides on :class:`MapSettings` (values parsed as JSON, else strings)."""
    for item in overrides:
        key, _, raw = item.partition("=")
        section, _, name = key.partition(".")
        try:
            value = json.loads(raw)
        except ValueError:
            value = raw
        sub = getattr(settings, section)
        settings = dataclasses.replace(settings, **{section: dataclasses.replace(sub, **{name: value})})
    return settings


def parse_variant(spec: str, base: MapSettings) -> tuple[str, MapSettings]:
    """``'LABEL:section.key=value;section.key=value'`` -> (label, ``base`` with those overrides)."""
    label, _, sets = spec.partition(":")
    return label, apply_overrides(base, [x for x in sets.split(";") if x])

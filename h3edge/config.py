"""Device profiles: ``h3edge/profiles/*.toml`` (package data) loaded into typed dataclasses (the
mapping tables through :mod:`h3edge.mapping.settings_file`, which the library reads on its own).

Each TOML table maps onto one dataclass section of :class:`Profile`; every key must be a field
of it (a typo is an error naming the file, table and key, not a silently ignored setting) and
values are checked against the field's type. Missing keys keep the dataclass default, which is
the paper's value where the paper has one.
"""

from __future__ import annotations

import dataclasses
import json
import typing
from dataclasses import dataclass
from pathlib import Path

from h3edge.eval.evaluate import EvalConfig
from h3edge.io.ros import RosConfig
from h3edge.mapping.engine import MapSettings
from h3edge.mapping.onnx_decoders import InferenceConfig
from h3edge.mapping.settings_file import MAPPING_TABLES, ProfileError, map_settings, read_profile_tables, section
from h3edge.serving.service import ServiceConfig


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


def load_profile(path: str | Path) -> Profile:
    """Load a profile file; a bare name like ``x86-cpu`` is one of the profiles shipped in the package."""
    p, data = read_profile_tables(path)
    own = {f.name for f in dataclasses.fields(Profile)} - {"name", "mapping"}
    kwargs: dict = {"name": data.pop("name", p.stem)}
    for key, value in data.items():
        if key not in own | MAPPING_TABLES:
            raise ProfileError(f"{p}: unknown table [{key}] (known: {', '.join(sorted(own | MAPPING_TABLES))})")
        if not isinstance(value, dict):
            raise ProfileError(f"{p}: [{key}] must be a table")
        if key in own:
            kwargs[key] = section(typing.get_type_hints(Profile)[key], value, f"{p}: [{key}]")
    return Profile(mapping=map_settings(data, str(p)), **kwargs)


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

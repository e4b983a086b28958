"""Device profiles: ``h3edge/profiles/*.toml`` (package data) loaded into typed dataclasses (the
mapping tables through :mod:`h3edge.mapping.settings_file`, which the library reads on its own).

Each TOML table maps onto one dataclass section of :class:`Profile`; every key must be a field
of it (a typo is an error naming the file, table and key, not a silently ignored setting) and
values are checked against the field's type. Missing keys keep the dataclass default, which is
the paper's value where the paper has one.
"""

from __future__ import annotations

import ast
import dataclasses
import inspect
import json
import re
import sys
import textwrap
import typing
from dataclasses import dataclass
from pathlib import Path

from h3edge.eval.evaluate import EvalConfig
from h3edge.io.ros import RosConfig
from h3edge.mapping.engine import MapSettings
from h3edge.mapping.onnx_decoders import InferenceConfig
from h3edge.mapping.settings_file import (
    MAPPING_TABLES,
    PROFILES_DIR,
    ProfileError,
    map_settings,
    read_profile_tables,
    section,
)
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


def parse_override(item: str) -> tuple[str, str, object]:
    """``'section.key=value'`` -> (section, key, value); the value parsed as JSON, else a string."""
    key, _, raw = item.partition("=")
    section, _, name = key.partition(".")
    try:
        value = json.loads(raw)
    except ValueError:
        value = raw
    return section, name, value


def apply_overrides(settings: MapSettings, overrides: list[str]) -> MapSettings:
    """``section.key=value`` overrides on :class:`MapSettings` (:func:`parse_override`)."""
    for item in overrides:
        section, name, value = parse_override(item)
        sub = getattr(settings, section)
        settings = dataclasses.replace(settings, **{section: dataclasses.replace(sub, **{name: value})})
    return settings


def parse_variant(spec: str, base: MapSettings) -> tuple[str, MapSettings]:
    """``'LABEL:section.key=value;section.key=value'`` -> (label, ``base`` with those overrides)."""
    label, _, sets = spec.partition(":")
    return label, apply_overrides(base, [x for x in sets.split(";") if x])


def field_docs(cls) -> dict[str, str]:
    """Field name -> its docstring (the string literal under the field in ``cls``'s body)."""
    tree = ast.parse(textwrap.dedent(inspect.getsource(cls)))
    body = tree.body[0].body
    out = {}
    for k, st in enumerate(body):
        nxt = body[k + 1] if k + 1 < len(body) else None
        if (isinstance(st, ast.AnnAssign) and isinstance(st.target, ast.Name) and isinstance(nxt, ast.Expr)
                and isinstance(nxt.value, ast.Constant) and isinstance(nxt.value.value, str)):
            out[st.target.id] = " ".join(nxt.value.value.split())
    return out


def sections() -> list[tuple[str, type]]:
    """(TOML table, settings dataclass) of every table a profile may hold, in file order."""
    hints = typing.get_type_hints(MapSettings)
    own = typing.get_type_hints(Profile)
    return ([(f.name, hints[f.name]) for f in dataclasses.fields(MapSettings)]
            + [(name, own[name]) for name in ("eval", "service", "inference", "ros")])


def _profile_value(profile: Profile, table: str, key: str, default) -> str:
    """A profile's value of ``[table] key`` for the reference: ``.`` where it is the default."""
    section_ = getattr(profile.mapping, table) if table in MAPPING_TABLES else getattr(profile, table)
    value = getattr(section_, key)
    return "." if value == default else f"`{value!r}`"


def reference_markdown() -> str:
    """docs/configuration.md: every table and key a profile may set, its type, its default, the
    shipped profiles' values where they differ, and its docstring (``python -m h3edge.config``
    writes it; a test keeps the file equal to this)."""
    shipped = sorted(p.stem for p in PROFILES_DIR.glob("*.toml"))
    profiles = {name: load_profile(name) for name in shipped}
    lines = ["# Configuration reference", "",
             "Every setting a profile (`h3edge/profiles/*.toml`, or a TOML file of your own passed as",
             "`--profile PATH` / `Mapper.from_profile(PATH)`) may hold: one table per section, one key per",
             "field. A key a table does not have is an error naming the file, table and key; a missing key",
             "takes the default. Where a shipped profile sets another value, its column shows it (`.`: the",
             "default); `research/decisions.md` says why, by the decision id in the profile's comment.",
             "Generated from the dataclasses' field docstrings (`python -m h3edge.config >",
             "docs/configuration.md`); the test suite fails when this file is out of date.", ""]
    for table, cls in sections():
        docs = field_docs(cls)
        hints = typing.get_type_hints(cls)
        lines += [f"## [{table}]", ""]
        if cls.__doc__ and not cls.__doc__.startswith(cls.__name__ + "("):  # not dataclass's generated one
            lines += [" ".join(cls.__doc__.split("\n\n")[0].split()), ""]
        lines += ["| key | type | default | " + " | ".join(shipped) + " | what |",
                  "|---|---|---|" + "---|" * len(shipped) + "---|"]
        for f in dataclasses.fields(cls):
            if hints[f.name] not in (int, float, str, bool):
                continue  # a nested section: its own table
            values = [_profile_value(profiles[n], table, f.name, f.default) for n in shipped]
            lines.append(f"| `{f.name}` | {hints[f.name].__name__} | `{f.default!r}` | " + " | ".join(values)
                         + f" | {docs.get(f.name, '').replace('|', '/')} |")
        lines.append("")
    return "\n".join(lines)


def profile_comments(name: str) -> dict[tuple[str, str], str]:
    """(table, key) -> the comment a shipped profile's TOML gives that key (the comment lines right
    above it and the one on its line), as one line."""
    out: dict[tuple[str, str], str] = {}
    table, block = "", []
    for raw in (PROFILES_DIR / f"{name}.toml").read_text().splitlines():
        line = raw.strip()
        if line.startswith("[") and line.endswith("]"):
            table, block = line[1:-1], []
        elif line.startswith("#"):
            block.append(line[1:].strip())
        elif "=" in line and table:
            key, _, rest = line.partition("=")
            trailing = rest.split("#", 1)[1].strip() if "#" in rest else ""
            out[(table, key.strip())] = " ".join(block + ([trailing] if trailing else []))
            block = []
        else:
            block = []
    return out


DECISION_ID = re.compile(r"\bD\d+-\d+\b")


def departures() -> list[dict]:
    """Every mapping setting where a shipped device profile departs from the paper (the dataclass
    default, which ``paper-reference`` keeps): table, key, the paper's value, each device profile's
    value, and the decision ids its profile comments cite (empty: none given, which a test refuses)."""
    devices = [p.stem for p in sorted(PROFILES_DIR.glob("*.toml")) if p.stem != "paper-reference"]
    profiles = {n: load_profile(n) for n in devices}
    comments = {n: profile_comments(n) for n in devices}
    paper = MapSettings()
    out = []
    for table, cls in sections():
        if table not in MAPPING_TABLES:
            continue
        hints = typing.get_type_hints(cls)
        for f in dataclasses.fields(cls):
            if hints[f.name] not in (int, float, str, bool):
                continue
            ref = getattr(getattr(paper, table), f.name)
            values = {n: getattr(getattr(profiles[n].mapping, table), f.name) for n in devices}
            if all(v == ref for v in values.values()):
                continue
            ids = sorted({d for n in devices if values[n] != ref
                          for d in DECISION_ID.findall(comments[n].get((table, f.name), ""))})
            out.append({"table": table, "key": f.name, "paper": ref, "profiles": values, "decisions": ids})
    return out


def departures_markdown() -> str:
    """:func:`departures` as a markdown table. ``research/decisions.md`` holds it between
    ``<!-- departures -->`` marks; a test keeps it current (``python -m h3edge.config --departures``)."""
    rows = departures()
    devices = list(rows[0]["profiles"]) if rows else []
    lines = ["| setting | paper | " + " | ".join(devices) + " | decision |",
             "|---|---|" + "---|" * len(devices) + "---|"]
    for r in rows:
        cells = [f"`{r['profiles'][n]!r}`" if r["profiles"][n] != r["paper"] else "=" for n in devices]
        lines.append(f"| `[{r['table']}] {r['key']}` | `{r['paper']!r}` | " + " | ".join(cells) + " | "
                     + (", ".join(r["decisions"]) or "**none**") + " |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    sys.stdout.write(departures_markdown() if "--departures" in sys.argv[1:] else reference_markdown())

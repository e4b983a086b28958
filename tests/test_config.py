import pytest

from h3edge.config import load_profile
from h3edge.mapping.settings_file import PROFILES_DIR, ProfileError


@pytest.mark.parametrize("path", sorted(PROFILES_DIR.glob("*.toml")), ids=lambda p: p.stem)
def test_every_profile_loads(path):
    from h3edge.mapping.memory_plan import keyframe_bytes, memory_plan

    prof = load_profile(path)
    assert prof.name == path.stem
    assert prof.eval.n_points > 0
    settings = prof.map_settings()
    px = prof.service.max_frame_pixels
    plan = memory_plan(settings, prof.service.memory_budget_mb, keyframe_bytes(settings, px), px,
                       prof.service.ingest_queue)
    assert plan["fits"], (
        plan
    )  # the budget holds the tables, the voxel cap, query scratch, the largest frame's buffers and >= 8 keyframes
    assert prof.inference.decoders in ("onnx", "torch")


def test_profile_by_name():
    assert load_profile("x86-cpu").eval.n_points == 200_000


@pytest.mark.parametrize("text, msg", [
    ("[eval]\nn_pionts = 3\n", "unknown key 'n_pionts'"),
    ("[evaluation]\n", "unknown table"),
    ("[eval]\nn_points = 'many'\n", "expected int"),
    ("[eval\n", "profile.toml"),
    ("[mapper]\nedge_rays = 1.5\n", "edge_rays is a share"),
    ("[train]\ncarve_behind = false\n", "unknown key 'carve_behind'"),  # deleted (D49-1)
    ("[mapper]\nedge_max_incidence = 90.0\n", r"edge_max_incidence must be in \[0, 90\)"),
    ("[mapper]\nobserve_stride = 0\n", "observe_stride is a pixel stride"),
])
def test_bad_profiles_are_named(tmp_path, text, msg):
    p = tmp_path / "profile.toml"
    p.write_text(text)
    with pytest.raises(ProfileError, match=msg):
        load_profile(p)


def test_missing_profile(tmp_path):
    with pytest.raises(ProfileError, match="not found"):
        load_profile(tmp_path / "nope.toml")


def test_every_setting_has_a_docstring():
    """Each key a profile may set has a docstring under its field (what, unit, the paper's value):
    the configuration reference is generated from them."""
    import dataclasses
    import typing

    from h3edge.config import field_docs, sections

    missing = [f"[{table}] {f.name}" for table, cls in sections() for f in dataclasses.fields(cls)
               if typing.get_type_hints(cls)[f.name] in (int, float, str, bool) and not field_docs(cls).get(f.name)]
    assert not missing, missing


def test_configuration_reference_is_current():
    """docs/configuration.md is what ``python -m h3edge.config`` writes from the dataclasses now."""
    from pathlib import Path

    from h3edge.config import reference_markdown

    doc = Path(__file__).resolve().parents[1] / "docs" / "configuration.md"
    assert doc.read_text() == reference_markdown(), "regenerate: python -m h3edge.config > docs/configuration.md"


def test_every_departure_from_the_paper_cites_a_decision_in_the_log():
    """research/decisions.md lists every setting where a device profile departs from the paper
    (generated, current), and every departing key's profile comment cites a decision id that has
    its own entry there (a departure without one fails here)."""
    import re
    from pathlib import Path

    from h3edge.config import departures, departures_markdown

    rows = departures()
    assert rows and not [r for r in rows if not r["decisions"]], [
        f"[{r['table']}] {r['key']}" for r in rows if not r["decisions"]]
    log = (Path(__file__).resolve().parents[1] / "research" / "decisions.md").read_text()
    entries = set(re.findall(r"^## (D\d+-\d+):", log, re.M))
    cited = {d for r in rows for d in r["decisions"]}
    assert cited <= entries, cited - entries
    block = re.search(r"<!-- departures -->\n(.*)<!-- /departures -->", log, re.S)
    assert block and block.group(1) == departures_markdown(), "regenerate: python -m h3edge.config --departures"


def test_the_defaults_are_the_papers_values():
    """paper-reference sets no mapping key: its settings are the dataclass defaults, the paper's
    values (issue [2/5]); a profile states each departure (above)."""
    from pathlib import Path

    from h3edge.mapping.engine import MapSettings

    assert load_profile("paper-reference").mapping == MapSettings()
    text = (Path(__file__).resolve().parents[1] / "h3edge" / "profiles" / "paper-reference.toml").read_text()
    assert not [line for line in text.splitlines() if line.startswith("[")], "paper-reference sets no table"

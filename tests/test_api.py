"""The library façade, ``h3edge.Mapper``: docs/python-api.md's example runs as written; bad input is
an InputError or a counted drop that leaves the map as it was; a saved map loads with its own
settings."""

from __future__ import annotations

import dataclasses
import logging
import re
from pathlib import Path

import numpy as np
import pytest

import h3edge
from h3edge import Intrinsics, Mapper
from h3edge.config import load_profile
from h3edge.errors import InputError
from h3edge.io import open_sequence
from h3edge.mapping.map_file import CheckpointError, read_header
from h3edge.mapping.settings_file import ProfileError

DOC = Path(__file__).resolve().parents[1] / "docs" / "python-api.md"


def test_python_api_page_runs(tmp_path, monkeypatch):
    """Every ``python`` block of docs/python-api.md, in order, in one namespace (as a reader would
    paste them), in a scratch folder."""
    blocks = re.findall(r"```python\n(.*?)```", DOC.read_text(), re.S)
    assert len(blocks) >= 4
    monkeypatch.chdir(tmp_path)
    ns: dict = {}
    for code in blocks:
        exec(compile(code, str(DOC), "exec"), ns)
    assert (tmp_path / "room.ply").stat().st_size > 1000
    assert ns["again"].stats()["frames_mapped"] == 40
    assert ns["stats"]["iterations"]["between_frames"] > 0  # train() ran steps


@pytest.fixture(scope="module")
def small_mapper(tmp_path_factory, tiny_scene):
    """A lean map of the first 8 tiny frames (fast settings; the façade does not care)."""
    from h3edge.mapping.engine import MapSettings

    st = MapSettings()
    st = dataclasses.replace(st, mapper=dataclasses.replace(st.mapper, device="cpu", rays_per_iteration=512),
                             field=dataclasses.replace(st.field, geo_log2_table=12, tex_log2_table=12))
    m = Mapper(st)
    frames = [f for _, f in zip(range(8), open_sequence(tiny_scene))]
    for f in frames:
        assert m.add_frame(f.color, f.depth, f.pose, f.intrinsics, f.timestamp).mapped
        m.train(steps=1)
    return m, frames


def test_bad_input_is_refused_and_changes_nothing(small_mapper):
    m, frames = small_mapper
    f = frames[-1]
    before = m.stats()
    with pytest.raises(InputError, match="uint8"):
        m.add_frame(f.color.astype(np.float32), f.depth, f.pose, f.intrinsics)
    with pytest.raises(InputError, match="float metres"):
        m.add_frame(f.color, (f.depth * 1000).astype(np.uint16), f.pose, f.intrinsics)
    with pytest.raises(InputError, match=r"\(H, W\)"):
        m.add_frame(f.color, f.depth[:-1], f.pose, f.intrinsics)
    with pytest.raises(InputError, match="4, 4"):
        m.add_frame(f.color, f.depth, f.pose[:3], f.intrinsics)
    with pytest.raises(InputError, match="intrinsics are for"):
        m.add_frame(f.color, f.depth, f.pose, Intrinsics(64, 48, 50.0, 50.0, 32.0, 24.0))
    skew = f.pose.copy()
    skew[:3, :3] *= 1.5  # not a rotation
    r = m.add_frame(f.color, f.depth, skew, f.intrinsics, timestamp=1e6)
    stale = m.add_frame(f.color, f.depth, f.pose, f.intrinsics, timestamp=0.0)  # before the last mapped
    after = m.stats()
    assert not r.mapped and not stale.mapped
    assert sum(after["dropped"].values()) == sum(before["dropped"].values()) + 2
    assert after["frames_mapped"] == before["frames_mapped"] and after["voxels"] == before["voxels"]
    with pytest.raises(InputError, match=r"\(N, 3\)"):
        m.signed_distance(np.zeros((4, 2)))
    with pytest.raises(InputError, match="aabb"):
        m.mesh(aabb=[[1, 1, 1], [0, 0, 0]])


def test_torch_inputs_and_k_matrix_are_taken(small_mapper, tiny_scene):
    torch = pytest.importorskip("torch")
    m, frames = small_mapper
    f = list(open_sequence(tiny_scene))[8]
    r = m.add_frame(torch.from_numpy(f.color), torch.from_numpy(f.depth), torch.from_numpy(f.pose),
                    torch.from_numpy(f.intrinsics.K), timestamp=f.timestamp)
    assert r.mapped, r.reason


def test_queries_answer_in_world_metres(small_mapper):
    m, frames = small_mapper
    f = frames[4]
    color, depth = m.render(f.intrinsics, f.pose)
    assert color.shape == (f.intrinsics.height, f.intrinsics.width, 3) and color.dtype == np.uint8
    seen = (depth > 0) & (f.depth > 0)
    assert seen.mean() > 0.5
    assert np.median(np.abs(depth[seen] - f.depth[seen])) < 0.05  # metres, against the sensor
    # points on the measured surface read near zero; points half-way to the camera read free
    v, u = np.nonzero(seen)
    pick = np.linspace(0, len(v) - 1, 50).astype(int)
    rays = np.stack([(u[pick] + 0.5 - f.intrinsics.cx) / f.intrinsics.fx,
                     (v[pick] + 0.5 - f.intrinsics.cy) / f.intrinsics.fy, np.ones(len(pick))], 1)
    z = f.depth[v[pick], u[pick]][:, None]
    world = lambda p: p @ f.pose[:3, :3].T + f.pose[:3, 3]  # noqa: E731
    on = m.signed_distance(world(rays * z), gradient=True)
    half = m.signed_distance(world(rays * z * 0.5))
    assert np.nanmedian(np.abs(on.sdf)) < 0.03 and on.gradient.shape == (50, 3)
    assert (half.state == 1).mean() >= 0.75  # FREE (the paper's defaults: 40 of these 50 after 8 frames)
    box = m.mesh().bounds
    assert box is not None and np.all(box[1] - box[0] > 0.5)
    snap = m.snapshot()
    assert np.array_equal(snap.render(f.intrinsics, f.pose)[1], depth)
    sl = m.slice(float(f.pose[2, 3]), (-3.0, -3.0), (3.0, 3.0), 0.1)
    assert sl.occupancy.shape == (60, 60) and (sl.occupancy == 0).any()
    # beyond mapper.max_position: a render is refused at once, distances read unknown, a slice too big is refused
    far = f.pose.copy()
    far[0, 3] = 1e17
    with pytest.raises(InputError, match="max_position"):
        m.render(f.intrinsics, far)
    out = m.signed_distance(np.array([[1e17, 0.0, 0.0], [0.0, 1e300, 0.0], world(rays * z)[0]]))
    assert out.state[:2].tolist() == [0, 0] and np.isnan(out.sdf[:2]).all() and out.state[2] != 0
    assert (m.slice(1e300, (0.0, 0.0), (1.0, 1.0), 0.5).occupancy == -1).all()
    with pytest.raises(InputError, match="cells"):
        m.slice(0.0, (-1e308, -1e308), (1e308, 1e308), 1.0)


def test_saved_map_loads_with_its_own_settings(small_mapper, tmp_path):
    m, frames = small_mapper
    path = tmp_path / "small.h3ckpt"
    assert m.save(path, map_id="bench") > 0
    header, _ = read_header(path)
    assert header["map_id"] == "bench" and header["settings"]["field"]["geo_log2_table"] == 12
    back = Mapper.load(path)  # no profile given: the file's lean settings, not a profile's
    assert back.settings == m.settings and back.device == "cpu"
    f = frames[4]
    assert np.array_equal(back.render(f.intrinsics, f.pose)[1], m.render(f.intrinsics, f.pose)[1])
    # mapping goes on after a load: the frame numbering and timestamps carry over
    nxt = frames[-1]
    assert not back.add_frame(nxt.color, nxt.depth, nxt.pose, nxt.intrinsics, timestamp=nxt.timestamp).mapped
    (tmp_path / "junk.h3ckpt").write_bytes(b"not a map")
    with pytest.raises(CheckpointError, match="bad magic"):
        Mapper.load(tmp_path / "junk.h3ckpt")


def test_the_service_refuses_a_map_saved_under_other_settings(small_mapper, tmp_path):
    """Issue [4/5] 6: ``load`` and ``--resume`` took a map saved under another profile and answered
    ok; the map changed silently. Now the checkpoint loader names the settings that differ."""
    from h3edge.mapping.map_file import settings_differences
    from h3edge.profiling.timing import Timings
    from h3edge.serving.checkpointing import Checkpointer

    m, frames = small_mapper
    m.save(tmp_path / "map.h3ckpt", map_id="m")
    same = Checkpointer(tmp_path, "m", "lean", m.settings, Timings(), lambda c, t: None)
    assert same.read_mapper(tmp_path / "map.h3ckpt")[0].frames_mapped == m.frames_mapped
    on_cuda = dataclasses.replace(m.settings, mapper=dataclasses.replace(m.settings.mapper, device="cuda"))
    assert settings_differences(m.settings, on_cuda) == []  # where it runs is no difference
    # how the map is read is no difference: it is served with the service's render settings (D53-7)
    read_otherwise = dataclasses.replace(m.settings, render=dataclasses.replace(m.settings.render, free_floor=0.7))
    served = Checkpointer(tmp_path, "m", "lean", read_otherwise, Timings(), lambda c, t: None)
    assert served.read_mapper(tmp_path / "map.h3ckpt")[0].settings.render.free_floor == 0.7
    other = dataclasses.replace(m.settings, voxels=dataclasses.replace(m.settings.voxels, truncation=0.08))
    ckpt = Checkpointer(tmp_path, "m", "x86-cpu", other, Timings(), lambda c, t: None)
    with pytest.raises(CheckpointError, match=r"voxels.truncation: 0.05 -> 0.08"):
        ckpt.read_mapper(tmp_path / "map.h3ckpt")
    with pytest.raises(CheckpointError, match="cannot resume"):
        ckpt.resume()


def test_a_map_saved_with_a_refused_render_floor_loads_with_the_shipped_one(caplog):
    """Maps saved before D53-7 hold render.free_floor = 0.1, which the settings now refuse; their
    own settings read it as the shipped floor, with a warning, and everything else as saved."""
    from h3edge.mapping.settings_file import SAVED_FREE_FLOOR, map_settings_from_saved

    saved = dataclasses.asdict(load_profile("x86-cpu").map_settings())
    saved["render"]["free_floor"], saved["voxels"]["truncation"] = 0.1, 0.06
    with caplog.at_level(logging.WARNING):
        back = map_settings_from_saved(saved, "old.h3ckpt: settings")
    assert back.render.free_floor == SAVED_FREE_FLOOR and back.voxels.truncation == 0.06
    assert "free_floor" in caplog.text
    saved["render"]["free_floor"] = 0.0  # off stays off
    assert map_settings_from_saved(saved, "old").render.free_floor == 0.0
    saved["render"]["free_floor"], saved["field"]["beta"] = 0.1, 0.0  # a corrupt header: a clear error
    with pytest.raises(ProfileError, match="beta"):
        map_settings_from_saved(saved, "old")


def test_profile_errors_name_the_key(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text("[voxels]\nvoxel_sise = 0.1\n")
    with pytest.raises(ProfileError, match="voxel_sise"):
        Mapper.from_profile(bad)
    assert Mapper.from_profile("x86-cpu", device="cpu").device == "cpu"


def test_import_h3edge_is_light():
    """``import h3edge`` (and ``h3edge --version``) loads no torch; the façade's names resolve lazily."""
    import subprocess
    import sys

    code = "import sys, h3edge; print(h3edge.__version__, 'torch' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    assert out == [h3edge.__version__, "False"]
    assert h3edge.Mapper is Mapper

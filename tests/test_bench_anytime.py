"""The anytime benchmark: a replay at a camera rate through the live path beside TSDF fusion, scored
at its checkpoints, with its table, JSON, plot and picture."""

import json

from benchmarks.anytime import checkpoints, main


def test_checkpoints_every_period_then_the_last_frame_then_standing_still():
    marks = checkpoints(100, 10.0, 4.0, [10.0, 30.0])
    assert [(m.label, m.t) for m in marks] == [("4 s", 4.0), ("8 s", 8.0), ("last frame", 9.9),
                                               ("still 10 s", 19.9), ("still 30 s", 39.9)]


def test_anytime_replay_scores_both_methods_at_every_checkpoint(tiny_scene, tmp_path, capsys):
    out = tmp_path / "any"
    assert main(["--datasets", str(tiny_scene), "--hz", "10", "--every-s", "2", "--still-s", "1", "--views", "2",
                 "--modes", "live", "--set", "mapper.rays_per_iteration=256", "--set", "voxels.min_points=3",
                 "--tsdf-blocks", "4096",
                 "--out", str(out)]) == 0
    assert "| last frame | h3edge live |" in capsys.readouterr().out
    (r,) = json.loads(out.with_suffix(".json").read_text())
    labels = ["2 s", "last frame", "still 1 s"]
    for method, rows in r["runs"].items():
        assert [row["checkpoint"] for row in rows] == labels, method
        last = rows[1]
        assert last["frames_integrated"] + last["skipped"] <= r["frames"] and last["psnr_db"] > 0
        assert 0 <= last["stray_pct"] < 5, method  # both meshes scored against the scene's own
    live = r["summaries"]["h3edge live"]
    assert live["training_steps"]["frame"] == 0 and live["training_steps"]["between_frames"] > 0
    assert live["frames_integrated"] + live["skipped"] + live["dropped"] == r["frames"]
    for suffix in (".md", "_scene.png", "_scene_views.png"):  # the table, the plot, the renders
        assert (tmp_path / f"any{suffix}").is_file(), suffix

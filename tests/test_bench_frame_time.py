"""The frame-time benchmark maps every frame of a sequence and reports one JSON row."""

import json

from benchmarks.frame_time import main
from h3edge.io.replica import ReplicaSequence


def test_frame_time_reports_every_frame(tiny_scene, tmp_path, capsys):
    out = tmp_path / "rows.jsonl"
    assert main([str(tiny_scene), "--label", "here", "--set", "mapper.rays_per_iteration=256",
                 "--set", "mapper.iterations=1", "--out", str(out)]) == 0
    assert "| here |" in capsys.readouterr().out
    row = json.loads(out.read_text().strip().splitlines()[-1])
    assert row["label"] == "here" and row["set"] == ["mapper.rays_per_iteration=256", "mapper.iterations=1"]
    assert row["frames"] == len(ReplicaSequence(tiny_scene))
    assert 0 < row["median_ms"] and 0 < row["mean_ms"] and row["wall_s"] > row["median_ms"] / 1000

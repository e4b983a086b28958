"""Host transfers of the torch backend (issue [3/5]): the Orin profiles' mapping run on the CPU with
every tensor-to-host call h3edge makes counted. Integration makes none; the training step makes
one, the transfer of its losses (research/bench_host_transfers.md): a new ``.cpu()`` / ``.item()`` /
``bool(tensor)`` in the step fails here."""

from __future__ import annotations

import torch

from benchmarks.host_transfers import count_transfers, lean_torch_settings
from h3edge.io import open_sequence
from h3edge.profiling.host_transfers import HostTransfers

# path:function -> transfers a steady training step makes there: the step's one transfer of its losses
STEP_BUDGET = {
    "h3edge/mapping/trainer.py:step": 1,  # the losses, once: kept
}
# where a steady step may make host data tensors (on CUDA a copy up, and the host waits for the stream
# first): the frames' images once (device_frames), the votes' rows marked since the last step and the
# voxel index when voxels were added; no constant, no ray batch
STEP_UPLOADS = {"h3edge/mapping/device_frames.py:_tensor", "h3edge/mapping/cell_votes.py:on_device",
                "h3edge/mapping/voxels.py:device_index"}
# data-dependent shapes a steady step makes at most today (research/bench_host_transfers.md: the
# sparse hash-grid updates' unique rows, the texture warps' weak voxels, the in-voxel compactions);
# a ratchet: a new one fails here
STEP_SYNCS = 22


def test_integration_makes_no_host_transfer_and_the_step_stays_in_its_budget(tiny_scene):
    frames = [f for _, f in zip(range(6), open_sequence(tiny_scene))]
    result = count_transfers(lean_torch_settings("orin-agx"), frames)
    assert result["frames"] >= 2
    assert result["integration"]["max"] == 0
    over = {k: v for k, v in result["step_by_function"].items() if v > STEP_BUDGET.get(k, 0)}
    assert not over, f"new host transfers in the training step: {over} (lines: {result['step_by_line']})"
    assert result["step"]["max"] <= sum(STEP_BUDGET.values())
    assert result["step_syncs"]["max"] <= STEP_SYNCS, result["step_syncs_by_function"]
    # the rays are drawn on the device from frames' images uploaded once (h3edge.mapping.device_frames): at
    # most twice a frame (the newest frame's step, then as a keyframe), RGB + depth + valid counts + edges
    uploads = result["step_uploads_by_function"]
    assert set(uploads) <= STEP_UPLOADS, f"new host data made tensors in the training step: {uploads}"
    assert uploads.get("h3edge/mapping/device_frames.py:_tensor", 0) <= 2 * result["frames"] * (
        result["frame_pixels"] * (3 + 4 + 8) + 64), uploads


def test_the_counter_sees_a_transfer_in_h3edge_code_and_ignores_others():
    """A ``.cpu()`` put back into trainer.py (code compiled under its file name) is counted with
    its line and function; the same call from a test is not."""
    import h3edge.mapping.trainer as trainer

    original, original_nonzero = torch.Tensor.cpu, torch.nonzero
    ns: dict = {}
    exec(compile("def _put_back(x):\n    return x.detach().cpu().numpy(), float(x.sum()), x[x > 0], x[:2]\n",
                 trainer.__file__, "exec"), ns)
    with HostTransfers() as ht:
        ns["_put_back"](torch.ones(3))
        torch.ones(3).cpu().numpy()  # this test's own call
        torch.nonzero(torch.ones(3))
    assert ht.total == 2 and ht.by_function() == {"h3edge/mapping/trainer.py:_put_back": 2}
    assert ht.syncs_by_function() == {"h3edge/mapping/trainer.py:_put_back": 1}  # the mask, not the slice
    assert set(ht.by_line()) == {"h3edge/mapping/trainer.py:2 cpu", "h3edge/mapping/trainer.py:2 float"}
    assert torch.Tensor.cpu is original and torch.nonzero is original_nonzero  # the patches are undone


def test_the_cuda_check_runs_where_no_gpu_is(tmp_path):
    """``benchmarks/cuda_check.py`` (the first thing to run on a lent GPU) runs end to end with the
    CPU in CUDA's place: the Orin profile on the torch backend, its step's one host transfer, the
    timings, the memory plan and the bounds, in its JSON."""
    import json

    from benchmarks import cuda_check

    code = cuda_check.main(["--device", "cpu", "--frames", "3", "--cpu-frames", "0", "--out", str(tmp_path),
                            "--set", "mapper.rays_per_iteration=256", "--set", "votes.points=256",
                            "--set", "field.geo_log2_table=12", "--set", "field.tex_log2_table=12"])
    res = json.loads((tmp_path / "cuda_check.json").read_text())
    assert code in (0, 1) and res["ok"] == (code == 0)
    run = res["cuda_run"]
    assert run["device"] == "cpu" and run["step_host_transfers_max"] == 1 and res["bounds"]["one_host_transfer_a_step"]
    assert {"integration", "idle_training"} <= set(run["timings_ms"]) and run["plan_mb"] > 0


def test_training_turns_and_exclusive_callers_order_the_training_stream(tiny_scene):
    """On CUDA a step's kernels go to a stream of its own (h3edge.mapping.training_stream); what keeps
    them in order with the default stream's is called where it must be: every training turn (ray
    draw, update) starts after the default stream's work, with the priors marked as used there, and
    records its end; every exclusive caller waits for that end; the whole step runs in the stream's
    context. A recorder stands in for CUDA's streams here."""
    import contextlib

    from h3edge.mapping.engine import MapEngine

    calls = []

    class Recorder:
        @contextlib.contextmanager
        def active(self):
            calls.append("enter")
            yield
            calls.append("leave")

        def follow_default(self, shared=()):
            calls.append(("follow", tuple(t is m.voxels.priors for t in shared)))

        def mark_turn_end(self):
            calls.append("mark")

        def before_exclusive_work(self):
            calls.append("wait")

    frames = [f for _, f in zip(range(3), open_sequence(tiny_scene))]
    m = MapEngine(lean_torch_settings("orin-agx"))
    m._stream = Recorder()
    m.integrate(frames[0])
    assert calls == ["wait"]  # integration holds the map: after the last update
    calls.clear()
    assert m.train_once() is not None
    assert calls[0] == "enter" and calls[-1] == "leave" and "wait" not in calls
    turns = calls[1:-1]
    assert len(turns) >= 4 and turns == [("follow", (True,)), "mark"] * (len(turns) // 2)  # draw, update, ...
    calls.clear()
    with m.exclusive():
        pass
    assert calls == ["wait"]

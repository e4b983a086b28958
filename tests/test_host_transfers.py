"""Host transfers of the torch backend (issue [3/5]): the Orin profiles' mapping run on the CPU with
every tensor-to-host call h3edge makes counted. Integration makes none; the training step makes
the ones listed in STEP_BUDGET (research/bench_host_transfers.md), a ratchet towards the one
transfer of the step's losses: a new ``.cpu()`` / ``.item()`` / ``bool(tensor)`` in the step fails
here, and a budget line goes when its transfer is removed."""

from __future__ import annotations

import torch

from benchmarks.host_transfers import count_transfers, lean_torch_settings
from h3edge.io import open_sequence
from h3edge.profiling.host_transfers import HostTransfers

# path:function -> transfers a steady training step makes there now (the target: trainer.py:step's
# one transfer of the losses, and nothing else)
STEP_BUDGET = {
    "h3edge/mapping/cell_votes.py:sample_free": 3,  # the voted-free cells drawn by a numba kernel
    "h3edge/mapping/trainer.py:reading_inside": 2,  # which band samples read inside (votes)
    "h3edge/mapping/trainer.py:_rgb_term": 2,  # guards on empty selections
    "h3edge/mapping/losses.py:per_ray_mean": 2,
    "h3edge/mapping/trainer.py:sample": 1,  # the voxel lookup of the samples (numba)
    "h3edge/mapping/trainer.py:composite": 1,
    "h3edge/mapping/trainer.py:locate_surface_points": 1,
    "h3edge/mapping/trainer.py:_depth_term": 1,
    "h3edge/mapping/losses.py:depth_l1": 1,
    "h3edge/mapping/trainer.py:surface_color_loss": 1,
    "h3edge/mapping/trainer.py:apply": 1,
    "h3edge/mapping/trainer.py:step": 1,  # the losses, once: kept
    "h3edge/mapping/trainer.py:seen_free_loss": 1,
}


def test_integration_makes_no_host_transfer_and_the_step_stays_in_its_budget(tiny_scene):
    frames = [f for _, f in zip(range(6), open_sequence(tiny_scene))]
    result = count_transfers(lean_torch_settings("orin-agx"), frames)
    assert result["frames"] >= 2
    assert result["integration"]["max"] == 0
    over = {k: v for k, v in result["step_by_function"].items() if v > STEP_BUDGET.get(k, 0)}
    assert not over, f"new host transfers in the training step: {over} (lines: {result['step_by_line']})"
    assert result["step"]["max"] <= sum(STEP_BUDGET.values())


def test_the_counter_sees_a_transfer_in_h3edge_code_and_ignores_others():
    """A ``.cpu()`` put back into trainer.py (code compiled under its file name) is counted with
    its line and function; the same call from a test is not."""
    import h3edge.mapping.trainer as trainer

    original = torch.Tensor.cpu
    ns: dict = {}
    exec(compile("def _put_back(x):\n    return x.detach().cpu().numpy(), float(x.sum())\n",
                 trainer.__file__, "exec"), ns)
    with HostTransfers() as ht:
        ns["_put_back"](torch.ones(3))
        torch.ones(3).cpu().numpy()  # this test's own call
    assert ht.total == 2 and ht.by_function() == {"h3edge/mapping/trainer.py:_put_back": 2}
    assert set(ht.by_line()) == {"h3edge/mapping/trainer.py:2 cpu", "h3edge/mapping/trainer.py:2 float"}
    assert torch.Tensor.cpu is original  # the patch is undone

"""The rule "no single message changes what later valid messages do" as a differential fuzzer
(issue [4/5]; ``benchmarks/fuzz.py`` is the long run): hostile frames generated from the input
grammar (poses, depth, shapes, intrinsics, stamps) interleaved with four good frames leave the map
the good frames alone make, every array of its state equal; each is an InputError or a counted
drop. Hostile wire messages (truncated, bit-flipped, a header field replaced) are ProtocolErrors or
decode, nothing else; hostile query requests are refused or within the caps. Seeded (derandomized)
and bounded."""

from __future__ import annotations

import collections

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from benchmarks.fuzz import (
    decode_or_refuse,
    hostile_bytes,
    hostile_frame,
    hostile_query,
    hostile_ros,
    map_signature,
    parse_or_refuse,
    ros_good_stream,
    run_interleaved,
    run_ros,
    same_map,
    wire_messages,
)
from h3edge.io import open_sequence

SETTINGS = settings(max_examples=20, deadline=None, derandomize=True, suppress_health_check=list(HealthCheck))


@pytest.fixture(scope="module")
def good(tiny_scene):
    return [f for _, f in zip(range(4), open_sequence(tiny_scene))]


@pytest.fixture(scope="module")
def reference(good):
    return map_signature(run_interleaved(good, []))


def test_hostile_frames_leave_the_map_the_good_frames_make(good, reference):
    tally: collections.Counter = collections.Counter()

    @SETTINGS
    @given(st.lists(st.tuples(st.integers(0, len(good)), hostile_frame(good[1])), min_size=1, max_size=6))
    def run(items):
        m = run_interleaved(good, [(p, k, a) for p, (k, a) in items], tally)
        diff = same_map(map_signature(m), reference)
        assert not diff, diff

    run()
    assert {k for k, _ in tally} == {"pose", "depth", "shape", "intrinsics", "stamp"}  # every class tried


def test_hostile_wire_messages_are_protocol_errors(good):
    frame_bytes, pose_bytes = wire_messages(good)
    seen: collections.Counter = collections.Counter()

    @SETTINGS
    @given(hostile_bytes(frame_bytes, pose_bytes))
    def run(item):
        seen[decode_or_refuse(*item)] += 1  # anything but ProtocolError propagates and fails

    run()
    assert seen["refused"] > 0


def test_hostile_query_requests_are_refused_or_within_the_caps():
    """Query requests of every kind with hostile field values (huge and non-finite numbers, nested
    lists, long and path-like strings, raw sdf bytes of any length) are QueryErrors (error replies) or
    requests within the service's caps; nothing else escapes the parsers."""
    seen: collections.Counter = collections.Counter()

    @settings(max_examples=200, deadline=None, derandomize=True, suppress_health_check=list(HealthCheck))
    @given(hostile_query())
    def run(item):
        seen[(item[0], parse_or_refuse(*item))] += 1

    run()
    assert {k for k, _ in seen} == {"mesh", "render", "sdf", "slice", "save", "export"}
    assert {v for _, v in seen} == {"ok", "refused"}
    # what the long run found: a JSON integer of 400 digits raised OverflowError (an internal error reply)
    huge = 10 ** 400
    assert parse_or_refuse("render", {"pose": {"t": [0, 0, 0], "q": [0, 0, 0, 1]}, "fov_deg": huge}, None) == "refused"
    assert parse_or_refuse("slice", {"z": huge, "aabb": [[0, 0], [1, 1]]}, None) == "refused"
    assert parse_or_refuse("mesh", {"aabb": [[0, 0, 0], [huge, 1, 1]]}, None) == "refused"


@pytest.mark.parametrize("pose_type", ["odometry", "tf"])
def test_hostile_ros_messages_leave_the_frames_the_good_ones_make(good, pose_type):
    """ROS 2 messages that must be refused (unreadable images, images of another size at a good frame's
    stamp, unusable camera infos, non-finite or non-rotation poses, TF messages whose robot link is
    broken or absent among up to 2,000 others, truncated messages) interleaved with a camera's good
    colour, depth, camera info and odometry / TF: the ROS ingest hands on exactly the frames and poses
    the good messages alone make, and raises nothing."""
    stream = ros_good_stream(good, pose_type)
    frames, poses, _ = run_ros(stream, [], pose_type)
    assert len(frames) == len(good) and len(poses) == len(good)
    seen: collections.Counter = collections.Counter()

    @SETTINGS
    @given(st.lists(st.tuples(st.integers(0, len(stream)), hostile_ros(good, pose_type)), min_size=1, max_size=6))
    def run(items):
        got_frames, got_poses, drops = run_ros(stream, [(p, role, data) for p, (role, _, data) in items], pose_type)
        seen.update(cls for _, (_, cls, _) in items)
        assert got_frames == frames and got_poses == poses
        assert "ros_internal_error" not in drops, drops

    run()
    assert set(seen) == {"image", "size", "info", "pose", "bytes"}

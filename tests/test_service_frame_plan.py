"""The garbler's frame sizing: a frame every few ms of garbling, but not hundreds per run."""

from types import SimpleNamespace

from snail_garbler.daemon import MAX_FRAME_BYTES, MAX_FRAMES, frame_plan


def frames_of(n_and: int, n_steps: int) -> tuple[int, int]:
    """(frame bytes, frames per run) for a half-gates circuit of this shape."""
    _, size = frame_plan(SimpleNamespace(n_and=n_and, n_steps=n_steps))
    return size, -(-32 * n_and // size)


def test_a_large_circuit_streams_few_full_frames():
    """n = 256 (7.4 M AND): 1 MiB frames, not ~570 frames of 0.4 MiB each paying the
    per-frame cost in both daemons."""
    size, frames = frames_of(7_424_757, 16_000)
    assert size == MAX_FRAME_BYTES
    assert frames < 240


def test_a_small_circuit_keeps_its_overlap():
    """n = 6 (0.19 M AND, 3,700 steps): still dozens of frames, so the evaluator starts
    after a few ms of garbling instead of waiting for the whole stream."""
    size, frames = frames_of(189_000, 3_700)
    assert 30 <= frames <= MAX_FRAMES
    assert size < 256 << 10

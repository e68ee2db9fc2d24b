"""The garbler's frame sizing: a frame every few ms of garbling, but not hundreds per run."""

from types import SimpleNamespace

from snail_garbler.daemon import MAX_FRAME_BYTES, MAX_FRAMES, frame_plan


def frames_of(n_and: int, n_steps: int, engine: str = "numpy") -> tuple[int, int]:
    """(frame bytes, frames per run) for a half-gates circuit of this shape."""
    _, size = frame_plan(SimpleNamespace(n_and=n_and, n_steps=n_steps), engine=engine)
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


def test_the_native_kernel_sends_few_full_frames():
    """The native kernel garbles n = 6 in a few ms: a handful of 1 MiB frames (each frame
    costs both daemons thread hand-offs and a TLS write and read), and n = 256 as numpy."""
    size, frames = frames_of(175_752, 3_500, "native")
    assert size == MAX_FRAME_BYTES and frames <= 8
    assert frames_of(5_980_000, 15_000, "native") == frames_of(5_980_000, 15_000)

"""The tracking schedule: how many secure runs each frame of a stream gets and where they
start, as a small state machine (ORB-SLAM's Tracking) that the tracker asks and that is
tested without servers.

States: ``initializing`` (no pose yet), ``tracking``, ``lost``.

``runs_per_frame=0`` pads every frame instead, as before the fixed schedule existed.
``warmup=W``: frames 1 .. W get at least two runs, fixed in advance like the rest (the
map-owner setting's device sees a fit only where a run evaluated it: with one run, the
prediction's, and before any motion is known that is not the answer's).

- initializing: the frame gets today's padded localization (at least ``min_invocations``
  runs) from its own initial pose. Only the first frame is: that is fixed in advance.
- tracking: exactly ``runs_per_frame`` (K) runs, each one GN or LM step (steps.py), from
  the prediction: the last trusted pose moved by the caller's odometry for every frame
  since (``motion``), or, with ``motion_model="constant-velocity"``, by the motion between
  the last two trusted frames (none by default: on real hand-held frames it did not help).
- lost: the last answer failed a check (RMS above the bad-fit threshold, points behind the
  camera, no usable points). Still K runs, so the servers see nothing change: from the
  lost frame's answer when it fit better than its start (a re-localization spread over the
  frames' own slots), else from the last trusted pose. The first trusted frame after lost
  ones is ``relocalized``. With ``on_lost="reveal"`` the next frame gets a padded
  localization instead, which the servers can tell from K runs: its plan is ``revealed``.

A frame is also ``revealed`` when what the servers saw was not the schedule's: another
circuit (its point count changed, see ``--pad-points``) or another number of runs (a
padded frame that needed more than ``min_invocations``).

Frames in flight: with D frames in flight, frame t is planned before the answers of
frames t-D+1 .. t-1 are in (some may be, by then: that is timing). So that a frame's start
depends on the data alone, ``plan(t, lag=D)`` uses the state as it was once frame t-D was
observed, and moves its pose over every frame since. The tracker waits for every answer
before planning while initializing.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .geometry import rvec_from_matrix, so3_exp
from .problem import PoseVectors

INITIALIZING, TRACKING, LOST = "initializing", "tracking", "lost"
RELOCALIZED = "relocalized"  # a frame's track status: trusted again after lost frames
ON_LOST = ("wait", "reveal")
MOTION_MODELS = ("auto", "none", "constant-velocity")
VOTE_MEMORY = 0.8  # auto: the weight of the past frames' votes against the newest one
MAX_LAG = 64  # frames in flight at most (states kept for plans of later frames)


@dataclass(frozen=True)
class Plan:
    """What frame ``index`` gets: a padded localization (at least ``runs``) or exactly
    ``runs``, from ``start`` (None: the frame's own initial pose)."""

    index: int
    padded: bool
    runs: int
    start: PoseVectors | None
    revealed: bool = False  # the plan itself departs from the schedule (on_lost reveal)
    # what moved the start from the last answer over the frame before this one:
    # "odometry", "constant-velocity" or nothing ("last-pose"); None: the frame's own
    prediction: str | None = None


@dataclass(frozen=True)
class Outcome:
    """What a frame gave: its answer, whether it passed the checks, whether it fit better
    than its start (worth continuing from when lost), its runs and its circuit."""

    trusted: bool
    pose: PoseVectors | None
    runs: int
    circuit: str | None = None
    improved: bool = False


@dataclass(frozen=True)
class _State:
    """What a prediction is made from: the state, the last trusted (frame, pose), the
    lost answer worth keeping, the motion between the last two answers to go on from and
    whether a prediction moves by it."""

    state: str
    anchor: tuple[int, PoseVectors] | None
    lost_at: tuple[int, PoseVectors] | None
    velocity: PoseVectors | None
    extrapolate: bool


@dataclass(frozen=True)
class Observed:
    track_status: str  # tracking, lost or relocalized
    revealed: bool


def compose(motion: PoseVectors, pose: PoseVectors) -> PoseVectors:
    """The world-to-camera pose after the camera moved by ``motion`` (x' = M x_cam)."""
    rot = so3_exp(motion.rvec)
    return PoseVectors(rvec_from_matrix(rot @ so3_exp(pose.rvec)),
                       rot @ pose.tvec + motion.tvec)


def relative(before: PoseVectors, after: PoseVectors) -> PoseVectors:
    """The camera's motion from ``before`` to ``after``: compose(relative(a, b), a) == b.
    What a caller with absolute odometry passes as one frame's ``motion``."""
    rot = so3_exp(after.rvec) @ so3_exp(before.rvec).T
    return PoseVectors(rvec_from_matrix(rot), after.tvec - rot @ before.tvec)


class Schedule:
    """The state machine; see the module docstring."""

    def __init__(self, runs_per_frame: int = 1, min_invocations: int = 20,
                 on_lost: str = "wait", motion_model: str = "auto", warmup: int = 0) -> None:
        if runs_per_frame < 0:
            raise ValueError(f"--runs-per-frame: must not be negative, got {runs_per_frame}")
        if on_lost not in ON_LOST:
            raise ValueError(f"--on-lost: expected one of {ON_LOST}, got {on_lost!r}")
        if motion_model not in MOTION_MODELS:
            raise ValueError(f"--motion-model: expected one of {MOTION_MODELS}, "
                             f"got {motion_model!r}")
        self.runs_per_frame, self.min_invocations = runs_per_frame, min_invocations
        self.warmup = warmup
        self.on_lost, self.motion_model = on_lost, motion_model
        self.state = INITIALIZING
        self.circuit: str | None = None  # the schedule's circuit: the first frame's
        self._anchor: tuple[int, PoseVectors] | None = None  # last trusted (frame, pose)
        self._lost_at: tuple[int, PoseVectors] | None = None  # a lost answer worth keeping
        self._velocity: PoseVectors | None = None  # between the last two answers to go on from
        self._last: tuple[int, PoseVectors] | None = None  # the last answer to go on from
        self._vote = 0.0  # auto: > 0 while constant velocity predicted better, recently
        self._motions: dict[int, PoseVectors | None] = {}
        self._seen: dict[int, _State] = {}  # the state once each recent frame was observed
        self._first: int | None = None  # the first frame observed

    @property
    def waits_for_answers(self) -> bool:
        """Plan no frame while an earlier one is in flight: there is no pose to predict
        from until the padded first localization is back."""
        return self.state == INITIALIZING

    def plan(self, index: int, motion: PoseVectors | None = None, lag: int = 1) -> Plan:
        """Frame ``index``'s runs and start; ``motion``: the camera's motion since the
        previous frame (odometry), if the caller knows it; ``lag``: frames in flight (the
        state once frame ``index - lag`` was observed is what counts)."""
        self._motions[index] = motion
        state = self._state_at(index - lag)
        if state.state == INITIALIZING:
            return Plan(index, True, self.min_invocations, None)
        start, by = self._predict(state, index)
        if not self.runs_per_frame:  # padded every frame, as before the fixed schedule
            return Plan(index, True, self.min_invocations, start, prediction=by)
        if state.state == LOST and self.on_lost == "reveal":
            return Plan(index, True, self.min_invocations, start, True, by)
        runs = max(self.runs_per_frame, 2) if index <= self.warmup else self.runs_per_frame
        return Plan(index, False, runs, start, prediction=by)

    def predict(self, index: int, lag: int = 1) -> PoseVectors | None:
        """The start of frame ``index``: the last trusted pose (or, when lost, the lost
        answer worth keeping) moved over the frames since; None before any pose."""
        return self._predict(self._state_at(index - lag), index)[0]

    def _predict(self, state: _State, index: int) -> tuple[PoseVectors | None, str | None]:
        """The start, and what moved it over the last frame (Plan.prediction)."""
        base = state.lost_at if state.state == LOST and state.lost_at else state.anchor
        if base is None:
            return None, None
        (at, pose), by = base, "last-pose"
        for frame in range(at + 1, index + 1):
            motion, by = self._motions.get(frame), "odometry"
            if motion is None and state.extrapolate and state.velocity is not None:
                motion, by = state.velocity, "constant-velocity"
            if motion is None:
                by = "last-pose"
            else:
                pose = compose(motion, pose)
        return pose, by

    def _state_at(self, index: int) -> _State:
        """The state once frame ``index`` was observed (the first frame's, before it):
        with frames in flight, later answers may be in already and must not count."""
        if self._first is None:
            return self._now()
        return self._seen.get(max(index, self._first)) or self._now()

    def _now(self) -> _State:
        extrapolate = (self.motion_model == "constant-velocity"
                       or (self.motion_model == "auto" and self._vote > 0))
        return _State(self.state, self._anchor, self._lost_at, self._velocity, extrapolate)

    def observe(self, plan: Plan, outcome: Outcome) -> Observed:
        """Take frame ``plan.index``'s outcome (in frame order): the new state, and the
        frame's track status and whether what the servers saw departed from the
        schedule."""
        if self.circuit is None and outcome.circuit is not None:
            self.circuit = outcome.circuit
        other_circuit = outcome.circuit is not None and outcome.circuit != self.circuit
        other_count = (outcome.runs > plan.runs if plan.padded
                       else outcome.runs != plan.runs)
        revealed = plan.revealed or other_circuit or other_count
        was_lost = self.state == LOST
        if outcome.trusted and outcome.pose is not None:
            self._moved(plan.index, outcome.pose)
            self._anchor, self._lost_at, self.state = (plan.index, outcome.pose), None, TRACKING
            status = RELOCALIZED if was_lost else TRACKING
        else:
            if outcome.pose is not None and outcome.improved:
                self._moved(plan.index, outcome.pose)
                self._lost_at = (plan.index, outcome.pose)
            elif outcome.pose is not None:
                self._lost_at = None  # it went nowhere: back to the last trusted pose
                self._last = self._velocity = None
            self.state, status = LOST, LOST
        if self._first is None:
            self._first = plan.index
        self._seen[plan.index] = self._now()
        self._forget(plan.index)
        return Observed(status, revealed)

    def _moved(self, index: int, pose: PoseVectors) -> None:
        """An answer to go on from (trusted, or lost but better than its start): the
        motion since the one before when consecutive, and auto's vote on the prediction
        that motion would have made. A map-owner device with one run a frame judges only
        the prediction's fit, so its first tracked frames, predicted without a motion
        yet, may come out lost: their answers still carry the motion on."""
        last = self._last
        consecutive = last is not None and last[0] == index - 1
        if consecutive and self._velocity is not None and self._motions.get(index) is None:
            self._vote = VOTE_MEMORY * self._vote + (1 - VOTE_MEMORY) * _vote(
                last[1], compose(self._velocity, last[1]), pose)
        # not consecutive: no per-frame motion to take
        self._velocity = relative(last[1], pose) if consecutive else None
        self._last = (index, pose)

    def _forget(self, index: int) -> None:
        """Drop the states no plan will ask for again (frames in flight are at most
        MAX_LAG), and the motions of frames no prediction will move over again."""
        for frame in [f for f in self._seen if f < index - MAX_LAG and f != self._first]:
            del self._seen[frame]
        bases = [b[0] for state in self._seen.values()
                 for b in (state.anchor, state.lost_at) if b is not None]
        if bases:
            oldest = min(bases)
            for frame in [f for f in self._motions if f <= oldest]:
                del self._motions[frame]


def _vote(still: PoseVectors, moved: PoseVectors, answer: PoseVectors) -> float:
    """+1 when the constant-velocity prediction ``moved`` was nearer the answer than the
    last pose ``still`` in both rotation and translation, -1 when farther in both, else 0
    (the two are in different units: no weighting of one against the other is needed)."""
    def apart(a: PoseVectors) -> tuple[float, float]:
        turn = float(np.linalg.norm(relative(a, answer).rvec))
        return turn, float(np.linalg.norm(_centre(a) - _centre(answer)))

    (rot_still, move_still), (rot_moved, move_moved) = apart(still), apart(moved)
    if rot_moved < rot_still and move_moved < move_still:
        return 1.0
    if rot_moved > rot_still and move_moved > move_still:
        return -1.0
    return 0.0


def _centre(pose: PoseVectors) -> np.ndarray:
    """The camera's centre in the world."""
    return -so3_exp(pose.rvec).T @ pose.tvec

"""What the servers learn from a tracked stream: an easy sequence (slow, steady) and a hard
one (fast, shaky, frames with nothing in view, frames with wrong matches that lose the
track) leave the same circuits, run counts and run order in the garbler's and the
evaluator's session logs. Only the data differ, and the logs must not show it."""

from __future__ import annotations

import time

import numpy as np
import pytest
from daemons import session_lines

from snail_client.api import Localizer
from snail_client.embedded import embedded_services
from snail_common.loc.problem import Problem
from snail_common.net.linkrates import MAX_AHEAD
from snail_sim.sequences import handheld

FRAMES = 30


def _hard(rng: np.random.Generator) -> list:
    """Fast shaky walking, two frames with nothing usable, two whose matches are
    shuffled (a bad fit: the track is lost and found again)."""
    frames: list = list(handheld(rng, 6, FRAMES, speed=2.5, shake_deg=1.5).problems)
    for k in (7, 18):
        frames[k] = (np.zeros((3, 2)), np.zeros((3, 3)))  # three points: nothing to run
    for k in (11, 23):
        p = frames[k]
        frames[k] = Problem(K=p.K, dist=p.dist, points2d=p.points2d[::-1].copy(),
                            points3d=p.points3d, initial_pose=None, image_size=p.image_size)
    return frames


def _logged(frames: list, tmp_path_factory, in_flight: int
            ) -> tuple[list, dict[str, list[dict]]]:
    """Track ``frames`` against daemons of their own; their session lines."""
    cache = tmp_path_factory.mktemp("cache")
    with embedded_services(log_level="info", env={"SNAIL_CACHE_DIR": str(cache)}) as svc:
        camera = _camera(next(f for f in frames if isinstance(f, Problem)))
        with Localizer(camera=camera, garbler=svc.garbler_addr, evaluator=svc.evaluator_addr,
                       tls_dir=str(svc.tls_dir), in_flight=in_flight) as loc:
            poses = list(loc.track(frames))
        return poses, _settled(svc)


def _settled(svc, quiet_s: float = 0.5, most_s: float = 30.0) -> dict[str, list[dict]]:
    """Both daemons' session lines once no new one has come for ``quiet_s`` (the client
    has gone: the sessions it garbled ahead and never used end as it cancelled them)."""
    logs, last, deadline = None, time.monotonic(), time.monotonic() + most_s
    while time.monotonic() < deadline:
        now = {role: session_lines(getattr(svc, role).log) for role in ("garbler", "evaluator")}
        if logs is None or any(len(now[r]) != len(logs[r]) for r in now):
            logs, last = now, time.monotonic()
        elif time.monotonic() - last >= quiet_s:
            break
        time.sleep(0.05)
    return logs


def _camera(problem: Problem):
    from snail_client.inputs.camera import Camera

    return Camera(problem.K, problem.dist, problem.image_size)


@pytest.fixture(scope="module", params=[1, 2], ids=["one in flight", "two in flight"])
def runs(request, tmp_path_factory):
    easy = list(handheld(np.random.default_rng(1), 6, FRAMES, speed=0.2,
                         shake_deg=0.05).problems)
    return (_logged(easy, tmp_path_factory, request.param),
            _logged(_hard(np.random.default_rng(2)), tmp_path_factory, request.param))


def _seen(line: dict, role: str) -> tuple:
    """What a session line shows of its run: the circuit, its size, scheme and outcome,
    and the bytes the daemon took in and (garbler) sent: the tables and the labels. The
    evaluator's bytes out carry its timing figures, whose encoded length varies."""
    seen = (line["circuit"], line["and"], line.get("scheme"), line["outcome"],
            line["bytes_in"])
    return seen + ((line["bytes_out"],) if role == "garbler" else ())


def test_the_hard_sequence_is_hard(runs):
    (easy_poses, _), (hard_poses, _) = runs
    assert all(p.record["track_status"] == "tracking" for p in easy_poses)
    statuses = [p.record["track_status"] for p in hard_poses]
    assert statuses.count("lost") >= 4 and "relocalized" in statuses
    assert [p.status for p in hard_poses][7] == "failed"
    assert not any(p.record["revealed"] for p in easy_poses + hard_poses)


@pytest.mark.parametrize("role", ["garbler", "evaluator"])
def test_the_servers_see_the_same_runs_in_the_same_order(runs, role):
    (_, easy), (_, hard) = runs
    n = 20 + FRAMES - 1  # the padded first frame, then 1 a frame
    ran = {name: [_seen(s, role) for s in logs[role] if s["outcome"] == "ok"]
           for name, logs in (("easy", easy), ("hard", hard))}
    assert ran["easy"][:n] == ran["hard"][:n]
    # the other sessions were garbled ahead and never used: they come after every run,
    # in both logs alike. The evaluator ends them as the client cancels (or leaves);
    # the garbler's part of one is over once its tables are sent, so one streamed in
    # time is ok there too
    for name, logs in (("easy", easy), ("hard", hard)):
        outcomes = "".join("o" if s["outcome"] == "ok" else "x" for s in logs[role])
        assert outcomes[:n] == "o" * n
        assert len(outcomes) - n <= MAX_AHEAD + 1
        if role == "evaluator":
            assert len(ran[name]) == n

"""What the map-owner setting adds per iteration (``snail-bench service --map-points M``).

Issue 18 asks for the extra cost of keeping the map with its owner, beside the first
setting's: for each scene size n the plain in-circuit-solve circuit (``lm-sil-ldlt-nN``,
the first setting's comparable family) is measured as ``service`` measures it, then for
each map size M a ``snail-mapd`` on loopback holding a random M-point map that contains the
n points of a random scene (all started with the embedded servers, whose garbler may dial
only them) serves ``repeat`` frames that localize against it over TLS (four processes, as
a device would). Reported per (n, M):

- seconds per iteration (median over every timed iteration of every frame) next to the
  plain circuit's, from the same run and daemons: its ``service`` median
  (``plain_median_s``, back-to-back invocations) and the same frames through the same LM
  driver with the points at the client (``plain_frame_median_s``, the first setting;
  ``extra_s`` is against this one, like for like);
- AND gates of the map-owner circuit next to the plain one's, and of the selection: 0,
  because the selection is a 1-out-of-M OT per point (``ot/selection.py``), no circuit;
- the OT of the pad bits per invocation (map owner <-> garbler) and the selection per
  frame (device <-> map owner): seconds as the map owner logs its sessions (its
  ``session`` lines, ``circuit: map_owner``; the only place the map owner's own time is
  visible), bytes per link from the client's counters;
- bytes per link per iteration and per frame, and whether the garbled pose equals the
  cleartext run of the plain circuit on the map owner's normalized points.
"""

from __future__ import annotations

import json
import secrets
import statistics
import tempfile
from pathlib import Path

import numpy as np

from snail_client.embedded import Daemon, connected
from snail_client.localize import GarbledBackend, Options
from snail_client.mapowner import MapOwnerLink
from snail_client.owner_localize import run_frame
from snail_common.circuit import registry
from snail_common.loc.backends import CircuitBackend
from snail_common.loc.mapfile import Frame, MapPoints
from snail_common.loc.owner import localize_known, owner_values
from snail_common.loc.synthetic import random_scene
from snail_common.net.linkrates import AUTO
from snail_common.pnp.spec import Spec

from .service import _measure

# invocations per frame (padding included): the per-iteration figures do not depend on
# it, and the product's default of 20 would make n = 64 frames take minutes
FRAME_INVOCATIONS = 5
PAD_BITS_PER_POINT = 96  # three float32 words per selected point
SELECTION = "1-out-of-M OT per frame point (snail_common/ot/selection.py): no circuit"
LOG_SOURCE = "snail-mapd session log lines (event session, circuit map_owner)"
CLIENT_SOURCE = "the client's per-link counters (snail-result traffic)"
PER_ITERATION_LINKS = ("client_to_garbler", "client_to_evaluator", "garbler_to_evaluator",
                       "evaluator_to_client", "garbler_to_client", "garbler_to_mapowner",
                       "mapowner_to_garbler")
SELECTION_LINKS = ("client_to_mapowner", "mapowner_to_client")


def scene_and_map(rng: np.random.Generator, n: int, m: int) -> tuple[Frame, MapPoints]:
    """A random scene's frame and an m-point map holding its n points at random places
    among m - n others spread like the scene (so normalization keeps its scale)."""
    if m < n:
        raise ValueError(f"--map-points {m}: the map must hold the scene's {n} points")
    problem = random_scene(rng, n)
    ids = rng.permutation(1 << 24)[:m].astype(np.int64)
    where = rng.permutation(m)[:n]
    xyz = rng.normal(problem.points3d.mean(axis=0), 2.0, (m, 3))
    xyz[where] = problem.points3d
    frame = Frame(K=problem.K, dist=problem.dist, points2d=problem.points2d,
                  map_ids=ids[where], initial_pose=problem.initial_pose)
    return frame, MapPoints(ids=ids, xyz=xyz)


def write_map(points: MapPoints, path: Path) -> Path:
    path.write_text(json.dumps({"format": "snail-map/1", "points": [
        {"id": int(i), "xyz": p.tolist()} for i, p in zip(points.ids, points.xyz)]}))
    return path


def map_owner_sessions(log: Path) -> tuple[list[dict], list[dict]]:
    """(selections, pad-bit OTs): the map owner's session lines, told apart by peer (a
    device's selection names its certificate; the garbler's invocations log none)."""
    lines = [json.loads(line) for line in log.read_text().splitlines() if line.strip()]
    sessions = [e for e in lines if e.get("event") == "session"
                and e.get("circuit") == "map_owner"]
    return ([s for s in sessions if s.get("peer")], [s for s in sessions if not s.get("peer")])


def _median(values: list[float], digits: int = 4) -> float | None:
    return round(statistics.median(values), digits) if values else None


def map_owner_row(runner, tls_dir: Path, daemon: Daemon, frame: Frame, points: MapPoints,
                  repeat: int, plain: dict, options: Options) -> dict:
    """One (n, M) measurement against ``daemon``, the map owner holding ``points``; see
    the module docstring for the fields."""
    n, m = len(frame.map_ids), len(points.ids)
    try:
        with MapOwnerLink(daemon.address, tls_dir) as link:
            link.open()  # map_info and base OTs: once per link, not per frame
            records = [run_frame(frame, link, GarbledBackend(runner), options)
                       for _ in range(repeat)]
    finally:
        daemon.stop()  # its log is complete once it has gone
    selections, pad_ots = map_owner_sessions(daemon.log)
    published, values = owner_values(points)
    want = localize_known(frame, published, values, options, CircuitBackend())
    # the first setting on the same frames and driver: the client holds the points
    first_setting = [localize_known(frame, published, values, options,
                                    GarbledBackend(runner)) for _ in range(repeat)]
    plain_walls = [w for r in first_setting for w in r.walls]
    got = records[0]
    walls = [w for r in records for w in r["timing"]["per_iteration_s"]]
    invocations = [r["invocations"] for r in records]
    per_iteration = {k: int(statistics.median(r["traffic"][k] // r["invocations"]
                                              for r in records))
                     for k in PER_ITERATION_LINKS}
    per_frame = {k: int(statistics.median(r["traffic"][k] for r in records))
                 for k in (*PER_ITERATION_LINKS, *SELECTION_LINKS)}
    # the map owner's bytes_out per invocation are its OT message to the garbler, the
    # labels to the evaluator and a done: the evaluator's share is what the garbler did
    # not receive (the garbler counts every byte from the map owner on its link)
    owner_out = [s["bytes_out"] for s in pad_ots]
    to_evaluator = (sum(owner_out) - sum(r["traffic"]["mapowner_to_garbler"]
                                         for r in records)) // max(len(pad_ots), 1)
    mo = registry.interface(Spec("lm", "sil", options.solver, n, owner=True,
                                 arith=options.arith_used).registry_id)
    return {
        "points": n, "map_points": m, "repeat": repeat,
        "invocations_per_frame": statistics.median(invocations),
        "and": mo.counts["and"], "depth": mo.depth,
        "median_s": _median(walls), "min_s": round(min(walls), 4),
        "max_s": round(max(walls), 4), "timed_iterations": len(walls),
        "plain_circuit": plain["circuit"], "plain_and": plain["and"],
        "plain_median_s": plain["median_s"],
        "plain_frame_median_s": _median(plain_walls),
        "plain_frame_source": "the same frames and LM driver on the plain circuit, the "
                              "points in the clear at the client (the first setting)",
        "extra_s": round(_median(walls) - _median(plain_walls), 4),
        "selection": {
            "and": 0, "how": SELECTION, "per": "frame",
            "map_owner_s": _median([s["seconds"] for s in selections]),
            "map_owner_s_source": LOG_SOURCE,
            "bytes_to_device": per_frame["mapowner_to_client"],
            "bytes_from_device": per_frame["client_to_mapowner"],
            "bytes_source": f"{CLIENT_SOURCE}: the device's link with the map owner, the "
                            f"selection and each run's pad correction",
            "frames": len(selections)},
        "pad_ot": {
            "ots_per_invocation": PAD_BITS_PER_POINT * n, "per": "invocation",
            "kind": "chosen-message IKNP, garbler sender, map owner receiver",
            "map_owner_s": _median([s["seconds"] for s in pad_ots[1:]] or
                                   [s["seconds"] for s in pad_ots]),
            "first_s": round(pad_ots[0]["seconds"], 4) if pad_ots else None,
            "first_includes": "the base OTs of the garbler-map owner link",
            "map_owner_s_source": LOG_SOURCE, "sessions": len(pad_ots),
            "garbler_to_mapowner": per_iteration["garbler_to_mapowner"],
            "mapowner_to_garbler": per_iteration["mapowner_to_garbler"],
            "mapowner_to_evaluator": to_evaluator,
            "mapowner_to_evaluator_source": "map owner's logged bytes_out minus the "
                                            "garbler's count of mapowner_to_garbler",
            "bytes_source": CLIENT_SOURCE},
        "traffic_per_iteration": per_iteration,
        "traffic_per_frame": per_frame,
        "pose_equals_first_setting": bool(
            got["rvec"] == [float(x) for x in first_setting[0].rvec]
            and got["tvec"] == [float(x) for x in first_setting[0].tvec]),
        "pose_equals_cleartext": bool(got["rvec"] == [float(x) for x in want.rvec]
                                      and got["tvec"] == [float(x) for x in want.tvec]),
        "rvec": got["rvec"], "tvec": got["tvec"], "status": got["status"],
    }


def map_owner_report(points: tuple[int, ...], map_points: tuple[int, ...], repeat: int,
                     scheme: str = AUTO, lanes: tuple[str, ...] = ()) -> dict:
    """``{"service": {plain id: row}, "map_owner": {mo id: {str(M): row}}}`` on embedded
    daemons (the map owners need certificates from the same throwaway CA, and the garbler
    their addresses at its start: every map is made before the servers start)."""
    options = Options(solve="circuit", min_invocations=FRAME_INVOCATIONS, scheme=scheme)
    rng = np.random.default_rng(secrets.randbits(128))
    scenes = {(n, m): scene_and_map(rng, n, m) for n in points for m in map_points}
    service: dict[str, dict] = {}
    owner: dict[str, dict] = {}
    with tempfile.TemporaryDirectory(prefix="snail-bench-maps-") as tmp:
        maps = [write_map(xyz, Path(tmp) / f"map-n{n}-m{m}.json")
                for (n, m), (_, xyz) in scenes.items()]
        with connected(None, None, None, lanes, scheme=scheme, maps=maps) as (
                runner, services):
            owners = dict(zip(scenes, services.map_owners))
            for n in points:
                spec = Spec("lm", "sil", options.solver, n, arith=options.arith_used)
                row = _measure(runner, spec, repeat)  # with the schemes its sessions used
                service[spec.circuit_id] = row
                plain = {"circuit": spec.circuit_id, "and": row["and"],
                         "median_s": row["median_s"]}
                mo_id = Spec("lm", "sil", options.solver, n, owner=True,
                             arith=options.arith_used).circuit_id
                owner[mo_id] = {str(m): {**map_owner_row(runner, services.tls_dir,
                                                         owners[n, m], *scenes[n, m],
                                                         repeat, plain, options),
                                         "scheme": scheme}
                                for m in map_points}
    return {"service": service, "map_owner": owner}

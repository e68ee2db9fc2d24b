"""``snail-client localize --input FRAME.json --map-owner HOST:PORT`` (or ``--map MAP.json``):
localize a device's frame against a map the device never holds (the map-owner setting).

Per frame the device selects its map points obliviously from the map owner (it gets them
under the map owner's pads, mapowner.py), names the frame handle to the secure runner, and
runs the map-owner circuit (snail_common.loc.owner): its share of the points goes in as
labels it derives, the map owner's pads by OT between the map owner and the garbler.
With ``--relay`` the device reaches the map owner only through the evaluator (relay.py),
so the map owner never sees its address.

``--map`` starts a map owner on loopback with that map (with the embedded servers, which
are told to allow it, or beside remote ones with --tls-dir, whose garbler must allow its
address with --map-owner): for trying the setting out. It gives no privacy against
yourself: this machine then holds the map and the device's data together.
With ``--backend cleartext`` or ``float64`` (``--map`` only) the same localization runs
in the clear on the selected points.
"""

from __future__ import annotations

import contextlib
import tempfile
from collections.abc import Iterator
from pathlib import Path

from snail_common.loc.backends import Backend, CircuitBackend, Float64Backend, interface
from snail_common.loc.mapfile import Frame, load_frame, load_map
from snail_common.loc.owner import localize_known, localize_shared, owner_values
from snail_common.loc.pipeline import Localized
from snail_common.loc.problem import PoseVectors, ProblemError

from .audit import IntegrityFailure
from .embedded import connected, start_daemon
from .localize import RESULT_FORMAT, GarbledBackend, Options, audit_counts, audits_since
from .mapowner import MapOwnerLink
from .relay import EVALUATOR
from .sessions import LINKS, OWNER_LINKS, parse_address

MAP_OWNER_LINKS = ("client_to_mapowner", "mapowner_to_client", *OWNER_LINKS)


def check(options: Options, map_owner: str | None, map_path: str | None) -> None:
    """ValueError naming the flag when the map-owner flags do not fit the others."""
    if map_owner and map_path:
        raise ValueError("--map-owner and --map: choose one (--map starts a local map owner)")
    if options.mode != "sil" or options.solve == "client":
        raise ValueError("--map-owner/--map: the map-owner setting runs SIL iterations that "
                         "solve inside the circuit (--mode sil, --solve circuit)")
    if map_owner and options.backend != "garbled":
        raise ValueError("--map-owner: only --backend garbled reaches a map owner (--map "
                         "with --backend cleartext runs in the clear)")
    if map_owner and not options.tls_dir:
        raise ValueError("--map-owner needs --tls-dir with the CA the map owner trusts "
                         "(and --garbler/--evaluator)")
    if options.relay and options.backend != "garbled":
        raise ValueError("--relay: only --backend garbled reaches a map owner")
    if options.relay not in (None, EVALUATOR):
        parse_address(options.relay, "--relay")


def localize_frame(path: str, options: Options, map_owner: str | None,
                   map_path: str | None) -> dict:
    """The snail-result/1 record of one snail-frame/1 file (ProblemError names a bad
    field of the frame or the map; ServiceError a failed run)."""
    try:
        frame = load_frame(path)
    except (ProblemError, ValueError) as exc:
        raise ProblemError(f"{path}: {exc}") from None
    with session(options, map_owner, map_path) as (backend, link, known):
        if link is None:
            published, values = known
            return record(localize_known(frame, published, values, options, backend),
                          options, dict.fromkeys((*LINKS, *MAP_OWNER_LINKS), 0))
        return run_frame(frame, link, backend, options)


@contextlib.contextmanager
def session(options: Options, map_owner: str | None, map_path: str | None
            ) -> Iterator[tuple[Backend, MapOwnerLink | None, tuple | None]]:
    """(backend, map-owner link, None) for garbled runs: the servers and the map owner
    connected (started here for ``--map``) for the block; (backend, None, (published
    map, its points)) in the clear for ``--map`` with --backend cleartext or float64."""
    if options.backend != "garbled":
        try:
            known = owner_values(load_map(map_path))
        except (ProblemError, ValueError) as exc:
            raise ProblemError(f"--map {map_path}: {exc}") from None
        yield (Float64Backend() if options.backend == "float64" else CircuitBackend()), \
            None, known
        return
    with connected(options.garbler, options.evaluator, options.tls_dir,
                   busy_wait=options.busy_wait, cert_name=options.cert_name,
                   link_timeout=options.link_timeout, scheme=options.scheme,
                   maps=(map_path,) if map_path else (), audit_rate=options.audit_rate,
                   evidence_dir=options.evidence) as (runner, services):
        tls_dir = services.tls_dir if services is not None else options.tls_dir
        if services is not None and services.map_owners:
            map_owner = services.map_owners[0].address
        evaluator = options.evaluator or (services.evaluator_addr if services else None)
        relay = evaluator if options.relay == EVALUATOR else options.relay
        with _map_owner(map_owner, map_path, tls_dir, evaluator) as address, \
                MapOwnerLink(address, tls_dir, options.cert_name, relay=relay) as link:
            yield GarbledBackend(runner), link, None


def run_frame(frame: Frame, link: MapOwnerLink, backend: GarbledBackend,
              options: Options, start: PoseVectors | None = None,
              runs: int | None = None) -> dict:
    """One frame over an open map-owner link and a garbled backend: padded from its own
    initial pose, or (a stream's tracking schedule) exactly ``runs`` from ``start``."""
    before = _bytes(backend.traffic(), link.traffic)
    audited = audit_counts(backend)
    published = link.published or link.open()
    handle, masked = link.select(frame.map_ids)
    backend.secure.use_frame(handle, link.address, link.relay)
    backend.frame = handle  # this frame's runs (frames in flight: each names its own)
    try:
        result = localize_shared(frame, published, masked, options, backend, start, runs)
    except IntegrityFailure as exc:  # the frame's audits go with its failure
        exc.audits = audits_since(audited, audit_counts(backend))
        raise
    after = _bytes(backend.traffic(), link.traffic)
    out = record(result, options, {k: after.get(k, 0) - before.get(k, 0)
                                   for k in (*LINKS, *MAP_OWNER_LINKS)},
                 tracked=runs is not None)
    out["audits"] = audits_since(audited, audit_counts(backend))
    return out


def _bytes(runs: dict[str, int], selections: dict[str, int]) -> dict[str, int]:
    """Bytes per link so far: the runs' (the device's pad corrections among them) and the
    map-owner link's (the published map, the base OTs, the selections)."""
    return {k: runs.get(k, 0) + selections.get(k, 0) for k in runs.keys() | selections}


@contextlib.contextmanager
def _map_owner(address: str | None, map_path: str | None, tls_dir: str | Path,
               evaluator: str | None) -> Iterator[str]:
    """The map owner's address: the given one, or one started here for ``--map`` beside
    remote servers (it may send its labels to ``evaluator`` alone)."""
    if address:
        yield address
        return
    with tempfile.TemporaryDirectory(prefix="snail-mapd-") as tmp:
        daemon = start_daemon("mapd", ["--map", str(map_path), "--tls-dir", str(tls_dir),
                                       "--evaluator", str(evaluator),
                                       "--log-level", "warning"], Path(tmp) / "mapd.log")
        try:
            yield daemon.address
        finally:
            daemon.stop()


def record(result: Localized, options: Options, traffic: dict[str, int],
           tracked: bool = False) -> dict:
    """A snail-result/1 record with ``"setting": "map-owner"``. The device holds no 3D
    point, so the trust checks are those of the cost alone: converged (or ``tracked``, a
    frame of the fixed schedule) and the RMS, at the last pose a run evaluated."""
    if not result.converged and not tracked:
        status, warnings = "not_converged", ["the iteration limit came before convergence"]
    elif not result.rms_px <= options.max_rms_px:
        status, warnings = "bad_fit", [f"reprojection RMS {result.rms_px:.2f} px is above "
                                       f"--max-rms-px {options.max_rms_px:g}"]
    else:
        status, warnings = ("tracked" if tracked else "converged"), []
    if tracked and result.invocations == 1:
        warnings.append("rms_px is the prediction's: with one run a frame no run evaluates "
                        "the answer (--runs-per-frame 2 checks the first step's pose)")
    iface = interface(result.spec)
    out = {
        "format": RESULT_FORMAT, "setting": "map-owner",
        "rvec": [float(x) for x in result.rvec], "tvec": [float(x) for x in result.tvec],
        "status": status, "warnings": warnings, "converged": status == "converged",
        "iterations": result.iterations, "invocations": result.invocations,
        "cost": float(result.cost), "rms_px": result.rms_px,
        "algorithm": options.step if tracked else options.algorithm,  # what the runs took
        "mode": "sil", "solve": "circuit",
        "solver": options.solver, "backend": options.backend,
        "timing": {"total_s": result.total_s, "per_iteration_s": result.walls},
        "traffic": traffic,
        "circuit": {"and": iface.counts["and"], "xor": iface.counts["xor"],
                    "depth": iface.depth, "points": result.spec.points},
    }
    if options.backend == "garbled":
        out["scheme"] = options.scheme
    return out

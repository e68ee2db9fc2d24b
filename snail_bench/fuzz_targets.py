"""Fuzz targets: every parser of untrusted bytes, as a function of one byte string.

A target returns normally or raises the error its parser documents for bad input (a
``ProtocolError`` for frames, a ``ProblemError`` for files); anything else is a crash.
Hangs and unbounded allocation are caught by the fuzzer's time and memory limits
(``snail-bench fuzz``). ``seeds()`` gives each target valid inputs to mutate from.
"""

from __future__ import annotations

import base64
import contextlib
import json
import os
import struct
import tempfile
from collections.abc import Callable
from pathlib import Path

from snail_client.inputs.camera import load_camera
from snail_client.inputs.colmap import read_model
from snail_client.inputs.tagmap import load_tagmap
from snail_common.loc.mapfile import load_frame, load_map
from snail_common.loc.problem import ProblemError, load_problem, read_sequence
from snail_common.net import messages
from snail_common.net.errors import ProtocolError
from snail_common.net.frames import LENGTH, FrameReader, decode, encode_bytes
from snail_common.net.seal import EVALUATOR_TO_GARBLER, GARBLER_TO_EVALUATOR, FrameSeal
from snail_common.net.tls import TLSFileError, add_client, client_context, make_certs, read_revoked

Target = Callable[[bytes], None]
_SCRATCH = Path(os.environ.get("SNAIL_FUZZ_DIR") or
                (Path("/dev/shm") if Path("/dev/shm").is_dir() else Path(tempfile.gettempdir())))


def frames(data: bytes) -> None:
    """A byte stream into the frame reader, cut where its first byte says: what a peer
    on a TLS connection can send."""
    _read_in_cuts(FrameReader(max_frame=1 << 16), data[1:], 1 + (data[0] if data else 0))


def _read_in_cuts(reader: FrameReader, wire: bytes | bytearray, cut: int) -> None:
    """``wire`` into ``reader`` ``cut`` bytes at a time, as a transport delivers it."""
    for start in range(0, len(wire), cut):
        chunk = wire[start:start + cut]
        view = reader.buffer()
        size = min(len(view), len(chunk))
        view[:size] = chunk[:size]
        reader.filled(size)


_FUZZ_KEY = bytes(range(32))  # the sealed link's key in the fuzz target (fixed: replayable)


def sealed_frames(data: bytes) -> None:
    """What reaches a sealed table link's reader (--table-link aead): the frames of the
    stream after the first three bytes, each sealed as the other server would, one bit
    flipped where bytes 1-2 say (none past the end: the frames decode, so the fuzzer
    reaches the messages behind the seal), cut where byte 0 says."""
    if len(data) < 3:
        return
    sender = FrameSeal(_FUZZ_KEY, GARBLER_TO_EVALUATOR, EVALUATOR_TO_GARBLER)
    wire, rest = bytearray(), memoryview(data)[3:]
    while len(rest) >= LENGTH.size:
        (length,) = LENGTH.unpack_from(rest)
        body = rest[LENGTH.size : LENGTH.size + min(length, 1 << 16)]
        wire += b"".join(bytes(p) for p in sender.seal([b"", body]))
        rest = rest[LENGTH.size + len(body):]
    flip = int.from_bytes(data[1:3], "big")
    if flip < len(wire):
        wire[flip] ^= 1
    reader = FrameReader(max_frame=1 << 16,
                         seal=FrameSeal(_FUZZ_KEY, EVALUATOR_TO_GARBLER, GARBLER_TO_EVALUATOR))
    _read_in_cuts(reader, wire, 1 + data[0])


def message(data: bytes) -> None:
    """One frame body through decoding and the message catalogue's validators."""
    decode(data)


def _scratch_dir() -> Path:
    path = _SCRATCH / f"snail-fuzz-{os.getpid()}"
    path.mkdir(parents=True, exist_ok=True)
    return path


def _file(data: bytes, load: Callable[[Path], object]) -> None:
    """``data`` as a file read by the loader the command line uses."""
    path = _scratch_dir() / "input.json"
    path.write_bytes(data)
    load(path)


def problem(data: bytes) -> None:
    """A snail-problem/1 file."""
    _file(data, load_problem)


def camera(data: bytes) -> None:
    """A snail-camera/1 file."""
    _file(data, load_camera)


def tagmap(data: bytes) -> None:
    """A snail-tagmap/1 file."""
    _file(data, load_tagmap)


def sequence(data: bytes) -> None:
    """A track sequence file (JSON lines, an array or one problem)."""
    _file(data, read_sequence)


def map_file(data: bytes) -> None:
    """A snail-map/1 file (the map owner's)."""
    _file(data, load_map)


def frame_file(data: bytes) -> None:
    """A snail-frame/1 file (the device's, in the map-owner setting)."""
    _file(data, load_frame)


def _colmap(data: bytes, kind: str) -> None:
    """A COLMAP model: the input split into cameras, images and points3D files by its
    first four bytes (two little-endian 16-bit lengths)."""
    head, body = data[:4].ljust(4, b"\0"), data[4:]
    a, b = struct.unpack("<HH", head)
    parts = (body[:a], body[a:a + b], body[a + b:])
    folder = _scratch_dir() / kind
    folder.mkdir(exist_ok=True)
    for name, part in zip(("cameras", "images", "points3D"), parts):
        (folder / f"{name}.{kind}").write_bytes(part)
    read_model(folder)


def colmap_bin(data: bytes) -> None:
    _colmap(data, "bin")


def colmap_txt(data: bytes) -> None:
    _colmap(data, "txt")


def revoked(data: bytes) -> None:
    """A daemon's revoked.txt."""
    folder = _scratch_dir()
    (folder / "revoked.txt").write_bytes(data)
    read_revoked(folder)


_TLS_FILES = ("ca.pem", "client.pem", "client.key", "ca.key")


def _tls_folder() -> Path:
    """A valid TLS folder made once per process, put back before each input: only the
    file the previous input replaced is rewritten, and a certificate it issued removed."""
    work = _scratch_dir() / "tls"
    if not work.is_dir():
        make_certs(work)
        _TLS_VALID.update({f.name: f.read_bytes() for f in work.iterdir()})
    for name in _TLS_DIRTY:
        (work / name).write_bytes(_TLS_VALID[name])
    _TLS_DIRTY.clear()
    for extra in work.glob("robot.*"):
        extra.unlink()
    return work


_TLS_VALID: dict[str, bytes] = {}
_TLS_DIRTY: set[str] = set()


def certificates(data: bytes) -> None:
    """A TLS folder whose CA, certificate or key file is ``data[1:]`` (``data[0]`` picks
    which; a PEM seed is kept whole), or with bit 3 of ``data[0]`` set, the valid file
    with its DER patched by ``data[1:]`` (see ``_patched``): loaded as a client's context
    and used to issue a client certificate, as a device and ``snail-client certs
    --client`` do."""
    folder = _tls_folder()
    pick = data[0] if data else 0
    name = _TLS_FILES[pick % len(_TLS_FILES)]
    _TLS_DIRTY.add(name)
    (folder / name).write_bytes(_patched(_TLS_VALID[name], data[1:]) if pick & 8
                                else data[1:])
    if pick & 4:
        add_client(folder, "robot")
    else:
        client_context(folder, "client")


def _patched(pem: bytes, patch: bytes) -> bytes:
    """``pem`` with bytes of its DER body XORed by ``patch``'s (offset: 2 bytes, mask)
    triples, re-encoded as PEM. The parsers are C (OpenSSL), where atheris sees no
    coverage: without this, libFuzzer shrinks its corpus to short garbage and almost no
    input is a near-valid certificate or key."""
    lines = pem.strip().split(b"\n")
    der = bytearray(base64.b64decode(b"".join(lines[1:-1])))
    for k in range(0, len(patch) - 2, 3):
        der[int.from_bytes(patch[k:k + 2], "little") % len(der)] ^= patch[k + 2]
    body = base64.encodebytes(bytes(der)).replace(b"\n", b"")
    wrapped = [body[i:i + 64] for i in range(0, len(body), 64)]
    return b"\n".join([lines[0], *wrapped, lines[-1]]) + b"\n"


# each parser with the errors it documents for bad input (TLSFileError is a ValueError)
PARSERS: dict[str, tuple[Target, tuple[type[Exception], ...]]] = {
    "frames": (frames, (ProtocolError,)), "message": (message, (ProtocolError,)),
    "sealed_frames": (sealed_frames, (ProtocolError,)),
    "problem": (problem, (ProblemError,)), "sequence": (sequence, (ProblemError,)),
    "camera": (camera, (ProblemError,)), "tagmap": (tagmap, (ProblemError,)),
    "colmap_bin": (colmap_bin, (ProblemError,)), "colmap_txt": (colmap_txt, (ProblemError,)),
    "revoked": (revoked, (TLSFileError,)), "certificates": (certificates, (TLSFileError,)),
    "map": (map_file, (ProblemError,)), "frame": (frame_file, (ProblemError,)),
}


def _target(parse: Target, documented: tuple[type[Exception], ...]) -> Target:
    def run(data: bytes) -> None:
        with contextlib.suppress(*documented):
            parse(data)
    return run


TARGETS: dict[str, Target] = {name: _target(*entry) for name, entry in PARSERS.items()}


def seeds(target: str) -> list[bytes]:
    """Valid inputs of ``target`` (mutation starts from what the parser accepts)."""
    catalogue = [messages.make("hello", role="client", software="seed", max_frame=1 << 20),
                 messages.make("session_start", sid=bytes(16), circuit="loc/ne-sil-n6",
                               hash="0" * 64),
                 messages.make("input_labels", sid=bytes(16), start=0, total=2,
                               labels=bytes(32)),
                 messages.error("busy", "full", bytes(16)),
                 messages.make("health_request"),
                 # the map owner's protocol
                 messages.make("map_info", points=3, transform=bytes(32), start=0,
                               ids=bytes(12)),
                 messages.make("ot_ext_u", sid=bytes(16), start=0, m=8, u=bytes(128)),
                 messages.make("sel_table", frame=bytes(16), start=0, key=bytes(16),
                               offset=0, total=24, table=bytes(24)),
                 messages.make("owner_labels", sid=bytes(16), start=0, total=2,
                               labels=bytes(32))]
    wire = [encode_bytes(m) for m in catalogue]
    problem_json = {"format": "snail-problem/1",
                    "camera": {"fx": 800, "fy": 800, "cx": 320, "cy": 240,
                               "dist": [0, 0, 0, 0, 0]},
                    "points2d": [[300, 200], [340, 200], [340, 260], [300, 260]],
                    "points3d": [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 1]],
                    "initial_pose": {"rvec": [0, 0, 0], "tvec": [0, 0, 5]}}
    by_target = {
        "frames": [b"\x00" + b"".join(wire), b"\x03" + wire[0]],
        "sealed_frames": [b"\x00\xff\xff" + b"".join(wire), b"\x07\xff\xff" + wire[1]],
        "message": [w[4:] for w in wire],
        "problem": [json.dumps(problem_json).encode()],
        "sequence": [(json.dumps(problem_json) + "\n") .encode() * 2],
        "camera": [json.dumps({"format": "snail-camera/1", "fx": 800, "fy": 810, "cx": 320,
                               "cy": 240, "dist": [0.1, 0, 0, 0, 0], "width": 640,
                               "height": 480}).encode()],
        "tagmap": [json.dumps({"format": "snail-tagmap/1", "family": "tag36h11",
                               "tags": [{"id": 3, "size": 0.1,
                                         "rvec": [0, 0, 0], "tvec": [0, 0, 0]}]}).encode()],
        "colmap_bin": [_colmap_bin_seed()],
        "colmap_txt": [_colmap_txt_seed()],
        "revoked": [b"# lost\nrobot7\n" + b"ab:" * 31 + b"cd\n"],
        "certificates": _tls_seeds(),
        "map": [json.dumps({"format": "snail-map/1", "points": [
            {"id": 17, "xyz": [0, 0, 0]}, {"id": 4, "xyz": [1.5, 0, 0.25]},
            {"id": 90, "xyz": [1, 1, 0]}]}).encode()],
        "frame": [json.dumps({"format": "snail-frame/1", "camera": problem_json["camera"],
                              "points2d": problem_json["points2d"], "map_ids": [17, 4, 90, 5],
                              "initial_pose": problem_json["initial_pose"]}).encode()],
    }
    return by_target[target]


def _tls_seeds() -> list[bytes]:
    """Each TLS file of a valid folder, behind the byte that puts it back in place, once
    for loading and once for issuing; and each as an empty patch of its DER."""
    folder = _tls_folder()
    return [bytes([i + flag]) + (folder / name).read_bytes()
            for flag in (0, 4) for i, name in enumerate(_TLS_FILES)] + [
        bytes([i + flag, 0, 0, 0])  # an empty patch: libFuzzer grows it
        for flag in (8, 12) for i in range(len(_TLS_FILES))]


def _split(*parts: bytes) -> bytes:
    return struct.pack("<HH", len(parts[0]), len(parts[1])) + b"".join(parts)


def _colmap_bin_seed() -> bytes:
    cameras = struct.pack("<Q", 1) + struct.pack("<iiQQ", 1, 1, 640, 480) + \
        struct.pack("<4d", 800, 800, 320, 240)
    images = struct.pack("<Q", 1) + struct.pack("<i7di", 1, 1, 0, 0, 0, 0, 0, 5, 1) + \
        b"a.png\0" + struct.pack("<Q", 1) + struct.pack("<ddq", 300.0, 200.0, 1)
    points = struct.pack("<Q", 1) + struct.pack("<Q3d3Bd", 1, 0, 0, 0, 255, 0, 0, 0.5) + \
        struct.pack("<Q", 1) + struct.pack("<ii", 1, 0)
    return _split(cameras, images, points)


def _colmap_txt_seed() -> bytes:
    return _split(b"1 PINHOLE 640 480 800 800 320 240\n",
                  b"1 1 0 0 0 0 0 5 1 a.png\n300 200 1\n",
                  b"1 0 0 0 255 0 0 0.5 1 0\n")

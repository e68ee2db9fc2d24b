"""The Python API: one session for a stream of frames (images or arrays), each seeded by
the last trusted pose; a garbled session opens its two connections once."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

import snail_client.secure as secure
from snail_client.api import Localizer, first_pose
from snail_client.inputs.fields import InputError
from snail_common.loc.problem import PoseVectors
from snail_common.loc.trust import pose_error
from snail_demo.render import render
from snail_demo.scenes import random_tag_scene, view


@pytest.fixture(scope="module")
def walk():
    """A 3-tag board and four frames of a camera moving along it."""
    rng = np.random.default_rng(21)
    scene = random_tag_scene(rng, tags=3, obliquity=(35, 36))
    poses = [view(35 + 2 * k, 60 + k, scene.distance * (1 - 0.02 * k), 0) for k in range(4)]
    images = [render(scene.tagmap, scene.camera, p, scene.look, rng) for p in poses]
    return scene, poses, images


def test_a_stream_of_images_is_seeded_frame_to_frame(walk, tmp_path):
    scene, poses, images = walk
    (tmp_path / "cam.json").write_text(json.dumps(scene.camera.to_json()))
    (tmp_path / "map.json").write_text(json.dumps(scene.tagmap.to_json()))
    with Localizer(camera=tmp_path / "cam.json", tag_map=tmp_path / "map.json",
                   backend="float64", min_invocations=0) as loc:
        iterations = []
        for image, truth in zip(images, poses):
            pose = loc.localize_image(image)
            assert pose.trusted and sorted(pose.tag_ids) == sorted(scene.tagmap.tags)
            err = pose_error(pose.rvec, pose.tvec, truth)
            assert err["rotation_deg"] < 1.0 and err["translation"] < 0.02 * scene.distance
            assert np.array_equal(loc.last.rvec, pose.rvec)
            iterations.append(pose.record["iterations"])
            centre = -cv2.Rodrigues(truth.rvec)[0].T @ truth.tvec
            assert np.linalg.norm(pose.camera_position - centre) == pytest.approx(
                err["translation"])
        cv2.imwrite(str(tmp_path / "f.png"), images[0])
        assert loc.localize_image(tmp_path / "f.png").trusted  # a file works too
        loc.reset()
        assert loc.last is None
        with pytest.raises(InputError, match="no tag36h11 tag detected"):
            loc.localize_image(np.full_like(images[0], 100))


def test_arrays_localize_with_a_computed_start(walk):
    scene, poses, _ = walk
    rng = np.random.default_rng(4)
    for planar in (True, False):
        world = rng.uniform([-0.3, -0.3, 0], [0.3, 0.3, 0 if planar else 0.3], size=(12, 3))
        truth = poses[0]
        pix, _ = cv2.projectPoints(world, truth.rvec, truth.tvec, scene.camera.K,
                                   scene.camera.dist)
        pix = pix.reshape(-1, 2) + rng.normal(scale=0.3, size=(12, 2))
        start = first_pose(pix, world, scene.camera)
        assert pose_error(start.rvec, start.tvec, truth)["rotation_deg"] < 5
        with Localizer(camera=scene.camera, backend="float64", min_invocations=0) as loc:
            pose = loc.localize_points(pix, world)
        err = pose_error(pose.rvec, pose.tvec, truth)
        assert pose.trusted and err["rotation_deg"] < 0.5


def test_bad_options_and_missing_inputs_are_named(walk):
    scene, _, images = walk
    with pytest.raises(ValueError, match="--backend"):
        Localizer(backend="quantum")
    with Localizer(backend="float64") as loc, pytest.raises(ValueError, match="camera"):
        loc.localize_image(images[0])
    with Localizer(camera=scene.camera, backend="float64") as loc, pytest.raises(
            ValueError, match="at least 4 matched pairs"):
        loc.localize_points(np.zeros((3, 2)), np.zeros((3, 3)))


def test_a_garbled_session_keeps_its_connections(walk, monkeypatch):
    """Three frames over one session: two TLS connections in all (one per server), every
    frame padded to min_invocations, poses as the cleartext circuit's. One tag per frame
    (max_tags=1, n = 4: the circuit the other image tests compile)."""
    scene, poses, images = walk
    opened = []
    real_connect = secure.connect

    async def counting(*args, **kw):
        opened.append(args[4])  # connect(host, port, ctx, "client", role, ...)
        return await real_connect(*args, **kw)

    monkeypatch.setattr(secure, "connect", counting)
    with Localizer(camera=scene.camera, tag_map=scene.tagmap, backend="garbled",
                   min_invocations=3, max_tags=1) as loc:
        garbled = [loc.localize_image(image) for image in images[:3]]
    with Localizer(camera=scene.camera, tag_map=scene.tagmap, backend="cleartext",
                   min_invocations=0, max_tags=1) as loc:
        clear = [loc.localize_image(image) for image in images[:3]]
    assert sorted(opened) == ["evaluator", "garbler"]
    for g, c, truth in zip(garbled, clear, poses):
        assert g.trusted and g.record["invocations"] >= 3 and len(g.tag_ids) == 1
        assert g.record["rvec"] == c.record["rvec"] and g.record["tvec"] == c.record["tvec"]
        assert pose_error(g.rvec, g.tvec, PoseVectors(truth.rvec, truth.tvec))[
            "rotation_deg"] < 1.0

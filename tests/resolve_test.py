"""Settings resolved from the training data (``resolve``): the input scale, the scaling of
each view and the body whose handedness the views take at inference."""

import json

import numpy as np
import pytest

from c3dpo_jax import resolve
from c3dpo_jax.data import (
    KeypointData,
    alike_view_size_ratio,
    bodies,
    humans,
    importers,
    json_dataset,
)
from configs import own_json


def test_resolve_input_scale_only_replaces_zero():
    data = KeypointData(kp=np.array([[[0.0, 0.0], [2.0, 0.0]]]), vis=np.ones((1, 2)))
    c = own_json.get_config()
    assert c.model.keypoint_rescale == 0
    assert resolve.resolve_input_scale(c, data).model.keypoint_rescale == pytest.approx(1.0)
    assert c.model.keypoint_rescale == 0  # a copy, the caller's config is unchanged
    c.model.keypoint_rescale = 0.25
    assert resolve.resolve_input_scale(c, data).model.keypoint_rescale == 0.25


def test_the_input_scale_uses_the_intrinsics_only_for_a_perspective_model():
    # Two points 2 px apart (RMS radius 1), 0.004 apart once calibrated by a focal length
    # of 500 px (RMS radius 0.002).
    k = np.array([[[500.0, 0, 320], [0, 500, 240], [0, 0, 1]]])
    data = KeypointData(kp=np.array([[[320.0, 240.0], [322.0, 240.0]]]), vis=np.ones((1, 2)),
                        intrinsics=k)
    c = own_json.get_config()
    assert resolve.resolve_input_scale(c, data).model.keypoint_rescale == pytest.approx(1.0)
    c.model.projection_type = "perspective"
    assert resolve.resolve_input_scale(c, data).model.keypoint_rescale == pytest.approx(500.0)


def test_each_view_is_scaled_by_its_own_size_when_alike_views_differ_in_size():
    """``keypoint_scaling="auto"``: views of people at one distance keep one input scale;
    the same views each scaled by a factor 0.5-2x apart get "per_view"; a perspective model,
    a value that is not "auto" and a saved config's value are kept, "global" for a saved
    config that predates the option."""

    people = humans.make_split(60, views_per_pose=10, seed=1)
    rng = np.random.default_rng(0)
    factor = np.exp(rng.uniform(np.log(0.5), np.log(2.0), len(people)))[:, None, None]
    far_and_near = type(people)(kp=people.kp * factor, vis=people.vis)
    assert alike_view_size_ratio(people) < resolve.ALIKE_SIZE_RATIO
    assert alike_view_size_ratio(far_and_near) > resolve.ALIKE_SIZE_RATIO
    c = own_json.get_config()
    assert c.model.keypoint_scaling == "auto"
    assert resolve.resolve_keypoint_scaling(c, people).model.keypoint_scaling == "global"
    assert resolve.resolve_keypoint_scaling(c, far_and_near).model.keypoint_scaling == "per_view"
    assert c.model.keypoint_scaling == "auto"  # a copy
    saved = {"model": {"keypoint_scaling": "global"}}
    assert resolve.resolve_keypoint_scaling(c, far_and_near, saved).model.keypoint_scaling == (
        "global")
    older = {"model": {"n_keypoints": 17}}  # a run made before the option: one input scale
    assert resolve.resolve_keypoint_scaling(c, far_and_near, older).model.keypoint_scaling == (
        "global")
    c.model.projection_type = "perspective"
    assert resolve.resolve_keypoint_scaling(c, far_and_near).model.keypoint_scaling == "global"
    c.model.keypoint_scaling = "per_view"
    assert resolve.resolve_keypoint_scaling(c, people) is c


def test_coco_detections_of_people_at_different_distances_resolve_both_settings(tmp_path):
    """People photographed at different distances, as a detector's COCO file gives them
    (COCO's 17 keypoints, image coordinates: y down, pixels, hidden points v=0), read by
    the importer: ``configs/own_json.py``'s "auto" settings take the coco body's handedness
    and scale each view by its own size."""

    people = humans.make_split(40, views_per_pose=10, seed=2)
    rng = np.random.default_rng(1)
    size = np.exp(rng.uniform(np.log(60.0), np.log(240.0), len(people)))  # pixels per metre
    # The camera turned upside down about its axis: image rows grow downwards.
    xy = -humans.coco_from_h36m(people.kp3d)[..., :2] * size[:, None, None] + [320.0, 240.0]
    vis = humans.coco_visibility_from_h36m(people.vis)
    annotations = [{"image_id": i, "category_id": 1, "keypoints": np.concatenate(
        [xy[i], 2 * vis[i, :, None]], 1).reshape(-1).tolist()} for i in range(len(xy))]
    path = tmp_path / "person_keypoints.json"
    path.write_text(json.dumps({"annotations": annotations}))
    importers.main(["coco", str(path), "--out", str(tmp_path / "coco.json")])
    data = json_dataset.load(str(tmp_path / "coco.json"))
    c = own_json.get_config()
    c.model.n_keypoints = 17
    got = resolve.resolve_from_data(c, data)
    assert got.model.keypoint_scaling == "per_view"
    assert (got.inference.handedness_reference, got.inference.one_handedness) == ("coco", True)


def test_handedness_from_a_body_whose_projections_fit_the_training_views():
    """``"auto"``: people in the h36m body's joint order (the built-in humans' views, upright
    cameras, self-occlusion) get the body's handedness with one handedness on, in COCO's
    order (the face points' visibility the head's) the coco body's; the same
    views with their points in another order, another number of points, a perspective
    model or a value that is not "auto" keep what the config says; a saved config's value
    is kept."""

    people = humans.make_split(20, views_per_pose=5, seed=1)
    body = bodies.human_body("h36m")
    order = np.random.default_rng(0).permutation(17)
    shuffled = type(people)(kp=people.kp[:, order], vis=people.vis[:, order])
    assert resolve.body_fit_2d(body, people) < 0.5 * resolve.BODY_FIT_2D
    assert resolve.body_fit_2d(body, shuffled) > 1.2 * resolve.BODY_FIT_2D
    c = own_json.get_config()
    c.model.n_keypoints = 17
    assert c.inference.handedness_reference == "auto"
    assert not c.inference.one_handedness
    got = resolve.resolve_handedness(c, people).inference
    assert (got.handedness_reference, got.one_handedness) == ("h36m", True)
    assert c.inference.handedness_reference == "auto"  # a copy
    # The same people in COCO's order (the detectors'): the coco body fits, the h36m one not.
    vis = humans.coco_visibility_from_h36m(people.vis)  # the face: the head's
    coco = type(people)(kp=humans.coco_from_h36m(people.kp3d)[..., :2], vis=vis)
    coco_body = bodies.human_body("coco")
    assert resolve.body_fit_2d(coco_body, coco) < 0.5 * resolve.BODY_FIT_2D
    assert resolve.body_fit_2d(body, coco) > 1.2 * resolve.BODY_FIT_2D
    assert resolve.body_fit_2d(coco_body, people) > 1.2 * resolve.BODY_FIT_2D
    got = resolve.resolve_handedness(c, coco).inference
    assert (got.handedness_reference, got.one_handedness) == ("coco", True)
    # No body fits: each output weighed by its tetrahedra against the training views' mean
    # (its rows filled when the run evaluates); a perspective model: the mean shape, as is.
    for data, change, want in (
            (shuffled, {}, ("views_mean", True, "tetrahedra", True)),
            (people, {"n_keypoints": 20}, ("views_mean", True, "tetrahedra", True)),
            (people, {"projection_type": "perspective"},
             ("mean_shape", False, "procrustes", False))):
        c2 = own_json.get_config()
        c2.model.n_keypoints = 17
        c2.model.update(change)
        got = resolve.resolve_handedness(c2, data).inference
        assert (got.handedness_reference, got.one_handedness, got.handedness_evidence,
                got.handedness_from_output) == want
        assert got.handedness_body == ()
    # A saved "views_mean" keeps how its views were weighed, and takes VIEWS_MEAN_SETTINGS
    # where the saved config predates them.
    for saved, want in (({"handedness_reference": "views_mean", "one_handedness": True,
                          "handedness_evidence": "procrustes", "handedness_from_output": False},
                         ("procrustes", False)),
                        ({"handedness_reference": "views_mean", "one_handedness": True},
                         ("tetrahedra", True))):
        got = resolve.resolve_handedness(c, shuffled, {"inference": saved}).inference
        assert (got.handedness_reference, got.one_handedness, got.handedness_evidence,
                got.handedness_from_output) == ("views_mean", True, *want)
    for saved in ({"inference": {"handedness_reference": "mean_shape", "one_handedness": True}},
                  {"model": {"test_time_handedness_reference": "mean_shape",
                             "test_time_one_handedness": True}}):
        got = resolve.resolve_handedness(c, people, saved).inference
        assert (got.handedness_reference, got.one_handedness) == ("mean_shape", True)
    # A saved model without one handedness, scored with it asked for (--mode=eval): it holds.
    saved = {"inference": {"handedness_reference": "mean_shape", "one_handedness": False}}
    assert not resolve.resolve_handedness(c, people, saved).inference.one_handedness
    asked = c.copy_and_resolve_references()
    asked.inference.one_handedness = True
    got = resolve.resolve_handedness(asked, people, saved).inference
    assert (got.handedness_reference, got.one_handedness) == ("mean_shape", True)
    c.inference.handedness_reference = "mean_shape"
    assert resolve.resolve_handedness(c, people) is c

"""Multi-view training data: frame ids from the importer and the JSON files, batches of
whole frames, and the term that asks one frame's views for one canonical shape
(``loss.w_multiview``)."""

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import c3dpo_jax
from c3dpo_jax import device_data, losses, train, validation
from c3dpo_jax.data import KeypointData, importers, json_dataset
from configs import default, own_json


def _sequence(frames=30, k=7, seed=0):
    rng = np.random.default_rng(seed)
    base = rng.normal(size=(k, 3))
    return base + 0.2 * rng.normal(size=(frames, k, 3))


def _pairwise(x):
    return np.linalg.norm(x[..., :, None, :] - x[..., None, :, :], axis=-1)


def test_the_importer_gives_each_view_its_frame_and_json_keeps_it(tmp_path):
    train_split, test_split = importers.views_from_sequence(_sequence(), views_per_frame=3,
                                                           n_blocks=5, seed=1)
    for split in (train_split, test_split):
        ids, counts = np.unique(split.frame, return_counts=True)
        assert set(counts) == {3}
        for f in ids:  # one frame's views: one pose under three rotations
            d = _pairwise(split.kp3d[split.frame == f])
            np.testing.assert_allclose(d, d[:1].repeat(3, 0), atol=1e-4)
    assert not set(train_split.frame) & set(test_split.frame)
    path = str(tmp_path / "views.json")
    json_dataset.save(train_split, path)
    np.testing.assert_array_equal(json_dataset.load(path).frame, train_split.frame)


@pytest.mark.parametrize("bad, message", [
    ("3", r"entry 1: field 'frame_id' must be an integer, not '3'"),
    (1.5, r"entry 1: field 'frame_id' must be an integer, not 1.5"),
    (True, r"entry 1: field 'frame_id' must be an integer, not True"),
    (None, r"entry 1: field 'frame_id' is missing \(other entries have it\)"),
])
def test_a_bad_frame_id_is_named(tmp_path, bad, message):
    entries = [{"kp_loc": [[0, 1, 2], [1, 0, 2]], "kp_vis": [1, 1, 1], "frame_id": 0}
               for _ in range(3)]
    if bad is None:
        del entries[1]["frame_id"]
    else:
        entries[1]["frame_id"] = bad
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(entries))
    with pytest.raises(ValueError, match=message):
        json_dataset.load(str(path), cache=False)


def test_batches_are_whole_frames():
    """By frame: ``B / V`` frames, each giving ``V`` of its own views, distinct where it has
    ``V`` or more (cyclically from a random one), the same frame where it has fewer."""
    frame = np.repeat(np.arange(40), 4)
    frame[-8:] = 99  # one frame with 8 views
    frame[:2] = 100  # and one with 2
    rng = np.random.default_rng(0)
    perm = rng.permutation(len(frame))  # the file's order does not matter
    data = KeypointData(kp=rng.normal(size=(len(frame), 5, 2)), vis=np.ones((len(frame), 5)),
                        frame=frame[perm])
    on_device = device_data.device_train_data(data, False, by_frame=True)
    sorted_frames = np.sort(frame[perm], kind="stable")
    seen = set()
    for seed in range(20):
        idx = np.asarray(device_data.sample_indices(on_device, jax.random.key(seed), 30, 3))
        groups = sorted_frames[idx].reshape(10, 3)
        assert (groups == groups[:, :1]).all()
        for g, f in zip(idx.reshape(10, 3), groups[:, 0], strict=True):
            assert len(set(g)) == min(3, np.sum(frame == f))
            seen.add(int(f))
    assert {99, 100} <= seen
    with pytest.raises(ValueError, match="the train split has no frame ids"):
        device_data.device_train_data(KeypointData(kp=data.kp, vis=data.vis), False,
                                      by_frame=True)
    with pytest.raises(ValueError, match="no frame of the train split has two views"):
        device_data.device_train_data(KeypointData(kp=data.kp, vis=data.vis,
                                                   frame=np.arange(len(frame))), False,
                                      by_frame=True)


def test_the_multiview_term_matches_numpy():
    """The mean, over views and their class's points, of the pseudo-Huber penalty
    (eps (sqrt(1 + d^2 / eps^2) - 1)) of each point's squared distance from its group's mean
    canonical shape."""
    rng = np.random.default_rng(3)
    x = rng.normal(size=(6, 5, 3))
    mask = np.ones((6, 5))
    mask[4, 1] = 0.0
    eps = 0.1
    groups = x.reshape(2, 3, 5, 3)
    d2 = ((groups - groups.mean(1, keepdims=True)) ** 2).sum(-1).reshape(6, 5)
    penalty = eps * (np.sqrt(1.0 + d2 / eps**2) - 1.0)
    want = np.mean((penalty * mask).sum(1) / mask.sum(1))
    got = losses.multiview(jnp.asarray(x), jnp.asarray(mask), 3, eps)
    np.testing.assert_allclose(got, want, rtol=1e-5)
    same = np.repeat(x[::3], 3, axis=0)  # every view of a frame with one shape: no penalty
    assert float(losses.multiview(jnp.asarray(same), jnp.asarray(mask), 3, eps)) < 1e-10


def test_the_config_is_checked():
    c = default.get_config()
    c.loss.w_multiview = 1.0
    c.train.batch_size = 256
    assert validation.config_problems(c) == [
        "config.train.batch_size=256 (loss.w_multiview > 0 makes batches of groups of "
        "loss.multiview_views=3 views: a multiple of 3, e.g. 255)"]
    c.train.batch_size = 255
    c.data.class_balanced = True
    assert validation.config_problems(c) == [
        "config.loss.w_multiview > 0 draws whole frames, not classes: set "
        "config.data.class_balanced=False"]
    c.data.class_balanced = False
    with pytest.raises(ValueError, match="batch_size 256 is not a multiple of the 3 views"):
        train.make_train_chunk(lambda *a: a, 256, views=3)
    c.loss.multiview_views = 1
    assert len(validation.config_problems(c)) == 1
    assert validation.config_problems(c)[0].startswith("config.loss.multiview_views=1")


def test_a_run_with_multiview_data_trains_on_whole_frames(tmp_path):
    """End to end from the importer's files: the term is logged, finite, and its weight
    makes one frame's canonical shapes agree more than a run without it."""
    train_split, test_split = importers.views_from_sequence(_sequence(60), views_per_frame=3,
                                                           n_blocks=5, seed=0)
    paths = {}
    for name, split in (("train", train_split), ("test", test_split)):
        paths[name] = str(tmp_path / f"seq_{name}.json")
        json_dataset.save(split, paths[name])
    spread = {}
    for weight in (0.0, 10.0):
        c = own_json.get_config("smoke")
        c.data.train_path, c.data.test_path = paths["train"], paths["test"]
        c.model.n_keypoints = 7
        c.loss.w_multiview = weight
        c.train.batch_size, c.train.num_steps, c.train.progress_bar = 30, 60, False
        c.train.log_every = 10
        workdir = str(tmp_path / f"w{weight}")
        train.train_and_evaluate(c, workdir)
        with open(f"{workdir}/metrics.jsonl") as f:
            logs = [json.loads(line) for line in f]
        assert ("loss/multiview" in logs[-1]) == (weight > 0)
        # Phi's own canonical shapes: what training learnt, no view mirrored at inference
        canon = c3dpo_jax.reconstruct(
            c3dpo_jax.load(workdir), train_split.kp, train_split.vis, refine_iters=0,
            one_handedness=False, handedness_reference="mean_shape").shape_canonical
        groups = canon.reshape(-1, 3, 7, 3)  # the importer writes a frame's views together
        groups = groups - groups.mean(2, keepdims=True)
        spread[weight] = float(np.mean(np.linalg.norm(groups - groups.mean(1, keepdims=True),
                                                      axis=-1)) / np.sqrt(np.mean(groups**2)))
    assert np.isfinite(spread[10.0]) and spread[10.0] < spread[0.0]

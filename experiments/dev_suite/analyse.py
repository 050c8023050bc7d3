"""What bounds the suite's errors: references computed from the 3D truth, and errors per clip.

  python experiments/dev_suite/analyse.py floors               # every dataset with views
  python experiments/dev_suite/analyse.py clips --run=results/runs/nodeform/deepmimic__s0

``floors``: for each dataset whose views ``suite.py`` has made, on the test views, with the
3D truth C3DPO never sees: the training split's Procrustes mean shape under the oracle
rotation of each test shape, and the best fit of a D-dimensional PCA basis of the aligned
training shapes (D = 10, C3DPO's default basis size) under its oracle rotation: what a
rigid model and a linear model of that size could reach with a perfect camera (mean distance
per point, units of the normalised sequence; humans: metres). Also the mean 2D distance of
the best rigid fit of the mean shape (the rigid baseline) to the test views, beside which a
model's ``reprojection`` score tells whether it fits the 2D points better than a rigid shape.
Last, a PCA basis of the same size with its Gaussian prior (``baselines.pca_shape_basis``:
probabilistic PCA of the aligned training shapes) fitted to each test view's 2D points alone
(``baselines.fit_shape_basis``): a linear model built with the truth, lifting one view at a
time from its own 2D points.

``clips``: a trained run of a motion-capture dataset with clips (deepmimic, cmu131), test
MPJPE of the model and of the rigid baseline per clip.

``signs --runs=DIR,DIR,...``: for trained runs (their latest checkpoint), the fraction of
test views whose better orientation is the prediction itself rather than its depth flip:
near 1 or 0 when every view has the same handedness (0: the whole model is mirrored),
0.5 when the sign is a coin toss per view, as a user without 3D ground truth would see it.

``onebody --runs=DIR,DIR,...``: for trained runs of a motion-capture dataset with clips,
the test error without the protocol's flip with the model's own handedness, its mean shape's,
and the handedness of one 3D example of the points (the first frame of each clip in turn,
``reconstruct(..., handedness_reference=frame)``): the lowest, median and highest over the
clips; then the flip-resolved error.

``camera --runs=DIR,DIR,...``: for trained runs, test MPJPE of the model and of its own
canonical shapes under the camera with the least 2D error (the rigid baseline's fit): what
the network's regressed camera costs or gains against an optimised one.

``rotations --runs=DIR,DIR,...``: for trained runs, test MPJPE when each view's depth is
the mean (or the median) of the model's depths for copies of the view turned in-plane
about its centroid (orthographic depth does not change under an in-plane turn), each copy's
depth sign first matched to the unturned copy's: M angles spread evenly over the training
augmentation's range (+-``model.z_augment_rot_angle``), and over the full circle. Averaging
works where the regressed camera's errors differ between copies.

``selected --runs=DIR,DIR,...``: for trained runs, test MPJPE when the copies are M angles
spread evenly round the full circle (the unturned view among them) and only the copies whose
own mean 2D reprojection error (each against its turned input) is the lowest, or within
``SELECT_TOLERANCE`` times the lowest, give the depth (their median): a choice made from the
2D views alone.

``union --runs=DIR,DIR,...``: for trained runs, test MPJPE of the median over 32 copies round
the circle within ``SELECT_TOLERANCE`` times the lowest 2D error (as ``selected``), and of the
median over those together with every copy within the augmentation's range, kept whatever
their 2D error.

``refine --runs=DIR,DIR,... [--priors=0.3,1,3]``: for trained runs, test MPJPE with one pass
(Phi's output), with ``union32`` (the 32 turned copies, ``union`` above) and with each view
refined at test time (``inference.refine_iters=20``, one pass) under each prior weight,
last ``union32`` with every copy refined under the first prior: the library's path
(``reconstruct`` with the run's config changed).

``spread --runs=DIR,DIR,...``: for trained runs, on the test views, how much the model's
canonical shapes deform against the truth's: the RMS distance of the shapes (each centred,
scaled to unit RMS size, rotated or mirrored onto their mean) to that mean, for the model
and for the 3D truth, and the spread (std) of the model's centred depths over the truth's
(1: depth neither flattened nor stretched).

``objective --runs=DIR,DIR,...``: for trained runs, on up to 2,000 training views, does the
training objective prefer the truth? The mean 3D and 2D distances of the truth's own linear
model (a PCA basis of ``--n_basis`` vectors of the aligned training shapes, fitted to each
view's 3D truth under its best rotation) against C3DPO's (3D: the test protocol's MPJPE; 2D:
its reprojection to the input points). A C3DPO fit as close in 2D as the truth's model and
far from it in 3D is a factorisation the reprojection loss cannot tell from the truth. C3DPO's
numbers are Phi's own output (one pass, no refinement), what the training loss sees, then
those of the run's own inference (the default's: refined).

``handedness --runs=DIR,DIR,...``: for trained runs, on the test views, the fraction of views
whose unflipped prediction is the better one (``signs``) and the error without the
protocol's flip, without and with ``inference.one_handedness`` (which leaves the
flip-resolved error unchanged), then with the handedness of each human body
(``inference.handedness_reference=h36m`` or ``coco``, models of 17 points): 0 or 1
when every view has one handedness, 1 when it is the truth's.

``basis --runs=DIR,DIR,...``: for trained runs, is it the learnt shape basis or the choice of
its coefficients that separates the model from the truth? The mean distance of the best fit
to each 3D shape (free rotation, mirror and scale) in the span of the truth's PCA basis of
the run's size and in the span of the run's own basis, on test and training views; then, on
up to 500 test views, the run's inference and each view's 2D reprojection error minimised
in the learnt span without a prior, from the inference and from the truth's best fit: their
3D error and 2D distance.

``bones --runs=DIR,DIR,...``: for trained runs of the human sets (deepmimic, cmu131,
humans), which way the bones point in depth, on the test views: a bone turned towards the
camera instead of away from it (or the reverse) fits a view's 2D points exactly as well,
with the same length. The fraction of bones whose depth direction is the truth's opposite
(among the bones whose depth extent is at least ``BONE_DEPTH_SHARE`` of their length, after
the view's better overall flip; also of the arms, the legs and the rest), the test MPJPE,
and the MPJPE after each view's bones are turned (a bone's far end and everything below it
reflected in depth about its near end), one turn at a time, each the one that brings the
view nearest the truth, while one does (an oracle: how much of the error is the bones'
depth directions), with the turns per view. Then the same for the rigid baseline and for
the truth's PCA basis of ``--n_basis`` vectors fitted to each view's 2D points (``floors``'
last column) of each dataset. ``--training_views``: on up to 2,000 training views instead
(``objective``'s), without the references.

``relift --runs=DIR,DIR,...``: for trained runs of the human sets, can the network's own
view of a reconstruction from the side tell which way its bones point? Each candidate shape
(the prediction, the prediction with one bone turned as ``bones`` turns them, the truth's
depth under the prediction's x, y) is turned about the camera's vertical axis by
``RELIFT_AZIMUTHS``, projected and lifted again by the network in one pass; a candidate is
the more self-consistent the nearer the re-lifted depths are to its own turned ones. The
share of views whose truth is more consistent than the prediction, and the MPJPE when each
view takes its most consistent candidate, beside the oracle's choice among the same ones.

``chirality``: for the built-in synthetic dataset and each dataset whose views ``suite.py``
has made, the share of the 3D truth's test shapes whose whole-shape or tetrahedra
handedness evidence against the training shapes' Procrustes mean is negative: how far each
evidence can be trusted to name a view's handedness on that kind of shape.

``decide --runs=DIR,DIR,...``: for trained runs, the test views' ``mpjpe_global`` once
each view is given the handedness that its canonical shape or its output (the input's x, y
and the model's depth) shows against a prototype (the basis' mean shape, or the mean
canonical shape of up to 2,000 training views), by the whole-shape or the tetrahedra
evidence (``lift.evidence``): which per-view decision gives a user one handedness.

``ensemble --runs=DIR,DIR,...``: runs of one dataset (several seeds): each run's test MPJPE,
then that of the mean of the runs' predictions, each view's depth sign matched to the first
run's: whether their errors are independent (the mean is better) or shared (it is not).
"""

import dataclasses
import os
import sys

import numpy as np
from absl import app, flags

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.normpath(os.path.join(HERE, "..", "..")))

import suite  # noqa: E402
from runner import run_main  # noqa: E402

import c3dpo_jax  # noqa: E402
import c3dpo_jax.cli  # noqa: E402
from c3dpo_jax import baselines, evaluation  # noqa: E402
from c3dpo_jax import inference as inference_lib  # noqa: E402
from c3dpo_jax import lift as lift_lib  # noqa: E402
from c3dpo_jax import model as model_lib  # noqa: E402
from c3dpo_jax.data import importers, json_dataset  # noqa: E402

FLAGS = flags.FLAGS
flags.DEFINE_string("run", "", "clips: the workdir of a trained run (suite's results/runs/...)")
flags.DEFINE_integer("n_basis", 10, "floors, objective, bones: size of the PCA basis")
flags.DEFINE_list("runs", [], "workdirs of trained runs (every subcommand but floors and clips)")
flags.DEFINE_list("priors", ["0.3", "1", "3"], "refine: the prior weights scored")
flags.DEFINE_bool("training_views", False, "bones: score up to 2,000 training views instead "
                  "of the test views (no references)")


def _rotation_onto(x: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """(M, 3, 3): for each shape of ``x`` (M, N, 3) the rotation (no reflection) ``Q`` with
    ``x @ Q`` closest to ``ref`` (M, N, 3) or (N, 3) (orthogonal Procrustes)."""
    ref = np.broadcast_to(ref, x.shape)
    u, _, vt = np.linalg.svd(np.einsum("mni,mnj->mij", x, ref))
    d = np.sign(np.linalg.det(u @ vt))
    u[:, :, 2] *= d[:, None]
    return u @ vt


def _rotate_onto(x: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """Each shape of ``x`` (M, N, 3) under the rotation closest to ``ref`` (``_rotation_onto``)."""
    return np.einsum("mni,mij->mnj", x, _rotation_onto(x, ref))


def _centred(x) -> np.ndarray:
    x = np.asarray(x, np.float64)
    return x - x.mean(1, keepdims=True)


def oracle_basis_fit(train_kp3d: np.ndarray, shapes: np.ndarray, n_basis: int,
                     n_iters: int = 5) -> np.ndarray:
    """(M, N, 3): the best fit to each of ``shapes`` (M, N, 3; centred) of a PCA basis of
    ``n_basis`` vectors of the aligned, centred ``train_kp3d``, under its best rotation,
    in the frame of ``shapes`` (alternately the best shape in the span and the best
    rotation, ``n_iters`` + 1 times, from the rotation onto the Procrustes mean)."""
    mean, mu, basis = _truth_pca(train_kp3d, n_basis)
    return _rotate_onto(_fit_in_span(_rotate_onto(shapes, mean), mu, basis, n_iters), shapes)


def _truth_pca(train_kp3d: np.ndarray, n_basis: int):
    """``(mean, mu, basis)``: the Procrustes mean shape (N, 3) of ``train_kp3d``, and the
    mean (3N,) and first ``n_basis`` principal directions (n_basis, 3N; orthonormal rows) of
    the centred training shapes rotated onto it."""
    mean = _centred(baselines.procrustes_mean_shape(train_kp3d)[None])[0]
    aligned = _rotate_onto(_centred(train_kp3d), mean).reshape(len(train_kp3d), -1)
    mu = aligned.mean(0)
    return mean, mu, np.linalg.svd(aligned - mu, full_matrices=False)[2][:n_basis]


def _fit_in_span(x: np.ndarray, offset, basis: np.ndarray, n_iters: int) -> np.ndarray:
    """The best fit to each of ``x`` (M, N, 3; centred, roughly rotated onto the model) of
    ``offset`` (3N,) plus the span of ``basis``' orthonormal rows, under its best rotation
    (alternately the nearest shape in the span and the best rotation, ``n_iters`` + 1
    times), in the model's frame."""
    for _ in range(n_iters + 1):
        fit = ((x.reshape(len(x), -1) - offset) @ basis.T @ basis + offset).reshape(x.shape)
        x = _rotate_onto(x, fit)
    return fit


def deformation_spread(shapes: np.ndarray, n_iters: int = 5) -> float:
    """RMS distance of ``shapes`` (M, N, 3), each centred, scaled to unit RMS size and
    rotated, or mirrored and rotated, whichever is nearer, onto their mean, to that mean
    (alternately aligning and averaging, ``n_iters`` times from the first shape): 0 for
    rotated or mirrored copies of one shape, so that a model's mixed handedness does not
    count as deformation."""
    x = _centred(shapes)
    x = x / np.sqrt((x**2).sum((1, 2), keepdims=True) / x.shape[1])
    mirror = x * np.array([1.0, 1.0, -1.0])
    mean = x[0]
    for _ in range(n_iters):
        a, b = _rotate_onto(x, mean), _rotate_onto(mirror, mean)
        nearer = (((b - mean) ** 2).sum((1, 2)) < ((a - mean) ** 2).sum((1, 2)))
        aligned = np.where(nearer[:, None, None], b, a)
        mean = aligned.mean(0)
        mean = mean / np.sqrt((mean**2).sum() / len(mean))
    return float(np.sqrt(((aligned - aligned.mean(0)) ** 2).sum(-1).mean()))


def sign_aligned_mean(preds: np.ndarray) -> np.ndarray:
    """The mean over ``preds`` (R, M, N, 3; centred depths) with each view's depth sign
    matched to ``preds[0]``'s (the flip nearer to it, by mean point distance)."""
    ref, out = preds[0], [preds[0]]
    for p in preds[1:]:
        flipped = p * np.array([1.0, 1.0, -1.0])
        nearer = (np.linalg.norm(flipped - ref, axis=-1).mean(-1)
                  < np.linalg.norm(p - ref, axis=-1).mean(-1))
        out.append(np.where(nearer[:, None, None], flipped, p))
    return np.mean(out, axis=0)


def floors(name: str, data_dir: str, n_basis: int) -> dict:
    train = json_dataset.load(os.path.join(data_dir, f"{name}_train.json"))
    test = json_dataset.load(os.path.join(data_dir, f"{name}_test.json"))
    mean = _centred(baselines.procrustes_mean_shape(train.kp3d)[None])[0]
    truth = _centred(test.kp3d)
    rigid = np.linalg.norm(_rotate_onto(truth, mean) - mean, axis=-1).mean()
    scale, rows, centred, kp_mean = baselines.fit_camera(mean, test.kp, test.vis)
    dist = np.linalg.norm(baselines.project(scale, rows, centred, kp_mean) - test.kp, axis=-1)
    return {"rigid mean shape, oracle rotation": float(rigid),
            f"PCA basis D={n_basis}, oracle fit": float(np.linalg.norm(
                oracle_basis_fit(train.kp3d, truth, n_basis) - truth, axis=-1).mean()),
            "rigid baseline, mean 2D distance": float((dist * test.vis).sum() / test.vis.sum()),
            f"PCA basis D={n_basis}, fitted to the 2D views": evaluation.evaluate(
                _pca_fit_2d(train, test, n_basis), test)["mpjpe"]}


def _rigid_fit(train, test) -> np.ndarray:
    """The rigid baseline on ``test``: the Procrustes mean of ``train``'s 3D shapes under
    each view's best rigid fit."""
    return baselines.fit_mean_shape(baselines.procrustes_mean_shape(train.kp3d), test.kp,
                                    test.vis)


def _pca_fit_2d(train, test, n_basis: int) -> np.ndarray:
    """The truth's probabilistic PCA of ``n_basis`` vectors (``train``'s 3D shapes) fitted
    to each of ``test``'s views from its 2D points alone."""
    return baselines.fit_shape_basis(baselines.pca_shape_basis(train.kp3d, n_basis), test.kp,
                                     test.vis)


def _dataset(run: str) -> str:
    """The dataset of a suite run (its folder is DATASET__sSEED)."""
    return os.path.basename(os.path.normpath(run)).split("__")[0]


def _mocap_run(run: str, command: str) -> tuple[str, str]:
    """``(dataset, its sequence file)`` of a run of a motion-capture set with clips."""
    dataset = _dataset(run)
    if dataset not in suite.MOCAP:
        raise app.UsageError(f"{run}: {command} needs a run of one of {sorted(suite.MOCAP)}")
    return dataset, os.path.join(FLAGS.data_root, "mocap",
                                 f"{dataset.removesuffix('_clips')}.npz")


def per_clip(run: str) -> list[tuple[str, int, float, float]]:
    dataset, path = _mocap_run(run, "clips")
    info = suite.make_data(dataset, FLAGS.data_root, FLAGS.out)
    clip = importers.load_clips(path)
    with np.load(path) as z:
        names = [str(n) for n in z["clip_names"]]
    test_frames = importers.clip_split(clip, 0.2, 5, 0, suite.MOCAP[dataset])
    view_clip = np.repeat(clip[test_frames], 3)  # the importer's views are frame-major
    train = json_dataset.load(info["train"])
    test = json_dataset.load(info["test"])
    if len(view_clip) != len(test):
        raise app.UsageError(f"{run}: the test views do not match {path}'s clips")
    model = c3dpo_jax.load(run)
    pred = c3dpo_jax.reconstruct(model, test.kp, test.vis).shape_3d
    rigid = _rigid_fit(train, test)
    rows = []
    for c in np.unique(view_clip):
        idx = np.flatnonzero(view_clip == c)
        sub = test.subset(idx)
        rows.append((names[c], len(idx), evaluation.evaluate(pred[idx], sub)["mpjpe"],
                     evaluation.evaluate(rigid[idx], sub)["mpjpe"]))
    return rows


def _test_split_and_model(run: str):
    """``(test split, the run's model)`` for a suite run."""
    dataset = _dataset(run)
    test = json_dataset.load(os.path.join(FLAGS.out, "data", f"{dataset}_test.json"))
    return test, c3dpo_jax.load(run)


def _test_reconstruction(run: str):
    """``(test split, the run's model, its Reconstruction of the split)`` for a suite run."""
    test, model = _test_split_and_model(run)
    return test, model, c3dpo_jax.reconstruct(model, test.kp, test.vis)


def _per_view(shape_3d, test) -> dict:
    """``evaluation.mpjpe``'s per-view errors of ``shape_3d`` on ``test``, depths centred."""
    return evaluation.mpjpe(evaluation.center_depth(np.asarray(shape_3d, np.float64), test.vis),
                            evaluation.center_depth(test.kp3d, test.vis), test.vis)


def sign_agreement(run: str) -> float:
    """Fraction of the run's test views whose unflipped prediction is the better one."""
    test, _, rec = _test_reconstruction(run)
    per = _per_view(rec.shape_3d, test)
    return float(np.mean(per["mpjpe_orig"] <= per["mpjpe_flip"]))


def camera_refit(run: str) -> tuple[float, float]:
    """Test MPJPE of the run's model, and of its own canonical shapes under the camera with
    the least 2D error (``baselines.fit_mean_shape`` with one shape per view: the rigid
    baseline's fit, the model's shapes instead of the training mean; its least-squares scale
    absorbs the canonical frame's units): how much the network's regressed camera costs."""
    test, _, rec = _test_reconstruction(run)
    refit = baselines.fit_mean_shape(rec.shape_canonical, test.kp, test.vis)
    return (evaluation.evaluate(rec.shape_3d, test)["mpjpe"],
            evaluation.evaluate(refit, test)["mpjpe"])


def _turned_depths(model, kp: np.ndarray, vis: np.ndarray, angles, with_2d: bool = False):
    """(A, M, N) depths of the model for the views ``kp`` turned in-plane by each angle
    about their visible centroid, mean depth removed, signs matched to the first angle's;
    with ``with_2d``, also the (A, M) mean 2D distance of each copy's reprojection to its
    turned input."""
    w = vis[..., None]
    centre = (kp * w).sum(1, keepdims=True) / np.maximum(w.sum(1, keepdims=True), 1)
    depths, errs = [], []
    for a in angles:
        turn = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
        turned = ((kp - centre) @ turn.T + centre).astype(np.float32)
        rec = c3dpo_jax.reconstruct(model, turned, vis, turns=1)
        depth = np.asarray(rec.shape_3d[..., 2], np.float64)
        depths.append(depth - (depth * vis).sum(1, keepdims=True) / vis.sum(1, keepdims=True))
        dist = np.linalg.norm(np.asarray(rec.kp_reprojected, np.float64) - turned, axis=-1)
        errs.append((dist * vis).sum(1) / vis.sum(1))
    sign = np.sign(np.einsum("amn,mn->am", np.array(depths) * vis, depths[0]))
    depths = np.array(depths) * np.where(sign < 0, -1.0, 1.0)[..., None]
    return (depths, np.array(errs)) if with_2d else depths


ROTATION_COPIES = (3, 5, 9)
CIRCLE_COPIES = 16


def _circle(m: int) -> np.ndarray:
    """``m`` angles spread evenly round the full circle, 0 first."""
    return 2 * np.pi * np.arange(m) / m


def _depth_scoring(run: str):
    """``(model, kp, vis, its test MPJPE, score)`` for a suite run: ``score(depth)`` is the
    test MPJPE of the model's x, y (hidden points reprojected) with ``depth`` (M, N)."""
    test, model, rec = _test_reconstruction(run)
    kp, vis = np.asarray(test.kp, np.float64), np.asarray(test.vis, np.float64)
    xy = np.asarray(rec.shape_3d[..., :2], np.float64)

    def score(depth):
        return evaluation.evaluate(np.concatenate([xy, depth[..., None]], -1), test)["mpjpe"]

    return model, kp, vis, evaluation.evaluate(rec.shape_3d, test)["mpjpe"], score


def rotation_average(run: str) -> list[float]:
    """Test MPJPE of the model, then of the mean and the median depth over
    ``ROTATION_COPIES`` turned copies within the augmentation range, then over
    ``CIRCLE_COPIES`` copies around the full circle (mean, median)."""
    model, kp, vis, own, score = _depth_scoring(run)
    span = model.config.z_augment_rot_angle if model.config.z_augment else 0.0
    out = [own]
    for m in ROTATION_COPIES:  # odd: the unturned copy first, then pairs +-a
        half = np.linspace(0.0, span, m // 2 + 1)[1:]
        d = _turned_depths(model, kp, vis, [0.0, *half, *(-half)])
        out += [score(d.mean(0)), score(np.median(d, 0))]
    d = _turned_depths(model, kp, vis, _circle(CIRCLE_COPIES))
    return out + [score(d.mean(0)), score(np.median(d, 0))]


SELECT_COPIES = (16, 32, 64)
SELECT_TOLERANCE = 1.1


def selected_average(run: str) -> list[float]:
    """Test MPJPE of the model (with its ``inference.turns``), then, for each of
    ``SELECT_COPIES`` copies round the full circle, of the copy with the lowest 2D
    reprojection error and of the median over the copies within ``SELECT_TOLERANCE`` times
    that error."""
    model, kp, vis, own, score = _depth_scoring(run)
    out = [own]
    for m in SELECT_COPIES:
        d, err = _turned_depths(model, kp, vis, _circle(m), with_2d=True)
        keep = err <= SELECT_TOLERANCE * err.min(0)
        out += [score(d[np.argmin(err, 0), np.arange(d.shape[1])]),
                score(np.nanmedian(np.where(keep[..., None], d, np.nan), 0))]
    return out


UNION_COPIES = 32


def union_average(run: str) -> list[float]:
    """Test MPJPE of the model (with its ``inference.turns``), then, with ``UNION_COPIES``
    copies round the full circle, of the median over the copies within ``SELECT_TOLERANCE``
    times the lowest 2D reprojection error (``selected``), and of the median over those and
    every copy within the augmentation's range (the in-range copies always kept)."""
    model, kp, vis, own, score = _depth_scoring(run)
    in_range = lift_lib.turns_in_range(dataclasses.replace(
        model.inference, turns=UNION_COPIES), model.config)  # the library's copies' grid
    d, err = _turned_depths(model, kp, vis, _circle(UNION_COPIES), with_2d=True)
    fit = err <= SELECT_TOLERANCE * err.min(0)
    return [own] + [score(np.nanmedian(np.where(keep[..., None], d, np.nan), 0))
                    for keep in (fit, fit | in_range[:, None])]


REFINE_ITERS = 20


def refined(run: str) -> list[float]:
    """Test MPJPE of the run's checkpoint with one pass, with ``union32`` and refined at test
    time (``REFINE_ITERS`` steps, one pass) with each of ``--priors``: the library's path."""
    test, model = _test_split_and_model(run)

    def score(**options) -> float:
        return evaluation.evaluate(c3dpo_jax.reconstruct(model, test.kp, test.vis,
                                                         **options).shape_3d, test)["mpjpe"]

    none = {"refine_iters": 0}
    return ([score(turns=1, **none),
             score(turns=UNION_COPIES, turn_span="circle_and_range", **none)]
            + [score(turns=1, refine_iters=REFINE_ITERS, refine_prior=float(w))
               for w in FLAGS.priors]
            + [score(turns=UNION_COPIES, turn_span="circle_and_range",
                     refine_iters=REFINE_ITERS, refine_prior=float(FLAGS.priors[0]))])


def spread(run: str) -> list[float]:
    """The model's and the truth's ``deformation_spread`` on the test views, and the std of
    the model's centred depths over the truth's."""
    test, _, rec = _test_reconstruction(run)
    depth = evaluation.center_depth(np.asarray(rec.shape_3d, np.float64), test.vis)[..., 2]
    truth = evaluation.center_depth(test.kp3d.astype(np.float64), test.vis)[..., 2]
    return [deformation_spread(np.asarray(rec.shape_canonical, np.float64)),
            deformation_spread(test.kp3d), float(depth.std() / truth.std())]


OBJECTIVE_VIEWS = 2000


def _training_split_and_views(run: str):
    """``(training split, up to OBJECTIVE_VIEWS of its views)`` of a suite run (a fixed
    random choice), and the random generator the choice was drawn from."""
    dataset = _dataset(run)
    train = json_dataset.load(os.path.join(FLAGS.out, "data", f"{dataset}_train.json"))
    rng = np.random.default_rng(0)
    return train, train.subset(np.sort(rng.permutation(len(train))[:OBJECTIVE_VIEWS])), rng


def objective(run: str) -> list[float]:
    """On up to ``OBJECTIVE_VIEWS`` training views: the truth's PCA model's 3D and 2D mean
    distances (``oracle_basis_fit``), then the MPJPE and the mean 2D reprojection distance
    of Phi's output (one pass) and of the run's own inference."""
    train, views, _ = _training_split_and_views(run)
    truth = _centred(views.kp3d)
    fit = oracle_basis_fit(train.kp3d, truth, FLAGS.n_basis)
    model = c3dpo_jax.load(run)
    one_pass = model.replace(inference=dataclasses.replace(
        model.inference, turns=1, refine_iters=0))
    w = views.vis / views.vis.sum()
    out = [float(np.linalg.norm(fit - truth, axis=-1).mean()),
           float(np.linalg.norm(fit[..., :2] - truth[..., :2], axis=-1).mean())]
    for m in (one_pass, model):
        rec = c3dpo_jax.reconstruct(m, views.kp, views.vis)
        out += [evaluation.evaluate(rec.shape_3d, views)["mpjpe"], float(
            (w * np.linalg.norm(np.asarray(rec.kp_reprojected) - views.kp, axis=-1)).sum())]
    return out


def _span_fit(shapes: np.ndarray, vectors: np.ndarray, n_iters: int = 10):
    """The best fit to each of ``shapes`` (M, N, 3) in the linear span of ``vectors`` (R, N,
    3; the first a shape the others deform) under a rotation, or a mirror and a rotation,
    whichever fits a shape better (``_fit_in_span``, from the rotation onto ``vectors[0]``):
    any scale, any handedness. Returns
    ``(rows, weights, rotations, signs, error)``: the span's orthonormal rows (R, 3N), each
    fit's weights on them (M, R), the rotation (M, 3, 3) taking it to ``shapes`` (``fit @
    rotation``) mirrored by ``signs`` (M,) on depth, and the mean point distance of each fit
    (M,)."""
    truth = _centred(shapes)
    rows = np.linalg.svd(_centred(vectors).reshape(len(vectors), -1),
                         full_matrices=False)[2][:len(vectors)]
    best = None
    for sign in (1.0, -1.0):
        x = truth * np.array([1.0, 1.0, sign])
        fit = _fit_in_span(_rotate_onto(x, _centred(vectors[:1])[0]), 0.0, rows, n_iters)
        w = fit.reshape(len(x), -1) @ rows.T
        rot = _rotation_onto(fit, x)
        err = np.linalg.norm(fit @ rot - x, axis=-1).mean(-1)
        if best is None:
            best = [w, rot, np.full(len(x), sign), err]
        else:
            better = err < best[3]
            best = [np.where(better[:, None], w, best[0]),
                    np.where(better[:, None, None], rot, best[1]),
                    np.where(better, sign, best[2]), np.minimum(err, best[3])]
    return (rows, *best)


def _refit_2d(rows, weights, rotations, kp, vis):
    """Each view's 2D reprojection error minimised from the given start (scipy's
    Levenberg-Marquardt over the weights on ``rows``, a rotation after ``rotations`` and a 2D
    translation; orthographic, visible points): ``(camera-frame shapes (M, N, 3), mean 2D
    distance of the visible points per view (M,))``."""
    from scipy.optimize import least_squares
    from scipy.spatial.transform import Rotation

    n = kp.shape[1]
    shapes, dist = [], []
    for w0, r0, k, v in zip(weights, rotations, kp, vis):
        def cam(p, w0=w0, r0=r0):
            canon = ((w0 + p[3:-2]) @ rows).reshape(n, 3)
            return canon @ r0 @ Rotation.from_rotvec(p[:3]).as_matrix()

        def residual(p, k=k, v=v, cam=cam):
            return ((cam(p)[:, :2] + p[-2:] - k) * v[:, None]).ravel()

        p = least_squares(residual, np.zeros(5 + len(w0)), method="lm").x
        shapes.append(cam(p) + np.array([*p[-2:], 0.0]))
        dist.append(np.linalg.norm(residual(p).reshape(n, 2), axis=-1).sum() / v.sum())
    return np.stack(shapes), np.array(dist)


REFIT_VIEWS = 500


def basis(run: str) -> list[float]:
    """Is the learnt basis or the choice of coefficients what separates a run from the truth?
    The mean point distance of the best fit to each 3D shape, with a free rotation, mirror
    and scale (``_span_fit``), in the span of the truth's own PCA basis of the run's size
    (with its mean shape) and in the span of the run's mean and basis shapes, on the test
    views and on up to ``OBJECTIVE_VIEWS`` training views; then, on up to ``REFIT_VIEWS``
    test views, the test MPJPE and mean 2D distance of the run's inference, and of each
    view's 2D reprojection error minimised in the learnt span (no prior) from two starts:
    the run's own reconstruction and the learnt span's best fit to the truth."""
    test, model = _test_split_and_model(run)
    train, views, rng = _training_split_and_views(run)
    d = model.config.shape_basis_size
    net, params = model_lib.make_network(model.config), model.variables["params"]
    shapes = np.stack([np.asarray(net.apply({"params": params}, a, method="shape"), np.float64)
                       for a in np.eye(d + 1, d, -1, np.float32)])
    learnt = np.concatenate([shapes[:1], shapes[1:] - shapes[:1]])
    _, mu, pca = _truth_pca(train.kp3d, d)
    truth = np.concatenate([mu[None], pca]).reshape(d + 1, -1, 3)
    out = [float(_span_fit(x, v)[-1].mean())
           for x, v in ((test.kp3d, truth), (test.kp3d, learnt), (views.kp3d, learnt))]
    sub = test.subset(np.sort(rng.permutation(len(test))[:REFIT_VIEWS]))
    rec = c3dpo_jax.reconstruct(model, sub.kp, sub.vis)
    out += [evaluation.evaluate(rec.shape_3d, sub)["mpjpe"], float(
        (np.linalg.norm(np.asarray(rec.kp_reprojected) - sub.kp, axis=-1) * sub.vis).sum()
        / sub.vis.sum())]
    for start in (np.asarray(rec.shape_3d, np.float64), sub.kp3d):
        rows, w, rot, sign, _ = _span_fit(start, learnt)
        mirror = np.stack([np.ones_like(sign), np.ones_like(sign), sign], -1)[:, None]
        refit, dist = _refit_2d(rows, w, rot * mirror, sub.kp, sub.vis)
        out += [evaluation.evaluate(refit, sub)["mpjpe"], float(dist.mean())]
    return out



MIRROR_COLUMNS = ["views of the truth's handedness", "2D: own", "mirror",
                  "span residual: mirror", "Psi: own", "mirror", "deformation: own", "mirror",
                  "the other views: 2D own", "mirror", "span residual: mirror", "Psi: own",
                  "mirror", "deformation: own", "mirror"]


def mirror_cost(run: str) -> list[float]:
    """What C3DPO's terms charge a view's mirror image, on up to ``OBJECTIVE_VIEWS`` training
    views (Phi's one pass, what training sees). For each view its lift and the mirror image
    (the camera-frame depth reflected: the same 2D points) put in the learnt basis' span (the
    best rotation and coefficients for the mirrored canonical shape, ``_mirror_in_span``): the
    mean 2D distance of each to the view's points, the mirror's RMS distance from the span,
    Psi's canonicalisation error (RMS distance of Psi's reconstruction of 8 random rotations
    of the shape to the shape) and the RMS deformation from the mean shape; all in units of
    the canonical shapes' RMS radius. First for the views whose lift has the truth's
    handedness, then for the others (the flip-resolved protocol's choice)."""
    import jax
    import jax.numpy as jnp

    from c3dpo_jax import inference, so3

    _, views, _ = _training_split_and_views(run)
    m = c3dpo_jax.load(run)
    cfg = m.config
    options = dataclasses.replace(m.inference, turns=1, refine_iters=0, one_handedness=False)
    pred = inference.predict_split(m.variables, views, cfg, options)
    net = model_lib.make_network(cfg)
    params = m.variables["params"]
    ones = jnp.ones(cfg.n_keypoints)
    mean = np.asarray(model_lib.mean_shape(net, params, ones))
    basis = np.asarray(jax.vmap(lambda a: model_lib.canonical_shape(net, params, a, ones))(
        jnp.eye(cfg.shape_basis_size))) - mean  # (D, N, 3)
    x = pred["shape_canonical"].astype(np.float64)
    size = float(np.sqrt(np.mean(np.sum((x - x.mean(1, keepdims=True)) ** 2, -1))))
    mirror, rot = _mirror_in_span(x * np.array([1.0, 1.0, -1.0]), mean, basis)
    # The mirror's camera: F R F rot^T, so that it puts the fit where F R x is (F the depth
    # reflection): the same 2D points as the lift's.
    flip = np.diag([1.0, 1.0, -1.0])
    cam = flip @ pred["rotation"] @ flip @ np.transpose(rot, (0, 2, 1))

    def reproject(shapes, rotations):
        x_cam = pred["scale"][:, None, None] * np.einsum("mij,mnj->mni", rotations, shapes)
        proj = x_cam[..., :2] - x_cam[..., :2].mean(1, keepdims=True)
        kp = pred["kp_norm"] - pred["kp_norm"].mean(1, keepdims=True)
        return np.linalg.norm(proj - kp, axis=-1).mean(1)

    keys = jax.random.split(jax.random.key(0), 8)
    rots = jax.vmap(so3.random_rotation)(keys)

    @jax.jit
    def psi_error(shapes):
        def one(shape):
            def per(r):
                alpha = net.apply(m.variables, shape @ r.T, False, method="psi")
                return jnp.sqrt(jnp.mean(jnp.sum(
                    (model_lib.canonical_shape(net, params, alpha, ones) - shape) ** 2, -1)))
            return jnp.mean(jax.vmap(per)(rots))
        return jax.vmap(one)(shapes)

    def rms(a, b):
        return np.sqrt(np.mean(np.sum((a - b) ** 2, -1), -1))

    costs = dict(
        repro_own=reproject(x, pred["rotation"]), repro_mirror=reproject(mirror, cam),
        span=rms(np.einsum("mij,mnj->mni", rot, x * np.array([1.0, 1.0, -1.0])), mirror),
        psi_own=np.asarray(psi_error(jnp.asarray(x, jnp.float32))),
        psi_mirror=np.asarray(psi_error(jnp.asarray(mirror, jnp.float32))),
        deform_own=rms(x, mean), deform_mirror=rms(mirror, mean))
    per = _per_view(pred["shape_3d"], views)
    truth_side = per["mpjpe_orig"] <= per["mpjpe_flip"]
    if truth_side.mean() < 0.5:  # the model's majority is the truth's mirror: name it so
        truth_side = ~truth_side
    out = [float(truth_side.mean())]
    for side in (truth_side, ~truth_side):
        out += [float(np.mean(v[side])) / size if side.any() else float("nan")
                for v in costs.values()]
    return out


def _mirror_in_span(shapes: np.ndarray, mean: np.ndarray, basis: np.ndarray, n_iters: int = 10):
    """``(fits, rotations)``: for each of ``shapes`` (M, N, 3), the shape ``mean + sum_d a_d
    basis_d`` and the rotation R nearest to R shape (alternating a Procrustes rotation and
    least-squares coefficients, from the mean shape)."""
    flat = basis.reshape(len(basis), -1).T  # (3N, D)
    fit = np.broadcast_to(mean, shapes.shape)
    centred = shapes - shapes.mean(1, keepdims=True)
    for _ in range(n_iters):
        rot = baselines.kabsch(centred, fit - fit.mean(1, keepdims=True))
        target = np.einsum("mij,mnj->mni", rot, centred) + fit.mean(1, keepdims=True)
        coef, *_ = np.linalg.lstsq(flat, (target - mean).reshape(len(shapes), -1).T, rcond=None)
        fit = mean + (flat @ coef).T.reshape(shapes.shape)
    rot = baselines.kabsch(centred, fit - fit.mean(1, keepdims=True))
    return fit, rot

# The human bodies of ``lift_lib.HANDEDNESS_REFERENCES`` (``handedness``' last columns).
BODIES = tuple(name for name, n in lift_lib.HANDEDNESS_REFERENCES.items() if n is not None)


def handedness(run: str) -> list[float]:
    """Sign agreement and no-flip error without and with ``inference.one_handedness``, then
    with the handedness of each of the built-in humans' average bodies (``BODIES``: the
    Human3.6M and COCO joint orders; models of 17 points only, NaN for others), and the
    flip-resolved error (the same every way)."""
    test, model = _test_split_and_model(run)
    out = []
    for on, reference in ((False, "mean_shape"), (True, "mean_shape"),
                          *((True, body) for body in BODIES)):
        options = dataclasses.replace(model.inference, one_handedness=on,
                                      handedness_reference=reference)
        if lift_lib.problems(options, model.config):
            out += [float("nan")] * 2
            continue
        per = _per_view(c3dpo_jax.reconstruct(model.replace(inference=options), test.kp,
                                              test.vis).shape_3d, test)
        out += [float(np.mean(per["mpjpe_orig"] <= per["mpjpe_flip"])),
                float(np.mean(per["mpjpe_orig"]))]
    return out + [float(np.mean(np.minimum(per["mpjpe_orig"], per["mpjpe_flip"])))]


def one_example_body(run: str) -> list[float]:
    """The no-flip error with the model's own handedness, with its mean shape's
    (``inference.one_handedness``), and with the handedness of one 3D example of the points
    (``handedness_reference=body``): the first frame of each clip of the run's motion capture
    in turn, the lowest, median and highest of those; then the flip-resolved error."""
    _, path = _mocap_run(run, "onebody")
    with np.load(path) as z:
        frames, clip = np.swapaxes(z["X"], 1, 2), z["clip"]
    test, model = _test_split_and_model(run)

    def errors(**options):
        per = _per_view(c3dpo_jax.reconstruct(model, test.kp, test.vis, **options).shape_3d,
                        test)
        return float(np.mean(per["mpjpe_orig"])), float(np.mean(
            np.minimum(per["mpjpe_orig"], per["mpjpe_flip"])))

    own, resolved = errors()
    mean_shape = errors(one_handedness=True, handedness_reference="mean_shape")[0]
    bodies = np.array([errors(handedness_reference=frames[np.flatnonzero(clip == c)[0]])[0]
                       for c in np.unique(clip)])
    return [own, mean_shape, bodies.min(), float(np.median(bodies)), bodies.max(), resolved]


REFERENCE_COLUMNS = ["the paper's mpjpe (per-view flip)", "mpjpe_global", "as it is",
                     "as it is, the reference's one decision", "the reference per view",
                     "the mean shape per view", "reference: 0 built-in body, 1 a 3D example"]


def reference(run: str) -> list[float]:
    """Test errors of a run against the 3D truth: the paper's per-view flip, the split as it
    is or all mirrored (``mpjpe_global``), and as it is: the model's own views, then with a
    reference's handedness, one decision for the model (``one_handedness=False``: its mean
    shape against the reference) and per view (``one_handedness=True``), and the mean shape's
    per view. The reference: the built-in h36m body for the 17-joint human sets, else one 3D
    example, the sequence's first frame (its own units and orientation)."""
    test, model = _test_split_and_model(run)
    dataset = _dataset(run)
    if model.config.n_keypoints == 17 and dataset in ("cmu131", "humans", "humans_v3"):
        body, kind = "h36m", 0.0
    else:
        full = suite._source(suite.SCALED.get(dataset, dataset))[0].removesuffix("_clips")
        folder = "nrsfm" if full in suite.NRSFM else "mocap"
        with np.load(os.path.join(FLAGS.data_root, folder, f"{full}.npz")) as z:
            body, kind = np.swapaxes(z["X"], 1, 2)[0], 1.0

    def per_view(**options) -> dict:
        """Per-view errors as they are with ``options`` (else the model's own handedness)."""
        options = {"one_handedness": False, "handedness_reference": "mean_shape", **options}
        return _per_view(c3dpo_jax.reconstruct(model, test.kp, test.vis, **options).shape_3d,
                         test)

    def as_is(**options) -> float:
        return float(np.mean(per_view(**options)["mpjpe_orig"]))

    own = per_view()
    orig, flip = float(np.mean(own["mpjpe_orig"])), float(np.mean(own["mpjpe_flip"]))
    return [float(np.mean(np.minimum(own["mpjpe_orig"], own["mpjpe_flip"]))), min(orig, flip),
            orig, as_is(handedness_reference=body),
            as_is(handedness_reference=body, one_handedness=True), as_is(one_handedness=True),
            kind]


CHIRALITY_COLUMNS = ["test views", "whole-shape evidence < 0", "tetrahedra evidence < 0",
                     "tetrahedra evidence, 1st percentile"]


def chirality(name: str, train, test) -> list[float]:
    """Of the 3D truth of ``test``'s views, against the Procrustes mean of ``train``'s: the
    share whose whole-shape and tetrahedra handedness evidence (``lift.evidence``) is
    negative (what a perfect model's views would read), and the tetrahedra's 1st
    percentile."""
    import jax
    import jax.numpy as jnp

    mean = jnp.asarray(baselines.procrustes_mean_shape(train.kp3d.astype(np.float64)),
                       jnp.float32)
    shapes = jnp.asarray(test.kp3d, jnp.float32)
    ones = jnp.ones(shapes.shape[1])
    out = [float(len(test))]
    for kind in lift_lib.HANDEDNESS_EVIDENCE:
        evidence = np.asarray(jax.vmap(lift_lib.evidence(kind), (0, None, None))(
            shapes, mean, ones))
        out.append(float(np.mean(evidence < 0)))
    return out + [float(np.percentile(evidence, 1))]


DECIDE_PROTOTYPES = ("basis' mean shape", "training views' mean")
DECIDE_SHAPES = ("canonical shape", "output")
DECIDE_COLUMNS = ["the paper's mpjpe (per-view flip)", "mpjpe_global, the model's own views"] + [
    f"per view: {s} vs {p}, {e}" for p in DECIDE_PROTOTYPES for s in DECIDE_SHAPES
    for e in lift_lib.HANDEDNESS_EVIDENCE] + [
    "training views reversing their mean's corners", "rigid fit: per-view flip", "mpjpe_global"]


def decide(run: str) -> list[float]:
    """``mpjpe_global`` of the test views after each is given the handedness its evidence
    (``lift.evidence``: "procrustes" or "tetrahedra") favours against a prototype (the
    basis' mean shape, or the training views' mean canonical shape,
    ``inference.training_views_mean``), read from its canonical shape or from its output (the
    input's x, y with the model's depth, what a user gets); first the paper's error and the
    model's own views' ``mpjpe_global``; last the share of those training views whose own
    canonical shape reverses their mean's small corners (``inference.with_views_mean``'s
    guard), the rigid fit's per-view-flip error and ``mpjpe_global`` (one shape: one
    handedness by construction)."""
    import jax
    import jax.numpy as jnp

    test, model = _test_split_and_model(run)
    own = {"one_handedness": False, "handedness_reference": "mean_shape"}
    rec = c3dpo_jax.reconstruct(model, test.kp, test.vis, **own)
    train = json_dataset.load(os.path.join(FLAGS.out, "data", f"{_dataset(run)}_train.json"))
    rows, reversed_share = inference_lib.training_views_mean(model.variables, train,
                                                             model.config, model.inference)
    net = model_lib.make_network(model.config)
    ones = jnp.ones(model.config.n_keypoints)
    prototypes = (model_lib.mean_shape(net, model.variables["params"], ones),
                  jnp.asarray(rows, jnp.float32))
    per = _per_view(rec.shape_3d, test)
    orig, flip = per["mpjpe_orig"], per["mpjpe_flip"]
    out = [float(np.mean(np.minimum(orig, flip))), float(min(orig.mean(), flip.mean()))]
    for proto in prototypes:
        for shapes in (rec.shape_canonical, rec.shape_3d):
            for kind in lift_lib.HANDEDNESS_EVIDENCE:
                evidence = jax.vmap(lift_lib.evidence(kind), (0, None, None))(
                    jnp.asarray(shapes, jnp.float32), proto, ones)
                mirrored = np.asarray(evidence) < 0
                a, b = np.where(mirrored, flip, orig), np.where(mirrored, orig, flip)
                out.append(float(min(a.mean(), b.mean())))
    rigid = evaluation.evaluate(_rigid_fit(train, test), test)
    return out + [reversed_share, rigid["mpjpe"], rigid["mpjpe_global"]]


# Kinematic trees of the human sets (``parents[j]``: j's parent, -1 for the root).
_H36M_PARENTS = (-1, 0, 1, 2, 0, 4, 5, 0, 7, 8, 9, 8, 11, 12, 8, 14, 15)
PARENTS = {
    # pelvis, rhip, rknee, rankle, rtoe, lhip, lknee, lankle, ltoe, spine, neck, head,
    # lshoulder, lelbow, lwrist, rshoulder, relbow, rwrist
    "deepmimic": (-1, 0, 1, 2, 3, 0, 5, 6, 7, 0, 9, 10, 10, 12, 13, 10, 15, 16),
    "cmu131": _H36M_PARENTS,
    "humans": _H36M_PARENTS,
}
# The bones (by their far joint) of the arms (elbows, wrists) and legs (knees, ankles, toes).
_H36M_LIMBS = {"arms": (12, 13, 15, 16), "legs": (2, 3, 5, 6)}
LIMBS = {"deepmimic": {"arms": (13, 14, 16, 17), "legs": (2, 3, 4, 6, 7, 8)},
         "cmu131": _H36M_LIMBS, "humans": _H36M_LIMBS}
BONE_DEPTH_SHARE = 0.3
BONES_COLUMNS = ["MPJPE", "bones pointing the wrong way in depth", "of the arms", "of the legs",
                 "of the rest", "MPJPE, the oracle's bone turns", "turns per view"]


def _descendants(parents, j: int) -> list[int]:
    """``j`` and every joint below it in the tree ``parents``."""
    out = [j]
    for k, p in enumerate(parents):  # a parent comes before its children in these trees
        if p in out:
            out.append(k)
    return out


def _bone_turns(pred: np.ndarray, parents) -> np.ndarray:
    """(M, bones, N, 3): ``pred`` (M, N, 3) with each bone turned in depth in turn (its far
    joint and everything below it reflected in depth about its near joint), the bones in
    the order of their far joints."""
    joints = [j for j, p in enumerate(parents) if p >= 0]
    turned = np.repeat(pred[:, None], len(joints), 1)
    for b, j in enumerate(joints):
        turned[:, b, _descendants(parents, j), 2] -= 2 * (pred[:, j, 2]
                                                          - pred[:, parents[j], 2])[:, None]
    return turned


def _view_errors(pred: np.ndarray, truth: np.ndarray) -> dict:
    """``evaluation.mpjpe``'s per-view errors of ``pred`` against ``truth`` (M, N, 3), depths
    centred over all points (the suite's human sets have every point visible)."""
    ones = np.ones(truth.shape[:2])
    return evaluation.mpjpe(evaluation.center_depth(pred, ones),
                            evaluation.center_depth(truth, ones), ones)


def bone_directions(pred, truth, dataset: str) -> list[float]:
    """``[MPJPE, fraction of deep bones pointing the wrong way in depth, the same for the
    arms, the legs and the rest, MPJPE after the oracle's bone turns, turns per view]`` of
    ``pred`` against ``truth`` (M, N, 3) of ``dataset`` (a key of ``PARENTS``)."""
    parents = PARENTS[dataset]
    pred, truth = np.asarray(pred, np.float64), np.asarray(truth, np.float64)
    per = _view_errors(pred, truth)
    pred = np.where((per["mpjpe_flip"] < per["mpjpe_orig"])[:, None, None],
                    pred * np.array([1.0, 1.0, -1.0]), pred)
    joints = [j for j, p in enumerate(parents) if p >= 0]
    dz_true = np.stack([truth[:, j, 2] - truth[:, parents[j], 2] for j in joints], 1)
    dz = np.stack([pred[:, j, 2] - pred[:, parents[j], 2] for j in joints], 1)
    length = np.stack([np.linalg.norm(truth[:, j] - truth[:, parents[j]], axis=-1)
                       for j in joints], 1)
    deep = np.abs(dz_true) >= BONE_DEPTH_SHARE * length
    wrong = deep & (np.sign(dz) != np.sign(dz_true))
    limbs = LIMBS[dataset]
    groups = [joints, limbs["arms"], limbs["legs"],
              [j for j in joints if j not in limbs["arms"] + limbs["legs"]]]
    err, turns = _view_errors(pred, truth)["mpjpe_orig"], np.zeros(len(pred))
    out = [float(err.mean())]
    for group in groups:
        cols = [joints.index(j) for j in group]
        out.append(float(wrong[:, cols].sum() / max(deep[:, cols].sum(), 1)))
    for _ in joints:  # each round, per view, the one turn that brings it nearest the truth
        turned = _bone_turns(pred, parents)
        errs = _view_errors(turned.reshape(-1, *pred.shape[1:]), np.repeat(
            truth, len(joints), 0))["mpjpe_orig"].reshape(len(pred), len(joints))
        best = np.argmin(errs, 1)
        new = errs[np.arange(len(pred)), best]
        better = new < err - 1e-12
        if not better.any():
            break
        pred[better] = turned[better, best[better]]
        err[better], turns = new[better], turns + better
    return out + [float(err.mean()), float(turns.mean())]


def _bones_dataset(run: str) -> str:
    dataset = _dataset(run)
    if dataset not in PARENTS:
        raise app.UsageError(f"{run}: bones needs a run of one of {sorted(PARENTS)}")
    return dataset


def bones(run: str) -> list[float]:
    """``bone_directions`` of the run's reconstruction (its own inference) of its test views,
    or with ``--training_views`` of up to ``OBJECTIVE_VIEWS`` of its training views."""
    if FLAGS.training_views:
        views = _training_split_and_views(run)[1]
        rec = c3dpo_jax.reconstruct(c3dpo_jax.load(run), views.kp, views.vis)
    else:
        views, _, rec = _test_reconstruction(run)
    return bone_directions(rec.shape_3d, views.kp3d, _bones_dataset(run))


def bones_references(dataset: str) -> dict:
    """``bone_directions`` of the rigid baseline and of the truth's PCA basis of ``--n_basis``
    vectors fitted to each test view's 2D points (``floors``), on ``dataset``'s test views."""
    data_dir = os.path.join(FLAGS.out, "data")
    train = json_dataset.load(os.path.join(data_dir, f"{dataset}_train.json"))
    test = json_dataset.load(os.path.join(data_dir, f"{dataset}_test.json"))
    return {f"{dataset}: {name}": bone_directions(pred, test.kp3d, dataset)
            for name, pred in (("rigid baseline", _rigid_fit(train, test)),
                               (f"truth's PCA D={FLAGS.n_basis} fitted to the 2D views",
                                _pca_fit_2d(train, test, FLAGS.n_basis)))}


RELIFT_AZIMUTHS = (-60.0, -30.0, 30.0, 60.0)  # degrees about the camera's vertical axis
RELIFT_COLUMNS = ["MPJPE", "truth's depth more self-consistent", "inconsistency: prediction",
                  "truth's depth", "MPJPE, most self-consistent single turn", "views turned",
                  "MPJPE, the oracle's single turn", "same choice as the oracle"]


def _about_vertical(degrees: float) -> np.ndarray:
    a = np.deg2rad(degrees)
    return np.array([[np.cos(a), 0.0, np.sin(a)], [0.0, 1.0, 0.0], [-np.sin(a), 0.0, np.cos(a)]])


def relift_inconsistency(lift, shapes: np.ndarray, azimuths=RELIFT_AZIMUTHS) -> np.ndarray:
    """(M,) how far ``lift`` ((M, N, 2) views -> (M, N, 3)) is from reproducing each of
    ``shapes`` (M, N, 3, every point visible) seen from the side: the shape turned about the
    camera's vertical axis by each azimuth and projected, the mean absolute difference of the
    lift's depths to the turned shape's (both centred; the better of the lift and its depth
    flip), averaged over the azimuths. 0 when the lifter sees the shape as it is from every
    one of those sides."""
    x = shapes - shapes.mean(1, keepdims=True)
    out = []
    for a in azimuths:
        turned = x @ _about_vertical(a).T
        z = np.asarray(lift(turned[..., :2]), np.float64)[..., 2]
        z = z - z.mean(1, keepdims=True)
        out.append(np.minimum(np.abs(z - turned[..., 2]).mean(1),
                              np.abs(z + turned[..., 2]).mean(1)))
    return np.mean(out, 0)


def relift_choice(lift, pred, truth, dataset: str) -> list[float]:
    """``RELIFT_COLUMNS`` for the predictions ``pred`` of views whose 3D truth is ``truth``
    (M, N, 3, every point visible) of ``dataset`` (a key of ``PARENTS``): can the lifter's own
    view of a shape from the side (``relift_inconsistency``) tell which way its bones point?
    The share of views whose truth (depth only: the prediction's x, y, the truth's depth with
    the prediction's overall flip) is more consistent than the prediction itself, the mean
    inconsistency of both; the MPJPE when each view takes the most consistent of the
    prediction and its single bone turns (``bone_directions``' turns) with the share of views
    turned; the MPJPE of the oracle's choice among the same candidates, and how often the two
    choices agree."""
    parents = PARENTS[dataset]
    pred, truth = np.asarray(pred, np.float64), np.asarray(truth, np.float64)
    per = _view_errors(pred, truth)
    flipped = (per["mpjpe_flip"] < per["mpjpe_orig"])[:, None]
    truth_depth = np.concatenate([pred[..., :2], np.where(flipped, -1.0, 1.0)[..., None]
                                  * truth[..., 2:]], -1)
    candidates = [pred, *np.moveaxis(_bone_turns(pred, parents), 1, 0)]
    scores = np.stack([relift_inconsistency(lift, c) for c in candidates])  # (1 + bones, M)
    per_candidate = [_view_errors(c, truth) for c in candidates]
    errors = np.stack([np.minimum(e["mpjpe_orig"], e["mpjpe_flip"]) for e in per_candidate])
    rows = np.arange(len(pred))
    pick, oracle = np.argmin(scores, 0), np.argmin(errors, 0)
    own, true = scores[0], relift_inconsistency(lift, truth_depth)
    return [float(errors[0].mean()), float(np.mean(true < own)), float(own.mean()),
            float(true.mean()), float(errors[pick, rows].mean()), float(np.mean(pick > 0)),
            float(errors[oracle, rows].mean()), float(np.mean(pick == oracle))]


def relift(run: str) -> list[float]:
    """``relift_choice`` of the run's test views, its inference (the run's own) lifting the
    views seen from the side in one pass (Phi's output: no turned copies, no refinement)."""
    test, model, rec = _test_reconstruction(run)

    def lift(kp):
        return c3dpo_jax.reconstruct(model, kp.astype(np.float32), np.ones(kp.shape[:2],
                                     np.float32), turns=1, refine_iters=0).shape_3d

    return relift_choice(lift, rec.shape_3d, test.kp3d, _bones_dataset(run))


def ensemble() -> list[float]:
    """Each ``--runs`` entry's test MPJPE, then that of ``sign_aligned_mean`` of them all."""
    names = {os.path.basename(os.path.normpath(r)).split("__")[0] for r in FLAGS.runs}
    if len(names) != 1:
        raise app.UsageError(f"ensemble needs runs of one dataset, got {sorted(names)}")
    test = _test_split_and_model(FLAGS.runs[0])[0]
    preds = np.stack([
        evaluation.center_depth(np.asarray(c3dpo_jax.reconstruct(
            c3dpo_jax.load(r), test.kp, test.vis).shape_3d, np.float64), test.vis)
        for r in FLAGS.runs])
    return ([evaluation.evaluate(p, test)["mpjpe"] for p in preds]
            + [evaluation.evaluate(sign_aligned_mean(preds), test)["mpjpe"]])


def _each_run(columns: list[str], fn) -> None:
    """A table with one row per ``--runs`` entry: ``fn(run)``'s values under ``columns``."""
    print("| run | " + " | ".join(columns) + " |\n|---|" + "---|" * len(columns))
    for run in FLAGS.runs:
        try:
            values = " | ".join(f"{v:.4f}" for v in np.atleast_1d(fn(run)))
        except FileNotFoundError as err:  # the committed runs keep no checkpoints
            missing = err.filename or str(err)
            values = ("no checkpoint (train it again with suite.py)"
                      if not os.path.isdir(os.path.join(run, "checkpoints"))
                      else f"missing {missing} (--out: the suite's output folder)")
        print(f"| {os.path.relpath(run, FLAGS.out)} | {values} |")


def _run_tables() -> dict:
    """Subcommand -> (its columns after the run's, the function of a run giving them)."""
    refined_cols = [f"refined, prior {w}" for w in FLAGS.priors]
    return {
        "rotations": (["model"] + [f"{m} turned, {k}" for m in ROTATION_COPIES
                                   for k in ("mean", "median")]
                      + [f"{CIRCLE_COPIES} round the circle, {k}" for k in ("mean", "median")],
                      rotation_average),
        "selected": (["model"] + [f"{m} round the circle, {k}" for m in SELECT_COPIES
                                  for k in ("lowest 2D error",
                                            f"median within {SELECT_TOLERANCE}x")],
                     selected_average),
        "union": (["model", f"{UNION_COPIES} round the circle, median within "
                   f"{SELECT_TOLERANCE}x", "the same and every copy within range"],
                  union_average),
        "refine": (["one pass", f"{UNION_COPIES} turned copies (union32)", *refined_cols,
                    f"union32, every copy refined, prior {FLAGS.priors[0]}"], refined),
        "spread": (["model's canonical spread", "truth's spread", "depth std, model / truth"],
                   spread),
        "objective": ([f"truth's PCA D={FLAGS.n_basis}, 3D", "its 2D", "Phi, 3D", "Phi, 2D",
                       "the run's inference, 3D", "its 2D"], objective),
        "basis": (["truth's PCA (the run's D), test", "learnt span, test",
                   "learnt span, training", "inference: MPJPE", "2D", "2D refit from it: MPJPE",
                   "2D", "2D refit from the truth's fit: MPJPE", "2D"], basis),
        "handedness": (["sign agreement", "no flip", "one handedness: sign agreement",
                        "no flip", *(c for body in BODIES for c in (
                            f"{body} body's handedness: sign agreement", "no flip")),
                        "flip-resolved"], handedness),
        "onebody": (["no flip: own handedness", "mean shape's", "a clip's first frame as the "
                     "body: lowest", "median", "highest", "flip-resolved"],
                    one_example_body),
        "camera": (["model", "its shapes, least-2D-error camera"], camera_refit),
        "signs": (["sign agreement"], sign_agreement),
        "bones": (BONES_COLUMNS, bones),
        "relift": (RELIFT_COLUMNS, relift),
        "mirror": (MIRROR_COLUMNS, mirror_cost),
        "reference": (REFERENCE_COLUMNS, reference),
        "decide": (DECIDE_COLUMNS, decide),
    }


def main(argv):
    c3dpo_jax.cli.setup_logging()  # no orbax chatter for every checkpoint loaded
    tables = _run_tables()
    if len(argv) != 2 or argv[1] not in (*tables, "floors", "chirality", "clips", "ensemble"):
        raise app.UsageError("usage: analyse.py floors | chirality | clips --run=RUN_DIR | "
                             "ensemble --runs=... | "
                             + " | ".join(f"{t} --runs=..." for t in tables)
                             + " (refine: [--priors=...])")
    if argv[1] in tables:
        _each_run(*tables[argv[1]])
        if argv[1] == "bones" and not FLAGS.training_views:
            for dataset in dict.fromkeys(_bones_dataset(r) for r in FLAGS.runs):
                for name, values in bones_references(dataset).items():
                    print(f"| {name} | " + " | ".join(f"{v:.4f}" for v in values) + " |")
        return
    if argv[1] == "ensemble":
        values = ensemble()
        print("| " + " | ".join([os.path.relpath(r, FLAGS.out) for r in FLAGS.runs]
                                + ["mean of all, signs matched"]) + " |")
        print("|" + "---|" * len(values))
        print("| " + " | ".join(f"{v:.4f}" for v in values) + " |")
        return
    if argv[1] == "chirality":
        from c3dpo_jax.data import load_splits
        from configs import synthetic

        print("| dataset | " + " | ".join(CHIRALITY_COLUMNS) + " |\n|---|" + "---|" * 4)
        data_dir = os.path.join(FLAGS.out, "data")
        splits = {"built-in synthetic (configs/synthetic.py)": load_splits(
            synthetic.get_config().data)}
        for name in suite.DATASETS:
            if os.path.exists(os.path.join(data_dir, f"{name}_test.json")):
                splits[name] = tuple(json_dataset.load(os.path.join(
                    data_dir, f"{name}_{split}.json")) for split in ("train", "test"))
        for name, (train, test) in splits.items():
            print(f"| {name} | " + " | ".join(
                f"{v:.4f}" for v in chirality(name, train, test)) + " |")
        return
    if argv[1] == "floors":
        data_dir = os.path.join(FLAGS.out, "data")
        print(f"| dataset | rigid mean shape, oracle rotation | PCA D={FLAGS.n_basis}, oracle "
              f"fit | rigid baseline's mean 2D distance | PCA D={FLAGS.n_basis} fitted to the 2D "
              "views |\n|---|---|---|---|---|")
        for name in suite.DATASETS:
            if os.path.exists(os.path.join(data_dir, f"{name}_test.json")):
                f = list(floors(name, data_dir, FLAGS.n_basis).values())
                print(f"| {name} | " + " | ".join(f"{v:.4f}" for v in f) + " |")
        return
    if not FLAGS.run:
        raise app.UsageError("clips needs --run=RUN_DIR")
    print("| clip | test views | model | rigid baseline |\n|---|---|---|---|")
    for name, n, model, rigid in per_clip(FLAGS.run):
        print(f"| {name} | {n} | {model:.3f} | {rigid:.3f} |")


if __name__ == "__main__":
    run_main(main, positional=True)

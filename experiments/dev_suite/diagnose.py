"""Where does the 3D error come from, and how does it evolve while training?

Trains one suite dataset with the library's loop (``train.train_and_evaluate``) and, at
every evaluation (``train.Hooks.after_evaluation``), measures on the training views (a fixed
subset) and on the test views::

  python experiments/dev_suite/diagnose.py --dataset=deepmimic --diag_out=runs/diag_deepmimic
  python experiments/dev_suite/diagnose.py --dataset=deepmimic --set=loss.w_canonicalization=10

Written to ``DIAG_OUT/diagnostics.jsonl``, one record per evaluation and split:

- ``mpjpe`` (best of the prediction and its depth flip, per view), ``mpjpe_orig``;
  ``sign_agreement``: the fraction of views whose better one is the unflipped prediction
  (near 0 or 1: one depth sign for all views; 0.5: the sign is a coin toss per view);
- ``reprojection``: mean 2D distance of the visible points to their reprojection;
- ``canon_view_spread``: views of the same frame (the importer's consecutive
  ``views_per_frame`` views) must give the same canonical shape; the RMS distance of each
  view's canonical shape to its frame's mean, over the RMS size of the shapes (computed
  from 2D data and the frame labels alone);
- ``canon_oracle``: the canonical shapes under the best rotation onto the 3D ground truth
  (shape or mirror image, per view): the error of the shape itself, with a perfect camera;
- ``canon_rotation_share``: the part of the canonical shapes' variance across views that a
  rotation of each onto their mean removes (high: the basis encodes rotations);
- ``alpha_rms``: RMS of the shape coefficients times the basis norm (the size of the
  deformations), ``mean_canon_size``: RMS radius of the canonical shapes.

The canonical shapes are the model's own (``lift.own_handedness``: before
``inference.one_handedness`` mirrors a view to a body's handedness, which would count as
spread and rotation between views of one frame). ``sign_agreement_own`` is the sign
agreement of the model's own depths (those views' depths mirrored back),
``sign_agreement`` that of the inference the config asks for.
"""

import json
import os
import sys

import jax
import numpy as np
from absl import flags

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.normpath(os.path.join(HERE, "..", ".."))
sys.path.insert(0, ROOT)

import suite  # noqa: E402
from runner import literal, override, run_main  # noqa: E402

from c3dpo_jax import (  # noqa: E402
    baselines,
    evaluation,
    inference,
    lift,
    resolve,
    run_records,
    train,
)
from c3dpo_jax.data import json_dataset  # noqa: E402

FLAGS = flags.FLAGS
flags.DEFINE_string("dataset", "deepmimic", "a dataset of the suite")
flags.DEFINE_integer("seed", 0, "training seed")
flags.DEFINE_multi_string("set", [], "config overrides KEY=VALUE")
flags.DEFINE_string("diag_out", os.path.join(ROOT, "runs", "dev_suite_diag"),
                    "workdir of the run")
flags.DEFINE_integer("n_train_views", 3000, "training views measured")


def _rms(x):
    return float(np.sqrt(np.mean(np.sum(x**2, -1))))


def _oracle(shapes: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """Per-view error of ``shapes`` under the best proper rotation onto ``gt``, the better
    of the shape and its mirror image (both centred)."""
    gt = gt - gt.mean(1, keepdims=True)
    errs = []
    for sign in (1.0, -1.0):
        s = shapes * np.array([1.0, 1.0, sign])
        s = s - s.mean(1, keepdims=True)
        rot = baselines.kabsch(s, gt)
        errs.append(np.linalg.norm(np.einsum("mij,mnj->mni", rot, s) - gt, axis=-1).mean(1))
    return np.minimum(*errs)


def _per_view(shape_3d, data) -> dict:
    """``evaluation.mpjpe``'s per-view errors of ``shape_3d``, depths centred."""
    return evaluation.mpjpe(evaluation.center_depth(shape_3d, data.vis),
                            evaluation.center_depth(data.kp3d, data.vis), data.vis)


def _sign_agreement(per: dict) -> float:
    """The fraction of views whose prediction is nearer the truth than its depth flip."""
    return float(np.mean(per["mpjpe_orig"] <= per["mpjpe_flip"]))


def measure(pred: dict, data, views_per_frame: int, protocol: str) -> dict:
    """The module docstring's measures of ``pred`` (``inference.predict_split``'s outputs)."""
    res = evaluation.evaluate(pred["shape_3d"], data, protocol)
    per = _per_view(pred["shape_3d"], data)
    own_3d = lift.own_handedness(pred["shape_3d"], pred["handedness_flipped"])
    canon = lift.own_handedness(pred["shape_canonical"], pred["handedness_flipped"])
    canon = canon / pred["kp_scale"][:, None, None]  # the data's units
    canon = canon - canon.mean(1, keepdims=True)
    out = dict(mpjpe=res["mpjpe"], mpjpe_orig=float(per["mpjpe_orig"].mean()),
               sign_agreement=_sign_agreement(per),
               sign_agreement_own=_sign_agreement(_per_view(own_3d, data)),
               reprojection=evaluation.reprojection_error(pred["kp_reprojected"], data),
               canon_oracle=float(_oracle(canon, data.kp3d).mean()),
               mean_canon_size=_rms(canon), alpha_rms=float(np.sqrt(np.mean(pred["alpha"]**2))))
    m = len(canon) // views_per_frame * views_per_frame
    if views_per_frame > 1 and m:
        frames = canon[:m].reshape(-1, views_per_frame, *canon.shape[1:])
        out["canon_view_spread"] = _rms(frames - frames.mean(1, keepdims=True)) / _rms(canon)
    mean = baselines.procrustes_mean_shape(canon, max_samples=len(canon))
    rot = baselines.kabsch(canon, mean)
    aligned = np.einsum("mij,mnj->mni", rot, canon)
    before, after = np.mean((canon - mean) ** 2), np.mean((aligned - mean) ** 2)
    out["canon_rotation_share"] = float(1 - after / max(before, 1e-12))
    return out


class _Records:
    """``diagnostics.jsonl``, appended to; its first write drops the records at or after its
    step (``run_records.trim_records``): a resumed run evaluates again the steps after its
    last checkpoint, which would otherwise be recorded twice."""

    def __init__(self, path: str):
        self.path, self.trimmed = path, False

    def write(self, row: dict) -> None:
        if not self.trimmed:
            run_records.trim_records(self.path, row["step"] - 1)
            self.trimmed = True
        with open(self.path, "a") as f:
            f.write(json.dumps(row) + "\n")


def main(argv):
    del argv
    c, info = suite.run_config(FLAGS.dataset, FLAGS.seed)
    override(c, {k: literal(v) for k, v in (i.partition("=")[::2] for i in FLAGS.set)})
    train_data = json_dataset.load(info["train"])
    test_data = json_dataset.load(info["test"])
    vpf = suite.views_per_frame(FLAGS.dataset)
    n = min(FLAGS.n_train_views, len(train_data)) // vpf * vpf
    start = np.random.default_rng(0).integers(0, (len(train_data) - n) // vpf + 1) * vpf
    train_sub = train_data.subset(np.arange(start, start + n))  # whole frames, in order
    c = resolve.resolve_from_data(c, train_data)  # once, before training
    spec = train.RunSpec.from_config(c)
    options = lift.inference_config(spec.model, spec.inference)
    os.makedirs(FLAGS.diag_out, exist_ok=True)
    records = _Records(os.path.join(FLAGS.diag_out, "diagnostics.jsonl"))

    def after_evaluation(record, state):
        variables = jax.device_get(state.variables)
        used = inference.with_views_mean(options, variables, train_data, spec.model)[0]
        for split, data in (("train", train_sub), ("test", test_data)):
            pred = inference.predict_split(variables, data, spec.model, used)
            row = dict(step=record["step"], split=split,
                       **measure(pred, data, vpf, info["protocol"]))
            records.write(row)
            print(" ".join(f"{k}={v:.4f}" if isinstance(v, float) else f"{k}={v}"
                           for k, v in row.items()), flush=True)

    train.train_and_evaluate(c, FLAGS.diag_out, train.Hooks(after_evaluation=after_evaluation))


if __name__ == "__main__":
    run_main(main)

"""EM-SfM run transductively on the test views of a dataset, beside the rigid baseline.

As the C3DPO paper ran its NRSfM baseline: ``c3dpo_jax.emsfm.em_sfm`` is fitted to the test
views alone (2D points only), and its camera-frame shapes are scored with the release's
protocol (MPJPE with the per-view depth flip, stress) and the NRSfM literature's errors
(``c3dpo_jax.nrsfm_metrics``: e3D and the mean relative Frobenius error, each under the
per-view depth flip and under one orthogonal alignment for the whole test set)::

  python experiments/emsfm/run.py --datasets=face,deepmimic
  python experiments/emsfm/run.py --data_dir=DIR --datasets=NAME --n_basis=0,2,5,10

A dataset NAME is the pair ``DIR/NAME_test.json`` and ``DIR/NAME_train.json`` (the format of
``c3dpo_jax.data.json_dataset``; ``experiments/dev_suite/suite.py`` writes the development
suite's there); the protocol comes from ``DIR/NAME.json`` when it exists. The training split
only serves the rigid baseline (its Procrustes mean 3D shape under the best rigid fit to each
test view), which uses 3D ground truth that EM-SfM never sees. Results go to
``--out/NAME.json`` and a table is printed.
"""

import json
import os
import sys
import time

from absl import flags

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", ".."))
sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))

from runner import machine, run_main  # noqa: E402

from c3dpo_jax import baselines, emsfm, evaluation, nrsfm_metrics  # noqa: E402
from c3dpo_jax.data import json_dataset  # noqa: E402

HERE = os.path.dirname(os.path.abspath(__file__))
COLUMNS = ("mpjpe", "stress", "e3d/flip", "e3d/sequence", "relative_error/flip",
           "relative_error/sequence", "seconds", "iterations")

FLAGS = flags.FLAGS
flags.DEFINE_string("data_dir", os.path.join(HERE, "..", "dev_suite", "results", "data"),
                    "directory with NAME_test.json, NAME_train.json (and NAME.json)")
flags.DEFINE_list("datasets", ["face", "deepmimic"], "dataset names in --data_dir")
flags.DEFINE_list("n_basis", ["0", "2", "5", "10"], "EM-SfM basis sizes D to run")
flags.DEFINE_integer("n_iters", 200, "most EM iterations")
flags.DEFINE_integer("seed", 0, "EM-SfM seed")
flags.DEFINE_string("out", os.path.join(HERE, "results"), "where NAME.json results go")


def score(pred, test, protocol: str) -> dict[str, float]:
    """The release's protocol and the NRSfM errors of one reconstruction."""
    res = evaluation.evaluate(pred, test, protocol)
    out = {"mpjpe": res["mpjpe"], "stress": res["stress"]}
    out.update(nrsfm_metrics.scores(pred, test.kp3d))
    return out


def run_dataset(name: str) -> tuple[dict[str, dict[str, float]], int]:
    """Rows ``{method: scores}`` of one dataset, and its number of test views."""
    path = os.path.join(FLAGS.data_dir, name)
    meta = {}
    if os.path.exists(path + ".json"):
        with open(path + ".json") as f:
            meta = json.load(f)
    protocol = meta.get("protocol", "default")
    test = json_dataset.load(path + "_test.json", cache=False)
    rows = {}
    if os.path.exists(path + "_train.json"):
        train = json_dataset.load(path + "_train.json", cache=False)
        if train.kp3d is not None:
            start = time.perf_counter()
            mean = baselines.procrustes_mean_shape(train.kp3d)
            pred = baselines.fit_mean_shape(mean, test.kp, test.vis)
            rows["rigid fit of the training mean"] = dict(
                score(pred, test, protocol), seconds=time.perf_counter() - start)
    for d in map(int, FLAGS.n_basis):
        start = time.perf_counter()
        res = emsfm.em_sfm(test.kp, test.vis, n_basis=d, n_iters=FLAGS.n_iters, seed=FLAGS.seed)
        rows[f"EM-SfM, D={d}"] = dict(score(res.shapes, test, protocol),
                                      seconds=time.perf_counter() - start,
                                      iterations=len(res.log_likelihood) - 1)
    return rows, len(test)


def table(name: str, n_views: int, rows: dict[str, dict[str, float]]) -> str:
    """A markdown table of one dataset's rows."""
    lines = [f"{name} ({n_views} test views)", "",
             "| method | " + " | ".join(COLUMNS) + " |", "|---" * (len(COLUMNS) + 1) + "|"]
    for method, row in rows.items():
        cells = [f"{row[c]:.4f}" if c in row and c != "iterations" else str(row.get(c, "-"))
                 for c in COLUMNS]
        cells[COLUMNS.index("seconds")] = f"{row['seconds']:.1f}"
        lines.append(f"| {method} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv):
    del argv
    os.makedirs(FLAGS.out, exist_ok=True)
    for name in FLAGS.datasets:
        rows, n_views = run_dataset(name)
        with open(os.path.join(FLAGS.out, name + ".json"), "w") as f:
            json.dump({"n_iters": FLAGS.n_iters, "seed": FLAGS.seed, "machine": machine(),
                       "rows": rows}, f, indent=1)
        print(table(name, n_views, rows) + "\n", flush=True)


if __name__ == "__main__":
    run_main(main)

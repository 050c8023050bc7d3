"""Time to accuracy: test MPJPE against wall-clock training time, next to the baselines.

One run = one dataset, one recipe, one seed. It trains for ``--budget_s`` seconds of
wall-clock time (compilation included, evaluation excluded), scores the test split
every ``--eval_every_s`` seconds with the C3DPO protocol (flip-resolved MPJPE, depth
centred) and writes ``OUT_DIR/DATASET__RECIPE__sSEED.json``::

  python experiments/time_to_accuracy/run.py --dataset=pickup --recipe=cpu --seed=0
  python experiments/time_to_accuracy/run.py --dataset=humans --recipe=official
  python experiments/time_to_accuracy/report.py   # table + figure from all results

Datasets: the sequences of the development data by name (drink, face, jaws, pickup,
stretch, yoga; not distributed with the repository, looked up in ``NRSFM_DIR``) or any
``.npz``/``.mat`` path (views made with ``c3dpo_jax.data.importers.views_from_sequence``:
``--views_per_frame`` random cameras per frame, test frames in unseen blocks), or
``humans`` (the built-in synthetic humans, configs/humans.py's data). Recipes: ``cpu``
(the library default: ``configs.default.cpu_recipe``; for ``humans`` configs/humans.py,
which sets its own canonicalisation weight) and ``official`` (the release's h36m-style
settings: 1024-wide 6-block trunks, SGD lr 1e-3, momentum 0.9, weight decay 5e-4, batch
256).

Replay mode (``--steps_per_s=R --compile_s=C``): instead of the clock, the run stops at
``R * (budget - C)`` steps and evaluates at the step counts the clock would have
reached, with R and C measured by a calibration run alone on the machine
(``--budget_s=60``, reads ``steps_per_s`` and ``compile_s`` from its output). Steps,
data order and augmentations depend only on the seed, so replayed runs can share the
machine (e.g. two at once, one core each) without changing their results.
"""

import ast
import json
import os
import sys
import time

from absl import app, flags, logging

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", ".."))  # for ``configs``

import flax  # noqa: E402
import jax  # noqa: E402
import numpy as np  # noqa: E402

from c3dpo_jax import baselines, device_data, evaluation, train  # noqa: E402
from c3dpo_jax.data import importers, json_dataset, load_splits  # noqa: E402
from c3dpo_jax.state import create_train_state  # noqa: E402
from configs import default, release  # noqa: E402
from configs import humans as humans_config  # noqa: E402

HERE = os.path.dirname(os.path.abspath(__file__))
NRSFM_DIR = os.path.join(HERE, "..", "..", "..", "shared", "data", "nrsfm")
SEQUENCES = ("drink", "face", "jaws", "pickup", "stretch", "yoga")

FLAGS = flags.FLAGS
flags.DEFINE_string("dataset", "pickup", f"one of {SEQUENCES}, 'humans', or a .npz/.mat path")
flags.DEFINE_enum("recipe", "cpu", ["cpu", "official"], "training recipe")
flags.DEFINE_integer("seed", 0, "initialisation and training seed")
flags.DEFINE_integer("data_seed", 0, "seed of the views (cameras, split); fixed across runs")
flags.DEFINE_float("budget_s", 600.0, "wall-clock training budget in seconds")
flags.DEFINE_float("eval_every_s", 30.0, "evaluate the test split every this many seconds")
flags.DEFINE_integer("views_per_frame", 10, "random cameras per frame of a sequence")
flags.DEFINE_enum("cameras", "upright", ["uniform", "upright"], "camera distribution")
flags.DEFINE_integer("train_poses", 0, "humans: training people/poses (0: configs/default.py's)")
flags.DEFINE_bool("self_occlusion", True, "humans: hide points behind the body")
flags.DEFINE_integer("chunk_steps", 0, "steps per compiled call (0: recipe default)")
flags.DEFINE_float("steps_per_s", 0.0, "replay mode: calibrated training steps per second")
flags.DEFINE_float("compile_s", 0.0, "replay mode: calibrated compile seconds")
flags.DEFINE_string("out_dir", os.path.join(HERE, "results"), "where results go")
flags.DEFINE_multi_string("set", [], "config overrides KEY=VALUE (e.g. optim.lr=1e-3)")
flags.DEFINE_string("tag", "", "suffix of the recipe name in the results (search runs)")
flags.DEFINE_bool("baselines_only", False, "only score the baselines (see baselines_only())")
flags.DEFINE_string("save_variables", "", "also write the final model variables here "
                    "(flax msgpack; read with flax.serialization.msgpack_restore)")


def sequence_path(name: str) -> str:
    """The file of a sequence: ``name`` itself if it exists, else ``NRSFM_DIR/name.npz``."""
    path = name if os.path.exists(name) else os.path.join(NRSFM_DIR, f"{name}.npz")
    if not os.path.exists(path):
        raise app.UsageError(f"no dataset {name!r}: not a file, not in {NRSFM_DIR}")
    return path


def dataset_name(name: str) -> str:
    """Result-file name of a dataset: ``pickup`` for ``pickup``, ``dir/pickup.npz`` and
    ``dir/pickup_train.json``."""
    return os.path.splitext(os.path.basename(name))[0].removesuffix("_train")


def load_dataset(name: str, views_per_frame: int, cameras: str, seed: int):
    """(train, test, protocol) for a sequence name/path, ``humans``, or a ``NAME_train.json``
    whose ``NAME_test.json`` lies beside it (e.g. a dataset made by experiments/dev_suite)."""
    if name.endswith("_train.json"):
        return (json_dataset.load(name), json_dataset.load(name.replace("_train.json",
                                                                          "_test.json")),
                "up3d" if os.path.basename(name).startswith("humans") else "default")
    if name == "humans":
        data_cfg = _override(humans_config.get_config(), FLAGS.set, "data.").data
        data_cfg.humans.n_train_poses = FLAGS.train_poses or data_cfg.humans.n_train_poses
        data_cfg.humans.self_occlusion = FLAGS.self_occlusion
        data_cfg.humans.seed = seed
        train_data, test_data = load_splits(data_cfg)
        return train_data, test_data, data_cfg.protocol
    x = importers.load_sequence(sequence_path(name))
    train_data, test_data = importers.views_from_sequence(
        x, views_per_frame=views_per_frame, cameras=cameras, seed=seed,
        name=dataset_name(name))
    return train_data, test_data, "default"


def recipe_config(recipe: str, dataset: str, n_keypoints: int, protocol: str):
    if recipe == "official":  # the release's h36m settings at batch 256
        c = release.release_config(
            None, name="experiment", n_keypoints=n_keypoints, basis=10, batch_size=256,
            rescale=1.0, argmin_translation=False, z_augment_angle=0.3925,
            samples_per_epoch=1_249_280, epochs=90, milestones=(60, 80), protocol=protocol)
    elif dataset == "humans":  # the built-in dataset's own config (cpu_recipe + its loss weight)
        c = humans_config.get_config()
    else:
        c = default.cpu_recipe(default.get_config())
    c.model.n_keypoints = n_keypoints
    c.data.protocol = protocol
    return _override(c, FLAGS.set)


def _override(c, items, prefix: str = ""):
    """Applies ``KEY=VALUE`` overrides (those whose key starts with ``prefix``) to ``c``."""
    for item in items:
        key, value = item.split("=", 1)
        if not key.startswith(prefix):
            continue
        *parents, leaf = key.split(".")
        node = c
        for p in parents:
            node = node[p]
        try:
            value = ast.literal_eval(value)
        except (ValueError, SyntaxError):
            pass  # a plain string, e.g. optim.optimizer=sgd
        old = node[leaf]
        node[leaf] = float(value) if isinstance(old, float) else value
    return c


def baseline_scores(train_data, test_data, protocol: str, n_basis: int) -> dict:
    mean_shape = baselines.procrustes_mean_shape(train_data.kp3d)
    preds = baselines.predict(mean_shape, test_data.kp, test_data.vis)
    preds["oracle mean shape"] = baselines.oracle_mean_shape(mean_shape, test_data.kp3d,
                                                             test_data.vis)
    pca = baselines.pca_shape_basis(train_data.kp3d, n_basis)
    preds["fitted PCA basis"] = baselines.fit_shape_basis(pca, test_data.kp, test_data.vis)
    out = {k: evaluation.evaluate(p, test_data, protocol)["mpjpe"] for k, p in preds.items()}
    split = evaluation.mpjpe_by_visibility(preds["fitted mean shape"], test_data)
    out.update({f"fitted mean shape, {k.removeprefix('mpjpe_')}": v for k, v in split.items()})
    return out


def run() -> dict:
    train_data, test_data, protocol = load_dataset(
        FLAGS.dataset, FLAGS.views_per_frame, FLAGS.cameras, FLAGS.data_seed)
    c = recipe_config(FLAGS.recipe, FLAGS.dataset, train_data.n_keypoints, protocol)
    c = train.resolve_input_scale(c, train_data)  # the cpu recipe sets it from the data
    spec = train.RunSpec.from_config(c)
    model_cfg = spec.model
    state = create_train_state(jax.random.key(FLAGS.seed), model_cfg, spec.optimizer())
    train_key = jax.random.fold_in(jax.random.key(FLAGS.seed), 1)
    train_step = spec.train_step()
    chunk = jax.jit(train.make_train_chunk(train_step, c.train.batch_size),
                    static_argnames="n_steps", donate_argnums=0)
    eval_fn = jax.jit(train.make_eval_fn(model_cfg))
    data = device_data.device_train_data(train_data, False)
    n_chunk = FLAGS.chunk_steps or (2 if FLAGS.recipe == "official" else 20)
    replay = FLAGS.steps_per_s > 0

    def score(step: int, t: float, wall: float, loss: float) -> dict:
        pred = train.predict(state.variables, test_data, model_cfg, 1024, eval_fn)
        res = evaluation.evaluate(pred["shape_image_coord"], test_data, protocol)
        rec = dict(t=t, wall_s=wall, step=step, loss=loss, mpjpe=res["mpjpe"], stress=res["stress"])
        rec.update(evaluation.mpjpe_by_visibility(pred["shape_image_coord"], test_data))
        logging.info("%s", rec)
        return rec

    curve, step, t_train, next_eval, compile_s = [], 0, 0.0, FLAGS.eval_every_s, None
    start = time.perf_counter()
    while True:
        tic = time.perf_counter()
        state, metrics = chunk(state, data, train_key, n_steps=n_chunk)
        loss = np.asarray(jax.device_get(metrics["loss"]))
        dt = time.perf_counter() - tic
        if compile_s is None:
            compile_s, first_chunk_s = dt, dt
        t_train += dt
        step += n_chunk
        if not np.all(np.isfinite(loss)):
            raise FloatingPointError(f"loss is not finite near step {step}")
        t = FLAGS.compile_s + step / FLAGS.steps_per_s if replay else t_train
        done = t >= FLAGS.budget_s
        if t >= next_eval or done:
            curve.append(score(step, t, time.perf_counter() - start, float(loss.mean())))
            next_eval = (np.floor(t / FLAGS.eval_every_s) + 1) * FLAGS.eval_every_s
        if done:
            break
    steady = (step - n_chunk) / max(t_train - first_chunk_s, 1e-9)
    if FLAGS.save_variables:
        with open(FLAGS.save_variables, "wb") as f:
            f.write(flax.serialization.msgpack_serialize(jax.device_get(state.variables)))
    return dict(
        dataset=dataset_name(FLAGS.dataset),
        recipe=FLAGS.recipe + FLAGS.tag,
        seed=FLAGS.seed,
        data_seed=FLAGS.data_seed,
        mode="replay" if replay else "wall",
        budget_s=FLAGS.budget_s,
        steps_per_s=FLAGS.steps_per_s if replay else steady,
        compile_s=FLAGS.compile_s if replay else compile_s - n_chunk / steady,
        n_train=len(train_data),
        n_test=len(test_data),
        n_keypoints=train_data.n_keypoints,
        protocol=protocol,
        cameras=FLAGS.cameras,
        views_per_frame=FLAGS.views_per_frame,
        baselines=baseline_scores(train_data, test_data, protocol, c.model.shape_basis_size),
        curve=curve,
        config=json.loads(c.to_json_best_effort()),
        devices=str(jax.devices()),
        cpu_affinity=len(os.sched_getaffinity(0)),
    )


def baselines_only() -> None:
    """``--baselines_only``: the baselines of one dataset (no training), written to
    ``OUT_DIR/baselines/DATASET.json``; report.py prefers these over a run's own copy."""
    train_data, test_data, protocol = load_dataset(
        FLAGS.dataset, FLAGS.views_per_frame, FLAGS.cameras, FLAGS.data_seed)
    c = recipe_config(FLAGS.recipe, FLAGS.dataset, train_data.n_keypoints, protocol)
    name = dataset_name(FLAGS.dataset)
    result = dict(dataset=name, data_seed=FLAGS.data_seed, cameras=FLAGS.cameras,
                  views_per_frame=FLAGS.views_per_frame, n_basis=c.model.shape_basis_size,
                  baselines=baseline_scores(train_data, test_data, protocol,
                                            c.model.shape_basis_size))
    os.makedirs(os.path.join(FLAGS.out_dir, "baselines"), exist_ok=True)
    path = os.path.join(FLAGS.out_dir, "baselines", f"{name}.json")
    with open(path, "w") as f:
        json.dump(result, f, indent=1)
    print(f"{name}: " + ", ".join(f"{k} {v:.4f}" for k, v in result["baselines"].items())
          + f" -> {path}")


def main(argv):
    del argv
    if FLAGS.baselines_only:
        return baselines_only()
    result = run()
    os.makedirs(FLAGS.out_dir, exist_ok=True)
    name = result["dataset"]
    path = os.path.join(FLAGS.out_dir, f"{name}__{result['recipe']}__s{FLAGS.seed}.json")
    with open(path, "w") as f:
        json.dump(result, f, indent=1)
    last = result["curve"][-1]
    print(f"{name} {result['recipe']} seed {FLAGS.seed}: step {last['step']} t {last['t']:.0f}s "
          f"MPJPE {last['mpjpe']:.4f} | baselines "
          + ", ".join(f"{k} {v:.4f}" for k, v in result["baselines"].items())
          + f" | {result['steps_per_s']:.1f} steps/s -> {path}")


if __name__ == "__main__":
    app.run(main)

"""Time to accuracy: test MPJPE against wall-clock training time, next to the baselines.

One run = one dataset, one recipe, one seed, trained by the library's loop
(``train.train_and_evaluate``, in ``OUT_DIR/runs/DATASET__RECIPE__sSEED``: the training a
user gets from the CLI, resumable) for ``--budget_s`` seconds of training time (compilation
included, evaluation and checkpoint writing excluded); its test curve and the baselines go
to ``OUT_DIR/DATASET__RECIPE__sSEED.json``::

  python experiments/time_to_accuracy/run.py --dataset=pickup --recipe=cpu --seed=0
  python experiments/time_to_accuracy/run.py --dataset=humans --recipe=official
  python experiments/time_to_accuracy/report.py   # table + figure from all results

Datasets: the sequences of the development data by name (drink, face, jaws, pickup,
stretch, yoga; not distributed with the repository: ``--data_root/nrsfm/NAME.npz``) or any
``.npz``/``.mat`` path (views made with ``c3dpo_jax.data.importers.views_from_sequence``:
``--views_per_frame`` random cameras per frame, test frames in unseen blocks), or
``humans`` (the built-in synthetic humans, configs/humans.py's data), written as JSON views
into the run's folder. Recipes: ``cpu`` (the library default: ``configs.default.cpu_recipe``;
for ``humans`` configs/humans.py, which sets its own canonicalisation weight) and
``official`` (the release's h36m-style settings: 1024-wide 6-block trunks, SGD lr 1e-3,
momentum 0.9, weight decay 5e-4, batch 256). With ``--supervised`` a recipe trains the same
networks with the 3D ground truth instead of C3DPO's losses (recipe ``cpu_supervised``: the
reference with 3D supervision in report.py's table)::

  python experiments/time_to_accuracy/run.py --dataset=face --supervised

Timed mode (the default): training stops at the first chunk where the loop's clock reaches
the budget, or where the recipe ends (the CLI's run: ``train.num_steps`` or its epochs), if
that comes first. Replay mode (``--steps_per_s=R --compile_s=C``): the clock is ``C + step / R``
and the run trains the steps that clock needs to reach the budget, with R and C measured by a
timed calibration run alone on the machine (``--budget_s=60``; its result holds
``steps_per_s`` and ``compile_s``). In both, the test split is scored at the first chunk at
or past every ``--eval_every_s`` seconds of the clock (``train.Hooks.should_evaluate``).
Steps, data order and augmentations depend only on
the seed, so replayed runs can share the machine (e.g. two at once, one core each) without
changing their results.
"""

import json
import math
import os
import sys

from absl import flags, logging

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", ".."))  # for ``configs``
sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))  # for ``runner``

import flax  # noqa: E402
import jax  # noqa: E402
import numpy as np  # noqa: E402
from runner import literal, machine, repo_path, run_main  # noqa: E402

from c3dpo_jax import baselines, evaluation, load, train  # noqa: E402
from c3dpo_jax.data import importers, json_dataset, load_splits  # noqa: E402
from configs import default, release  # noqa: E402
from configs import humans as humans_config  # noqa: E402

HERE = os.path.dirname(os.path.abspath(__file__))
SEQUENCES = ("drink", "face", "jaws", "pickup", "stretch", "yoga")

FLAGS = flags.FLAGS
flags.DEFINE_string("dataset", "pickup", f"one of {SEQUENCES} (under --data_root), 'humans', "
                    "or a .npz/.mat path")
flags.DEFINE_string("data_root", os.environ.get("C3DPO_DEV_DATA", ""),
                    "the folder holding nrsfm/NAME.npz, the development sequences, which are not "
                    "distributed with the repository (default: $C3DPO_DEV_DATA)")
flags.DEFINE_enum("recipe", "cpu", ["cpu", "official"], "training recipe")
flags.DEFINE_integer("seed", 0, "initialisation and training seed")
flags.DEFINE_integer("data_seed", 0, "seed of the views (cameras, split); fixed across runs")
flags.DEFINE_float("budget_s", 600.0, "wall-clock training budget in seconds")
flags.DEFINE_float("eval_every_s", 30.0, "evaluate the test split every this many seconds")
flags.DEFINE_integer("views_per_frame", 10, "random cameras per frame of a sequence")
flags.DEFINE_enum("cameras", "upright", ["uniform", "upright"], "camera distribution")
flags.DEFINE_integer("train_poses", 0, "humans: training people/poses (0: configs/default.py's)")
flags.DEFINE_bool("self_occlusion", True, "humans: hide points behind the body")
flags.DEFINE_integer("chunk_steps", 0, "steps per compiled call, config.train.log_every "
                     "(0: 20, 2 for the official recipe)")
flags.DEFINE_float("steps_per_s", 0.0, "replay mode: calibrated training steps per second")
flags.DEFINE_float("compile_s", 0.0, "replay mode: calibrated compile seconds")
flags.DEFINE_string("out_dir", os.path.join(HERE, "results"), "where results go")
flags.DEFINE_multi_string("set", [], "config overrides KEY=VALUE (e.g. optim.lr=1e-3)")
flags.DEFINE_string("tag", "", "suffix of the recipe name in the results (search runs)")
flags.DEFINE_bool("supervised", False, "train the same networks with the 3D ground truth "
                  "instead of C3DPO's losses (configs/default.py's 'supervised' variant: the "
                  "reference with 3D supervision); the recipe's name gets '_supervised'")
flags.DEFINE_bool("baselines_only", False, "only score the baselines (see baselines_only())")
flags.DEFINE_string("save_variables", "", "also write the final model variables here "
                    "(flax msgpack; read with flax.serialization.msgpack_restore)")


def sequence_path(name: str) -> str:
    """The file of a sequence: ``name`` itself if it exists, else
    ``--data_root/nrsfm/name.npz``."""
    if os.path.exists(name):
        return name
    if not FLAGS.data_root:
        raise ValueError(f"--dataset={name} is not a file, and --data_root (or $C3DPO_DEV_DATA), "
                         "the folder holding nrsfm/NAME.npz, is not given")
    path = os.path.join(FLAGS.data_root, "nrsfm", f"{name}.npz")
    if not os.path.exists(path):
        raise ValueError(f"--dataset={name}: not a file, and {path} does not exist")
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


def recipe_name() -> str:
    """The recipe's name in the results: ``--recipe``, ``_supervised`` with
    ``--supervised``, then ``--tag``."""
    return FLAGS.recipe + "_supervised" * FLAGS.supervised + FLAGS.tag


def recipe_config(recipe: str, dataset: str, n_keypoints: int, protocol: str):
    if recipe == "official":  # the release's h36m settings at batch 256
        c = release.release_config(
            None, name="experiment", n_keypoints=n_keypoints, basis=10, batch_size=256,
            rescale=1.0, argmin_translation=False, z_augment_angle=0.3925,
            samples_per_epoch=1_249_280, epochs=90, milestones=(60, 80), protocol=protocol)
    elif dataset == "humans":  # the built-in dataset's own config (cpu_recipe + its loss weight)
        c = humans_config.get_config()
        c.inference.refine_iters = 0  # the cpu recipe: Phi's single pass, as elsewhere
    else:
        c = default.cpu_recipe(default.get_config())
    if FLAGS.supervised:
        default.apply_variants(c, "supervised")
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
        value = literal(value)  # a plain string stays one, e.g. optim.optimizer=sgd
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


def _views(train_data, test_data, workdir: str) -> tuple[str, str]:
    """Writes the run's views as the JSON files the library's loop reads (once)."""
    paths = tuple(os.path.join(workdir, f"views_{s}.json") for s in ("train", "test"))
    if not all(os.path.exists(p) for p in paths):
        os.makedirs(workdir, exist_ok=True)
        for data, path in zip((train_data, test_data), paths):
            json_dataset.save(data, path)
    return paths


def rate_and_compile(workdir: str, final: dict) -> tuple[float, float]:
    """Steady steps/s (the median rate of the later half of the loop's logged chunks) and
    compile seconds (what the final clock holds beyond its steps at that rate)."""
    with open(os.path.join(workdir, "metrics.jsonl")) as f:
        rates = [json.loads(line)["steps_per_s"] for line in f if line.strip()]
    rate = float(np.median(rates[len(rates) // 2:]))
    return rate, max(final["train_s"] - final["step"] / rate, 0.0)


def run() -> dict:
    """One run through the library's loop (``train.train_and_evaluate``) in
    ``OUT_DIR/runs/DATASET__RECIPE__sSEED`` (resumable); returns the result record."""
    train_data, test_data, protocol = load_dataset(
        FLAGS.dataset, FLAGS.views_per_frame, FLAGS.cameras, FLAGS.data_seed)
    name, recipe = dataset_name(FLAGS.dataset), recipe_name()
    c = recipe_config(FLAGS.recipe, FLAGS.dataset, train_data.n_keypoints, protocol)
    workdir = os.path.join(FLAGS.out_dir, "runs", f"{name}__{recipe}__s{FLAGS.seed}")
    c.data.train_path, c.data.test_path = _views(train_data, test_data, workdir)
    c.seed = FLAGS.seed
    c.train.progress_bar = False
    c.train.log_every = FLAGS.chunk_steps or (2 if FLAGS.recipe == "official" else 20)
    replay = FLAGS.steps_per_s > 0
    chunk = c.train.log_every
    recipe_steps = train.RunSpec.from_config(c).total_steps  # where the CLI's run ends
    if replay:  # the clock of a replay: the calibrated compile time, then R steps a second
        def clock(step, train_s):
            return FLAGS.compile_s + step / FLAGS.steps_per_s
        # The first chunk at or past the budget, as the timed run would stop, unless the
        # recipe ends before it.
        needed = FLAGS.steps_per_s * (FLAGS.budget_s - FLAGS.compile_s)
        c.train.num_steps = min(recipe_steps, max(math.ceil(needed / chunk - 1e-9), 1) * chunk)
    else:  # timed: the loop's own clock, until the budget is spent or the recipe ends
        def clock(step, train_s):
            return train_s
        c.train.num_steps = recipe_steps
    next_eval = [FLAGS.eval_every_s]

    def should_evaluate(step, train_s):
        """At the first chunk at or past each multiple of ``eval_every_s`` of the clock."""
        t = clock(step, train_s)
        if t < next_eval[0]:
            return False
        next_eval[0] = (math.floor(t / FLAGS.eval_every_s) + 1) * FLAGS.eval_every_s
        return True

    c.train.eval_every_steps = c.train.eval_every_epochs = 0
    hooks = train.Hooks(should_evaluate=should_evaluate, should_stop=None if replay else (
        lambda step, train_s: train_s >= FLAGS.budget_s))
    results = train.train_and_evaluate(c, workdir, hooks)
    records = results["history"] + (
        [] if results["history"] and results["history"][-1]["step"] == results["final"]["step"]
        else [results["final"]])
    curve = [dict(step=r["step"], mpjpe=r["mpjpe"], stress=r["stress"],
                  t=clock(r["step"], r["train_s"]),
                  train_s=r["train_s"]) for r in records]
    for point in curve:
        logging.info("%s", point)
    rate, compile_s = ((FLAGS.steps_per_s, FLAGS.compile_s) if replay
                       else rate_and_compile(workdir, results["final"]))
    if FLAGS.save_variables:
        os.makedirs(os.path.dirname(os.path.abspath(FLAGS.save_variables)), exist_ok=True)
        with open(FLAGS.save_variables, "wb") as f:
            f.write(flax.serialization.msgpack_serialize(jax.device_get(load(workdir).variables)))
    return dict(
        dataset=name,
        recipe=recipe,
        seed=FLAGS.seed,
        data_seed=FLAGS.data_seed,
        mode="replay" if replay else "wall",
        budget_s=FLAGS.budget_s,
        recipe_steps=recipe_steps,  # the run's last point is its final model when reached
        ended=results["final"]["step"] >= recipe_steps,
        steps_per_s=rate,
        compile_s=compile_s,
        n_train=len(train_data),
        n_test=len(test_data),
        n_keypoints=train_data.n_keypoints,
        protocol=protocol,
        cameras=FLAGS.cameras,
        views_per_frame=FLAGS.views_per_frame,
        baselines=baseline_scores(train_data, test_data, protocol, c.model.shape_basis_size),
        curve=curve,
        config=_recorded(json.loads(c.to_json_best_effort())),
        devices=str(jax.devices()),
        cpu_affinity=len(os.sched_getaffinity(0)),
        machine=machine(),
    )


def _recorded(config: dict) -> dict:
    """The run's config as the result records it: its view files named relative to the
    repository when they lie inside it (``runner.repo_path``), not by this checkout's path."""
    for key in ("train_path", "test_path"):
        if config["data"].get(key):
            config["data"][key] = repo_path(config["data"][key])
    return config


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
    run_main(main)

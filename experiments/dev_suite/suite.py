"""The development suite: every dataset, several seeds, one table.

Each run is the command a user types (``python -m c3dpo_jax.main --config=configs/own_json.py``
on JSON files made by the library's importer), so the numbers are what the CLI gives::

  python experiments/dev_suite/suite.py                       # default recipe, 3 seeds, all data
  python experiments/dev_suite/suite.py --variant=canon10:loss.w_canonicalization=10
  python experiments/dev_suite/suite.py --datasets=deepmimic,cmu131 --seeds=0 --report_only
  python experiments/dev_suite/suite.py --rescore=inference.refine_iters=0   # finished runs

Datasets (``--data_root``: the directory holding ``nrsfm/`` and ``mocap/``):

- ``drink face jaws pickup stretch yoga``: ``nrsfm/NAME.npz``, 10 upright cameras per frame,
  test frames in 2 of 10 blocks of the sequence (the importer's defaults);
- ``deepmimic``: ``mocap/deepmimic.npz`` (15 clips, 18 joints) and ``cmu131``:
  ``mocap/cmu131.npz`` (3 clips, 17 joints): 3 upright cameras per frame, test frames in 1 of
  5 blocks of every clip (unseen stretches of each motion);
- ``deepmimic_clips`` (not in the default list): the same views with 3 of the 15 clips held
  out whole (unseen motions);
- ``humans``: the built-in synthetic humans (configs/humans.py's data, protocol ``up3d``);
- ``cmu131_k8``, ``deepmimic_k8``, ``cmu131_k12`` and ``face_k8`` (not in the default
  list): 8 or 12 of the full set's points (the pelvis, knees, ankles, head and wrists, and
  for 12 the hips and elbows; every fifth point of the face), the same frames in each split
  and the same training cameras, for data with far fewer points than the suite's;
- ``deepmimic_v10`` and ``cmu131_v10`` (not in the default list): the same frames and split
  seen by 10 cameras per frame instead of 3;
- ``cmu131_scaled``, ``humans_scaled`` and ``humans_coco_scaled`` (not in the default
  list): every view, 2D points and 3D truth, scaled by its own factor between 0.5 and 2
  (log-uniform): people at different distances;
- ``cmu131_coco`` and ``humans_coco`` (not in the default list): CMU 131's frames and
  split, and the built-in humans, with the people in COCO's 17 keypoints, the common 2D
  detectors' order (the limbs' joints are the same; the nose, eyes and ears are placed on
  the head by ``data.humans.coco_from_h36m``);
- ``humans_limbs`` and ``humans_coco_torso`` (not in the default list): the built-in humans
  with their 12 limb joints only, and in COCO's order with Human3.6M's pelvis, spine,
  thorax and head top added (21 points): which points the humans in COCO's order lack;
- ``humans_v3`` (not in the default list): the built-in humans seen by 3 cameras per pose
  instead of 30, with ten times the people and poses (the same number of views);
  ``humans_noise02`` and ``humans_noise05``: with Gaussian noise of 0.02 or 0.05 m on the 2D
  points (about 4% and 11% of the bodies' RMS radius), as detected keypoints have;
- ``cmu131_noise04`` and ``cmu131_noise11`` (not in the default list): CMU 131's views with
  Gaussian noise of 0.04 or 0.11 on the 2D points (the importer's ``noise``, in units of the
  normalised sequence's RMS radius).

A variant is ``NAME:KEY=VALUE,KEY=VALUE`` (config overrides, e.g.
``optim.lr=1e-3``); ``default`` is the config unchanged. Runs go to
``OUT/runs/VARIANT/DATASET__sSEED`` (a finished run is not run again; an unfinished one
resumes), ``--jobs`` of them at a time, each pinned to one core, in the order seed, dataset,
variant (the order of the flags); a run whose saved config differs from the one the suite
would make now (``--config`` and the variant's overrides: an older variant of the same name,
or one made before the base config changed) stops the suite with a message instead of being
reused or resumed. The table of the datasets
and seeds asked for is printed; ``OUT/VARIANT.md`` gets the table of every finished run of the
variant. It gives per dataset the mean (and spread) over seeds of: the rigid
baseline (the training mean shape, best rigid fit to each view) and zero depth; C3DPO after
2, 5 and 10 minutes of training (each run's own clock: one core, other runs on the other) and
at the end, also without the protocol's per-view depth flip (close to the flipped value when
the depth sign is the same for every view, as a user without 3D ground truth needs) and the
fraction of test views whose canonical shape has the other handedness
(``evaluation.mirrored_fraction``, from the 2D views alone); the best
point of the evaluation curve; the worst seed's final / best ratio (1.0:
no degradation) and the worst seed's baseline / final ratio (> 1: better than the baseline).
"""

import glob
import json
import math
import os
import re
import sys

import numpy as np
from absl import app, flags

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.normpath(os.path.join(HERE, "..", ".."))
sys.path.insert(0, ROOT)
sys.path.insert(0, os.path.join(ROOT, "experiments"))

from runner import cpu_model, is_finished, literal, repo_path, run_all, run_main  # noqa: E402

NRSFM = ("drink", "face", "jaws", "pickup", "stretch", "yoga")
# How the test frames are held out: "blocks" of every clip (unseen stretches of each motion)
# or whole "clips" (unseen motions; not in the default list).
MOCAP = {"deepmimic": "blocks", "cmu131": "blocks", "deepmimic_clips": "clips"}
DATASETS = NRSFM + ("deepmimic", "cmu131", "humans")
# Few-point sets (not in the default list): a full set's views with a subset of its points,
# for data with far fewer points than the suite's (where D nears 3K).
SUBSETS = {"cmu131_k8": ("cmu131", (0, 2, 3, 5, 6, 10, 13, 16)),  # pelvis, knees, ankles,
                                                                   # head, wrists
           "deepmimic_k8": ("deepmimic", (0, 2, 3, 6, 7, 11, 14, 17)),  # the same joints
           "cmu131_k12": ("cmu131", (0, 1, 2, 3, 4, 5, 6, 10, 12, 13, 15, 16)),  # and hips,
                                                                              # elbows
           "face_k8": ("face", tuple(range(0, 40, 5)))}
# More cameras (not in the default list): a motion-capture set's frames, split and held-out
# frames seen by 10 cameras per frame instead of 3 (is the 3-camera protocol what bounds it?).
VIEWS = {"deepmimic_v10": ("deepmimic", 10), "cmu131_v10": ("cmu131", 10)}
# Another joint order (not in the default list): CMU 131's people and the built-in humans in
# COCO's 17 keypoints, the common 2D detectors' (``humans.coco_from_h36m``: the face points
# placed on the head).
ORDERS = {"cmu131_coco": "cmu131", "humans_coco": "humans"}
# People at different distances (not in the default list): every view of a set, 2D points
# and 3D truth, scaled by its own factor, log-uniform in SCALE_RANGE (data seed 0), as the
# people of photographs are seen at sizes a few times apart.
SCALED = {"cmu131_scaled": "cmu131", "humans_scaled": "humans",
          "humans_coco_scaled": "humans_coco"}
SCALE_RANGE = (0.5, 2.0)
# The built-in humans with other points (not in the default list): which of COCO's points
# the humans in its order lack: ``humans_limbs``, the 12 limb joints COCO shares with
# Human3.6M (hips, knees, ankles, shoulders, elbows, wrists; Human3.6M's order);
# ``humans_coco_torso``, COCO's 17 and Human3.6M's pelvis, spine, thorax and head top.
LIMBS = (1, 2, 3, 4, 5, 6, 11, 12, 13, 14, 15, 16)
TORSO = (0, 7, 8, 10)
POINTS = {"humans_limbs": "limbs", "humans_coco_torso": "coco_torso"}
# The built-in humans made otherwise (not in the default list; ``data.humans`` settings of
# configs/humans.py): seen by 3 cameras per pose, as human motion capture often is (ten times
# the poses, the same number of views); with Gaussian noise on the 2D points (metres, the
# bodies' RMS radius about 0.45), as detected keypoints have.
HUMAN_DATA = {"humans_v3": dict(views_per_pose=3, n_train_poses=3000, n_test_poses=500),
              "humans_noise02": dict(noise=0.02), "humans_noise05": dict(noise=0.05)}
# A motion-capture set's views with Gaussian noise on the 2D points (not in the default
# list; the importer's ``noise``, in units of the normalised sequence's RMS radius).
NOISY = {"cmu131_noise04": ("cmu131", 0.04), "cmu131_noise11": ("cmu131", 0.11)}
# The rigid fits of the training mean shape (3D ground truth C3DPO never sees) to each test
# view: one scale for the split (the shape is in the data's units), each view's own scale,
# and the one-shot camera; the suite's bar is the best of them on each dataset.
RIGID_FITS = ("fitted mean shape", "fitted mean shape, per-view scale",
              "fitted mean shape, one-shot camera")
ONE_SHOT = RIGID_FITS[2]
MINUTES = (2, 5, 10)

FLAGS = flags.FLAGS
flags.DEFINE_list("datasets", list(DATASETS), "datasets of the suite to run")
flags.DEFINE_list("seeds", ["0", "1", "2"], "training seeds")
flags.DEFINE_multi_string("variant", [], "NAME:KEY=VALUE,... (config overrides); 'default' "
                          "(no overrides) runs when no variant is given")
flags.DEFINE_string("config", "configs/own_json.py", "the config every run starts from")
flags.DEFINE_string("data_root", os.environ.get("C3DPO_DEV_DATA", ""),
                    "the folder holding nrsfm/NAME.npz and mocap/NAME.npz, the development "
                    "sequences, which are not distributed with the repository (default: "
                    "$C3DPO_DEV_DATA); needed to make a dataset's views the first time")
flags.DEFINE_string("out", os.path.join(HERE, "results"), "where data, runs and tables go")
flags.DEFINE_integer("jobs", 2, "runs at a time (each pinned to one core)")
flags.DEFINE_integer("eval_every_steps", 1000, "test evaluations along the curve")
flags.DEFINE_bool("report_only", False, "only print the tables of the runs already made")
flags.DEFINE_list("rescore", [], "KEY=VALUE,... (config overrides, e.g. of inference.*): score "
                  "each finished run asked for again from its latest checkpoint with them "
                  "(--mode=eval: its final scores replaced, its curve kept), then tabulate")


def parse_variant(text: str) -> tuple[str, list[str]]:
    """``"name:a.b=1,c.d=x"`` -> ``("name", ["a.b=1", "c.d=x"])``."""
    name, _, rest = text.partition(":")
    # Split at commas that start the next KEY=, so tuple values such as (2000,4000) stay whole.
    overrides = [item for item in re.split(r",(?=[\w.]+=)", rest) if item]
    for item in overrides:
        if "=" not in item:
            raise app.UsageError(f"variant {name!r}: {item!r} is not KEY=VALUE")
    return name, overrides


def _same(saved, asked) -> bool:
    """Whether a value of a run's config.json (JSON: tuples as lists) is the expected one."""
    if isinstance(saved, (list, tuple)) and isinstance(asked, (list, tuple)):
        return len(saved) == len(asked) and all(map(_same, saved, asked))
    if isinstance(saved, bool) or isinstance(asked, bool):
        return saved is asked
    if isinstance(saved, (int, float)) and isinstance(asked, (int, float)):
        return math.isclose(saved, asked, rel_tol=1e-9)
    return saved == asked


def _flat(tree: dict, prefix: str = "") -> dict:
    """``{"a.b": value}`` for every leaf of nested dicts."""
    out = {}
    for key, value in tree.items():
        if isinstance(value, dict):
            out.update(_flat(value, f"{prefix}{key}."))
        else:
            out[prefix + key] = value
    return out


def base_config() -> dict:
    """``--config``'s config (file and arguments; a relative path from the repository's
    root, where the runs are made), flattened."""
    from c3dpo_jax import cli

    path = FLAGS.config.partition(":")[0]
    rooted = os.path.join(ROOT, FLAGS.config)
    spec = rooted if not os.path.isabs(path) and os.path.exists(os.path.join(ROOT, path)) \
        else FLAGS.config
    return _flat(cli.get_config(spec).to_dict())


def expected_config(base: dict, data: dict, overrides: list[str], seed) -> dict:
    """The flattened config a run of the suite is made with: ``base`` (``base_config``), the
    settings ``command`` passes, then the variant's overrides (the data paths, and the input
    scale, the scaling of each view and the handedness resolved from the data, left out)."""
    config = dict(base)
    config.update({"data.protocol": data["protocol"], "model.n_keypoints": data["n_keypoints"],
                   "seed": int(seed), "train.progress_bar": False,
                   "train.eval_every_steps": FLAGS.eval_every_steps})
    for item in overrides:
        key, _, text = item.partition("=")
        config[key] = literal(text)
    for key in ("data.train_path", "data.test_path"):
        config.pop(key, None)
    if config.get("model.keypoint_rescale") == 0:  # resolved from the training data
        config.pop("model.keypoint_rescale")
    if config.get("inference.handedness_reference") == "auto":  # the same, with its
        config.pop("inference.handedness_reference")  # one handedness setting
        config.pop("inference.one_handedness", None)
    if config.get("model.keypoint_scaling") == "auto":  # the same
        config.pop("model.keypoint_scaling")
    return config


def config_mismatches(workdir: str, expected: dict) -> list[str]:
    """``KEY: SAVED, not EXPECTED`` for each setting the run in ``workdir`` was made with
    otherwise than ``expected`` (``expected_config``) says. Settings its config.json does
    not record (added after the run) are not judged; no config.json, no mismatch."""
    path = os.path.join(workdir, "config.json")
    if not os.path.exists(path):
        return []
    with open(path) as f:
        saved = _flat(json.load(f))
    return [f"{key}: {json.dumps(saved[key])}, not {json.dumps(value)}"
            for key, value in expected.items()
            if key in saved and not _same(saved[key], value)]


def make_data(name: str, data_root: str, out: str) -> dict:
    """Writes the dataset's train/test JSON once; returns paths, K and protocol."""
    from c3dpo_jax.data import humans, importers, json_dataset, load_splits
    from configs import humans as humans_config

    paths = {s: os.path.join(out, "data", f"{name}_{s}.json") for s in ("train", "test")}
    info_path = os.path.join(out, "data", f"{name}.json")
    if not all(os.path.exists(p) for p in (info_path, *paths.values())):
        base = SCALED.get(name, name)
        if _built_in_humans(base):
            data_config = humans_config.get_config().data
            data_config.humans.update(HUMAN_DATA.get(base, {}))
            train, test = load_splits(data_config)
            if base in ORDERS:
                train, test = (_coco_people(d) for d in (train, test))
            elif base in POINTS:
                train, test = (_human_points(d, POINTS[base]) for d in (train, test))
            protocol = "up3d"
        else:
            full, points, views, noise = _source(base)
            folder = "nrsfm" if full in NRSFM else "mocap"
            if name not in {*DATASETS, *MOCAP, *SUBSETS, *VIEWS, *ORDERS, *SCALED, *POINTS,
                            *HUMAN_DATA, *NOISY}:
                raise ValueError(f"no dataset {name!r} in the suite (its datasets: the module "
                                 "docstring, --helpfull)")
            if not data_root:
                raise ValueError(f"{name}'s views are not made yet, and --data_root (or "
                                 "$C3DPO_DEV_DATA), the folder holding nrsfm/ and mocap/, is "
                                 "not given")
            path = os.path.join(data_root, folder, f"{full.removesuffix('_clips')}.npz")
            if not os.path.exists(path):
                raise ValueError(f"{path} does not exist (--data_root)")
            x = importers.load_sequence(path)
            kw = {} if full in NRSFM else dict(
                views_per_frame=views, clip=importers.load_clips(path),
                hold_out=MOCAP.get(full, "blocks"), n_blocks=5)
            if noise:
                kw["noise"] = noise
            if points is not None:
                x = x[:, list(points)]
            if base in ORDERS:
                x = humans.coco_from_h36m(x).astype(x.dtype)
            train, test = importers.views_from_sequence(x, seed=0, name=name, **kw)
            protocol = "default"
        if name in SCALED:
            train, test = (_scaled(d, seed) for d, seed in ((train, 0), (test, 1)))
        os.makedirs(os.path.dirname(info_path), exist_ok=True)
        for split, data in (("train", train), ("test", test)):
            json_dataset.save(data, paths[split])
        info = dict(n_keypoints=train.n_keypoints, protocol=protocol, n_train=len(train),
                    n_test=len(test))
        with open(info_path, "w") as f:
            json.dump(info, f)
    with open(info_path) as f:
        return dict(json.load(f), **paths)


def _coco_people(data):
    """The built-in humans' views in COCO's joint order: the 3D truth through
    ``humans.coco_from_h36m``, the 2D points its projection (the generator's views are
    orthographic and noiseless), each face point shown where the head is."""
    import dataclasses

    from c3dpo_jax.data import humans

    kp3d = humans.coco_from_h36m(data.kp3d).astype(data.kp3d.dtype)
    return dataclasses.replace(data, kp=kp3d[..., :2].copy(), kp3d=kp3d,
                               vis=humans.coco_visibility_from_h36m(data.vis))


def _human_points(data, points: str):
    """The built-in humans' views (Human3.6M's order) with ``POINTS``' other points:
    "limbs", the joints ``LIMBS``; "coco_torso", ``_coco_people``'s 17 and the joints
    ``TORSO``."""
    import dataclasses

    import numpy as np

    if points == "limbs":
        j = list(LIMBS)
        return dataclasses.replace(data, kp=data.kp[:, j], kp3d=data.kp3d[:, j],
                                   vis=data.vis[:, j])
    coco = _coco_people(data)
    t = list(TORSO)
    return dataclasses.replace(coco, kp=np.concatenate([coco.kp, data.kp[:, t]], 1),
                               kp3d=np.concatenate([coco.kp3d, data.kp3d[:, t]], 1),
                               vis=np.concatenate([coco.vis, data.vis[:, t]], 1))


def _built_in_humans(base: str) -> bool:
    """Whether a suite dataset (``SCALED``'s base) is made from the built-in humans."""
    return ORDERS.get(base, base) == "humans" or base in POINTS or base in HUMAN_DATA


def _source(base: str):
    """``(sequence, points, views per frame, 2D noise)`` of a suite dataset made from a
    sequence (``SCALED``'s base): ``NOISY``, ``SUBSETS``, ``VIEWS`` and ``ORDERS`` resolved
    to the sequence's name (views per frame: the mocap sets'; the sequences use the
    importer's 10)."""
    full, noise = NOISY.get(base, (base, 0.0))
    full, points = SUBSETS.get(full, (full, None))
    full, views = VIEWS.get(full, (full, 3))
    return ORDERS.get(full, full), points, views, noise


def views_per_frame(name: str) -> int:
    """How many consecutive views of a suite dataset show one frame (one pose)."""
    base = SCALED.get(name, name)
    if _built_in_humans(base):
        return HUMAN_DATA.get(base, {}).get("views_per_pose", 30)  # configs/humans.py's 30
    full, _, views, _ = _source(base)
    return 10 if full in NRSFM else views


def _scaled(data, seed: int):
    """``data`` with each view's 2D points and 3D truth times its own factor, log-uniform in
    ``SCALE_RANGE``."""
    import dataclasses

    import numpy as np

    low, high = np.log(SCALE_RANGE)
    s = np.exp(np.random.default_rng(seed).uniform(low, high, len(data)))[:, None, None]
    return dataclasses.replace(data, kp=(data.kp * s).astype(data.kp.dtype),
                               kp3d=(data.kp3d * s).astype(data.kp3d.dtype))


def run_config(name: str, seed: int):
    """The config of a suite run made in-process (``--config`` on the dataset's files, the
    seed, ``--eval_every_steps``, no progress bar): what ``command`` gives the CLI."""
    import importlib.util

    info = make_data(name, FLAGS.data_root, FLAGS.out)
    spec = importlib.util.spec_from_file_location("suite_config", os.path.join(ROOT, FLAGS.config))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    c = module.get_config()
    c.data.train_path, c.data.test_path = info["train"], info["test"]
    c.data.protocol, c.model.n_keypoints = info["protocol"], info["n_keypoints"]
    c.seed = seed
    c.train.progress_bar = False
    c.train.eval_every_steps = FLAGS.eval_every_steps
    return c, info


def run_dir(out: str, variant: str, dataset: str, seed) -> str:
    return os.path.join(out, "runs", variant, f"{dataset}__s{seed}")


def command(data: dict, overrides: list[str], seed, workdir: str) -> list[str]:
    """The CLI call of one run."""
    args = [sys.executable, "-m", "c3dpo_jax.main", f"--config={FLAGS.config}",
            f"--workdir={workdir}", "--nofigures",
            f"--config.data.train_path={repo_path(data['train'])}",
            f"--config.data.test_path={repo_path(data['test'])}",
            f"--config.data.protocol={data['protocol']}",
            f"--config.model.n_keypoints={data['n_keypoints']}",
            f"--config.seed={seed}", "--config.train.progress_bar=False",
            f"--config.train.eval_every_steps={FLAGS.eval_every_steps}"]
    return args + [f"--config.{item}" for item in overrides]


def at_minutes(history: list[dict], final: dict, minutes: float) -> float:
    """Test MPJPE of the last evaluation made within ``minutes`` of training (the final one
    when the run ended sooner); NaN when none was."""
    if final.get("train_s", np.inf) <= minutes * 60:
        return final["mpjpe"]
    made = [h["mpjpe"] for h in history if h.get("train_s", np.inf) <= minutes * 60]
    return made[-1] if made else float("nan")


def baseline_scores(name: str, out: str) -> dict[str, float]:
    """Test MPJPE of the baselines of ``inference.evaluate_baselines`` (the best rigid fit of the
    training mean shape, zero depth) on a suite dataset, cached with the hash of the
    baselines' source so that a change of ``c3dpo_jax.baselines`` recomputes them."""
    import hashlib
    import inspect

    from c3dpo_jax import baselines, evaluation, inference
    from c3dpo_jax.data import json_dataset

    digest = hashlib.sha1(inspect.getsource(baselines).encode()).hexdigest()[:12]
    path = os.path.join(out, "data", f"{name}_baselines.json")
    if os.path.exists(path):
        with open(path) as f:
            cached = json.load(f)
        if cached.get("source") == digest:
            return cached["mpjpe"]
    data = make_data(name, FLAGS.data_root, out)
    train_data, test = json_dataset.load(data["train"]), json_dataset.load(data["test"])
    res = inference.evaluate_baselines(train_data, test, data["protocol"])
    scores = {k: v["mpjpe"] for k, v in res.items()}
    one_shot = baselines.fit_mean_shape(baselines.procrustes_mean_shape(train_data.kp3d),
                                        test.kp, test.vis, n_iters=0)
    scores[ONE_SHOT] = evaluation.evaluate(one_shot, test, data["protocol"])["mpjpe"]
    with open(path, "w") as f:
        json.dump({"source": digest, "mpjpe": scores}, f)
    return scores


def summarise(workdir: str, base: dict[str, float]) -> dict:
    with open(os.path.join(workdir, "eval_results.json")) as f:
        res = json.load(f)
    curve = [h["mpjpe"] for h in res["history"]] + [res["final"]["mpjpe"]]
    final = res["final"]["mpjpe"]
    row = {f"{m} min": at_minutes(res["history"], res["final"], m) for m in MINUTES}
    row.update(end=final, no_flip=res["final"]["mpjpe_orig"], best=min(curve),
               global_=res["final"].get("mpjpe_global", min(res["final"]["mpjpe_orig"],
                                                            res["final"]["mpjpe_flip"])),
               mirrored=res["final"].get("mirrored", float("nan")),  # runs before it: "-"
               final_over_best=final / min(curve),
               steps=res["final"]["step"], train_s=res["final"].get("train_s", float("nan")),
               baseline=min(base[k] for k in RIGID_FITS), zero_depth=base["zero depth"])
    # The bar is the best of the rigid fits (the best 2D fit is not always the best 3D).
    row["baseline_over_final"] = row["baseline"] / final
    row["baseline_over_global"] = row["baseline"] / row["global_"]
    return row


def _fmt(values: list[float]) -> str:
    values = [v for v in values if np.isfinite(v)]
    if not values:
        return "-"
    mean = float(np.mean(values))
    digits = 4 if mean < 0.1 else 3
    if len(values) == 1:
        return f"{mean:.{digits}f}"
    return f"{mean:.{digits}f} ± {float(np.std(values)):.{digits}f}"


def table(out: str, variant: str, datasets, seeds) -> str:
    head = ["dataset", "seeds", "rigid baseline", "zero depth",
            *(f"{m} min" for m in MINUTES),
            "end, up to one mirror (mpjpe_global)", "end, per-view flip (the paper's mpjpe)",
            "end, as it is", "global / paper's (worst seed)", "mirrored (2D only)",
            "best on curve", "final / best (worst seed)",
            "rigid / global (worst seed)", "rigid / paper's (worst seed)", "steps, train min"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for d in datasets:
        done = [w for s in seeds if is_finished(w := run_dir(out, variant, d, s))]
        if not done:
            continue
        base = baseline_scores(d, out)
        rows = [summarise(w, base) for w in done]
        col = {k: [r[k] for r in rows] for k in rows[0]}
        cells = [d, str(len(rows)), _fmt(col["baseline"][:1]), _fmt(col["zero_depth"][:1]),
                 *(_fmt(col[f"{m} min"]) for m in MINUTES), _fmt(col["global_"]),
                 _fmt(col["end"]), _fmt(col["no_flip"]),
                 f"{max(g / e for g, e in zip(col['global_'], col['end'])):.2f}",
                 _fmt(col["mirrored"]), _fmt(col["best"]),
                 f"{max(col['final_over_best']):.2f}",
                 f"{min(col['baseline_over_global']):.2f}x",
                 f"{min(col['baseline_over_final']):.2f}x",
                 f"{int(np.mean(col['steps']))}, {np.mean(col['train_s']) / 60:.1f}"]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def finished(out: str, variant: str) -> tuple[list[str], list[str]]:
    """The datasets (the suite's order, then others by name) and seeds of the variant's
    finished runs."""
    names = [os.path.basename(w).rpartition("__s")
             for w in glob.glob(os.path.join(out, "runs", variant, "*__s*")) if is_finished(w)]
    found = {d for d, _, _ in names}
    datasets = [d for d in DATASETS if d in found] + sorted(found - set(DATASETS))
    return datasets, sorted({s for _, _, s in names}, key=int)


def provenance() -> str:
    """How a table was made: the command, this machine's CPU and the software."""
    import jax

    command = " ".join(["python experiments/dev_suite/suite.py", *sys.argv[1:]])
    return (f"Made by `{command}` on {os.cpu_count()} cores of {cpu_model()}, jax "
            f"{jax.__version__}, "
            f"{FLAGS.jobs} runs at a time, one core each.")


def main(argv):
    del argv
    variants = [parse_variant(v) for v in FLAGS.variant] or [("default", [])]
    os.makedirs(FLAGS.out, exist_ok=True)
    if not FLAGS.report_only:
        data = {d: make_data(d, FLAGS.data_root, FLAGS.out) for d in FLAGS.datasets}
        # Seed, then dataset, then variant: a screen of several variants that is stopped
        # early has compared all of them on the first datasets and seeds asked for.
        jobs, base = [], base_config()
        for seed in FLAGS.seeds:
            for d in FLAGS.datasets:
                for name, overrides in variants:
                    workdir = run_dir(FLAGS.out, name, d, seed)
                    wrong = config_mismatches(workdir,
                                          expected_config(base, data[d], overrides, seed))
                    if wrong:  # made from another config (an older variant of the same name)
                        raise app.UsageError(
                            f"{os.path.relpath(workdir, FLAGS.out)} was made with another config "
                            f"than variant {name!r} asks ({'; '.join(wrong[:3])}): give the "
                            "variant another name")
                    if FLAGS.rescore and is_finished(workdir):
                        jobs.append((workdir, command(data[d], overrides + FLAGS.rescore,
                                                     seed, workdir) + ["--mode=eval"]))
                    elif not is_finished(workdir) and not FLAGS.rescore:
                        jobs.append((workdir, command(data[d], overrides, seed, workdir)))
        run_all(jobs, FLAGS.jobs, FLAGS.out)
    for name, overrides in variants:
        header = f"### {name}" + (f" ({', '.join(overrides)})" if overrides else "")
        if not os.path.isdir(os.path.join(FLAGS.out, "runs", name)):
            print(f"\n{header}: no runs under {os.path.join(FLAGS.out, 'runs', name)}")
            continue
        if not FLAGS.report_only:
            # The file holds every finished run of the variant, not only those asked for now,
            # so that a run on a few datasets or seeds does not shrink the variant's table;
            # --report_only prints and writes nothing (a variant named without its overrides
            # would lose them from the file's header).
            with open(os.path.join(FLAGS.out, f"{name}.md"), "w") as f:
                f.write(f"{header}\n\n{provenance()}\n\n"
                        + table(FLAGS.out, name, *finished(FLAGS.out, name)) + "\n")
        print(f"\n{header}\n\n{table(FLAGS.out, name, FLAGS.datasets, FLAGS.seeds)}")
    missing = [w for w in glob.glob(os.path.join(FLAGS.out, "runs", "*", "*"))
               if not is_finished(w)]
    if missing:
        print(f"\nunfinished runs (see their log.txt): {len(missing)}")


if __name__ == "__main__":
    run_main(main)

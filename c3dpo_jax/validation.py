"""Config values checked before anything is loaded, compiled or written.

``check_config(config)`` raises one ``ValueError`` whose message is a single line naming
every field out of range and the range it must lie in, e.g.
``config.train.batch_size=0 (must be an integer >= 1)``. The entry points call it first,
so a bad value never surfaces as a ``ZeroDivisionError``, a shape error inside JAX, a
half-written checkpoint or a failure at the first evaluation minutes later.

``config`` is anything with ``to_dict()`` (a ``ConfigDict``) or a nested dict; fields it
does not have are not checked (older configs, subsets built by experiments).

Training and scoring also refuse, each in one line, a ``--workdir`` that is a file
(``check_workdir_is_a_folder``) and, once the splits are loaded, keypoint counts that
disagree (``check_split_keypoints``) or a split without what the model or the loss needs
(``check_data``).
"""

import dataclasses
import math
import os
from typing import Any

import numpy as np

from c3dpo_jax import lift, losses, model, state
from c3dpo_jax.data import KeypointData

# Evaluation protocols (``evaluation.evaluate``) and "none": no 3D scores.
PROTOCOLS = ("default", "up3d", "h36m", "pascal3d", "none")
OPTIMIZERS = ("sgd", "adam", "adamw")  # state.make_optimizer
MATMUL_PRECISIONS = (
    "default",
    "bfloat16",
    "tensorfloat32",
    "float32",
    "high",
    "highest",
    "bfloat16_3x",
)  # model.matmul_precision


@dataclasses.dataclass(frozen=True)
class Range:
    """Numbers from ``lo`` to ``hi`` (either end may be open or absent); ``integer``
    excludes non-integral values (and booleans)."""

    lo: int | float | None = None
    hi: int | float | None = None
    lo_open: bool = False
    hi_open: bool = False
    integer: bool = False
    why: str = ""  # said after the range in the message

    def __contains__(self, value: Any) -> bool:
        if isinstance(value, bool) or not isinstance(value, int | float):
            return False
        if self.integer and not float(value).is_integer():
            return False
        if not math.isfinite(value):
            return False
        if self.lo is not None and (value <= self.lo if self.lo_open else value < self.lo):
            return False
        return self.hi is None or (value < self.hi if self.hi_open else value <= self.hi)

    def __str__(self) -> str:
        kind = "an integer" if self.integer else "a finite number"
        lo = None if self.lo is None else f"{'>' if self.lo_open else '>='} {self.lo:g}"
        hi = None if self.hi is None else f"{'<' if self.hi_open else '<='} {self.hi:g}"
        text = f"{kind} {lo} and {hi}" if lo and hi else f"{kind} {lo or hi}" if lo or hi else kind
        return f"{text}: {self.why}" if self.why else text


@dataclasses.dataclass(frozen=True)
class OneOf:
    options: tuple[str, ...]

    def __contains__(self, value: Any) -> bool:
        return value in self.options

    def __str__(self) -> str:
        return "one of " + ", ".join(repr(o) for o in self.options)


POSITIVE_INT = Range(lo=1, integer=True)
COUNT = Range(lo=0, integer=True)
POSITIVE = Range(lo=0, lo_open=True)
NON_NEGATIVE = Range(lo=0)
ANGLE = Range(lo=0, hi=math.pi)

# Field -> allowed values. Each field is checked only when the config has it.
RULES: dict[str, Range | OneOf] = {
    "seed": Range(lo=0, hi=2**32 - 1, integer=True),
    "data.protocol": OneOf(PROTOCOLS),
    "data.min_visible": COUNT,
    "data.synthetic.n_keypoints": POSITIVE_INT,
    "data.synthetic.n_modes": POSITIVE_INT,
    "data.synthetic.n_train": POSITIVE_INT,
    "data.synthetic.n_test": POSITIVE_INT,
    "data.synthetic.occlusion": Range(lo=0, hi=1, hi_open=True),
    "data.synthetic.noise": NON_NEGATIVE,
    "data.humans.n_train_poses": POSITIVE_INT,
    "data.humans.n_test_poses": POSITIVE_INT,
    "data.humans.views_per_pose": POSITIVE_INT,
    "data.humans.dense_points": COUNT,
    "data.humans.noise": NON_NEGATIVE,
    "data.categories.n_train": POSITIVE_INT,
    "data.categories.n_test": POSITIVE_INT,
    "data.categories.occlusion": Range(lo=0, hi=1, hi_open=True),
    "model.n_keypoints": POSITIVE_INT,
    "model.shape_basis_size": POSITIVE_INT,
    # The residual blocks' inner width is H // 4.
    "model.n_fully_connected": Range(lo=4, integer=True),
    "model.n_layers": COUNT,
    "model.canonicalization_n_fully_connected": Range(lo=4, integer=True),
    "model.canonicalization_n_layers": COUNT,
    "model.n_rand_samples": POSITIVE_INT,
    "model.n_rand_reflections": COUNT,
    "model.keypoint_norm_type": OneOf(("to_mean", "to_root")),
    "model.root_joint": COUNT,
    "model.keypoint_rescale": NON_NEGATIVE,  # 0: from the training data
    "model.keypoint_scaling": OneOf((*model.KEYPOINT_SCALINGS, "auto")),
    "model.projection_type": OneOf(("orthographic", "perspective")),
    "model.perspective_depth_threshold": POSITIVE,
    "model.depth_offset": Range(),
    "model.z_augment_rot_angle": ANGLE,
    "model.z_equivariance_rot_angle": ANGLE,
    "model.canonicalization_rot_angle": ANGLE,
    "loss.huber_scaling": POSITIVE,
    "loss.reprojection_normalization": OneOf(losses.NORMALIZATIONS),
    "model.weight_init_std": NON_NEGATIVE,
    "model.matmul_precision": OneOf(MATMUL_PRECISIONS),
    "loss.w_reprojection": NON_NEGATIVE,
    "loss.w_canonicalization": NON_NEGATIVE,
    "loss.w_deformation": NON_NEGATIVE,
    "loss.w_supervised": NON_NEGATIVE,
    "loss.w_multiview": NON_NEGATIVE,
    "loss.multiview_views": Range(lo=2, integer=True),
    "optim.optimizer": OneOf(OPTIMIZERS),
    "optim.lr": POSITIVE,
    "optim.momentum": Range(lo=0, hi=1, hi_open=True),
    "optim.weight_decay": NON_NEGATIVE,
    "optim.gamma": POSITIVE,
    "optim.warmup_steps": COUNT,
    "optim.cosine_steps": COUNT,
    # BatchNorm normalises by the batch's statistics: one view alone is its own mean, and
    # trained so the model output garbage of size 1e9 at evaluation.
    "train.batch_size": Range(lo=2, integer=True, why="BatchNorm needs two views or more"),
    "train.samples_per_epoch": POSITIVE_INT,
    "train.epochs": COUNT,
    "train.num_steps": COUNT,  # 0: epochs * samples_per_epoch // batch_size
    "train.log_every": POSITIVE_INT,
    "train.ckpt_every": POSITIVE_INT,
    "train.eval_every_epochs": COUNT,  # 0: final evaluation only
    "train.eval_every_steps": COUNT,
    "train.eval_batch_size": POSITIVE_INT,
}

_MISSING = object()


def _lookup(tree: dict, path: str) -> Any:
    for part in path.split("."):
        if not isinstance(tree, dict) or part not in tree:
            return _MISSING
        tree = tree[part]
    return tree


def _cross_field(cfg: dict) -> list[str]:
    """Rules between fields: one message for each that fails."""

    def get(path: str) -> Any:
        return _lookup(cfg, path)

    problems = []
    n, root = get("model.n_keypoints"), get("model.root_joint")
    if (
        get("model.keypoint_norm_type") == "to_root"
        and isinstance(root, int)
        and isinstance(n, int)
        and not root < n
    ):
        problems.append(f"config.model.root_joint={root} (must be below model.n_keypoints={n})")
    projection = get("model.projection_type")
    for key, kind, rule in (("model.keypoint_scaling", str, model.keypoint_scaling_problem),
                            ("loss.w_supervised", (int, float), losses.supervised_problem)):
        value = get(key)  # settings for orthographic models only
        if isinstance(value, kind) and isinstance(projection, str):
            problem = rule(value, projection)
            problems.append(f"config.{key}={value} ({problem})" if problem else "")
    milestones = get("optim.lr_milestones")
    if milestones is not _MISSING:
        bad = [m for m in milestones or () if m not in COUNT]
        if bad:
            problems.append(
                f"config.optim.lr_milestones={tuple(milestones)} (every milestone "
                f"must be {COUNT}, in epochs)"
            )
    # The schedule's and the ramp's rules belong to their dataclasses, which ask them.
    schedule = get("optim.schedule")
    if schedule is not _MISSING:
        cosine_steps = get("optim.cosine_steps")
        problems.append(state.schedule_problem(schedule,
                                               0 if cosine_steps is _MISSING else cosine_steps))
    for term in losses.RAMPED_TERMS:
        ramp, final = get(f"loss.{term}_ramp"), get(f"loss.w_{term}_final")
        if ramp is not _MISSING:
            problems.append(losses.ramp_problem(ramp, None if final is _MISSING else final,
                                                term))
    weight, views, batch = (get(k) for k in ("loss.w_multiview", "loss.multiview_views",
                                             "train.batch_size"))
    multiview = isinstance(weight, int | float) and weight > 0
    if multiview and isinstance(views, int) and isinstance(batch, int) and views >= 2 and \
            batch % views:
        problems.append(f"config.train.batch_size={batch} (loss.w_multiview > 0 makes batches "
                        f"of groups of loss.multiview_views={views} views: a multiple of "
                        f"{views}, e.g. {batch - batch % views})")
    if multiview and get("data.class_balanced") is True:
        problems.append("config.loss.w_multiview > 0 draws whole frames, not classes: set "
                        "config.data.class_balanced=False")
    problems = [p for p in problems if p]
    if get("train.num_steps") == 0 and get("train.epochs") == 0:
        problems.append(
            "config.train.num_steps=0 and config.train.epochs=0 (nothing to "
            "train: set one of them >= 1)"
        )
    supervised = get("loss.w_supervised")
    if (get("loss.w_reprojection") == 0 and get("loss.w_canonicalization") == 0
            and not (isinstance(supervised, (int, float)) and supervised > 0)):
        problems.append(
            "config.loss.w_reprojection=0 and config.loss.w_canonicalization=0 "
            "(at least one loss weight must be > 0)"
        )
    return problems


def _inference(cfg: dict) -> list[str]:
    """The problems of the config's inference options (``lift.field_problems``, then
    ``lift.problems`` against its model when both are sound; the placeholders resolved from
    the training data allowed), and a model section that sets one of them
    (``model.MOVED_TO_INFERENCE``), each line naming its inference field."""
    section = {k: v for k, v in cfg.get("inference", {}).items() if k in lift.FIELDS}
    problems = [f"config.inference.{p}" for p in lift.field_problems(section)]
    problems += [f"config.model.{old} is now config.inference.{new}"
                 for old, new in model.MOVED_TO_INFERENCE.items() if old in cfg.get("model", {})]
    if problems or "model" not in cfg:
        return problems
    try:
        model_cfg = model.ModelConfig.from_dict(cfg["model"])
    except (TypeError, ValueError):  # the model's own problems are said by RULES
        return problems
    options = lift.InferenceConfig.from_dict(section)
    return [f"config.inference.{p}" for p in lift.problems(options, model_cfg, resolved=False)]


def config_problems(config) -> list[str]:
    """Every problem of ``config``, one ``config.FIELD=VALUE (must be ...)`` line each."""
    cfg = config.to_dict() if hasattr(config, "to_dict") else dict(config)
    problems = []
    for path, allowed in RULES.items():
        value = _lookup(cfg, path)
        if value is not _MISSING and value not in allowed:
            problems.append(f"config.{path}={value!r} (must be {allowed})")
    return problems + _inference(cfg) + _cross_field(cfg)


def check_config(config) -> None:
    """Raises ``ValueError`` with every problem of ``config`` on one line."""
    problems = config_problems(config)
    if problems:
        raise ValueError("invalid config: " + "; ".join(problems))


def check_workdir_is_a_folder(workdir: str) -> None:
    """Refuses a ``--workdir`` that names a file."""
    if os.path.exists(workdir) and not os.path.isdir(workdir):
        raise ValueError(f"the workdir {workdir} is a file; --workdir names a folder (made if "
                         "missing)")


def check_split_keypoints(train_data: KeypointData, test_data: KeypointData,
                          n_keypoints: int) -> None:
    """The splits' keypoint counts, against each other and then the model's: first of all,
    since what is worked out from the data (``resolve.resolve_from_data``) assumes them
    equal."""
    if train_data.n_keypoints != test_data.n_keypoints:
        raise ValueError(
            f"the train split has {train_data.n_keypoints} keypoints and the test split "
            f"{test_data.n_keypoints}: the two files disagree (config.data.train_path and "
            "test_path must hold the same points)")
    if train_data.n_keypoints != n_keypoints:
        raise ValueError(
            f"train split has {train_data.n_keypoints} keypoints but config.model.n_keypoints "
            f"is {n_keypoints}; set --config.model.n_keypoints={train_data.n_keypoints}")


def check_data(data: KeypointData, model_cfg: model.ModelConfig, split: str,
               with_3d: bool = False) -> None:
    """Refuses a split that lacks what the run needs: finite 3D points where the loss
    trains with them (``with_3d``), intrinsics for a perspective model."""
    if with_3d and (data.kp3d is None or not np.all(np.isfinite(data.kp3d))):
        what = "none" if data.kp3d is None else "some that is not finite"
        raise ValueError(f"config.loss.w_supervised > 0 trains with 3D ground truth, and the "
                         f"{split} split has {what} (kp_loc_3d)")
    if model_cfg.projection_type == "perspective" and data.intrinsics is None:
        raise ValueError(f"perspective model but the {split} split has no intrinsics 'K'")

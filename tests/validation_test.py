"""Config validation: every bundled config passes; each bad value is one line naming the
field and its range, before anything is written."""

import importlib
import math
import os
import subprocess
import sys

import numpy as np
import pytest

from c3dpo_jax import evaluation, model, state, validation
from c3dpo_jax.data import KeypointData
from configs import default

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
CONFIG_NAMES = sorted(
    n.removesuffix(".py")
    for n in os.listdir(os.path.join(ROOT, "configs"))
    if n.endswith(".py") and not n.startswith("_")
)


@pytest.mark.parametrize("name", CONFIG_NAMES)
def test_every_bundled_config_is_valid(name):
    module = importlib.import_module(f"configs.{name}")
    if not hasattr(module, "get_config"):  # a helper the dataset configs share
        return
    for arg in (None, "smoke"):
        assert validation.config_problems(module.get_config(arg)) == [], (name, arg)


BAD = [
    ("train.batch_size", 1, "config.train.batch_size=1 (must be an integer >= 2: BatchNorm "
                            "needs two views or more)"),
    ("train.batch_size", -4, "config.train.batch_size=-4 (must be an integer >= 2: BatchNorm "
                             "needs two views or more)"),
    ("train.ckpt_every", 0, "config.train.ckpt_every=0 (must be an integer >= 1)"),
    ("train.eval_batch_size", 0, "config.train.eval_batch_size=0 (must be an integer >= 1)"),
    ("train.num_steps", -5, "config.train.num_steps=-5 (must be an integer >= 0)"),
    ("train.epochs", -1, "config.train.epochs=-1 (must be an integer >= 0)"),
    ("train.samples_per_epoch", -10, "config.train.samples_per_epoch=-10 (must be an integer"),
    ("model.shape_basis_size", 0, "config.model.shape_basis_size=0 (must be an integer >= 1)"),
    ("model.n_keypoints", 0, "config.model.n_keypoints=0 (must be an integer >= 1)"),
    ("loss.huber_scaling", 0.0, "config.loss.huber_scaling=0.0 (must be a finite number > 0)"),
    ("model.projection_type", "fisheye", "(must be one of 'orthographic', 'perspective')"),
    ("optim.lr", -0.001, "config.optim.lr=-0.001 (must be a finite number > 0)"),
    ("optim.lr", 0.0, "config.optim.lr=0.0 (must be a finite number > 0)"),
    ("optim.lr", math.nan, "config.optim.lr=nan (must be a finite number > 0)"),
    ("optim.momentum", 1.5, "config.optim.momentum=1.5 (must be a finite number >= 0 and < 1)"),
    ("optim.optimizer", "lamb",
     "config.optim.optimizer='lamb' (must be one of 'sgd', 'adam', 'adamw')"),
    (
        "data.protocol",
        "h63m",
        "config.data.protocol='h63m' (must be one of 'default', 'up3d', "
        "'h36m', 'pascal3d', 'none')",
    ),
    ("data.min_visible", -1, "config.data.min_visible=-1 (must be an integer >= 0)"),
    ("loss.w_reprojection", -1.0, "config.loss.w_reprojection=-1.0 (must be a finite number"),
]


@pytest.mark.parametrize(("field", "value", "message"), BAD)
def test_each_bad_value_is_named_with_its_range(field, value, message):
    c = default.get_config("smoke")
    section, name = field.split(".")
    c[section][name] = value
    with pytest.raises(ValueError) as err:
        validation.check_config(c)
    text = str(err.value)
    assert message in text and "\n" not in text
    assert text.startswith("invalid config: ")


def test_cross_field_rules():
    c = default.get_config("smoke")
    c.train.num_steps, c.train.epochs = 0, 0
    c.model.keypoint_norm_type, c.model.root_joint, c.model.n_keypoints = "to_root", 17, 17
    c.optim.lr_milestones = (3, -1)
    c.loss.w_reprojection = c.loss.w_canonicalization = 0.0
    problems = validation.config_problems(c)
    assert problems == [
        "config.model.root_joint=17 (must be below model.n_keypoints=17)",
        "config.optim.lr_milestones=(3, -1) (every milestone must be an integer >= 0, in epochs)",
        "config.train.num_steps=0 and config.train.epochs=0 (nothing to train: set one of "
        "them >= 1)",
        "config.loss.w_reprojection=0 and config.loss.w_canonicalization=0 (at least one "
        "loss weight must be > 0)",
    ]
    c.model.root_joint = 16  # the others stay
    assert len(validation.config_problems(c)) == 3


def test_plain_dicts_and_partial_configs_are_checked():
    assert validation.config_problems({"train": {"batch_size": 8}}) == []
    assert validation.config_problems({"train": {"batch_size": True}}) == [
        "config.train.batch_size=True (must be an integer >= 2: BatchNorm needs two views or "
        "more)"
    ]
    assert validation.config_problems({"model": {"n_keypoints": "17"}}) == [
        "config.model.n_keypoints='17' (must be an integer >= 1)"
    ]


def test_range_membership_matches_its_description():
    """Property over edge values: ``v in Range`` is exactly the stated condition."""
    values = [
        -math.inf,
        -2,
        -1,
        -0.5,
        0,
        0.0,
        0.5,
        1,
        1.0,
        2,
        2.5,
        math.inf,
        math.nan,
        True,
        False,
        None,
        "1",
    ]
    rng = np.random.default_rng(0)
    for _ in range(200):
        lo, hi = sorted(rng.choice([-1, 0, 1, 2], 2))
        r = validation.Range(
            lo=float(lo),
            hi=float(hi),
            lo_open=bool(rng.integers(2)),
            hi_open=bool(rng.integers(2)),
            integer=bool(rng.integers(2)),
        )
        for v in values:
            numeric = isinstance(v, int | float) and not isinstance(v, bool)
            expect = (
                numeric
                and math.isfinite(v)
                and (not r.integer or float(v).is_integer())
                and (v > lo if r.lo_open else v >= lo)
                and (v < hi if r.hi_open else v <= hi)
            )
            assert (v in r) == expect, (r, v)


def test_choice_lists_match_the_code_that_uses_them():
    assert sorted(validation.OPTIMIZERS) == sorted(state._OPTIMIZERS)
    assert validation.MATMUL_PRECISIONS == model._PRECISIONS
    rng = np.random.default_rng(0)
    kp3d = rng.normal(size=(2, 3, 3))
    data = KeypointData(kp=kp3d[..., :2], vis=np.ones((2, 3)), kp3d=kp3d)
    for protocol in validation.PROTOCOLS:
        if protocol != "none":
            assert evaluation.evaluate(kp3d, data, protocol)["mpjpe"] == pytest.approx(0.0)
    with pytest.raises(ValueError, match="unknown evaluation protocol"):
        evaluation.evaluate(kp3d, data, "h63m")


def test_cli_reports_bad_values_in_one_line_and_writes_nothing(tmp_path):
    workdir = tmp_path / "run"
    out = subprocess.run(
        [
            sys.executable,
            "-m",
            "c3dpo_jax.main",
            "--config=configs/synthetic.py:smoke",
            f"--workdir={workdir}",
            "--config.train.batch_size=0",
            "--config.train.ckpt_every=0",
            "--config.optim.lr=-1",
            "--config.data.protocol=h63m",
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert out.returncode == 2, out.stderr[-3000:]
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: invalid config: "), out.stderr
    for field in (
        "train.batch_size=0",
        "train.ckpt_every=0",
        "optim.lr=-1.0",
        "data.protocol='h63m'",
    ):
        assert field in lines[0]
    assert not workdir.exists()


def test_schedule_and_ramp_rules():
    c = default.get_config("smoke")
    c.optim.schedule = "cosine"
    c.loss.canonicalization_ramp = (50, 10)
    c.loss.w_canonicalization_final = 3.0
    problems = validation.config_problems(c)
    assert len(problems) == 2
    assert problems[0].startswith("config.optim.cosine_steps must be >= 1")
    assert problems[1].startswith("config.loss.canonicalization_ramp=(50, 10)")
    c.optim.cosine_steps, c.loss.canonicalization_ramp = 100, (10, 50)
    assert validation.config_problems(c) == []
    c.optim.schedule = "linear"
    assert validation.config_problems(c) == [
        "config.optim.schedule='linear' (must be one of 'multistep', 'cosine')"]
    c.optim.schedule = "cosine"
    c.loss.deformation_ramp = (3000, 5000)  # no final weight
    problems = validation.config_problems(c)
    assert len(problems) == 1 and problems[0].startswith(
        "config.loss.deformation_ramp=(3000, 5000) with config.loss.w_deformation_final=None")
    c.loss.w_deformation_final = 0.0
    assert validation.config_problems(c) == []


def test_turns_rules():
    c = default.get_config()
    c.model.z_augment = True
    c.inference.turns = 5
    assert validation.config_problems(c) == []
    c.inference.turns = 4
    c.model.projection_type = "perspective"
    (problem,) = validation.config_problems(c)
    assert problem.startswith("config.inference.turns=4 (must be an odd number and used "
                              "with model.projection_type='orthographic' only")
    c.inference.turns, c.model.projection_type, c.model.z_augment = 3, "orthographic", False
    (problem,) = validation.config_problems(c)
    assert "model.z_augment=True" in problem
    c.inference.turns = 0
    assert validation.config_problems(c) == [
        f"config.inference.turns=0 (must be {validation.POSITIVE_INT})"]
    # Round the circle: any number of copies, no in-plane augmentation needed.
    c.inference.turns, c.inference.turn_span = 4, "circle"
    assert validation.config_problems(c) == []
    # Round the circle and the range: any number of copies, the augmentation's range.
    c.inference.turn_span = "circle_and_range"
    (problem,) = validation.config_problems(c)
    assert "model.z_augment=True" in problem
    c.model.z_augment = True
    assert validation.config_problems(c) == []
    c.inference.turn_span = "spiral"
    assert validation.config_problems(c) == [
        "config.inference.turn_span='spiral' (must be one of 'augmentation', 'circle', "
        "'circle_and_range')"]


def test_an_inference_option_under_its_model_name_names_its_new_field():
    """A dict config (a saved config.json's, a script's) whose model section sets an
    inference option: one line naming its inference field."""
    c = default.get_config().to_dict()
    c["model"]["test_time_refine_iters"] = 0
    assert validation.config_problems(c) == [
        "config.model.test_time_refine_iters is now config.inference.refine_iters"]


ORTHOGRAPHIC_ONLY = [  # field, a value for orthographic models only, its text and value off
    ("inference.refine_iters", 20, "0 (no refinement)", 0),
    ("inference.one_handedness", True, "False", False),
    ("model.keypoint_scaling", "per_view", "'global' or 'auto'", "global"),
    ("loss.w_supervised", 1.0, "0", 0.0),
]


@pytest.mark.parametrize(("field", "value", "off", "off_value"), ORTHOGRAPHIC_ONLY)
def test_orthographic_only_settings_are_refused_with_perspective(field, value, off, off_value):
    c = default.get_config()
    section, name = field.split(".")
    c[section][name] = value
    assert validation.config_problems(c) == []
    c.model.projection_type = "perspective"
    assert validation.config_problems(c) == [
        f"config.{field}={value} (must be {off} for a perspective model: orthographic models "
        "only)"]
    c[section][name] = off_value  # the release's perspective models are untouched
    assert validation.config_problems(c) == []


def test_a_body_reference_needs_its_joint_count_and_an_orthographic_model():
    c = default.get_config()
    c.model.n_keypoints = 20
    c.inference.handedness_reference = "h36m"
    c.inference.one_handedness = True
    assert validation.config_problems(c) == [
        "config.inference.handedness_reference='h36m' (a body of 17 points in its joint "
        "order; the model has 20)"]
    c.model.n_keypoints = 17
    assert validation.config_problems(c) == []
    c.inference.one_handedness = False  # one mirror decision for the whole model
    assert validation.config_problems(c) == []
    c.model.projection_type = "perspective"
    assert validation.config_problems(c) == [
        "config.inference.handedness_reference='h36m' (must be 'mean_shape' for a "
        "perspective model: orthographic models only)"]
    c.model.projection_type = "orthographic"
    c.inference.handedness_reference = "h63m"
    assert validation.config_problems(c) == [
        "config.inference.handedness_reference='h63m' (must be one of 'mean_shape', "
        "'h36m', 'coco', 'body', 'views_mean', 'auto', or a body file (.npy, .json, .txt, .csv))"]
    c.inference.handedness_reference = "my_rig.npy"  # read when training starts
    assert validation.config_problems(c) == []
    c.inference.handedness_reference = "auto"  # resolved from the training data
    assert validation.config_problems(c) == []


def test_refinement_and_supervised_weight_ranges():
    c = default.get_config()
    c.loss.w_reprojection = c.loss.w_canonicalization = 0.0
    c.loss.w_supervised = 1.0  # the truth's term alone is enough to train
    assert validation.config_problems(c) == []
    c.inference.refine_iters, c.inference.refine_prior = -1, -0.5
    c.loss.w_supervised = -1.0
    assert validation.config_problems(c) == [
        f"config.loss.w_supervised=-1.0 (must be {validation.NON_NEGATIVE})",
        f"config.inference.refine_iters=-1 (must be {validation.COUNT})",
        f"config.inference.refine_prior=-0.5 (must be {validation.NON_NEGATIVE})",
        "config.loss.w_reprojection=0 and config.loss.w_canonicalization=0 (at least one "
        "loss weight must be > 0)"]

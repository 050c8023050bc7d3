"""Lifting one view at inference: the options that act there (``InferenceConfig``), their
checks, and the per-example eval forward pass ``forward_eval``.

Glossary: N keypoints, D shape-basis size, A turned copies of a view. Points are rows:
``kp (N, 2)``, ``X (N, 3)``; rotations act as ``X @ R.T`` (see ``so3``).

``forward_eval`` runs Phi with its running BatchNorm statistics (no Psi) and then, as the
options say, refines Phi's camera and coefficients (Levenberg-Marquardt,
``refine_camera_and_shape``), takes the median depth over copies of the view turned
in-plane (``turns``) and gives the view the handedness of a reference (``one_handedness``).
A reference body reaches it as an array (``body``, resolved on the host by
``reference_body``); the options are static. ``inference.forward_batch`` batches it and
``reconstruct.reconstruct`` runs it on a user's keypoints.
"""

import dataclasses
import math
from collections.abc import Mapping
from functools import partial
from typing import Any

import jax
import jax.numpy as jnp
import jax.scipy.linalg
import numpy as np
from jaxtyping import Array, Float

from c3dpo_jax import geometry, model
from c3dpo_jax.data import bodies
from c3dpo_jax.model import ModelConfig, Prediction, Variables
from c3dpo_jax.types import Kp2, Vis

TURN_SPANS = ("augmentation", "circle", "circle_and_range")
# "circle": the copies kept are those whose mean 2D reprojection distance is at most this
# times the lowest of the view's copies (evidence: experiments/dev_suite/inference.md,
# "Turned copies round the circle, chosen by their 2D fit").
TURN_KEEP_RATIO = 1.1
# "circle_and_range": a copy counts as within the augmentation's range up to this many
# radians beyond it (the circle's grid of 32 puts a copy at 2 pi / 16 = 0.39270 rad, the
# release's range being 0.3925).
TURN_RANGE_SLACK = 1e-3
# What the views' handedness can be taken from, with the number of points of the body's
# joint order: the basis' mean shape (None) or a built-in body (``bodies.HUMAN_BODIES``).
HANDEDNESS_REFERENCES = {"mean_shape": None, **bodies.HUMAN_BODIES}
# The references whose points are rows of ``handedness_body``: a user's 3D example, and the
# training views' mean canonical shape (``inference.training_views_mean``).
ROWS_REFERENCES = ("body", "views_mean")
# The inference options that say which handedness a view is given.
HANDEDNESS_FIELDS = ("one_handedness", "handedness_reference", "handedness_body",
                     "handedness_evidence", "handedness_from_output")
# The ways of weighing a shape's handedness against a reference (``evidence``).
HANDEDNESS_EVIDENCE = ("procrustes", "tetrahedra")
# Levenberg-Marquardt's damping: its start, and its factors after a step that lowers the
# cost (accepted) and after one that does not (rejected, the damping raised).
REFINE_DAMPING, REFINE_DAMPING_DOWN, REFINE_DAMPING_UP = 1e-3, 0.3, 10.0


@dataclasses.dataclass(frozen=True)
class InferenceConfig:
    """The options that act when a trained model lifts a view (none changes training);
    the release's inference is the defaults. Checked field by field when made; against a
    model by ``problems`` (``inference_config`` makes and checks one in one call).

    Attributes:
      refine_iters: Levenberg-Marquardt steps that refine Phi's camera rotation and
        shape coefficients for each view (and each turned copy), starting from Phi's, on
        the view's mean squared 2D reprojection distance plus ``refine_prior`` times the
        mean squared distance of the canonical shape's points to Phi's (0: Phi's output,
        as the release; orthographic models only; ``refine_camera_and_shape``; evidence:
        experiments/dev_suite/inference.md, "Refining the regressed camera and
        coefficients at test time").
      refine_prior: the weight of that prior (>= 0).
      refine_handedness: the weight (>= 0) of a third term of that fit, the square of how
        far the canonical shape's handedness evidence against the basis' mean shape
        (``handedness_evidence``) falls below Phi's or ``refine_handedness_margin``,
        whichever is lower: the 2D points do not see a shape's handedness, so without it
        the refinement can carry a view near the boundary over to the other side (0: the
        fit as above; evidence: experiments/dev_suite/handedness.md, "The refinement's
        handedness").
      refine_handedness_margin: the evidence (in (0, 1]) below which that term charges a
        fall (1: any fall below Phi's, which takes from the refinement where it reshapes
        views most).
      turns: copies of each view turned in-plane about its centre whose median depth is
        kept (an orthographic depth does not change under an in-plane turn; 1: one pass,
        as the release; orthographic models only).
      turn_span: where the copies are turned: "augmentation", spread evenly over
        +-``z_augment_rot_angle`` (the training augmentation's range; odd ``turns``,
        models trained with ``z_augment``), all kept; "circle", evenly round the full
        circle, only the copies whose 2D reprojection error is within
        ``TURN_KEEP_RATIO`` of the lowest kept (a copy the network is lost on fits its own
        turned input badly); "circle_and_range", round the circle, the copies "circle"
        keeps and every copy within the augmentation's range.
      one_handedness: give every view the handedness of ``handedness_reference``: a view
        whose canonical shape is, up to a rotation, nearer to the reference's mirror
        image than to the reference is given its mirror image, which fits the 2D points
        equally (``one_handedness``; orthographic models only). Without it, a body
        reference gives the whole model one decision: every view is mirrored, as
        ``one_handedness`` mirrors one, when the basis' mean shape is nearer, up to a
        proper rotation, to the body's mirror image than to the body, and none otherwise
        (the views keep the model's own mix of handednesses, all of them turned to the
        body's side when the model's mean shape is the body's mirror image).
      handedness_reference: "mean_shape" (the basis' mean shape, whose own handedness the
        2D views leave open), a built-in body of ``HANDEDNESS_REFERENCES`` ("h36m",
        "coco": every view gets a real body's handedness, so a model whose mean shape came
        out mirrored still gives the body's), or "body", the body in ``handedness_body``,
        with which each view takes the handedness that the body and the basis' mean shape
        given the body's handedness favour together (``mean_shape_handed_as``,
        ``handedness_evidence``), or "views_mean", the mean canonical shape of the training
        views as the model lifts them, its rows in ``handedness_body`` (training fills them,
        ``inference.training_views_mean``; without ``one_handedness`` the views stay as they are). A
        training config may also hold "auto" (a body whose projections fit the training
        views, else the training views' mean; ``resolve.resolve_handedness``) or a body
        file (``bodies.BODY_FILE_SUFFIXES``), which are resolved before training.
      handedness_body: with "body": one 3D example of the points, N rows of (x, y, z) in
        the model's order, in any position, orientation and scale (a frame of motion
        capture, a rig's rest pose); with "views_mean", that mean shape's rows.
      handedness_evidence: how ``one_handedness`` weighs a view's handedness against the
        reference: "procrustes" (the whole shape: is a proper rotation or a reflection the
        better map onto it) or "tetrahedra" (its small parts: do the tetrahedra of each
        point and its three nearest keep their chirality; ``local_handedness_evidence``).
      handedness_from_output: ``one_handedness`` weighs the output (the input's x, y at
        the visible points, the model's depth: what a view is scored by and a user gets)
        instead of the canonical shape; a view whose canonical shape has the reference's
        handedness can give an output whose depth fits its mirror image better.
      replace_keypoints_with_input: the 3D output's x, y at visible points are the input
        itself (as the release), else the reprojection.
    """

    refine_iters: int = 0
    refine_prior: float = 0.3
    refine_handedness: float = 0.0
    refine_handedness_margin: float = 0.05
    turns: int = 1
    turn_span: str = "augmentation"
    one_handedness: bool = False
    handedness_reference: str = "mean_shape"
    handedness_body: tuple = ()
    handedness_evidence: str = "procrustes"
    handedness_from_output: bool = False
    replace_keypoints_with_input: bool = True

    def __post_init__(self):
        rows = _rows(self.handedness_body)  # hashable rows of floats (JSON gives lists)
        if rows is not None:
            object.__setattr__(self, "handedness_body", rows)
        found = field_problems(dataclasses.asdict(self))
        if found:
            raise ValueError("inference config: " + "; ".join(found))

    @classmethod
    def from_dict(cls, d) -> "InferenceConfig":
        """From a dict or ConfigDict (config.json's "inference" section; the defaults where
        it has no field); unknown keys are an error."""
        d = dict(d)
        unknown = sorted(set(d) - set(FIELDS))
        if unknown:
            raise ValueError(f"unknown inference option(s) {unknown}; known: {list(FIELDS)}")
        if found := field_problems(d):
            raise ValueError("inference config: " + "; ".join(found))
        return cls(**_typed(d))

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


FIELDS = tuple(f.name for f in dataclasses.fields(InferenceConfig))


def _rows(body) -> tuple | None:
    """``body`` as rows of floats, or None when it is not rows of numbers."""
    try:
        return tuple(tuple(float(v) for v in row) for row in np.asarray(body, object))
    except (TypeError, ValueError):
        return None


def _typed(values: Mapping[str, Any]) -> dict[str, Any]:
    """``values`` (fields without ``field_problems``) in their fields' types: numpy numbers
    as Python's, a body's lists (JSON) as rows."""
    types = {f.name: f.type for f in dataclasses.fields(InferenceConfig)}
    return {k: _rows(v) if types[k] is tuple else types[k](v) for k, v in values.items()}


def _is_number(value) -> bool:
    """A real number (not a bool), Python's or numpy's."""
    return not isinstance(value, bool | np.bool_) and isinstance(
        value, int | float | np.integer | np.floating)


def _is_count(value, least: int) -> bool:
    return (not isinstance(value, bool | np.bool_) and isinstance(value, int | np.integer)
            and bool(value >= least))


def field_problems(values: Mapping[str, Any]) -> list[str]:
    """One ``field=value (why)`` line for each option of ``values`` (a dict of the
    ``InferenceConfig``'s fields, the defaults where missing) that is wrong whatever the
    model: a type or range, an unknown name, a body that does not fit its reference."""
    v = {**_DEFAULTS, **values}
    found = [f"{name}={v[name]!r} (must be an integer >= {least})"
             for name, least in (("refine_iters", 0), ("turns", 1))
             if not _is_count(v[name], least)]
    found += [f"{name}={v[name]!r} (must be a finite number >= 0)"
              for name in ("refine_prior", "refine_handedness")
              if not (_is_number(v[name]) and math.isfinite(v[name]) and v[name] >= 0)]
    margin = v["refine_handedness_margin"]
    if not (_is_number(margin) and 0 < margin <= 1):
        found.append(f"refine_handedness_margin={margin!r} (must be a number in (0, 1])")
    if v["turn_span"] not in TURN_SPANS:
        found.append(f"turn_span={v['turn_span']!r} (must be one of "
                     + ", ".join(repr(s) for s in TURN_SPANS) + ")")
    found += [f"{name}={v[name]!r} (must be True or False)"
              for name in ("one_handedness", "handedness_from_output",
                           "replace_keypoints_with_input")
              if not isinstance(v[name], bool | np.bool_)]
    if v["handedness_evidence"] not in HANDEDNESS_EVIDENCE:
        found.append(f"handedness_evidence={v['handedness_evidence']!r} (must be one of "
                     + ", ".join(repr(k) for k in HANDEDNESS_EVIDENCE) + ")")
    reference, body = v["handedness_reference"], v["handedness_body"]
    known = (*HANDEDNESS_REFERENCES, *ROWS_REFERENCES, "auto")
    if not (isinstance(reference, str) and (reference in known or bodies.is_body_file(reference))):
        found.append(f"handedness_reference={reference!r} (must be one of "
                     + ", ".join(repr(k) for k in known) + ", or a body file ("
                     + ", ".join(bodies.BODY_FILE_SUFFIXES) + "))")
    elif _rows(body) is None:
        found.append(f"handedness_body={body!r} (rows of three numbers)")
    elif reference == "body" and not len(body):
        found.append("handedness_body is empty: give its N rows of (x, y, z), or name a body "
                     f"file ({', '.join(bodies.BODY_FILE_SUFFIXES)})")
    elif len(body) and reference not in ROWS_REFERENCES:
        found.append(f"handedness_body is given but handedness_reference is {reference!r}, "
                     "not 'body' or 'views_mean'")
    return found


_DEFAULTS = {f.name: f.default for f in dataclasses.fields(InferenceConfig)}


def problems(options: InferenceConfig, model_cfg: ModelConfig, resolved: bool = True
             ) -> list[str]:
    """One ``field=value (why)`` line for each option of ``options`` that the model
    ``model_cfg`` cannot use (``resolved``: the placeholder "auto" is one too; a training
    config may hold it)."""
    found = []
    if why := _turns_problem(options, model_cfg):
        found.append(f"turns={options.turns} ({why})")
    projection = model_cfg.projection_type
    if why := model.orthographic_only(options.refine_iters > 0, "0 (no refinement)", projection):
        found.append(f"refine_iters={options.refine_iters} ({why})")
    if why := model.orthographic_only(options.one_handedness, "False", projection):
        found.append(f"one_handedness=True ({why})")
    elif why := model.orthographic_only(
            options.handedness_reference not in ("mean_shape", "auto"), "'mean_shape'",
            projection):
        found.append(f"handedness_reference={options.handedness_reference!r} ({why})")
    reference, n = options.handedness_reference, model_cfg.n_keypoints
    if resolved and reference == "auto":
        found.append("handedness_reference='auto' (a training setting, resolved from the "
                     "training views before training, resolve.resolve_handedness; name a "
                     "body or 'mean_shape')")
    elif HANDEDNESS_REFERENCES.get(reference) not in (None, n):
        found.append(f"handedness_reference={reference!r} (a body of "
                     f"{HANDEDNESS_REFERENCES[reference]} points in its joint order; the model "
                     f"has {n})")
    elif (reference == "body" or len(options.handedness_body)) and (
            why := bodies.body_problem(options.handedness_body, n)):
        found.append(f"handedness_body ({why})")
    return found


def _turns_problem(options: InferenceConfig, model_cfg: ModelConfig) -> str:
    """Why the model cannot take ``options.turns`` copies ('' if it can; a single pass
    always can)."""
    if options.turns == 1:
        return ""
    span = options.turn_span
    ranged = span != "circle"  # the training augmentation's range is used
    why = [
        "an odd number" if span == "augmentation" and options.turns % 2 == 0 else "",
        "used with model.projection_type='orthographic' only"
        if model_cfg.projection_type == "perspective" else "",
        f"used with model.z_augment=True and model.z_augment_rot_angle > 0 only (turn_span "
        f"{span!r} uses the training augmentation's range; turn_span='circle' does not)"
        if ranged and (not model_cfg.z_augment or model_cfg.z_augment_rot_angle == 0) else "",
    ]
    return "must be " + " and ".join(w for w in why if w) if any(why) else ""


def inference_config(model_cfg: ModelConfig, base: InferenceConfig | None = None,
                     **overrides) -> InferenceConfig:
    """``base`` (default: the release's inference) with ``overrides`` (each an
    ``InferenceConfig`` field; None keeps base's), checked against the model: a
    ``ValueError`` of one line naming every problem.

    ``handedness_reference`` may also be an (N, 3) array or a body file, read here: the
    reference "body" with those points (as may ``handedness_body``); a body reference given
    without ``one_handedness`` turns it on."""
    base = InferenceConfig() if base is None else base
    unknown = sorted(set(overrides) - set(FIELDS))
    if unknown:
        raise ValueError(f"unknown inference option(s) {unknown}; known: {', '.join(FIELDS)}")
    given = {k: v for k, v in overrides.items() if v is not None}
    reference = given.get("handedness_reference")
    if reference is not None and not (isinstance(reference, str)
                                      and not bodies.is_body_file(reference)):
        given["handedness_reference"], given["handedness_body"] = "body", reference
    if "handedness_body" in given:
        body = given["handedness_body"]
        if bodies.is_body_file(body):
            body = reference_body(body)
        given["handedness_body"] = body if _rows(body) is None else _rows(body)
        given.setdefault("handedness_reference", "body")
    if "handedness_reference" in given:
        if given["handedness_reference"] != "body":
            given.setdefault("handedness_body", ())
        # A body to take the handedness from turns one handedness on.
        given.setdefault("one_handedness", given["handedness_reference"] != "mean_shape"
                         or base.one_handedness)
    values = {**base.to_dict(), **given}
    found = field_problems(values)
    if not found:
        options = InferenceConfig(**_typed(values))
        found = problems(options, model_cfg)
    if found:
        raise ValueError("; ".join(found))
    return options


def saved_options(config: Mapping) -> dict[str, Any]:
    """The inference options a saved config (config.json as a dict) holds: its
    "inference" section, or, in a config whose model section holds them, those under
    their names there (``model.MOVED_TO_INFERENCE``); options it does not hold are left
    out (a run made before an option used its default)."""
    if "inference" in config:
        return dict(config["inference"])
    section = config.get("model", {})
    return {new: section[old] for old, new in model.MOVED_TO_INFERENCE.items() if old in section}


def reference_body(reference, body=()) -> np.ndarray | None:
    """The (N, 3) body, on the host, that ``handedness_reference=reference`` names:
    None for "mean_shape", ``body`` for "body", a built-in body for its name
    (``bodies.human_body``), a body file's (``bodies.read_body``) or an array's points."""
    if not isinstance(reference, str):
        return np.asarray(reference, np.float64)
    if bodies.is_body_file(reference):
        return bodies.read_body(reference)
    if reference in ROWS_REFERENCES:
        return np.asarray(body, np.float64)
    if reference == "auto":
        raise ValueError("handedness_reference='auto' means 'from the training data' and was "
                         "not resolved (resolve.resolve_handedness(config, train_data), as "
                         "train_and_evaluate does; a loaded model has it)")
    if HANDEDNESS_REFERENCES[reference] is None:
        return None
    return bodies.human_body(reference)


def options_body(options: InferenceConfig) -> np.ndarray | None:
    """``forward_eval``'s ``body`` for ``options``, float32 (None: none is used)."""
    if options.handedness_reference == "views_mean" and not len(options.handedness_body):
        raise ValueError("handedness_reference='views_mean' has no rows in handedness_body: "
                         "the training views' mean canonical shape is written when a run "
                         "ends (inference.training_views_mean); finish the run, or give "
                         "handedness_reference='mean_shape' or a body")
    body = reference_body(options.handedness_reference, options.handedness_body)
    return None if body is None else np.asarray(body, np.float32)


def without_handedness(options: InferenceConfig) -> InferenceConfig:
    """``options`` giving the views the model's own handedness: the handedness settings'
    defaults (the mean shape's reference, no ``one_handedness``, no rows)."""
    return dataclasses.replace(options, **{k: _DEFAULTS[k] for k in HANDEDNESS_FIELDS})


def static_options(options: InferenceConfig) -> InferenceConfig:
    """``options`` as a compiled function's static argument: without the training views'
    mean rows, which reach it as the ``body`` array (so that new rows, at each evaluation
    of a run, do not compile it again)."""
    if options.handedness_reference != "views_mean":
        return options
    return dataclasses.replace(options, handedness_body=())


def turn_angles(options: InferenceConfig, cfg: ModelConfig) -> Float[Array, " A"]:
    """The ``turns - 1`` nonzero in-plane angles of the turned copies: pairs +-a spread
    evenly up to ``z_augment_rot_angle`` ("augmentation"), or steps of 2 pi / ``turns``
    round the circle ("circle", "circle_and_range")."""
    if options.turn_span != "augmentation":
        return 2 * jnp.pi * jnp.arange(1, options.turns) / options.turns
    k = (options.turns - 1) // 2
    half = cfg.z_augment_rot_angle * jnp.arange(1, k + 1) / k
    return jnp.concatenate([half, -half])


def turns_in_range(options: InferenceConfig, cfg: ModelConfig) -> np.ndarray:
    """(``turns``,) bool, static: which copies of "circle_and_range" (the view itself
    first, then ``turn_angles``) are turned by at most ``z_augment_rot_angle`` plus
    ``TURN_RANGE_SLACK``, either way round."""
    turned_by = 2 * np.pi * np.arange(options.turns) / options.turns
    off = np.abs(np.remainder(turned_by + np.pi, 2 * np.pi) - np.pi)
    return off <= cfg.z_augment_rot_angle + TURN_RANGE_SLACK


def own_handedness(shapes, handedness_flipped):
    """Shapes ``(..., N, 3)`` of a ``Prediction`` with the mirroring of ``one_handedness``
    undone (the third axis negated where ``handedness_flipped``, shape ``(...)``): the
    model's own ``shape_canonical``, and its own camera-frame or input-coordinate depths up
    to their offset; numpy or jax arrays alike."""
    flipped = handedness_flipped[..., None, None] > 0
    return shapes * (1.0 - 2.0 * (flipped & (np.arange(3) == 2)))


def mean_shape_handed_as(net, params, class_mask, body):
    """The basis' mean shape, mirrored (third axis negated) when it is nearer, up to a
    proper rotation, to the mirror image of ``body`` (N, 3) than to the body. A user's body
    (``handedness_reference="body"``) is one example in one pose, which the views of other
    poses may not resemble; the mean shape, the model's typical pose, may. So a view weighs
    both (``one_handedness`` with the two references)."""
    mean = model.mean_shape(net, params, class_mask)
    return mean * jnp.where(_nearer_mirror(mean, body, class_mask),
                            jnp.array([1.0, 1.0, -1.0]), 1.0)[None]


def _nearer_mirror(x, reference, class_mask):
    """Whether the best orthogonal map of the centred shape ``x`` onto ``reference`` is a
    reflection (det of their cross-covariance < 0): ``x`` is nearer, up to a proper
    rotation, to the reference's mirror image than to the reference."""
    return jnp.linalg.det(model.class_centred(x, class_mask).T
                          @ model.class_centred(reference, class_mask)) < 0


def handedness_evidence(x, reference, class_mask, floor=0.0):
    """How much better a proper rotation than a reflection maps the shape ``x`` (N, 3) onto
    ``reference``: ``(r_mirror - r_proper) / (r_mirror + r_proper)`` of the two Procrustes
    residuals of the centred, unit-size shapes, in [-1, 1] (negative: nearer the mirror
    image)."""
    a, b = (model.class_centred(y, class_mask) for y in (x, reference))
    a, b = (y / jnp.maximum(jnp.linalg.norm(y), 1e-12) for y in (a, b))
    cov = a.T @ b
    sigma = jnp.linalg.svd(cov, compute_uv=False)
    third = jnp.sign(jnp.linalg.det(cov)) * sigma[2]
    proper, mirror = (jnp.sqrt(jnp.maximum(2.0 - 2.0 * (sigma[0] + sigma[1] + sign * third),
                                           floor)) for sign in (1.0, -1.0))
    return (mirror - proper) / jnp.maximum(mirror + proper, 1e-12)


def _tetrahedra(reference, class_mask):
    """(N, 4) point indices: each point of ``reference`` (N, 3) and its three nearest points
    of the class there, and (N,) 1.0 where all four are the class's points, else 0.0."""
    n = reference.shape[0]
    inside = class_mask > 0
    d = jnp.sum((reference[:, None] - reference[None]) ** 2, -1)
    d = jnp.where(inside[None] & ~jnp.eye(n, dtype=bool), d, jnp.inf)
    _, near = jax.lax.top_k(-d, 3)
    tetra = jnp.concatenate([jnp.arange(n)[:, None], near], 1)
    return tetra, jnp.all(inside[tetra], 1).astype(reference.dtype)


def _signed_volumes(x, tetra, floor):
    """(T,) each tetrahedron's signed volume over the product of its three edges from its
    first point (the sine-like chirality of its corner, in [-1, 1])."""
    edges = x[tetra[:, 1:]] - x[tetra[:, :1]]
    lengths = jnp.sqrt(jnp.sum(edges ** 2, -1) + floor)
    return jnp.linalg.det(edges) / jnp.maximum(jnp.prod(lengths, -1), 1e-12)


def local_handedness_evidence(x, reference, class_mask, floor=0.0):
    """How much the shape ``x`` (N, 3) keeps the chirality of ``reference``'s small
    tetrahedra, each point with its three nearest points there: the sum over them of the
    reference's signed volume times ``x``'s (each over the product of its edges) over the
    sum of the reference's absolute ones, in [-1, 1] (negative: nearer the mirror image).
    Unchanged by a rotation or a scale of ``x``, negated by its mirror image. Unlike
    ``handedness_evidence`` it reads local parts (a torso, a foot), which keep their
    chirality when the pose as a whole turns far from the reference's (evidence:
    experiments/dev_suite/handedness.md, "Local handedness")."""
    tetra, inside = _tetrahedra(reference, class_mask)
    w = _signed_volumes(reference, tetra, 0.0) * inside
    return jnp.sum(w * _signed_volumes(x, tetra, floor)) / jnp.maximum(jnp.sum(jnp.abs(w)),
                                                                        1e-12)


def evidence(kind: str):
    """The evidence function ``(x, reference, class_mask, floor=0.0) -> [-1, 1]`` that
    ``kind`` (one of ``HANDEDNESS_EVIDENCE``) names."""
    return {"procrustes": handedness_evidence,
            "tetrahedra": local_handedness_evidence}[kind]


def one_handedness(net, params, x_cam, t, x_canon, rot, theta, class_mask, reference=None,
                   kind="procrustes", judged=None):
    """``(x_cam, x_canon, rot, theta)`` of one view, mirrored when its canonical shape
    ``x_canon`` is nearer, up to a proper rotation, to the mirror image of ``reference``
    (N, 3), by default the basis' mean shape, than to the reference itself (``kind``
    "procrustes": the best orthogonal map from one centred shape onto the other is then a
    reflection, det of their cross-covariance < 0; comparing the two Procrustes residuals
    says the same), or when its small tetrahedra take the chirality of the reference's
    mirror image (``kind`` "tetrahedra": ``local_handedness_evidence`` < 0). With a tuple
    of references, mirrored when the sum of their evidence of that kind is negative.
    ``judged``: the shape (N, 3) weighed instead of ``x_canon`` (the output's, with
    ``handedness_from_output``). The mirror image: the camera-frame depth reflected about
    the translation's (``t``; an orthographic view's 2D points unchanged), the canonical
    shape's third axis negated and the rotation conjugated by that reflection (``theta``'s
    first two components negated), so that ``scale * x_canon @ rot.T + t`` is still
    ``x_cam``. Also returns 1.0 where the view was mirrored, else 0.0."""
    if reference is None:
        reference = model.mean_shape(net, params, class_mask)
    shape = x_canon if judged is None else judged
    if isinstance(reference, tuple):
        mirrored = sum(evidence(kind)(shape, r, class_mask) for r in reference) < 0
    elif kind == "tetrahedra":
        mirrored = local_handedness_evidence(shape, reference, class_mask) < 0
    else:
        mirrored = _nearer_mirror(shape, reference, class_mask)
    return mirror_if(mirrored, x_cam, t, x_canon, rot, theta)


def mirror_if(mirrored, x_cam, t, x_canon, rot, theta):
    """``(x_cam, x_canon, rot, theta, flag)`` of one view, its mirror image where
    ``mirrored`` (a bool scalar) as ``one_handedness`` describes it, and 1.0 there, else
    the view as it is and 0.0."""
    flip = jnp.where(mirrored, jnp.array([1.0, 1.0, -1.0]), 1.0)
    x_cam = (x_cam - t[None]) * flip[None] + t[None]
    theta = theta * jnp.where(mirrored, jnp.array([-1.0, -1.0, 1.0]), 1.0)  # log of F R F
    return (x_cam, x_canon * flip[None], flip[:, None] * rot * flip[None], theta,
            mirrored.astype(x_cam.dtype))


def refine_camera_and_shape(cfg: ModelConfig, options: InferenceConfig, net, params, phi_out,
                            kp_norm, vis, class_mask):
    """Phi's output ``phi_out`` with its ``theta`` and ``alpha`` refined for one view:
    ``options.refine_iters`` Levenberg-Marquardt steps from Phi's values on the mean
    squared 2D distance of the reprojected visible points to ``kp_norm`` plus
    ``options.refine_prior`` times the mean squared distance of the canonical shape's
    points (those of ``class_mask``) to Phi's canonical shape plus
    ``options.refine_handedness`` times the square of how far the canonical shape's
    handedness evidence against the basis' mean shape falls below Phi's or
    ``options.refine_handedness_margin``, whichever is lower. Scale and
    translation stay Phi's. A step that does not lower the cost is not taken (the damping
    rises instead), so the cost never rises above Phi's."""
    x_phi = model.canonical_shape(net, params, phi_out["alpha"], class_mask)
    w2d = jnp.sqrt(vis / jnp.maximum(jnp.sum(vis), 1.0))[:, None]
    w3d = jnp.sqrt(options.refine_prior * class_mask
                   / jnp.maximum(jnp.sum(class_mask), 1.0))[:, None]
    keep_handedness = options.refine_handedness > 0  # static: none of the term's cost at 0
    if keep_handedness:
        # floor=1e-8: a finite derivative where a shape fits the mean shape exactly
        evidence = partial(handedness_evidence, reference=model.mean_shape(
            net, params, class_mask), class_mask=class_mask, floor=1e-8)
        least = jnp.minimum(evidence(x_phi), options.refine_handedness_margin)  # free above

    def residuals(p):
        out = dict(phi_out, theta=p[:3], alpha=p[3:])
        x_canon = model.canonical_shape(net, params, out["alpha"], class_mask)
        x_cam, t, _ = model.camera_frame(cfg, out, x_canon)
        proj, _, _ = model.reproject(cfg, x_cam + t[None], kp_norm, vis)
        terms = [((proj - kp_norm) * w2d).ravel(), ((x_canon - x_phi) * w3d).ravel()]
        if keep_handedness:
            terms.append(jnp.sqrt(options.refine_handedness) * jax.nn.relu(
                least - evidence(x_canon))[None])
        return jnp.concatenate(terms)

    def step(carry, _):
        p, damping = carry
        # One pass gives the residuals and their Jacobian (the residuals as jacfwd's aux).
        jac, r = jax.jacfwd(lambda q: (lambda v: (v, v))(residuals(q)), has_aux=True)(p)
        normal = jac.T @ jac
        # Marquardt's scaling, floored so that a direction the cost does not see (a hidden
        # view's rotation, an unused basis vector) still gets a damped, finite step.
        # The damped normal matrix is symmetric positive definite: Cholesky, not LU.
        delta = jax.scipy.linalg.cho_solve(jax.scipy.linalg.cho_factor(
            normal + damping * jnp.diag(jnp.diag(normal) + 1e-9)), -jac.T @ r)
        # False for a NaN step: it is not taken.
        lower = jnp.sum(residuals(p + delta) ** 2) < jnp.sum(r**2)
        return (jnp.where(lower, p + delta, p),
                damping * jnp.where(lower, REFINE_DAMPING_DOWN, REFINE_DAMPING_UP)), None

    start = jnp.concatenate([phi_out["theta"], phi_out["alpha"]])
    (p, _), _ = jax.lax.scan(step, (start, jnp.asarray(REFINE_DAMPING)), None,
                             length=options.refine_iters)
    return dict(phi_out, theta=p[:3], alpha=p[3:])


def _phi_eval(cfg, options, net, variables, kp_norm, vis, class_mask):
    """Phi's eval-mode output for one view, refined when ``refine_iters`` > 0."""
    out = net.apply(variables, kp_norm, vis, False, method="phi")
    if options.refine_iters > 0:
        out = refine_camera_and_shape(cfg, options, net, variables["params"], out, kp_norm,
                                      vis, class_mask)
    return out


def _turned_depth(cfg, options, net, variables, kp_norm, vis, class_mask, x_cam):
    """The median depth (N,) over the view (camera-frame shape ``x_cam``) and its copies
    turned in-plane by ``turn_angles``, each copy's depth about its visible mean with its
    sign matched to the unturned view's ("circle": over the copies whose mean 2D
    reprojection distance to their own turned input is within ``TURN_KEEP_RATIO`` of the
    lowest; "circle_and_range": those and every copy within ``z_augment_rot_angle`` (plus
    ``TURN_RANGE_SLACK``) of the view), then the unturned mean depth added back."""
    w = vis / jnp.maximum(jnp.sum(vis), 1.0)

    def centred_depth_and_fit(x, kp_in):
        _, depth, dist_sq = model.reproject(cfg, x, kp_in, vis)
        return depth - jnp.sum(w * depth), jnp.sum(w * jnp.sqrt(dist_sq))

    centred, fit = centred_depth_and_fit(x_cam, kp_norm)

    def copy(angle):
        c, s = jnp.cos(angle), jnp.sin(angle)
        turned = kp_norm @ jnp.array([[c, s], [-s, c]])
        out = _phi_eval(cfg, options, net, variables, turned, vis, class_mask)
        x, t, _ = model.camera_frame(cfg, out, model.canonical_shape(
            net, variables["params"], out["alpha"], class_mask))
        d, f = centred_depth_and_fit(x + t[None], turned)
        return jnp.where(jnp.sum(w * d * centred) < 0, -d, d), f

    depths, fits = jax.vmap(copy)(turn_angles(options, cfg))
    depths = jnp.concatenate([centred[None], depths])
    if options.turn_span != "augmentation":
        fits = jnp.concatenate([fit[None], fits])
        keep = fits <= TURN_KEEP_RATIO * jnp.min(fits)
        if options.turn_span == "circle_and_range":
            keep = keep | turns_in_range(options, cfg)
        median = jnp.nanmedian(jnp.where(keep[:, None], depths, jnp.nan), axis=0)
    else:
        median = jnp.median(depths, axis=0)
    return median + (x_cam[:, 2] - centred)


def _handed(cfg, options, net, params, body, x_cam, t, x_canon, rot, theta, class_mask,
            kp_norm, vis):
    """The view given the handedness that ``options`` ask for, with the flag of
    ``mirror_if``: view by view (``one_handedness``), or, without it and with a body
    reference, the whole model's (every view mirrored when the basis' mean shape is nearer,
    up to a proper rotation, to the body's mirror image than to the body); the view as it
    is, flag 0, when they ask for none. ``kp_norm``, ``vis``: the view's normalised input,
    the output's x, y at the visible points (``handedness_from_output``)."""
    reference = None  # the mean shape
    if options.handedness_reference != "mean_shape":
        if body is None:
            raise ValueError(f"handedness_reference={options.handedness_reference!r} needs "
                             "its body: pass lift.options_body(options)")
        reference = jnp.asarray(body)
    if not options.one_handedness:
        if reference is None or options.handedness_reference == "views_mean":
            return x_cam, x_canon, rot, theta, jnp.zeros((), x_cam.dtype)
        mean = model.mean_shape(net, params, class_mask)
        return mirror_if(_nearer_mirror(mean, reference, class_mask), x_cam, t, x_canon, rot,
                         theta)
    if options.handedness_reference == "body":  # the example and the mean shape
        reference = (reference, mean_shape_handed_as(net, params, class_mask, reference))
    judged = None
    if options.handedness_from_output:
        judged = x_cam.at[:, :2].set(jnp.where(vis[:, None] > 0, kp_norm, x_cam[:, :2]))
    return one_handedness(net, params, x_cam, t, x_canon, rot, theta, class_mask, reference,
                          options.handedness_evidence, judged)


@model.under_precision
def forward_eval(
    variables: Variables,
    kp: Kp2,
    vis: Vis,
    class_mask: Float[Array, " N"],
    intrinsics: Float[Array, "3 3"] | None,
    body: Float[Array, "N 3"] | None,
    cfg: ModelConfig,
    options: InferenceConfig,
) -> Prediction:
    """Eval-mode reconstruction of one example (running BatchNorm statistics, no Psi) with
    the inference ``options``; ``body``: the reference body that they name
    (``options_body``), None for none. The fields of the ``Prediction`` are documented
    there. Options the model cannot use (``problems``) raise a ``ValueError`` while
    tracing."""
    if found := problems(options, cfg):
        raise ValueError("; ".join(found))
    net = model.make_network(cfg)
    params = variables["params"]
    kp_cal, kp_norm, centre, scale = model.normalised_input(cfg, kp, vis, intrinsics)
    phi_out = _phi_eval(cfg, options, net, variables, kp_norm, vis, class_mask)
    x_canon = model.canonical_shape(net, params, phi_out["alpha"], class_mask)
    x_cam, t, rot = model.camera_frame(cfg, phi_out, x_canon)
    x_cam = x_cam + t[None]
    if options.turns > 1:
        x_cam = x_cam.at[:, 2].set(_turned_depth(cfg, options, net, variables, kp_norm, vis,
                                                 class_mask, x_cam))
    x_cam, x_canon, rot, theta, flipped = _handed(cfg, options, net, params, body, x_cam, t,
                                                  x_canon, rot, phi_out["theta"], class_mask,
                                                  kp_norm, vis)
    proj, depth, dist_sq = model.reproject(cfg, x_cam, kp_norm, vis)
    reproj_image = geometry.unnormalise_keypoints(proj, centre, scale)
    image_xy = reproj_image
    if options.replace_keypoints_with_input:
        image_xy = jnp.where(vis[:, None] > 0, kp_cal, reproj_image)
    shape_3d = jnp.concatenate([image_xy, depth[:, None] / scale], axis=1)
    if cfg.projection_type == "perspective":
        # Reprojections back to pixels; shape_3d stays in calibrated units.
        reproj_image = geometry.uncalibrate(reproj_image, intrinsics)
    return Prediction(
        shape_3d=shape_3d,
        shape_camera=x_cam,
        shape_canonical=x_canon,
        rotation=rot,
        theta=theta,
        alpha=phi_out["alpha"],
        translation=t,
        scale=phi_out["scale"],
        kp_reprojected=reproj_image,
        kp_norm=kp_norm,
        kp_mean=centre,
        kp_scale=scale,
        dist_sq=dist_sq,
        handedness_flipped=flipped,
    )

"""C3DPO's objective: every loss term, its options, its reduction and its weight.

Glossary: B batch, N keypoints, S canonicalisation samples. The per-example forward
(``model.forward_train``, vmapped over the batch) returns geometry: squared distances
per point. This module owns the rest, with its options in ``LossConfig``: the penalty of
each point (pseudo-Huber, ``huber``, or the plain square), the one explicit
masked reduction of each term (so the normalisation is written down in one place), the
weights, and the objective ``make_loss_fn`` that the train step differentiates.

Paper: eq. 4 (l1, reprojection), eq. 5 (l2, canonicalisation), eq. 6 (l3, the
reprojection loss with the shape coefficients of an in-plane rotated copy).
"""

import dataclasses
from functools import partial

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from c3dpo_jax import geometry, lift, model, so3

__all__ = ["LossConfig", "canonicalisation", "canonicalisation_per_sample", "deformation",
           "draw_rotations", "huber", "make_loss_fn", "reprojection", "supervised"]


def huber(dist_sq: Float[Array, "*S"], scaling: float) -> Float[Array, "*S"]:
    """Pseudo-Huber of a squared distance: ``(sqrt(1 + d2/eps^2) - 1) * eps``.

    Written on the squared distance so its gradient is finite at a perfect fit
    (the norm itself is not differentiable at 0), and in the algebraically equal form
    ``d2 / (eps (sqrt(1 + d2/eps^2) + 1))``, which has no cancellation for tiny
    residuals in float32.
    """
    return dist_sq / (scaling * (jnp.sqrt(1.0 + dist_sq / scaling**2) + 1.0))


def reprojection(
    repro: Float[Array, "B N"], vis: Float[Array, "B N"], normalization: str
) -> Float[Array, ""]:
    """Masked mean of per-point reprojection errors over the batch.

    ``kp_total_count`` divides the sum over all visible points of the batch by their
    number (the release's default); ``kp_count_per_image`` averages each image over its
    own visible points first, then averages the images (the release crashes on this
    option; here it works).
    """
    masked = jnp.where(vis > 0, repro * vis, 0.0)  # a hidden point's inf never becomes NaN
    if normalization == "kp_total_count":
        return jnp.sum(masked) / jnp.maximum(jnp.sum(vis), 1.0)
    if normalization == "kp_count_per_image":
        return jnp.mean(jnp.sum(masked, axis=1) / jnp.maximum(jnp.sum(vis, axis=1), 1.0))
    raise ValueError(f"unknown reprojection_normalization {normalization!r}")


def canonicalisation_per_sample(
    dist_sq: Float[Array, "B S N"], class_mask: Float[Array, "B N"], huber_scaling: float
) -> Float[Array, "B S"]:
    """Eq. 5 per example and rotation: the pseudo-Huber penalty of each point's squared
    distance, averaged over the points of the example's class."""
    return jax.vmap(jax.vmap(geometry.masked_mean, in_axes=(0, None)))(
        huber(dist_sq, huber_scaling), class_mask)


def canonicalisation(canon: Float[Array, "B S"]) -> Float[Array, ""]:
    """Mean over examples and random rotations of the per-sample point means."""
    if canon.shape[-1] == 0:
        return jnp.zeros(())
    return jnp.mean(canon)


def multiview(x_canon: Float[Array, "B N 3"], class_mask: Float[Array, "B N"], views: int,
              scaling: float) -> Float[Array, ""]:
    """Mean over views of the mean, over the class's points, of the pseudo-Huber penalty of
    each point's squared distance from its group's mean canonical shape; the batch is
    ``B / views`` groups of ``views`` consecutive views of one frame."""
    groups = x_canon.reshape(-1, views, *x_canon.shape[1:])
    dist_sq = jnp.sum((groups - jnp.mean(groups, axis=1, keepdims=True)) ** 2, axis=-1)
    return jnp.mean(jax.vmap(geometry.masked_mean)(huber(dist_sq.reshape(x_canon.shape[:2]),
                                                         scaling), class_mask))


def handedness(x_canon: Float[Array, "B N 3"], mean_shape: Float[Array, "B N 3"],
               class_mask: Float[Array, "B N"], margin: float = 0.0,
               kind: str = "procrustes") -> Float[Array, ""]:
    """Mean over examples of how far each canonical shape falls short of ``margin`` in its
    handedness evidence against the mean shape (held fixed; ``kind``: ``lift.evidence``'s
    "procrustes", how much better a proper rotation than a reflection maps it onto the mean
    shape, or "tetrahedra", how much its small tetrahedra keep the mean shape's chirality):
    zero for a shape of the mean shape's handedness by the margin, positive for one nearer
    the mean shape's mirror image."""
    evidence = jax.vmap(partial(lift.evidence(kind), floor=1e-8))(
        x_canon, jax.lax.stop_gradient(mean_shape), class_mask)
    return jnp.mean(jax.nn.relu(margin - evidence))


def views_mean(x_canon: Float[Array, "B N 3"], class_mask: Float[Array, "B N"]
               ) -> Float[Array, "N 3"]:
    """Each point's mean canonical position over the examples whose class has it (held
    fixed): the batch's typical shape, which the basis' mean shape (coefficients 0) need
    not be."""
    return jax.lax.stop_gradient(geometry.point_means(x_canon, class_mask))


def supervised_problem(weight: float, projection_type: str) -> str:
    """'' or why ``w_supervised`` cannot be ``weight`` with ``projection_type`` (the camera
    frame's depth is compared up to a shift: orthographic models only)."""
    return model.orthographic_only(weight > 0, "0", projection_type)


def supervised(sup_dist_sq: Float[Array, "B N"], class_mask: Float[Array, "B N"]
               ) -> Float[Array, ""]:
    """Mean over examples of the mean, over the class's points, of each point's distance to
    the 3D ground truth (the square root taken here, with a floor that keeps its gradient
    finite at a perfect fit)."""
    return jnp.mean(jax.vmap(geometry.masked_mean)(jnp.sqrt(sup_dist_sq + 1e-12), class_mask))


def deformation(deform_sq: Float[Array, "B N"], class_mask: Float[Array, "B N"]
                ) -> Float[Array, ""]:
    """Mean over examples of the mean, over the class's points, of each point's squared
    distance to the mean shape."""
    return jnp.mean(jax.vmap(geometry.masked_mean)(deform_sq, class_mask))


NORMALIZATIONS = ("kp_total_count", "kp_count_per_image")
# What the handedness term weighs each canonical shape against: the basis' mean shape or
# the mean canonical shape of the batch's views (``views_mean``).
HANDEDNESS_PROTOTYPES = ("basis_mean", "views_mean")
# The weights that may ramp (``{term}_ramp``, ``w_{term}_final``).
RAMPED_TERMS = ("canonicalization", "deformation", "handedness")


def ramp_problem(ramp, final, term: str = "canonicalization") -> str | None:
    """What is wrong with the ramp of a loss weight (``term``: ``canonicalization`` or
    ``deformation``) and its final weight (None: nothing), one line; ``LossConfig`` raises
    it and ``validation`` lists it."""
    if not ramp:
        return None
    if (len(ramp) != 2 or any(not isinstance(r, int) or isinstance(r, bool) or r < 0
                              for r in ramp)
            or ramp[0] > ramp[1] or not isinstance(final, (int, float)) or not final >= 0):
        return (f"config.loss.{term}_ramp={tuple(ramp)} with "
                f"config.loss.w_{term}_final={final} (the ramp is (first_step, "
                "last_step), 0 <= first <= last, and the final weight a number >= 0)")
    return None


def _ramped(first_weight, final_weight, ramp, step):
    """The weight at ``step`` (a scalar, traced or not) of a linear ramp from
    ``first_weight`` at step ``ramp[0]`` to ``final_weight`` at ``ramp[1]``; constant
    without a ramp."""
    if not ramp:
        return first_weight
    first, last = ramp
    step = jnp.asarray(step, jnp.float32)
    frac = jnp.clip((step - first) / (last - first), 0.0, 1.0) if last > first else (
        (step >= first).astype(jnp.float32))
    return first_weight + frac * (final_weight - first_weight)


@dataclasses.dataclass(frozen=True)
class LossConfig:
    """The objective ``w_reprojection * l_repro + w_canonicalization * l_canon +
    w_deformation * l_deform`` and the options of its terms (the release's names; the
    release keeps them with the model).

    ``w_deformation`` (0: the paper's objective, which has no such term) weights the mean
    squared distance of the canonical shape's points to the mean shape: a Gaussian prior on
    the deformations, as EM-SfM's, which charges a view for any deformation its 2D points
    do not ask for (depth the reprojection leaves free included).

    ``huber_scaling``: epsilon of the pseudo-Huber penalty of both terms;
    ``squared_reprojection_loss``: the plain squared distance in the reprojection term
    instead; ``reprojection_normalization``: ``kp_total_count`` or ``kp_count_per_image``
    (see ``reprojection``). ``canonicalization_ramp=(first, last)`` (steps) moves the
    canonicalisation weight linearly from ``w_canonicalization`` at step ``first`` to
    ``w_canonicalization_final`` at step ``last`` (``first == last``: a jump); empty: the
    weight is constant. ``deformation_ramp`` and ``w_deformation_final`` do the same for
    the deformation prior's weight.

    ``w_supervised`` (0: C3DPO, which never sees 3D) weights the mean distance of the
    camera-frame shape's points to the training views' 3D ground truth (both centred): the
    same network trained with the truth, the reference of what one view's points allow
    (evidence: experiments/dev_suite/results.md). Its training split needs 3D points.

    ``w_multiview`` (0: C3DPO, which lifts each view alone) weights the agreement of the
    canonical shapes of views that show one pose at one instant (cameras filming together:
    the training split's ``frame`` ids): each batch is made of groups of
    ``multiview_views`` views of one frame, and the term is the pseudo-Huber penalty of each
    view's squared point distances from its group's mean canonical shape. Not in the paper
    (evidence: experiments/dev_suite/data_variants.md, "Multi-view training data")."""

    w_reprojection: float = 1.0
    w_canonicalization: float = 1.0
    w_canonicalization_final: float | None = None
    canonicalization_ramp: tuple[int, ...] = ()
    w_deformation: float = 0.0
    w_deformation_final: float | None = None
    deformation_ramp: tuple[int, ...] = ()
    w_supervised: float = 0.0
    huber_scaling: float = 0.01
    reprojection_normalization: str = "kp_total_count"
    squared_reprojection_loss: bool = False
    w_multiview: float = 0.0
    multiview_views: int = 3
    w_handedness: float = 0.0
    w_handedness_final: float | None = None
    handedness_ramp: tuple[int, ...] = ()
    handedness_margin: float = 0.0
    handedness_evidence: str = "procrustes"
    handedness_prototype: str = "basis_mean"

    def __post_init__(self):
        if self.handedness_evidence not in lift.HANDEDNESS_EVIDENCE:
            raise ValueError(f"unknown handedness_evidence {self.handedness_evidence!r}; "
                             f"known: {lift.HANDEDNESS_EVIDENCE}")
        if self.handedness_prototype not in HANDEDNESS_PROTOTYPES:
            raise ValueError(f"unknown handedness_prototype {self.handedness_prototype!r}; "
                             f"known: {HANDEDNESS_PROTOTYPES}")
        if self.reprojection_normalization not in NORMALIZATIONS:
            raise ValueError(f"unknown reprojection_normalization "
                             f"{self.reprojection_normalization!r}; known: {NORMALIZATIONS}")
        for term in RAMPED_TERMS:
            ramp = getattr(self, f"{term}_ramp")
            problem = ramp_problem(ramp, getattr(self, f"w_{term}_final"), term)
            if problem:
                raise ValueError(problem)
            object.__setattr__(self, f"{term}_ramp", tuple(int(s) for s in ramp))

    def penalty(self, dist_sq):
        """The reprojection term of each point from its squared distance (eq. 4)."""
        return dist_sq if self.squared_reprojection_loss else huber(dist_sq, self.huber_scaling)

    def canonicalization_weight(self, step):
        """The canonicalisation weight at ``step`` (a scalar, traced or not)."""
        return _ramped(self.w_canonicalization, self.w_canonicalization_final,
                       self.canonicalization_ramp, step)

    def handedness_weight(self, step):
        """The handedness term's weight at ``step`` (a scalar, traced or not)."""
        return _ramped(self.w_handedness, self.w_handedness_final, self.handedness_ramp, step)

    def deformation_weight(self, step):
        """The deformation prior's weight at ``step`` (a scalar, traced or not)."""
        return _ramped(self.w_deformation, self.w_deformation_final, self.deformation_ramp,
                       step)


def draw_rotations(key: jax.Array, cfg: model.ModelConfig) -> model.TrainRotations:
    """The random rotations of one training example: the in-plane augmentation, the
    equivariance copy's in-plane rotation (eq. 6) and Psi's ``n_rand_samples`` rotations
    (eq. 5; any rotation, uniform on SO(3), when ``canonicalization_rot_angle`` is pi: the
    release's axis-angle draw with a uniform angle is not uniform)."""
    k_aug, k_eq, k_canon = jax.random.split(key, 3)
    r_aug = (so3.in_plane_rotation(k_aug, cfg.z_augment_rot_angle) if cfg.z_augment
             else jnp.eye(2))
    r_eq = (so3.in_plane_rotation(k_eq, cfg.z_equivariance_rot_angle) if cfg.z_equivariance
            else jnp.eye(2))
    if cfg.canonicalization:
        angle = cfg.canonicalization_rot_angle
        max_angle = None if angle >= jnp.pi else angle
        rots = jax.vmap(lambda k: so3.random_rotation(k, max_angle))(
            jax.random.split(k_canon, cfg.n_rand_samples))
        if cfg.n_rand_reflections:  # uniform on O(3)'s other half: a rotation times a mirror
            # (a key of its own, so that the rotations are the same as without reflections)
            refl = jax.vmap(lambda k: so3.random_rotation(k, max_angle))(jax.random.split(
                jax.random.fold_in(k_canon, 1), cfg.n_rand_reflections))
            rots = jnp.concatenate([rots, refl * jnp.array([1.0, 1.0, -1.0])])
    else:
        rots = jnp.zeros((0, 3, 3))
    return model.TrainRotations(augment=r_aug, equivariance=r_eq, canonicalisation=rots)


def make_loss_fn(model_cfg: model.ModelConfig, loss_cfg: LossConfig):
    """``loss_fn(params, batch_stats, batch, key, step=0) -> (objective, (batch_stats,
    metrics))``; ``step`` only matters for the ramped weights.

    ``batch`` holds ``kp`` (B, N, 2), ``vis`` (B, N) and ``class_mask`` (B, N) (ones for
    single-class data), as ``KeypointData.model_inputs()`` gives them; ``intrinsics``
    (B, 3, 3) for perspective models, and ``kp3d`` (B, N, 3) when ``loss_cfg.w_supervised``
    is set. ``model_cfg.keypoint_rescale`` must be resolved (``resolve.resolve_input_scale``).
    """

    def loss_fn(params, batch_stats, batch, key, step=0):
        variables = {"params": params, "batch_stats": batch_stats}
        keys = jax.random.split(key, batch["vis"].shape[0])
        rotations = jax.vmap(partial(draw_rotations, cfg=model_cfg))(keys)
        intrinsics = batch.get("intrinsics")
        kp3d = batch["kp3d"] if loss_cfg.w_supervised else None
        per_example = partial(model.forward_train, cfg=model_cfg)
        # BatchNorm's statistics are batch means: one value, not one per example.
        terms, stats = jax.vmap(
            per_example, in_axes=(None, 0, 0, 0, None if intrinsics is None else 0, 0,
                                  None if kp3d is None else 0),
            out_axes=(0, None), axis_name="batch",
        )(variables, batch["kp"], batch["vis"], batch["class_mask"], intrinsics, rotations,
          kp3d)
        l_repro = reprojection(loss_cfg.penalty(terms["dist_sq"]), batch["vis"],
                               loss_cfg.reprojection_normalization)
        per_sample = canonicalisation_per_sample(
            terms["canon_dist_sq"], batch["class_mask"], loss_cfg.huber_scaling)
        l_canon = canonicalisation(per_sample[:, :model_cfg.n_rand_samples])
        l_deform = deformation(terms["deform_sq"], batch["class_mask"])
        w_canon = loss_cfg.canonicalization_weight(step)
        objective = loss_cfg.w_reprojection * l_repro + w_canon * l_canon
        if loss_cfg.w_deformation or loss_cfg.w_deformation_final:
            # Only with the prior on: without it the objective is the paper's, op for op.
            objective = objective + loss_cfg.deformation_weight(step) * l_deform
        extra = {}
        if model_cfg.canonicalization and model_cfg.n_rand_reflections:
            # Psi undoes reflections too, with the canonicalisation's weight.
            extra["loss/reflection"] = canonicalisation(
                per_sample[:, model_cfg.n_rand_samples:])
            objective = objective + w_canon * extra["loss/reflection"]
        if loss_cfg.w_handedness or loss_cfg.w_handedness_final:
            reference = terms["mean_shape"]
            if loss_cfg.handedness_prototype == "views_mean":
                reference = jnp.broadcast_to(views_mean(terms["x_canon"], batch["class_mask"]),
                                             reference.shape)
            extra["loss/handedness"] = handedness(terms["x_canon"], reference,
                                                  batch["class_mask"], loss_cfg.handedness_margin,
                                                  loss_cfg.handedness_evidence)
            objective = objective + loss_cfg.handedness_weight(step) * extra["loss/handedness"]
        if loss_cfg.w_multiview:
            extra["loss/multiview"] = multiview(terms["x_canon"], batch["class_mask"],
                                                loss_cfg.multiview_views,
                                                loss_cfg.huber_scaling)
            objective = objective + loss_cfg.w_multiview * extra["loss/multiview"]
        if kp3d is not None:
            extra["loss/supervised"] = supervised(terms["sup_dist_sq"], batch["class_mask"])
            objective = objective + loss_cfg.w_supervised * extra["loss/supervised"]
        metrics = {
            "loss": objective,
            "loss/reprojection": l_repro,
            "loss/canonicalisation": l_canon,
            "loss/deformation": l_deform,
            **extra,
        }
        return objective, (stats, metrics)

    return loss_fn

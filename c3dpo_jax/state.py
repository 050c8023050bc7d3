"""Arrays-only train state, the optimiser and the learning-rate schedule.

``TrainState`` holds nothing but arrays (``step``, ``params``, ``batch_stats``,
``opt_state``): it is saved by orbax as is, printed, donated to the compiled step, and
is the same pytree in a notebook as in the training loop. The network and optimiser
are closed over by the step factories in ``train``.
"""

import dataclasses
from typing import Any

import flax.struct
import jax
import jax.numpy as jnp
import optax

from c3dpo_jax import model


@flax.struct.dataclass
class TrainState:
    step: Any  # int32 scalar array (Any: orbax and tree_map rebuild it with other leaves)
    params: Any
    batch_stats: Any
    opt_state: Any

    @property
    def variables(self) -> dict[str, Any]:
        return {"params": self.params, "batch_stats": self.batch_stats}


SCHEDULES = ("multistep", "cosine")


@dataclasses.dataclass(frozen=True)
class OptimConfig:
    """Optimiser settings; the defaults are the release's (SGD, lr 1e-3, x0.1 at milestones)."""

    optimizer: str = "sgd"  # "sgd" | "adam" | "adamw" (decoupled decay of the kernels)
    lr: float = 1e-3
    momentum: float = 0.9
    weight_decay: float = 5e-4
    lr_milestones: tuple[int, ...] = ()  # in epochs
    gamma: float = 0.1
    warmup_steps: int = 0
    # "multistep": x gamma at each milestone; "cosine": from lr to 0 over cosine_steps steps;
    # milestones and gamma are then unused. warmup_steps > 0 scales the first steps of either
    # linearly from 0, without moving them.
    schedule: str = "multistep"
    cosine_steps: int = 0

    def __post_init__(self):
        problem = schedule_problem(self.schedule, self.cosine_steps)
        if problem:
            raise ValueError(problem)

    @classmethod
    def from_dict(cls, d) -> "OptimConfig":
        d = dict(d)
        d["lr_milestones"] = tuple(int(m) for m in d.get("lr_milestones", ()))
        return cls(**d)


def schedule_problem(schedule, cosine_steps) -> str | None:
    """What is wrong with a learning-rate schedule's settings (None: nothing), one line;
    ``OptimConfig`` raises it and ``validation`` lists it."""
    if schedule not in SCHEDULES:
        return (f"config.optim.schedule={schedule!r} (must be one of "
                f"{', '.join(map(repr, SCHEDULES))})")
    if schedule == "cosine" and not (isinstance(cosine_steps, int) and cosine_steps >= 1):
        return "config.optim.cosine_steps must be >= 1 with optim.schedule='cosine'"
    return None


def make_schedule(cfg: OptimConfig, steps_per_epoch: int) -> optax.Schedule:
    """Multistep decay with milestones given in epochs (converted to steps), or a cosine
    decay to 0 over ``cosine_steps``; an optional linear warm-up scales the first steps of
    either."""
    if cfg.schedule == "cosine":  # OptimConfig has checked the settings
        schedule = optax.cosine_decay_schedule(cfg.lr, cfg.cosine_steps)
    else:
        boundaries = {int(m) * steps_per_epoch: cfg.gamma for m in cfg.lr_milestones}
        schedule = optax.piecewise_constant_schedule(cfg.lr, boundaries)
    if cfg.warmup_steps > 0:
        # The warm-up scales the schedule's first steps from 0 up to 1; milestones and the
        # cosine keep their absolute steps (a decay "at epoch 8" stays at epoch 8).
        ramp = optax.linear_schedule(0.0, 1.0, cfg.warmup_steps)
        after = schedule
        return lambda step: ramp(step) * after(step)
    return schedule


def _sgd(cfg: OptimConfig, schedule: optax.Schedule) -> optax.GradientTransformation:
    # PyTorch's SGD adds weight_decay * param to the gradient before momentum; so does this.
    return optax.chain(
        optax.add_decayed_weights(cfg.weight_decay),
        optax.sgd(schedule, momentum=cfg.momentum or None),
    )


def _adam(cfg: OptimConfig, schedule: optax.Schedule) -> optax.GradientTransformation:
    return optax.chain(optax.add_decayed_weights(cfg.weight_decay), optax.adam(schedule))


def _kernels(params):
    """True for dense kernels (the basis, the heads, the trunks' weights); False for
    biases (the mean shape among them) and BatchNorm's scales and offsets."""
    return jax.tree_util.tree_map_with_path(
        lambda path, _: getattr(path[-1], "key", None) == "kernel", params)


def _adamw(cfg: OptimConfig, schedule: optax.Schedule) -> optax.GradientTransformation:
    # Decoupled weight decay (Loshchilov & Hutter): each step shrinks the kernels by
    # lr * weight_decay, outside Adam's normalisation, so the decay is felt by every
    # kernel alike instead of being rescaled away as an L2 gradient term is.
    return optax.adamw(schedule, weight_decay=cfg.weight_decay, mask=_kernels)


_OPTIMIZERS = {"sgd": _sgd, "adam": _adam, "adamw": _adamw}


def make_optimizer(cfg: OptimConfig, steps_per_epoch: int) -> optax.GradientTransformation:
    if cfg.optimizer not in _OPTIMIZERS:
        raise ValueError(f"unknown optimizer {cfg.optimizer!r}; known: {sorted(_OPTIMIZERS)}")
    return _OPTIMIZERS[cfg.optimizer](cfg, make_schedule(cfg, steps_per_epoch))


def create_train_state(
    key: jax.Array, model_cfg: model.ModelConfig, tx: optax.GradientTransformation
) -> TrainState:
    variables = model.init_variables(key, model_cfg)
    return TrainState(
        step=jnp.zeros((), jnp.int32),
        params=variables["params"],
        batch_stats=variables["batch_stats"],
        opt_state=tx.init(variables["params"]),
    )

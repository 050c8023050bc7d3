"""Flax Linen modules of C3DPO: the residual trunk, Phi's heads, Psi and the shape layer.

Glossary: N keypoints, D shape-basis size, H hidden width. Modules take ONE example
(no batch axis); BatchNorm reduces over the vmapped axes named in ``axis_name``.

Architecture (paper Sec. 4.4 and supplementary Sec. B; release ``model.py``): a first
dense-BatchNorm-ReLU layer ``dim_in -> H``, then ``n_layers`` bottleneck residual
blocks ``H -> H/4 -> H/4 -> H`` (dense-BN-ReLU twice, dense-BN, skip, ReLU). The
release writes dense layers as 1x1 convolutions; parameter names follow its
state_dict (``conv1``, ``bn1``, ...), so converting official weights is a renaming.

Flattening follows the release so that converted weights line up: Phi's input is
``[x_1..x_N, y_1..y_N, v_1..v_N]`` and the shape layer's output is read as
``(3, N)`` (all x, then all y, then all z).
"""

import functools
import math
from collections.abc import Sequence
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from c3dpo_jax.types import Kp2, Kp3, Vis

AxisName = str | tuple[str, ...] | None


def _torch_uniform(fan_in: int) -> nn.initializers.Initializer:
    """PyTorch's default conv/linear init: U(-1/sqrt(fan_in), 1/sqrt(fan_in))."""
    bound = 1.0 / math.sqrt(fan_in)

    def init(key, shape, dtype=jnp.float32):
        return jax.random.uniform(key, shape, dtype, -bound, bound)

    return init


# float32 accumulation and output for reduced-precision operands.
_dot_f32 = functools.partial(jax.lax.dot_general, preferred_element_type=jnp.float32)


def _dense(features: int, fan_in: int, name: str, matmul_dtype: Any = None) -> nn.Dense:
    """Dense layer; with ``matmul_dtype`` (e.g. bfloat16) the input and the float32
    kernel are cast to it for the product, which accumulates and returns float32."""
    return nn.Dense(
        features,
        kernel_init=_torch_uniform(fan_in),
        bias_init=_torch_uniform(fan_in),
        dtype=matmul_dtype,
        dot_general=_dot_f32 if matmul_dtype is not None else None,
        name=name,
    )


def _batch_norm(train: bool, axis_name: AxisName, name: str) -> nn.BatchNorm:
    # PyTorch momentum 0.1 == flax momentum 0.9; the release initialises the scale U(0, 1).
    return nn.BatchNorm(
        use_running_average=not train,
        momentum=0.9,
        epsilon=1e-5,
        scale_init=nn.initializers.uniform(1.0),
        axis_name=axis_name if train else None,
        name=name,
    )


class ResBlock(nn.Module):
    """Bottleneck residual block ``H -> H/4 -> H/4 -> H`` with a skip connection."""

    features: int
    axis_name: AxisName = "batch"
    matmul_dtype: Any = None

    @nn.compact
    def __call__(self, x: Float[Array, "*B H"], train: bool) -> Float[Array, "*B H"]:
        inner, dt = self.features // 4, self.matmul_dtype
        y = _dense(inner, x.shape[-1], "conv1", dt)(x)
        y = nn.relu(_batch_norm(train, self.axis_name, "bn1")(y))
        y = _dense(inner, inner, "conv2", dt)(y)
        y = nn.relu(_batch_norm(train, self.axis_name, "bn2")(y))
        y = _dense(self.features, inner, "conv3", dt)(y)
        y = _batch_norm(train, self.axis_name, "bn3")(y)
        if x.shape[-1] == self.features:
            y = y + x
        return nn.relu(y)


class Trunk(nn.Module):
    """First dense-BN-ReLU layer followed by ``n_layers`` residual blocks."""

    features: int
    n_layers: int
    axis_name: AxisName = "batch"
    matmul_dtype: Any = None

    @nn.compact
    def __call__(self, x: Float[Array, "*B F"], train: bool) -> Float[Array, "*B H"]:
        y = _dense(self.features, x.shape[-1], "conv1", self.matmul_dtype)(x)
        y = nn.relu(_batch_norm(train, self.axis_name, "bn1")(y))
        for i in range(self.n_layers):
            block = ResBlock(self.features, self.axis_name, self.matmul_dtype, name=f"block{i + 1}")
            y = block(y, train)
        return y


class C3DPONet(nn.Module):
    """Phi, Psi and the shared shape layer, one example at a time.

    Attributes:
      n_keypoints: N.
      shape_basis_size: D.
      n_fully_connected, n_layers: Phi's trunk width H and residual blocks.
      psi_n_fully_connected, psi_n_layers: Psi's trunk.
      camera_translation, camera_scale: optional heads of Phi.
      weight_init_std: std of the Gaussian init of the heads (biases zero).
      phi_axis_name, psi_axis_name: vmapped axes BatchNorm reduces over.
      matmul_dtype: operand dtype of the trunks' dense products (None: float32); the
        heads and the shape layer stay float32.
    """

    n_keypoints: int
    shape_basis_size: int
    n_fully_connected: int = 1024
    n_layers: int = 6
    psi_n_fully_connected: int = 1024
    psi_n_layers: int = 6
    camera_translation: bool = False
    camera_scale: bool = False
    weight_init_std: float = 0.01
    phi_axis_name: AxisName = "batch"
    psi_axis_name: AxisName = ("batch", "sample")
    matmul_dtype: Any = None

    def setup(self):
        n, d = self.n_keypoints, self.shape_basis_size
        head = dict(
            kernel_init=nn.initializers.normal(self.weight_init_std),
            bias_init=nn.initializers.zeros,
        )
        self.phi_trunk = Trunk(
            self.n_fully_connected, self.n_layers, self.phi_axis_name, self.matmul_dtype
        )
        self.alpha_layer = nn.Dense(d, **head)
        self.rot_layer = nn.Dense(3, **head)
        if self.camera_translation:
            self.translation_layer = nn.Dense(3, **head)
        if self.camera_scale:
            self.scale_layer = nn.Dense(1, **head)
        self.shape_layer = nn.Dense(3 * n, **head)
        self.psi_trunk = Trunk(
            self.psi_n_fully_connected, self.psi_n_layers, self.psi_axis_name, self.matmul_dtype
        )
        self.alpha_layer_psi = nn.Dense(d, **head)

    def phi(self, kp_norm: Kp2, vis: Vis, train: bool) -> dict[str, Array]:
        """Phi(Y, v) -> alpha (D,), theta (3,), translation (3,), scale ()."""
        x = jnp.concatenate([(kp_norm * vis[:, None]).T.reshape(-1), vis])
        feats = self.phi_trunk(x, train)
        out = {"alpha": self.alpha_layer(feats), "theta": self.rot_layer(feats)}
        out["translation"] = (
            self.translation_layer(feats) if self.camera_translation else jnp.zeros(3)
        )
        out["scale"] = (
            jax.nn.softplus(self.scale_layer(feats)[0]) if self.camera_scale else jnp.ones(())
        )
        return out

    def psi(self, x_rot: Kp3, train: bool) -> Float[Array, " D"]:
        """Psi(R X) -> alpha_psi, the coefficients of the canonical shape."""
        return self.alpha_layer_psi(self.psi_trunk(x_rot.T.reshape(-1), train))

    def shape(self, alpha: Float[Array, " D"]) -> Kp3:
        """Canonical shape ``X = mean_shape + sum_d alpha_d S_d`` as (N, 3)."""
        return self.shape_layer(alpha).reshape(3, self.n_keypoints).T

    def __call__(self, kp_norm: Kp2, vis: Vis, train: bool = False) -> Kp3:
        """Touches every parameter (used by ``init``); returns Psi's reconstruction."""
        x = self.shape(self.phi(kp_norm, vis, train)["alpha"])
        return self.shape(self.psi(x, train))


def count_params(params) -> int:
    """Number of scalars in a parameter pytree."""
    return sum(int(p.size) for p in jax.tree.leaves(params))


def param_shapes(params) -> Sequence[tuple[str, tuple[int, ...]]]:
    """Flat list of ``(path, shape)`` for documentation and tests."""
    flat = jax.tree_util.tree_flatten_with_path(params)[0]
    return [(jax.tree_util.keystr(path), tuple(leaf.shape)) for path, leaf in flat]

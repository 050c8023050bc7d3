"""Shape glossary and array type aliases shared by every math module.

Glossary (used in every docstring and annotation of the package):
  B  batch size                    N  keypoints per sample
  D  shape-basis size              S  canonicalisation samples per example
  H  hidden width of a trunk       M  samples in a dataset

Coordinates always go on the **last** axis: 2D keypoints ``(N, 2)``, visibility
``(N,)`` float in {0, 1}, 3D points ``(N, 3)``, rotations ``(3, 3)``, shape
coefficients ``(D,)``. The release's JSON layout ``2 x N`` is transposed once, when
a file is read (``c3dpo_jax.data.json_dataset``).
"""

from jaxtyping import Array, Float

Kp2 = Float[Array, "N 2"]
Kp3 = Float[Array, "N 3"]
Vis = Float[Array, " N"]
Rot = Float[Array, "3 3"]
Vec3 = Float[Array, "3"]
Scalar = Float[Array, ""]

"""Independent re-implementations (numpy, scipy) of library quantities, shared by the tests
that check the library against them."""

import numpy as np


def procrustes_evidence(x, ref):
    """Independent of ``lift.handedness_evidence``: (mirror - proper) / (mirror + proper) of
    the residuals of ``x`` aligned onto ``ref`` (both centred, unit size) by the best proper
    rotation and by the best rotation of its mirror image (scipy's
    ``Rotation.align_vectors``)."""
    from scipy.spatial.transform import Rotation

    a, b = (y - y.mean(0) for y in (np.asarray(x, np.float64), np.asarray(ref, np.float64)))
    a, b = a / np.linalg.norm(a), b / np.linalg.norm(b)

    def residual(y):
        rot, _ = Rotation.align_vectors(b, y)
        return np.linalg.norm(rot.apply(y) - b)

    proper, mirror = residual(a), residual(a * np.array([1.0, 1.0, -1.0]))
    return (mirror - proper) / (mirror + proper)

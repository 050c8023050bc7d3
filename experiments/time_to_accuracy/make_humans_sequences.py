"""Three "sequences" of the synthetic-humans body for the humans ablation (README):

  python experiments/time_to_accuracy/make_humans_sequences.py OUT_DIR

writes OUT_DIR/{rand_fixed,rand_var,path_fixed}.npz (X: 300 frames x 3 x 17 joints):
- rand_fixed: one body (the rest proportions), 300 independent random poses;
- rand_var:   the same poses, every frame a different person (proportions spread 1);
- path_fixed: one body, poses along a smooth path through 13 random key poses.
run.py turns each into views like the mocap sequences (10 upright cameras per frame,
test frame blocks unseen, no occlusion).
"""

import os
import sys

import numpy as np

from c3dpo_jax.data import humans


def main(out_dir: str, n_frames: int = 300, seed: int = 0) -> None:
    rng = np.random.default_rng(seed)
    def save(name, offsets, angles):
        pos, _ = humans.forward_kinematics(offsets, angles)
        np.savez(os.path.join(out_dir, f"{name}.npz"), X=np.swapaxes(pos, 1, 2))

    os.makedirs(out_dir, exist_ok=True)
    one_body = np.repeat(humans.REST_OFFSETS[None], n_frames, 0)
    angles = humans.random_joint_angles(rng, n_frames)
    save("rand_fixed", one_body, angles)
    save("rand_var", humans.random_proportions(rng, n_frames), angles)
    keys = humans.random_joint_angles(rng, 13)
    t = np.linspace(0, 12, n_frames, endpoint=False)
    i = t.astype(int)
    f = ((1 - np.cos(np.pi * (t - i))) / 2)[:, None, None]
    save("path_fixed", one_body, keys[i] * (1 - f) + keys[i + 1] * f)


if __name__ == "__main__":
    if len(sys.argv) != 2 or sys.argv[1].startswith("-"):
        sys.exit(__doc__.split("\n\n")[1])  # the usage line: one folder, no options
    main(sys.argv[1])

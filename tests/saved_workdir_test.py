"""A workdir whose config.json keeps the inference options in its model section
(``test_time_*``, ``replace_keypoints_with_input``) loads with those options, and gives the
reconstructions and ``--mode=eval`` scores recorded beside it.

tests/testdata/saved_workdir is the step-20 checkpoint and config.json of
``python -m c3dpo_jax.main --config=configs/synthetic.py:smoke
--config.model.test_time_one_handedness=True --config.model.test_time_turns=3`` (refinement,
three turned copies and one handedness on); saved_workdir_outputs.npz holds six test views,
a body and ``reconstruct``'s outputs for them with the model's own options and three others;
saved_workdir_scores.json the scores of ``--mode=eval`` with the same options.
"""

import json
import pathlib
import shutil

import numpy as np
import pytest

from c3dpo_jax import cli, evaluate_workdir
from c3dpo_jax.reconstruct import load, reconstruct

DATA = pathlib.Path(__file__).parent / "testdata"
WORKDIR = DATA / "saved_workdir"


def _options(body):
    return {"own": {}, "plain": dict(turns=1, refine_iters=0, one_handedness=False),
            "circle": dict(turns=4, turn_span="circle", refine_iters=5),
            "body": dict(handedness_reference=body)}


def test_a_saved_workdir_gives_the_recorded_reconstructions():
    want = np.load(DATA / "saved_workdir_outputs.npz")
    params = load(str(WORKDIR))
    for name, options in _options(want["body"]).items():
        got = reconstruct(params, want["kp"], want["vis"], **options)
        for field, value in got._asdict().items():
            np.testing.assert_allclose(value, want[f"{name}/{field}"], rtol=1e-6, atol=1e-6,
                                       err_msg=f"{name}/{field}")


def test_a_saved_workdir_scores_the_recorded_scores(tmp_path):
    workdir = shutil.copytree(WORKDIR, tmp_path / "run")
    config = cli.get_config("configs/synthetic.py:smoke")
    config.unlock()
    config.inference.one_handedness = True
    config.inference.turns = 3
    got = evaluate_workdir.evaluate_checkpoint(config, str(workdir), save=False)
    want = json.loads((DATA / "saved_workdir_scores.json").read_text())
    assert "inference" not in got["final"]  # the run's own options
    assert got["final"].keys() == want["final"].keys()
    for key, value in want["final"].items():
        assert got["final"][key] == pytest.approx(value, rel=1e-6, abs=1e-6), key
    for method, scores in want["baselines"].items():
        for key, value in scores.items():
            assert got["baselines"][method][key] == pytest.approx(value, rel=1e-6), key

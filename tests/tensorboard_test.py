"""TensorBoard events: what the writer stores is what TensorBoard reads, resumes included."""

import json
import os

import pytest

from c3dpo_jax import tensorboard


def test_scalars_round_trip_with_test_prefix_and_nested_groups(tmp_path):
    writer = tensorboard.EventWriter(str(tmp_path))
    writer.scalars(5, {"step": 5, "loss": 0.5, "loss/reprojection": 0.25, "lr": 1e-3})
    writer.scalars(10, {"step": 10, "epoch": 1, "n_samples": 40, "mpjpe": 0.125,
                        "stress": float("nan"), "per_group": {"walk": 0.1}}, prefix="test/")
    writer.close()
    (path,) = os.listdir(tmp_path)
    assert path.startswith("events.out.tfevents.")
    assert tensorboard.read_scalars(str(tmp_path)) == {
        "loss": [(5, 0.5)], "loss/reprojection": [(5, 0.25)], "lr": [(5, pytest.approx(1e-3))],
        "test/mpjpe": [(10, 0.125)], "test/per_group/walk": [(10, pytest.approx(0.1))]}


def test_a_resumed_run_replaces_the_steps_past_its_last_record(tmp_path):
    first = tensorboard.EventWriter(str(tmp_path))
    for step in (5, 10, 15):  # a run killed after step 15, its last checkpoint at 10
        first.scalars(step, {"loss": 1.0 / step})
    first.close()
    (tmp_path / "metrics.jsonl").write_text(
        "".join(json.dumps({"step": s}) + "\n" for s in (5, 10)))  # trimmed at the resume
    second = tensorboard.EventWriter(str(tmp_path))
    second.scalars(15, {"loss": 0.5})
    second.close()  # within the same second as the first file: a file of its own
    assert len(os.listdir(tmp_path)) == 3
    assert tensorboard.read_scalars(str(tmp_path))["loss"] == [
        (5, pytest.approx(0.2)), (10, pytest.approx(0.1)), (15, 0.5)]

"""A run's records: the TensorBoard events hold what was logged, as TensorBoard reads them,
resumes included."""

import os

import pytest

from c3dpo_jax import run_records


def test_scalars_round_trip_with_test_prefix_and_nested_groups(tmp_path, read_scalars):
    with run_records.MetricsWriter(str(tmp_path), pbar=None) as writer:
        writer.scalars(5, {"step": 5, "loss": 0.5, "loss/reprojection": 0.25, "lr": 1e-3})
        writer.scalars(10, {"step": 10, "epoch": 1, "n_samples": 40, "mpjpe": 0.125,
                            "stress": float("nan"), "per_group": {"walk": 0.1}}, prefix="test/")
    (path,) = os.listdir(tmp_path)
    assert path.startswith("events.out.tfevents.")
    assert read_scalars(tmp_path) == {
        "loss": [(5, 0.5)], "loss/reprojection": [(5, 0.25)], "lr": [(5, pytest.approx(1e-3))],
        "test/mpjpe": [(10, 0.125)], "test/per_group/walk": [(10, pytest.approx(0.1))]}


def test_a_resumed_run_replaces_the_steps_past_its_checkpoint(tmp_path, read_scalars):
    with run_records.MetricsWriter(str(tmp_path), pbar=None) as first:
        for step in (5, 10, 15):  # a run killed after step 15, its last checkpoint at 10
            first.scalars(step, {"loss": 1.0 / step})
    with run_records.MetricsWriter(str(tmp_path), pbar=None, resumed_from=10) as second:
        second.scalars(15, {"loss": 0.5})
    assert len(os.listdir(tmp_path)) == 2  # within the same second as the first: its own file
    assert read_scalars(tmp_path)["loss"] == [
        (5, pytest.approx(0.2)), (10, pytest.approx(0.1)), (15, 0.5)]

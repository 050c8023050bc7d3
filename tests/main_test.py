"""The command line, as a user runs it: smoke training, resume, eval mode, bad input."""

import json
import os
import subprocess
import sys

import numpy as np
import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _read(*parts):
    with open(os.path.join(*parts)) as f:
        return f.read()


@pytest.fixture
def run_main(smoke_subprocess_env):
    """``run_main(*args)``: the main job in a subprocess (smoke-sized models only)."""
    env = smoke_subprocess_env()

    def run(*args):
        return subprocess.run([sys.executable, "-m", "c3dpo_jax.main", *args], cwd=ROOT,
                              env=env, capture_output=True, text=True, timeout=600)

    return run


def test_smoke_run_trains_evaluates_resumes_and_reevaluates(tmp_path, run_main):
    workdir = str(tmp_path / "run")
    first = run_main("--config=configs/synthetic.py:smoke", f"--workdir={workdir}")
    assert first.returncode == 0, first.stderr[-3000:]
    assert "fitted mean shape" in first.stdout and "C3DPO" in first.stdout
    # A short header, not the config's YAML; no library chatter, no metric dumps in the bar.
    assert first.stdout.startswith(f"c3dpo_jax train: configs/synthetic.py:smoke -> {workdir}\n"
                                   "  data: synthetic, 20 keypoints; 20 steps of batch 32\n")
    for noise in ("!!python/tuple", "backend 'tpu'", "orbax", "step 5: {", "step 10: test"):
        assert noise not in first.stdout + first.stderr, noise
    assert "training_curves.png" in os.listdir(os.path.join(workdir, "figures"))
    results = json.loads(_read(workdir, "eval_results.json"))
    assert results["final"]["step"] == 20 and results["final"]["mpjpe"] > 0
    lines = _read(workdir, "metrics.jsonl").splitlines()
    assert len(lines) == 4 and json.loads(lines[-1])["step"] == 20
    assert json.loads(_read(workdir, "config.json"))["model"]["n_fully_connected"] == 32
    # Running the same command again resumes at the end: nothing is retrained.
    again = run_main("--config=configs/synthetic.py:smoke", f"--workdir={workdir}", "--nofigures")
    assert again.returncode == 0, again.stderr[-3000:]
    assert "resumed from the checkpoint at step 20" in again.stderr
    assert len(_read(workdir, "metrics.jsonl").splitlines()) == 4
    evaluated = run_main("--config=configs/synthetic.py:smoke", f"--workdir={workdir}",
                         "--mode=eval")
    assert evaluated.returncode == 0, evaluated.stderr[-3000:]
    reevaluated = json.loads(_read(workdir, "eval_results.json"))
    assert reevaluated["final"]["mpjpe"] == pytest.approx(results["final"]["mpjpe"], rel=1e-5)
    assert "inference" not in reevaluated["final"]  # the training's own inference options
    # The run's clock survives the resume and the re-scoring (tables read the minutes from
    # final): no training happened after the first run, so at most the loop's overhead.
    assert reevaluated["final"]["epoch"] == results["final"]["epoch"]
    assert reevaluated["final"]["train_s"] == pytest.approx(results["final"]["train_s"], abs=0.5)
    assert [h["step"] for h in reevaluated["history"]] == [h["step"] for h in results["history"]]
    assert results["history"], "the smoke run evaluates at its epoch ends"
    # Nor with other settings of the same shapes (another input scale scores another
    # function of the same parameters).
    rescaled = run_main("--config=configs/synthetic.py:smoke", f"--workdir={workdir}",
                        "--mode=eval", "--config.model.keypoint_norm_type=to_root")
    assert rescaled.returncode == 2 and rescaled.stderr.endswith(
        "holds a network trained with other model settings than the config's "
        "(model.keypoint_norm_type: 'to_mean' in the checkpoint's run, 'to_root' now); "
        "evaluate it with the config it was trained with\n"), rescaled.stderr[-3000:]
    # A workdir it cannot write (here: the results' temporary name taken by a folder) still
    # prints the scores, then says what it could not save.
    os.mkdir(os.path.join(workdir, "eval_results.json.tmp"))
    unwritable = run_main("--config=configs/synthetic.py:smoke", f"--workdir={workdir}",
                          "--mode=eval")
    assert unwritable.returncode == 2 and "Traceback" not in unwritable.stderr
    assert "C3DPO" in unwritable.stdout and "results written" not in unwritable.stdout
    assert unwritable.stderr.endswith(f"error: cannot write {workdir}/eval_results.json: "
                                      "Is a directory\n"), unwritable.stderr[-500:]
    os.rmdir(os.path.join(workdir, "eval_results.json.tmp"))
    # Scoring with a config of another network says so, instead of calling the checkpoints
    # unreadable.
    other = run_main("--config=configs/synthetic.py:smoke", f"--workdir={workdir}",
                     "--mode=eval", "--config.model.shape_basis_size=5")
    assert other.returncode == 2, other.stderr[-3000:]
    assert other.stderr.endswith("holds a network of another shape than the config's "
                                 "(model.shape_basis_size: 10 in the checkpoint's run, 5 now); "
                                 "evaluate it with the config it was trained with\n")
    # A damaged newest checkpoint: the one before it is scored, and the final scores of
    # step 20 that eval_results.json holds are not replaced by step 10's without a word.
    step_dir = os.path.join(workdir, "checkpoints", "20")
    damaged = next(os.path.join(d, f) for d, _, files in os.walk(step_dir) for f in files
                   if os.sep + "ocdbt.process_0" + os.sep + "d" in d)
    with open(damaged, "r+b") as f:
        f.seek(10)
        f.write(b"XXXX")
    older = run_main("--config=configs/synthetic.py:smoke", f"--workdir={workdir}",
                     "--mode=eval")
    assert older.returncode == 0, older.stderr[-3000:]
    assert f"checkpoint {step_dir} cannot be read (" in older.stderr
    assert "), step 10:\n" in older.stdout
    assert older.stdout.rstrip().splitlines()[-1] == (
        f"scores not written to {workdir}/eval_results.json: it holds the final scores of "
        "step 20, whose checkpoint cannot be read now (the warnings above say why), and step "
        "10 is an earlier one")
    assert json.loads(_read(workdir, "eval_results.json"))["final"] == reevaluated["final"]


def test_a_diverging_run_stops_with_one_line(tmp_path, run_main):
    out = run_main("--config=configs/synthetic.py:smoke", f"--workdir={tmp_path}",
                   "--nofigures", "--config.optim.lr=1e6")
    assert out.returncode == 2, out.stderr[-3000:]
    assert "Traceback" not in out.stderr
    last = out.stderr.rstrip("\n").splitlines()[-1]
    assert last.startswith("error: loss is not finite at step ") and last.endswith(
        "a lower --config.optim.lr, or a look at the data, usually helps"), last


def test_wrong_keypoint_count_is_a_clear_error(tmp_path, run_main):
    out = run_main("--config=configs/synthetic.py:smoke", f"--workdir={tmp_path}",
               "--config.model.n_keypoints=7")
    assert out.returncode != 0
    assert "config.model.n_keypoints=20" in out.stderr


def _write_release_json(path, data):
    entries = [{"kp_loc": data.kp[i].T.tolist(), "kp_vis": data.vis[i].tolist(),
                "kp_loc_3d": data.kp3d[i].T.tolist()} for i in range(len(data))]
    with open(path, "w") as f:
        json.dump(entries, f)


def test_release_config_trains_on_json_files_and_resumes(tmp_path, run_main):
    from c3dpo_jax.data import synthetic

    train, test = synthetic.make_splits(n_keypoints=79, n_train=64, n_test=16, seed=3)
    _write_release_json(tmp_path / "a.json", train)
    _write_release_json(tmp_path / "b.json", test)
    args = ["--config=configs/up3d.py:smoke", f"--workdir={tmp_path / 'run'}",
            f"--config.data.train_path={tmp_path / 'a.json'}",
            f"--config.data.test_path={tmp_path / 'b.json'}", "--nofigures",
            "--config.train.num_steps=10"]
    first = run_main(*args)
    assert first.returncode == 0, first.stderr[-3000:]
    assert "(16 samples, protocol 'default')" in first.stdout
    args[-1] = "--config.train.num_steps=20"  # continue the same run further
    second = run_main(*args)
    assert second.returncode == 0, second.stderr[-3000:]
    assert "resumed from the checkpoint at step 10" in second.stderr
    assert json.loads(_read(str(tmp_path / "run"), "eval_results.json"))["final"]["step"] == 20
    assert not os.path.exists(tmp_path / "run" / "figures")  # --nofigures


def test_2d_only_keypoints_in_pixels_from_one_coco_file(tmp_path, run_main):
    """The own-data workflow for 2D detections: the importer splits the file by image, and
    the results name the unit of the 2D reprojection error."""
    from c3dpo_jax.data import importers, synthetic

    views = synthetic.make_split(64, n_keypoints=8, n_modes=2, deformation=0.3, occlusion=0.1,
                                 noise=0.0, perspective=False, shape_seed=0, seed=3)
    kp = views.kp * 100 + 320  # pixels
    coco = {"images": [{"id": i, "file_name": f"im{i // 2}.jpg"} for i in range(64)],
            "annotations": [{"image_id": i, "keypoints": np.column_stack(
                [kp[i], 2 * views.vis[i]]).ravel().tolist()} for i in range(64)]}
    (tmp_path / "people.json").write_text(json.dumps(coco))
    importers.main(["coco", str(tmp_path / "people.json"), "--out_dir", str(tmp_path)])
    out = run_main("--config=configs/own_json.py:smoke", f"--workdir={tmp_path / 'run'}",
                   f"--config.data.train_path={tmp_path / 'people_train.json'}",
                   f"--config.data.test_path={tmp_path / 'people_test.json'}",
                   "--config.model.n_keypoints=8", "--config.data.protocol=none", "--nofigures")
    assert out.returncode == 0, out.stderr[-3000:]
    assert "(12 samples, protocol 'none')" in out.stdout  # 6 of the 32 images, 2 views each
    assert ("reprojection: the mean 2D distance of the visible points to their reprojection, "
            "in px\n") in out.stdout

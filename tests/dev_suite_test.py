"""experiments/dev_suite: the suite runs the CLI on importer-made files and tabulates it."""

import json
import os
import subprocess
import sys

import numpy as np
import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SUITE = os.path.join(ROOT, "experiments", "dev_suite", "suite.py")


def _suite_value(module: str, expression: str):
    """The JSON value of ``expression`` after ``import MODULE`` from the suite's folder, in a
    subprocess (the suite's absl flags must not meet main's)."""
    code = (f"import sys, json; sys.path.insert(0, {os.path.dirname(SUITE)!r}); "
            f"import {module}; print(json.dumps({expression}))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         cwd=ROOT, check=True).stdout
    return json.loads(out.strip().splitlines()[-1])


def _mocap(path: str, n_clips: int = 3, frames: int = 20) -> None:
    """A small 'mocap' file as in shared/data/mocap: X (F, 3, K), clip ids, names."""
    rng = np.random.default_rng(0)
    base = rng.normal(size=(3, 9))
    t = np.linspace(0, 6 * np.pi, n_clips * frames)
    x = base[None] + np.sin(t)[:, None, None] * rng.normal(size=(1, 3, 9)) * 0.3
    np.savez(path, X=x.astype(np.float32), clip=np.repeat(np.arange(n_clips), frames),
             frame=np.tile(np.arange(frames), n_clips), clip_names=np.array(["a", "b", "c"]),
             kp_names=np.array([f"j{i}" for i in range(9)]))


def test_suite_trains_through_the_cli_and_tabulates_every_column(tmp_path, smoke_subprocess_env):
    (tmp_path / "data" / "mocap").mkdir(parents=True)
    _mocap(str(tmp_path / "data" / "mocap" / "cmu131.npz"))
    out = tmp_path / "out"
    cmd = [sys.executable, SUITE, "--datasets=cmu131", "--seeds=0", "--jobs=1",
           "--config=configs/own_json.py:smoke", f"--data_root={tmp_path / 'data'}",
           f"--out={out}", "--eval_every_steps=10", "--variant=lr:optim.lr=0.001"]
    proc = subprocess.run(cmd, check=True, capture_output=True, text=True, cwd=str(tmp_path),
                          env=smoke_subprocess_env())
    workdir = out / "runs" / "lr" / "cmu131__s0"
    with open(workdir / "config.json") as f:
        config = json.load(f)
    assert config["optim"]["lr"] == 0.001 and config["model"]["n_keypoints"] == 9
    assert config["model"]["keypoint_rescale"] > 0  # own_json's 0 ("auto") resolved, saved
    # 9 points, no built-in body: the training views' mean, its rows written when the run
    # ended, or the model's own handedness where its shapes do not keep their corners.
    inference = config["inference"]
    if inference["handedness_reference"] == "views_mean":
        assert np.asarray(inference["handedness_body"]).shape == (9, 3)
        assert inference["one_handedness"] and inference["handedness_from_output"]
    else:
        assert (inference["handedness_reference"], inference["one_handedness"]) == (
            "mean_shape", False)
    assert config["model"]["keypoint_scaling"] == "global"  # one distance: one input scale
    with open(workdir / "eval_results.json") as f:
        res = json.load(f)
    assert [h["step"] for h in res["history"]] == [10] and res["final"]["step"] == 20
    # 3 views per frame of 60 frames; a fifth of every clip is test.
    with open(out / "data" / "cmu131.json") as f:
        info = json.load(f)
    assert (info["n_train"], info["n_test"]) == (48 * 3, 12 * 3)
    row = next(line for line in proc.stdout.splitlines() if line.startswith("| cmu131"))
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert len(cells) == 17 and cells[1] == "1"
    assert all(c != "-" and "nan" not in c for c in cells)  # the run reports "mirrored" too
    assert 0.0 <= float(cells[11]) <= 1.0
    # The error up to one mirror flip is the split as it is or all mirrored: at least the
    # paper's per-view flip, at most the error as it is.
    assert float(cells[8]) <= float(cells[7]) + 1e-3 and float(cells[7]) <= float(cells[9]) + 1e-3
    assert (out / "lr.md").read_text().count("| cmu131 |") == 1
    assert "Made by `python experiments/dev_suite/suite.py " in (out / "lr.md").read_text()
    # The variant's file keeps every finished run when the table asked for has fewer.
    report = [*cmd[:-1], "--seeds=7", "--report_only", "--variant=lr:optim.lr=0.001"]
    proc = subprocess.run([c for c in report if c != "--seeds=0"], check=True,
                          capture_output=True, text=True, cwd=str(tmp_path),
                          env=smoke_subprocess_env())
    assert "| cmu131" not in proc.stdout
    assert (out / "lr.md").read_text().count("| cmu131 | 1 |") == 1
    # A finished run is not run again.
    again = subprocess.run(cmd, check=True, capture_output=True, text=True, cwd=str(tmp_path),
                           env=smoke_subprocess_env())
    assert "[core" not in again.stdout
    # --rescore: the finished run scored again with other inference options, its curve kept.
    rescored = subprocess.run([*cmd, "--rescore=inference.refine_iters=0"], check=True,
                              capture_output=True, text=True, cwd=str(tmp_path),
                              env=smoke_subprocess_env())
    assert "[core" in rescored.stdout
    with open(workdir / "eval_results.json") as f:
        again_res = json.load(f)
    assert again_res["history"] == res["history"] and again_res["final"]["step"] == 20
    assert again_res["final"]["inference"] == {"refine_iters": 0}
    assert again_res["final"]["mpjpe"] != res["final"]["mpjpe"]
    # A run of the variant's name made from another config is neither reused nor resumed.
    other = [c if not c.startswith("--variant=") else "--variant=lr:optim.lr=0.002" for c in cmd]
    refused = subprocess.run(other, capture_output=True, text=True, cwd=str(tmp_path),
                             env=smoke_subprocess_env())
    assert refused.returncode != 0 and "[core" not in refused.stdout
    assert "runs/lr/cmu131__s0 was made with another config" in refused.stderr
    assert "optim.lr: 0.001, not 0.002" in refused.stderr


def test_floors_are_zero_where_the_model_class_holds_the_truth(tmp_path):
    """analyse.floors: rigid data has a zero rigid floor; rank-1 deformations of it a zero
    PCA floor (D >= 1) and a positive rigid one; the rigid baseline's 2D distance is zero on
    noiseless rigid views. (In a subprocess: the suite's absl flags must not meet main's.)"""
    from c3dpo_jax.data import importers, json_dataset

    rng = np.random.default_rng(1)
    base, mode = rng.normal(size=(12, 3)), rng.normal(size=(12, 3))
    for name, amp in (("rigid", 0.0), ("rank1", 0.4)):
        x = base[None] + amp * np.sin(np.linspace(0, 9, 60))[:, None, None] * mode[None]
        train, test = importers.views_from_sequence(x, views_per_frame=4, seed=0, name=name)
        for split, data in (("train", train), ("test", test)):
            json_dataset.save(data, str(tmp_path / f"{name}_{split}.json"))
    rigid, rank1 = _suite_value("analyse", f"[list(analyse.floors(n, {str(tmp_path)!r}, 2)"
                                           ".values()) for n in ('rigid', 'rank1')]")
    np.testing.assert_allclose(rigid, 0.0, atol=1e-4)
    assert rank1[0] > 0.05 and rank1[1] < 1e-3 and rank1[2] > 0.01


def _made_from_a_small_cmu131(tmp_path, seed: int, names: tuple[str, ...]) -> list[dict]:
    """``suite.make_data`` of each of ``names`` from a random 60-frame, 3-clip ``cmu131``."""
    (tmp_path / "mocap").mkdir()
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(1, 3, 17)) + 0.2 * rng.normal(size=(60, 3, 17))
    np.savez(tmp_path / "mocap" / "cmu131.npz", X=x.astype(np.float32),
             clip=np.repeat(np.arange(3), 20))
    return _suite_value("suite", f"[suite.make_data(n, {str(tmp_path)!r}, "
                                 f"{str(tmp_path / 'out')!r}) for n in {names!r}]")


def test_few_point_sets_are_the_full_sets_views_of_their_points(tmp_path):
    """``cmu131_k8``: the full set's frames in each split and its training cameras, only its
    8 points (each training view the full view's points recentred and rescaled by one
    factor; the test cameras are drawn after the training views' per-point draws, so they
    differ)."""
    full, few = _made_from_a_small_cmu131(tmp_path, 2, ("cmu131", "cmu131_k8"))
    assert (full["n_keypoints"], few["n_keypoints"]) == (17, 8)
    assert (full["n_train"], full["n_test"]) == (few["n_train"], few["n_test"])
    with open(full["train"]) as f:
        a = np.asarray([v["kp_loc"] for v in json.load(f)["data"]], dtype=np.float64)
    with open(few["train"]) as f:
        b = np.asarray([v["kp_loc"] for v in json.load(f)["data"]], dtype=np.float64)
    a = a[..., [0, 2, 3, 5, 6, 10, 13, 16]]
    a, b = a - a.mean(-1, keepdims=True), b - b.mean(-1, keepdims=True)
    scale = (a * b).sum() / (a * a).sum()
    np.testing.assert_allclose(b, scale * a, atol=1e-5)


def test_ten_camera_sets_hold_out_the_same_frames(tmp_path):
    """``cmu131_v10``: the full set's frames and split, each frame seen by 10 cameras
    instead of 3 (frames told apart by the rotation-invariant distances between points)."""
    three, ten = _made_from_a_small_cmu131(tmp_path, 3, ("cmu131", "cmu131_v10"))
    assert ten["n_keypoints"] == three["n_keypoints"] == 17
    assert (10 * three["n_train"], 10 * three["n_test"]) == (3 * ten["n_train"],
                                                               3 * ten["n_test"])

    def frames(path):
        with open(path) as f:
            views = np.asarray([v["kp_loc_3d"] for v in json.load(f)["data"]])  # (M, 3, K)
        d = np.linalg.norm(views[:, :, :, None] - views[:, :, None, :], axis=1)
        return {tuple(np.round(v[np.triu_indices(17, 1)], 4)) for v in d}

    held_out = frames(three["test"])
    assert held_out == frames(ten["test"])
    assert len(held_out) == three["n_test"] // 3


def test_recorded_data_paths_are_relative_to_the_repository_inside_it_only(tmp_path,
                                                                          monkeypatch):
    """``runner.repo_path``: a path inside the checkout is written relative to its root (where
    the runs execute), one outside it (another folder, a sibling sharing the root's name as
    a prefix) unchanged."""
    monkeypatch.syspath_prepend(os.path.join(ROOT, "experiments"))
    import runner

    inside = os.path.join(runner.ROOT, "experiments", "dev_suite", "results", "data", "a.json")
    assert runner.repo_path(inside) == os.path.join("experiments", "dev_suite", "results",
                                                    "data", "a.json")
    for outside in (str(tmp_path / "a.json"), runner.ROOT + "_other" + os.sep + "a.json"):
        assert runner.repo_path(outside) == outside


def test_a_finished_run_of_other_steps_is_not_reused_and_jobs_are_checked(tmp_path,
                                                                        monkeypatch):
    monkeypatch.syspath_prepend(os.path.join(ROOT, "experiments"))
    import runner

    run = tmp_path / "cell"
    runner.check_steps(str(run), 40)  # nothing there yet
    run.mkdir()
    (run / "config.json").write_text(json.dumps({"train": {"num_steps": 20}}))
    runner.check_steps(str(run), 20)
    with pytest.raises(ValueError, match=r"cell holds a run of 20 steps, not 40"):
        runner.check_steps(str(run), 40)
    with pytest.raises(ValueError, match=r"--jobs=0 \(must be >= 1\)"):
        runner.run_all([(str(run), ["true"])], 0, str(tmp_path))


def test_overrides_set_existing_fields_and_refuse_unknown_ones(monkeypatch):
    """``runner.override`` (the in-process scripts' ``--set``): a flattened key sets its field,
    values as ``literal`` reads them; a misspelt key is refused in one line before anything
    changes, where ml-collections alone would add a field that nothing reads."""
    monkeypatch.syspath_prepend(os.path.join(ROOT, "experiments"))
    import runner
    from absl import app

    from configs import own_json

    c = own_json.get_config()
    runner.override(c, {"loss.deformation_ramp": runner.literal("(10,20)"),
                        "optim.optimizer": runner.literal("sgd")})
    assert c.loss.deformation_ramp == (10, 20) and c.optim.optimizer == "sgd"
    with pytest.raises(app.UsageError, match=r"the config has no field loss.w_canonicalisation"):
        runner.override(c, {"optim.lr": 1.0, "loss.w_canonicalisation": 3.0})
    assert c.optim.lr != 1.0 and "w_canonicalisation" not in c.loss
    with pytest.raises(app.UsageError, match=r"no field optim.lr.x"):
        runner.override(c, {"optim.lr.x": 1})


def test_scaled_sets_scale_each_views_points_and_truth_by_one_factor_in_range():
    """suite._scaled (``cmu131_scaled``, ``humans_scaled``): each view's 2D points and 3D
    truth are the original's times one factor of that view, within SCALE_RANGE, the factors
    spread over it; the visibility is unchanged."""
    code = """
import numpy as np
from c3dpo_jax.data import KeypointData
rng = np.random.default_rng(0)
kp3d = rng.normal(size=(400, 5, 3)).astype(np.float32)
data = KeypointData(kp=kp3d[..., :2].copy(), vis=np.ones((400, 5), np.float32), kp3d=kp3d)
out = suite._scaled(data, 0)
f = out.kp3d / data.kp3d
out = [float(np.abs(f - f[:, :1, :1]).max()), float(np.abs(out.kp / data.kp - f[:, :1, :1]).max()),
       float(f.min()), float(f.max()), list(suite.SCALE_RANGE), bool((out.vis == data.vis).all())]
"""
    spread, kp_vs_3d, low, high, (lo, hi), vis_same = _suite_value(
        "suite", f"(exec({code!r}, globals()), out)[1]")
    assert spread < 1e-5 and kp_vs_3d < 1e-4 and vis_same
    assert lo <= low < 1.1 * lo and hi / 1.1 < high <= hi


def test_diagnostics_keep_one_record_per_step_and_split_on_resume(tmp_path):
    """diagnose.py's records: a resumed run's first evaluation (here step 2, which the
    first run had recorded too) drops the records from that step on before appending, so
    every step and split keeps one record; earlier steps stay."""
    path = str(tmp_path / "diagnostics.jsonl")
    first = [dict(step=1, split="train", mpjpe=0.5), dict(step=1, split="test", mpjpe=0.6),
             dict(step=2, split="train", mpjpe=0.4)]
    resumed = [dict(step=2, split="train", mpjpe=0.3), dict(step=2, split="test", mpjpe=0.35),
               dict(step=3, split="train", mpjpe=0.2)]
    expression = ("[r.write(x) for r, rows in ((diagnose._Records({p!r}), {a!r}), "
                  "(diagnose._Records({p!r}), {b!r})) for x in rows] and 0")
    _suite_value("diagnose", expression.format(p=path, a=first, b=resumed))
    with open(path) as f:
        kept = [json.loads(line) for line in f]
    assert kept == first[:2] + resumed


@pytest.mark.parametrize("script, args, message", [
    ("experiments/dev_suite/analyse.py", ["nonsense"], "error: usage: analyse.py floors | "),
    ("experiments/emsfm/run.py", ["--n_iters=x"], "error: flag --n_iters=x: "),
])
def test_experiment_scripts_print_usage_errors_in_one_line(script, args, message):
    """The analysis scripts run as the library's commands do (``runner.run_main``): a usage
    error is one line and exit status 2, not absl's help page or a traceback."""
    out = subprocess.run([sys.executable, script, *args], cwd=ROOT, capture_output=True,
                         text=True, timeout=300)
    assert out.returncode == 2 and out.stderr.startswith(message), out.stderr[-2000:]
    assert out.stderr.count("\n") == 1 and not out.stdout


def test_analysis_helpers_on_shapes_with_known_answers():
    """analyse.deformation_spread is 0 for rotated, mirrored, scaled, shifted copies of one
    shape and positive for deformed ones; sign_aligned_mean undoes per-view depth flips;
    oracle_basis_fit recovers, in each view's own frame, rigid shapes with a basis of 1 and
    rank-1 deformations with a basis of 4 (the deformation and the 3 small rotations that
    aligning deformed shapes leaves), not with 1."""
    code = """
import numpy as np
import pytest
from scipy.spatial.transform import Rotation
rng = np.random.default_rng(3)
base, mode = rng.normal(size=(10, 3)), rng.normal(size=(10, 3))
rots = Rotation.random(40, random_state=4).as_matrix()
amp = rng.normal(size=40)
rigid = np.einsum('mij,nj->mni', rots, base) * rng.uniform(0.5, 2, (40, 1, 1)) + 3.0
mirrored = rigid * np.where(np.arange(40) % 2, 1.0, -1.0)[:, None, None]
deformed = np.einsum('mij,mnj->mni', rots, base + 0.5 * amp[:, None, None] * mode)
pred = rng.normal(size=(40, 10, 3))
flip = np.where(rng.random(40) < 0.5, -1.0, 1.0)[:, None, None]
flipped = np.concatenate([pred[..., :2], pred[..., 2:] * flip], -1)
def fit_error(shapes, d):
    c = shapes - shapes.mean(1, keepdims=True)
    return float(np.abs(analyse.oracle_basis_fit(shapes, c, d) - c).max())
out = [analyse.deformation_spread(mirrored), analyse.deformation_spread(deformed),
       float(np.abs(analyse.sign_aligned_mean(np.stack([pred, flipped, pred])) - pred).max()),
       fit_error(rigid / np.linalg.norm(rigid - rigid.mean(1, keepdims=True), axis=(1, 2),
                                        keepdims=True), 1),
       fit_error(deformed, 4), fit_error(deformed, 1)]
"""
    spread_rigid, spread_deformed, flip_err, rigid_err, rank1_err, rank1_d1_err = _suite_value(
        "analyse", f"(exec({code!r}, globals()), out)[1]")
    assert spread_rigid < 1e-6 and spread_deformed > 0.05
    assert flip_err < 1e-12
    assert rigid_err < 1e-9 and rank1_err < 1e-4 and rank1_d1_err > 0.05


def test_span_fit_and_2d_refit_recover_shapes_in_the_span():
    """analyse._span_fit represents scaled, rotated, half-mirrored copies of rank-1
    deformations exactly with the shape and its mode (weights, rotation and mirror give the
    shapes back), not with the shape alone; analyse._refit_2d, started near each view's
    answer, converges to it from the 2D points alone (a hidden point changes nothing)."""
    code = """
import numpy as np
import pytest
from scipy.spatial.transform import Rotation
rng = np.random.default_rng(5)
base, mode = rng.normal(size=(10, 3)), rng.normal(size=(10, 3))
rots = Rotation.random(12, random_state=6).as_matrix()
shapes = np.einsum('mij,mnj->mni', rots, base + rng.normal(size=(12, 1, 1)) * mode)
shapes = shapes * rng.uniform(0.5, 2, (12, 1, 1)) * np.array([1.0, 1.0, -1.0]) ** (
    np.arange(12) % 2)[:, None, None]
shapes = shapes - shapes.mean(1, keepdims=True)
rows, w, rot, sign, err = analyse._span_fit(shapes, np.stack([base, mode]))
mirror = np.stack([np.ones(12), np.ones(12), sign], -1)[:, None]
back = np.einsum('mnj,mjk->mnk', (w @ rows).reshape(shapes.shape), rot) * mirror
vis = np.ones((12, 10))
vis[:, 3] = 0.0
refit, dist = analyse._refit_2d(rows, w + 0.05 * rng.normal(size=w.shape), rot * mirror,
                                shapes[..., :2] + 1.0, vis)
out = [float(err.max()), float(np.abs(back - shapes).max()),
       float(analyse._span_fit(shapes, base[None])[-1].mean()), float(dist.max()),
       float(np.abs(refit - np.concatenate([shapes[..., :2] + 1.0, shapes[..., 2:]], -1)).max())]
"""
    err, back, rigid_err, dist, refit = _suite_value(
        "analyse", f"(exec({code!r}, globals()), out)[1]")
    assert err < 1e-6 and back < 1e-6
    assert rigid_err > 0.05
    assert dist < 1e-6 and refit < 1e-5


def test_bone_directions_count_and_undo_bones_turned_in_depth():
    """analyse.bone_directions on DeepMimic's tree: with the right wrist turned in depth
    about the elbow (the same 2D points and lengths) in some views and every other view
    mirrored whole, it counts exactly those bones as pointing the wrong way (of all the deep
    bones, of the arms', none of the legs' or the rest's), scores the MPJPE of the turned
    views, and its oracle undoes exactly those turns."""
    code = """
import numpy as np
import pytest
rng = np.random.default_rng(7)
parents = analyse.PARENTS['deepmimic']
m, n = 40, len(parents)
truth = np.zeros((m, n, 3))
for j, p in enumerate(parents):
    if p >= 0:
        d = rng.normal(size=(m, 3))
        truth[:, j] = truth[:, p] + d / np.linalg.norm(d, axis=1, keepdims=True)
dz = truth[:, 17, 2] - truth[:, 16, 2]
deep = np.stack([np.abs(truth[:, j, 2] - truth[:, p, 2]) >= 0.3 * np.linalg.norm(
    truth[:, j] - truth[:, p], axis=1) for j, p in enumerate(parents) if p >= 0], 1)
turn = (np.abs(dz) >= 0.3) & (np.arange(m) % 2 == 0)
pred = truth.copy()
pred[turn, 17, 2] -= 2 * dz[turn]
pred[1::2, :, 2] *= -1.0
c = lambda x: x - x[:, :, 2:].mean(1, keepdims=True) * np.array([0, 0, 1.0])
got = analyse.bone_directions(pred, truth, 'deepmimic')
unmirrored = pred.copy()
unmirrored[1::2, :, 2] *= -1.0
want = float(np.linalg.norm(c(unmirrored) - c(truth), axis=-1).mean())
arms = [13, 14, 16, 17]
joints = [j for j, p in enumerate(parents) if p >= 0]
out = [got, want, int(turn.sum()), int(deep.sum()),
       int(deep[:, [joints.index(j) for j in arms]].sum()), float(turn.mean())]
"""
    got, want_mpjpe, n_turned, n_deep, n_deep_arms, turned_share = _suite_value(
        "analyse", f"(exec({code!r}, globals()), out)[1]")
    mpjpe, wrong, arms, legs, rest, oracle, turns = got
    assert n_turned >= 5
    assert abs(mpjpe - want_mpjpe) < 1e-12 and mpjpe > 0.01
    assert abs(wrong - n_turned / n_deep) < 1e-12
    assert abs(arms - n_turned / n_deep_arms) < 1e-12
    assert legs == 0.0 and rest == 0.0
    assert oracle < 1e-9 and abs(turns - turned_share) < 1e-12


def test_relift_prefers_the_shapes_a_lifter_sees_from_every_side():
    """analyse.relift_choice with an exact lifter of one rigid body (the rigid fit of the
    body to the 2D points, which recovers noiseless views exactly): the truth is perfectly
    self-consistent, a view with the right wrist turned in depth is not, so exactly the
    turned views count as "truth more consistent", and taking each view's most consistent
    single turn undoes those turns, as the oracle does."""
    code = """
import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from c3dpo_jax import baselines
rng = np.random.default_rng(3)
parents = analyse.PARENTS['deepmimic']
n, m = len(parents), 30
body = np.zeros((n, 3))
for j, p in enumerate(parents):
    if p >= 0:
        d = rng.normal(size=3)
        body[j] = body[p] + d / np.linalg.norm(d)
body -= body.mean(0)
truth = np.einsum('mij,nj->mni', Rotation.random(m, random_state=4).as_matrix(), body)
dz = truth[:, 17, 2] - truth[:, 16, 2]
turn = (np.abs(dz) >= 0.3) & (np.arange(m) % 3 > 0)
pred = truth.copy()
pred[turn, 17, 2] -= 2 * dz[turn]
pred[::2, :, 2] *= -1.0
lift = lambda kp: baselines.fit_mean_shape(body, kp, np.ones(kp.shape[:2]))
out = [analyse.relift_choice(lift, pred, truth, 'deepmimic'), float(turn.mean()),
       float(analyse.relift_inconsistency(lift, truth).max())]
"""
    got, turned_share, truth_inconsistency = _suite_value(
        "analyse", f"(exec({code!r}, globals()), out)[1]")
    mpjpe, truer, own, true, picked, views_turned, oracle, agree = got
    assert turned_share >= 0.2 and truth_inconsistency < 1e-6
    assert mpjpe > 0.01 and own > 0.01 and true < 1e-6
    assert abs(truer - turned_share) < 1e-12
    assert picked < 1e-6 and oracle < 1e-6 and agree == 1.0
    assert abs(views_turned - turned_share) < 1e-12


def test_human_point_sets_take_the_joints_they_name_and_frames_have_their_views():
    """suite._human_points: ``humans_limbs`` is the 12 limb joints of the Human3.6M-order
    views, ``humans_coco_torso`` the COCO-order people (``_coco_people``) followed by the
    pelvis, spine, thorax and head top, 2D points and truth alike, each point's visibility
    its joint's; views_per_frame groups each suite set's consecutive views of one frame."""
    code = """
import numpy as np
from c3dpo_jax.data import KeypointData
rng = np.random.default_rng(0)
kp3d = rng.normal(size=(6, 17, 3)).astype(np.float32)
vis = (rng.uniform(size=(6, 17)) > 0.3).astype(np.float32)
data = KeypointData(kp=kp3d[..., :2].copy(), vis=vis, kp3d=kp3d)
limbs, torso, coco = (suite._human_points(data, "limbs"), suite._human_points(data, "coco_torso"),
                      suite._coco_people(data))
j, t = list(suite.LIMBS), list(suite.TORSO)
out = [limbs.n_keypoints, torso.n_keypoints,
       bool((limbs.kp3d == kp3d[:, j]).all() and (limbs.kp == kp3d[:, j, :2]).all()
            and (limbs.vis == vis[:, j]).all()),
       bool((torso.kp3d[:, :17] == coco.kp3d).all() and (torso.kp3d[:, 17:] == kp3d[:, t]).all()
            and (torso.kp == torso.kp3d[..., :2]).all() and (torso.vis[:, 17:] == vis[:, t]).all()
            and (torso.vis[:, :17] == coco.vis).all()),
       [suite.views_per_frame(n) for n in ("humans", "humans_coco_torso", "humans_coco_scaled",
                                           "drink", "face_k8", "cmu131_coco", "deepmimic_v10",
                                           "cmu131_k12", "humans_v3", "humans_noise02",
                                           "cmu131_noise11")]]
"""
    n_limbs, n_torso, limbs_ok, torso_ok, vpf = _suite_value(
        "suite", f"(exec({code!r}, globals()), out)[1]")
    assert (n_limbs, n_torso) == (12, 21) and limbs_ok and torso_ok
    assert vpf == [30, 30, 30, 10, 10, 3, 10, 3, 3, 30, 3]


def test_diagnostics_take_canonical_shapes_from_the_models_own_handedness():
    """diagnose.measure: a view that the inference mirrored (a body's handedness at
    inference, ``handedness_flipped``) counts with the model's own canonical shape and depth
    sign, so it is not spread between the views of a frame; the same mirrored shape not
    flagged is."""
    code = """
import numpy as np
from c3dpo_jax.data import KeypointData
rng = np.random.default_rng(0)
frames = rng.normal(size=(2, 1, 6, 3))
canon = np.repeat(frames, 3, axis=1).reshape(6, 6, 3)  # 2 frames x 3 views, one shape each
data = KeypointData(kp=canon[..., :2].astype(np.float32), vis=np.ones((6, 6), np.float32),
                    kp3d=canon.astype(np.float32))
mirrored = canon.copy()
mirrored[1, :, 2] *= -1  # one view given its mirror image, canonical shape and depth
flags = np.zeros(6)
pred = dict(shape_canonical=mirrored, shape_3d=mirrored, kp_reprojected=canon[..., :2],
            kp_scale=np.ones(6), alpha=np.zeros((6, 2)), handedness_flipped=flags)
flagged = diagnose.measure(dict(pred, handedness_flipped=np.eye(6)[1]), data, 3, "default")
unflagged = diagnose.measure(pred, data, 3, "default")
out = [flagged["canon_view_spread"], unflagged["canon_view_spread"],
       flagged["sign_agreement_own"], flagged["sign_agreement"], unflagged["sign_agreement_own"]]
"""
    flagged, unflagged, own, as_run, unflagged_own = _suite_value(
        "diagnose", f"(exec({code!r}, globals()), out)[1]")
    assert flagged < 1e-6 < 0.05 < unflagged
    assert own == 1.0 and as_run == unflagged_own == 5 / 6

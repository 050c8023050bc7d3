"""Train step, chunked loop, optimiser and resume."""

import json
import shutil

import chex
import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from c3dpo_jax import device_data, evaluate_workdir, model, run_records, train, validation
from c3dpo_jax.data import KeypointData, synthetic
from c3dpo_jax.lift import InferenceConfig
from c3dpo_jax.state import OptimConfig, create_train_state, make_optimizer, make_schedule
from configs import default, own_json

CFG = model.ModelConfig(
    n_keypoints=8, shape_basis_size=3, n_fully_connected=32, n_layers=1,
    canonicalization_n_fully_connected=32, canonicalization_n_layers=1, n_rand_samples=2,
    argmin_translation=True, z_augment=True,
)


@pytest.fixture(scope="module")
def setup():
    tx = make_optimizer(OptimConfig(optimizer="adam", lr=1e-3, weight_decay=0.0), 100)
    state = create_train_state(jax.random.key(0), CFG, tx)
    data = synthetic.make_split(512, n_keypoints=8, n_modes=2, deformation=0.3, occlusion=0.1,
                                noise=0.0, perspective=False, shape_seed=0, seed=1)
    step = train.make_train_step(CFG, train.LossConfig(), tx)
    chunk = jax.jit(train.make_train_chunk(step, 32), static_argnames="n_steps")
    return state, jax.device_put(data.model_inputs()), step, chunk


def test_one_step_is_deterministic_and_matches_golden_values(setup):
    state, data, step, _ = setup
    batch = jax.tree.map(lambda a: a[:16], data)
    jstep = jax.jit(step)
    s1, m1 = jstep(state, batch, jax.random.key(7))
    s2, m2 = jstep(state, batch, jax.random.key(7))
    chex.assert_trees_all_equal(s1, s2)
    chex.assert_trees_all_equal(m1, m2)
    assert int(s1.step) == 1
    # Golden values (recorded from this implementation at the commit that added them):
    # they catch unintended changes of the forward pass, losses or optimiser.
    np.testing.assert_allclose(float(m1["loss/reprojection"]), GOLDEN["repro"], rtol=1e-4)
    np.testing.assert_allclose(float(m1["loss/canonicalisation"]), GOLDEN["canon"], rtol=1e-4)
    np.testing.assert_allclose(float(m1["grad_norm"]), GOLDEN["grad_norm"], rtol=1e-4)


GOLDEN = {
    "repro": 0.8189995884895325,
    "canon": 0.00014182389713823795,
    "grad_norm": 0.05430825799703598,
}


def test_train_step_traces_once_for_repeated_calls(setup):
    state, data, step, _ = setup
    batch = jax.tree.map(lambda a: a[:16], data)
    counted = jax.jit(chex.assert_max_traces(step, n=1))
    for i in range(3):
        state, _ = counted(state, batch, jax.random.key(i))


def test_views_without_visible_points_leave_the_step_finite(setup):
    # Release files can hold such entries (PASCAL3D+'s bbox rule); release configs accept them.
    state, data, step, _ = setup
    batch = jax.tree.map(lambda a: a[:16], data)
    batch["vis"] = batch["vis"].at[:3].set(0.0)
    batch["kp"] = batch["kp"].at[:3].set(0.0)
    new_state, metrics = jax.jit(step)(state, batch, jax.random.key(3))
    assert all(np.isfinite(float(v)) for v in metrics.values())
    assert all(bool(jnp.all(jnp.isfinite(p))) for p in jax.tree.leaves(new_state.params))


def test_huge_values_at_hidden_points_never_reach_the_loss(setup):
    state, _, step, _ = setup
    data = synthetic.make_split(16, n_keypoints=8, n_modes=2, deformation=0.3, occlusion=0.3,
                                noise=0.0, perspective=False, shape_seed=0, seed=1)
    assert (data.vis == 0).any()
    kp = np.where(data.vis[..., None] > 0, data.kp, 1e20)  # "ignored" entries of a file
    huge = KeypointData(kp=kp, vis=data.vis).model_inputs()
    clean = KeypointData(kp=data.kp * data.vis[..., None], vis=data.vis).model_inputs()
    np.testing.assert_array_equal(huge["kp"], clean["kp"])
    _, metrics = jax.jit(step)(state, jax.device_put(huge), jax.random.key(3))
    assert np.isfinite(float(metrics["loss"]))


def test_loss_falls_within_200_steps(setup):
    state, data, _, chunk = setup
    state, metrics = chunk(state, data, jax.random.key(1), n_steps=200)
    loss = np.asarray(metrics["loss"])
    assert loss[-20:].mean() < 0.6 * loss[:20].mean()
    assert int(state.step) == 200


def test_sgd_matches_the_pytorch_update_with_weight_decay_in_the_gradient():
    cfg = OptimConfig(optimizer="sgd", lr=0.1, momentum=0.9, weight_decay=0.5)
    tx = make_optimizer(cfg, steps_per_epoch=10)
    p = {"w": jnp.array([1.0, -2.0])}
    g = {"w": jnp.array([0.3, 0.1])}
    opt = tx.init(p)
    buf, pn = np.zeros(2), np.array([1.0, -2.0])
    for _ in range(3):  # torch.optim.SGD: d = g + wd p; buf = m buf + d; p -= lr buf
        upd, opt = tx.update(g, opt, p)
        p = optax.apply_updates(p, upd)
        buf = 0.9 * buf + (np.array([0.3, 0.1]) + 0.5 * pn)
        pn = pn - 0.1 * buf
    np.testing.assert_allclose(p["w"], pn, rtol=1e-6)


def test_adamw_decays_the_kernels_outside_adam_and_leaves_biases_alone():
    # Adam's first step moves every parameter with a nonzero gradient by lr * sign(g)
    # (m / sqrt(v) = g / |g| after bias correction); the decoupled decay then subtracts
    # lr * wd * p from kernels only, so biases (the mean shape) and BatchNorm keep their
    # values when their gradient is zero.
    cfg = OptimConfig(optimizer="adamw", lr=0.1, weight_decay=0.5)
    tx = make_optimizer(cfg, steps_per_epoch=10)
    p = {"layer": {"kernel": jnp.array([1.0, -2.0]), "bias": jnp.array([3.0])},
         "bn": {"scale": jnp.array([2.0])}}
    g = {"layer": {"kernel": jnp.array([0.3, 0.0]), "bias": jnp.array([0.0])},
         "bn": {"scale": jnp.array([0.0])}}
    upd, _ = tx.update(g, tx.init(p), p)
    new = optax.apply_updates(p, upd)
    np.testing.assert_allclose(new["layer"]["kernel"],
                               [1.0 - 0.1 * 1.0 - 0.1 * 0.5 * 1.0, -2.0 + 0.1 * 0.5 * 2.0],
                               rtol=1e-5)
    np.testing.assert_array_equal(new["layer"]["bias"], [3.0])
    np.testing.assert_array_equal(new["bn"]["scale"], [2.0])


def test_learning_rate_milestones_are_given_in_epochs():
    sched = make_schedule(
        OptimConfig(lr=1e-3, lr_milestones=(2, 3), gamma=0.1), steps_per_epoch=100
    )
    np.testing.assert_allclose([sched(199), sched(200), sched(299), sched(300)],
                               [1e-3, 1e-4, 1e-4, 1e-5], rtol=1e-6)


def test_warm_up_ramps_the_rate_without_moving_the_milestones():
    cfg = OptimConfig(lr=2e-3, lr_milestones=(2,), gamma=0.1, warmup_steps=150)
    sched = make_schedule(cfg, steps_per_epoch=100)
    t = np.array([0, 75, 149, 150, 199, 200, 250, 400])
    # written out by hand: the rate rises linearly to 2e-3 at step 150, then the x0.1
    # decay happens at step 200 (epoch 2), not 150 steps later
    expected = 2e-3 * np.minimum(t / 150.0, 1.0) * np.where(t >= 200, 0.1, 1.0)
    np.testing.assert_allclose([float(sched(s)) for s in t], expected, rtol=1e-5, atol=1e-12)


def test_class_balanced_sampling_draws_classes_uniformly():
    group = np.array([0] * 90 + [1] * 10)
    data = KeypointData(kp=np.zeros((100, 3, 2)), vis=np.ones((100, 3)), group=group,
                        group_names=("a", "b"))
    dev = device_data.device_train_data(data, class_balanced=True)
    idx = np.asarray(device_data.sample_indices(dev, jax.random.key(0), 20000))
    assert abs((idx >= 90).mean() - 0.5) < 0.02
    assert idx.min() >= 0 and idx.max() < 100


def test_non_finite_loss_stops_training_and_names_the_step(tmp_path):
    class Bar:
        def update(self, n): ...
        def set_postfix(self, **kw): ...
    writer = run_records.MetricsWriter(str(tmp_path), Bar())
    ok = {"loss": np.ones(3), "loss/reprojection": np.ones(3), "loss/canonicalisation": np.ones(3)}
    writer.push(100, ok)
    writer.push(103, dict(ok, loss=np.array([1.0, np.nan, 2.0])))
    with pytest.raises(FloatingPointError, match="step 104"):
        writer.flush()
    assert json.loads((tmp_path / "metrics.jsonl").read_text())["step"] == 103


def _tiny_config(num_steps):
    c = default.apply_variants(default.get_config(), "smoke")
    c.model.n_keypoints = c.data.synthetic.n_keypoints = 8
    c.model.shape_basis_size = 3
    c.train.num_steps = num_steps
    c.train.ckpt_every = 10
    c.train.log_every = 5
    c.train.progress_bar = False
    return c


def test_stop_and_resume_equals_an_uninterrupted_run(tmp_path, caplog):
    from c3dpo_jax import checkpoint

    whole = train.train_and_evaluate(_tiny_config(20), str(tmp_path / "whole"))
    train.train_and_evaluate(_tiny_config(10), str(tmp_path / "split"))
    resumed = train.train_and_evaluate(_tiny_config(20), str(tmp_path / "split"))
    assert resumed["final"]["step"] == whole["final"]["step"] == 20
    cfg = _tiny_config(20)
    spec = train.RunSpec.from_config(cfg)
    template = create_train_state(jax.random.key(0), spec.model, spec.optimizer())
    a, _ = checkpoint.restore_latest(str(tmp_path / "whole"), template)
    b, _ = checkpoint.restore_latest(str(tmp_path / "split"), template)
    chex.assert_trees_all_close(a, b, atol=1e-6)
    assert resumed["final"]["mpjpe"] == pytest.approx(whole["final"]["mpjpe"], abs=1e-6)
    # Scoring again with other inference options says which were used: the history's
    # records were made with the run's own.
    cfg.inference.refine_iters = 3
    again = evaluate_workdir.evaluate_checkpoint(cfg, str(tmp_path / "whole"))
    assert again["final"]["inference"] == {"refine_iters": 3}
    assert "inference" not in whole["final"]  # main_test: nor when scored with the run's own
    # A workdir whose checkpoint is past the steps asked for is scored as it is, with a word.
    with caplog.at_level("WARNING"):
        shorter = train.train_and_evaluate(_tiny_config(10), str(tmp_path / "whole"))
    assert shorter["final"]["step"] == 20
    assert "holds a checkpoint at step 20, past the 10 steps asked for" in caplog.text


def test_an_evaluation_lost_to_a_kill_after_its_checkpoint_is_made_on_resuming(tmp_path):
    """A kill after the checkpoint of an evaluation's step and before that evaluation was
    recorded (its record removed here) leaves a curve without it; resuming makes it first,
    equal to the uninterrupted run's."""
    from c3dpo_jax import run_records

    c = _tiny_config(30)
    c.train.eval_every_steps = 10
    whole = train.train_and_evaluate(c, str(tmp_path / "whole"))
    c.train.num_steps = 20
    workdir = str(tmp_path / "killed")
    train.train_and_evaluate(c, workdir)
    records = run_records.read_results(workdir)
    run_records.write_results(workdir, {"history": [h for h in records["history"]
                                                    if h["step"] < 20]})
    c.train.num_steps = 30
    resumed = train.train_and_evaluate(c, workdir)
    assert [h["step"] for h in resumed["history"]] == [h["step"] for h in whole["history"]]
    lost = next(h for h in resumed["history"] if h["step"] == 20)
    want = next(h for h in whole["history"] if h["step"] == 20)
    assert lost["mpjpe"] == pytest.approx(want["mpjpe"], abs=1e-6)


def test_a_workdir_that_is_a_file_is_named(tmp_path):
    (tmp_path / "file").write_text("")
    for run in (train.train_and_evaluate, evaluate_workdir.evaluate_checkpoint):
        with pytest.raises(ValueError, match="is a file; --workdir names a folder"):
            run(_tiny_config(5), str(tmp_path / "file"))


def test_hooks_see_every_evaluation_and_a_stop_resumes_to_the_same_run(tmp_path, read_scalars):
    c = _tiny_config(20)
    c.train.eval_every_steps = 5
    whole = train.train_and_evaluate(c, str(tmp_path / "whole"))
    assert [h["step"] for h in whole["history"]] == [5, 10, 15]
    times = [h["train_s"] for h in whole["history"]] + [whole["final"]["train_s"]]
    assert all(0 < a <= b for a, b in zip(times, times[1:], strict=False))
    seen, chunks = [], []
    hooks = train.Hooks(after_chunk=lambda step, state: chunks.append(step),
                        after_evaluation=lambda record, state: seen.append(
                            (record["step"], int(state.step))),
                        should_stop=lambda step, train_s: step >= 10)
    stopped = train.train_and_evaluate(c, str(tmp_path / "split"), hooks)
    assert stopped["final"]["step"] == 10 and seen == [(5, 5), (10, 10)]
    assert chunks == sorted(chunks) and chunks[-1] == 10
    resumed = train.train_and_evaluate(c, str(tmp_path / "split"))
    assert [h["step"] for h in resumed["history"]] == [5, 10, 15]
    assert resumed["final"]["mpjpe"] == pytest.approx(whole["final"]["mpjpe"], abs=1e-6)
    # TensorBoard, next to metrics.jsonl, shows the resumed run as one run.
    curves = read_scalars(tmp_path / "split")
    assert [s for s, _ in curves["loss/reprojection"]] == [5, 10, 15, 20]
    assert curves["test/mpjpe"] == [(h["step"], pytest.approx(h["mpjpe"], rel=1e-6))
                                    for h in [*resumed["history"], resumed["final"]]]
    # Evaluations a hook asks for (e.g. at times of a clock) instead of every N steps.
    c.train.eval_every_steps = c.train.eval_every_epochs = 0
    asked = train.train_and_evaluate(c, str(tmp_path / "asked"), train.Hooks(
        should_evaluate=lambda step, train_s: train_s > 0 and step in (5, 15)))
    assert [h["step"] for h in asked["history"]] == [5, 15]
    assert [h["mpjpe"] for h in asked["history"]] == pytest.approx(
        [whole["history"][0]["mpjpe"], whole["history"][2]["mpjpe"]], abs=1e-6)


@pytest.mark.parametrize("variant", ["base", "equiv", "full", "perspective"])
def test_every_variant_and_perspective_projection_train(variant, tmp_path):
    import dataclasses

    cfg = dataclasses.replace(CFG, z_equivariance=variant != "base",
                              canonicalization=variant in ("full", "perspective"))
    data_kw = {}
    if variant == "perspective":
        cfg = dataclasses.replace(cfg, projection_type="perspective", camera_translation=True,
                                  depth_offset=6.0, argmin_translation=False)
        data_kw = {"perspective": True}
    data = synthetic.make_split(
        512,
        n_keypoints=8,
        n_modes=2,
        deformation=0.3,
        occlusion=0.1,
        noise=0.0,
        shape_seed=0,
        seed=1,
        **{"perspective": False, **data_kw},
    )
    assert (data.intrinsics is not None) == (variant == "perspective")
    tx = make_optimizer(OptimConfig(optimizer="adam", lr=1e-3, weight_decay=0.0), 100)
    state = create_train_state(jax.random.key(0), cfg, tx)
    chunk = jax.jit(train.make_train_chunk(train.make_train_step(cfg, train.LossConfig(), tx), 32),
                    static_argnames="n_steps")
    state, metrics = chunk(
        state, jax.device_put(data.model_inputs()), jax.random.key(1), n_steps=150
    )
    repro = np.asarray(metrics["loss/reprojection"])
    assert np.all(np.isfinite(repro))
    assert repro[-20:].mean() < 0.7 * repro[:20].mean()
    has_canon = np.asarray(metrics["loss/canonicalisation"])[-1] > 0
    assert has_canon == cfg.canonicalization
    res = train.evaluate_split(state.variables, data, cfg, InferenceConfig(), "default")
    assert np.isfinite(res["mpjpe"]) and np.isfinite(res["reprojection"])


def test_canonicalisation_weight_ramp(setup):
    """The ramped weight follows the linear schedule, and the objective uses the weight of
    the step it is given: objective = l_repro + w(step) * l_canon at any step."""
    ramp = train.LossConfig(w_canonicalization=1.0, w_canonicalization_final=3.0,
                            canonicalization_ramp=(100, 300))
    weights = [float(ramp.canonicalization_weight(s)) for s in (0, 100, 200, 300, 1000)]
    np.testing.assert_allclose(weights, [1.0, 1.0, 2.0, 3.0, 3.0])
    jump = train.LossConfig(w_canonicalization_final=0.5, canonicalization_ramp=(10, 10))
    assert [float(jump.canonicalization_weight(s)) for s in (9, 10)] == [1.0, 0.5]
    state, data, _, _ = setup
    batch = jax.tree.map(lambda a: a[:16], data)
    loss_fn = jax.jit(train.make_loss_fn(CFG, ramp))
    for step, w in ((0, 1.0), (250, 2.5)):
        objective, (_, m) = loss_fn(state.params, state.batch_stats, batch,
                                    jax.random.key(3), step)
        np.testing.assert_allclose(
            objective, m["loss/reprojection"] + w * m["loss/canonicalisation"], rtol=1e-6)
    with pytest.raises(ValueError, match="canonicalization_ramp"):
        train.LossConfig(canonicalization_ramp=(5, 1), w_canonicalization_final=2.0)
    with pytest.raises(ValueError, match="w_canonicalization_final"):
        train.LossConfig(canonicalization_ramp=(1, 5))


def test_deformation_prior_is_the_mean_squared_deformation(setup):
    """The deformation term is 0 for a basis of zeros, grows as the square of the basis'
    scale (Phi's coefficients do not depend on the basis), and enters the objective
    linearly with its weight; the default weight 0 leaves the paper's objective."""
    state, data, _, _ = setup
    batch = jax.tree.map(lambda a: a[:16], data)

    def terms(params, w):
        loss_fn = train.make_loss_fn(CFG, train.LossConfig(w_deformation=w))
        objective, (_, m) = loss_fn(params, state.batch_stats, batch, jax.random.key(3))
        return float(objective), m

    def scaled_basis(c):
        params = jax.tree.map(lambda a: a, state.params)  # a copy of the tree
        layer = dict(params["shape_layer"])
        layer["kernel"] = layer["kernel"] * c
        return {**params, "shape_layer": layer}

    _, m1 = terms(state.params, 0.0)
    _, m2 = terms(scaled_basis(2.0), 0.0)
    _, m0 = terms(scaled_basis(0.0), 0.0)
    d1 = float(m1["loss/deformation"])
    assert d1 > 0
    np.testing.assert_allclose(float(m2["loss/deformation"]), 4.0 * d1, rtol=1e-4)
    assert float(m0["loss/deformation"]) == 0.0
    base, _ = terms(state.params, 0.0)
    np.testing.assert_allclose(base, float(m1["loss/reprojection"])
                               + float(m1["loss/canonicalisation"]), rtol=1e-6)
    w = 1e5  # the initial basis is small: a weight that makes the term matter
    weighted, mw = terms(state.params, w)
    assert weighted > base + 0.1
    np.testing.assert_allclose(weighted, float(mw["loss/reprojection"]) + float(
        mw["loss/canonicalisation"]) + w * float(mw["loss/deformation"]), rtol=1e-6)
    np.testing.assert_allclose(float(mw["loss/deformation"]), d1, rtol=1e-6)
    decay = train.LossConfig(w_deformation=1.0, w_deformation_final=0.0,
                             deformation_ramp=(3000, 5000))
    np.testing.assert_allclose([float(decay.deformation_weight(s)) for s in (0, 3000, 4500, 6000)],
                               [1.0, 1.0, 0.25, 0.0])
    with pytest.raises(ValueError, match="w_deformation_final"):
        train.LossConfig(deformation_ramp=(1, 5))


def test_a_ramp_that_ends_after_the_run_is_warned_about():
    c = default.get_config()
    c.train.num_steps = 20
    c.loss.deformation_ramp, c.loss.w_deformation_final = (3000, 5000), 0.0
    messages = train.RunSpec.from_config(c).warnings()
    assert len(messages) == 1 and messages[0].startswith(
        "config.loss.deformation_ramp=(3000, 5000) ends after the run's 20 steps")
    c.loss.deformation_ramp = (5, 10)
    assert train.RunSpec.from_config(c).warnings() == []
    c.optim.warmup_steps = 21  # a warm-up longer than the run
    assert train.RunSpec.from_config(c).warnings() == [
        "config.optim.warmup_steps=21 is longer than the run's 20 steps: the learning rate "
        "never reaches config.optim.lr"]
    # The :smoke variant shrinks a config's ramps with its run: own_json's prior ramps
    # over 10-20% of its 10,000 steps, so over steps 2-4 of the smoke run's 20, unwarned.
    smoke = own_json.get_config("smoke")
    assert own_json.get_config().loss.deformation_ramp == (1000, 2000)
    assert smoke.loss.deformation_ramp == (2, 4) and smoke.train.num_steps == 20
    assert train.RunSpec.from_config(smoke).warnings() == []
    c.optim.warmup_steps = 0
    c.model.n_keypoints, c.model.shape_basis_size = 5, 15  # a basis of every 3K = 15 shape
    assert train.RunSpec.from_config(c).warnings() == [
        "config.model.shape_basis_size=15 is not below 3K = 15: such a basis fits any shape, "
        "so the views no longer constrain the depth (keep D well below 3K, docs/data.md)"]
    c.model.shape_basis_size = 14
    assert train.RunSpec.from_config(c).warnings() == []
    # :smoke shrinks the warm-up with the run too.
    assert own_json.get_config().optim.warmup_steps == 500
    assert smoke.optim.warmup_steps == 1  # 500 of 10,000 steps -> 1 of 20, unwarned above


def test_cosine_schedule_matches_its_formula():
    cfg = OptimConfig(optimizer="adam", lr=3e-3, schedule="cosine", cosine_steps=1000)
    sched = make_schedule(cfg, steps_per_epoch=100)
    t = np.array([0, 250, 500, 999, 1000, 1500])
    expected = 3e-3 * 0.5 * (1 + np.cos(np.pi * np.minimum(t, 1000) / 1000))
    np.testing.assert_allclose([float(sched(s)) for s in t], expected, rtol=1e-5, atol=1e-9)
    for bad in (dict(schedule="cosine"), dict(schedule="linear")):
        with pytest.raises(ValueError, match="optim"):
            make_schedule(OptimConfig(**bad), 100)


def test_results_file_is_replaced_whole_and_a_damaged_one_only_warns(tmp_path, caplog):
    run_records.write_results(str(tmp_path), {"history": [{"step": 5}]})
    assert sorted(p.name for p in tmp_path.iterdir()) == ["eval_results.json"]
    assert run_records.read_results(str(tmp_path)) == {"history": [{"step": 5}]}
    text = (tmp_path / "eval_results.json").read_text()
    (tmp_path / "eval_results.json").write_text(text[: len(text) // 2])  # a kill mid-write
    with caplog.at_level("WARNING"):
        assert run_records.read_results(str(tmp_path)) == {}
    assert "eval_results.json cannot be read" in caplog.text


def test_supervised_term_is_the_mean_distance_to_the_centred_truth(setup):
    """With a basis of zeros Phi's shape is one point, so the term is the mean distance of
    the centred, rescaled truth to its centre (numpy); a shift of the truth changes
    nothing; the objective adds it with its weight, and the default weight 0 leaves the
    objective and the metrics as they were."""
    state, data, _, _ = setup
    batch = jax.tree.map(lambda a: a[:16], data)
    train_3d = synthetic.make_split(512, n_keypoints=8, n_modes=2, deformation=0.3,
                                    occlusion=0.1, noise=0.0, perspective=False, shape_seed=0,
                                    seed=1).kp3d[:16]
    layer = {k: v * 0.0 for k, v in state.params["shape_layer"].items()}
    flat = {**state.params, "shape_layer": layer}

    def run(params, w, kp3d):
        loss_fn = train.make_loss_fn(CFG, train.LossConfig(w_supervised=w))
        objective, (_, m) = loss_fn(params, state.batch_stats, dict(batch, kp3d=kp3d),
                                    jax.random.key(3))
        return float(objective), m

    truth = train_3d * CFG.keypoint_rescale
    expected = np.linalg.norm(truth - truth.mean(1, keepdims=True), axis=-1).mean()
    _, m = run(flat, 1.0, jnp.asarray(train_3d))
    np.testing.assert_allclose(float(m["loss/supervised"]), expected, rtol=1e-5)
    shifted = run(flat, 1.0, jnp.asarray(train_3d + np.array([3.0, -2.0, 7.0])))[1]
    np.testing.assert_allclose(float(shifted["loss/supervised"]), expected, rtol=1e-5)
    objective, m = run(state.params, 2.5, jnp.asarray(train_3d))
    np.testing.assert_allclose(objective, float(m["loss/reprojection"]) + float(
        m["loss/canonicalisation"]) + 2.5 * float(m["loss/supervised"]), rtol=1e-6)
    off_objective, off = run(state.params, 0.0, jnp.asarray(train_3d))
    assert "loss/supervised" not in off
    np.testing.assert_allclose(off_objective, float(m["loss/reprojection"]) + float(
        m["loss/canonicalisation"]), rtol=1e-6)


def test_supervised_training_needs_finite_3d_points_in_the_training_split():
    data = synthetic.make_split(16, n_keypoints=8, n_modes=2, deformation=0.3, occlusion=0.1,
                                noise=0.0, perspective=False, shape_seed=0, seed=1)
    validation.check_data(data, CFG, "train", with_3d=True)
    for kp3d, what in ((None, "has none"), (np.full_like(data.kp3d, np.nan), "not finite")):
        bad = KeypointData(kp=data.kp, vis=data.vis, kp3d=kp3d)
        with pytest.raises(ValueError, match=f"w_supervised > 0 .* {what}"):
            validation.check_data(bad, CFG, "train", with_3d=True)
        validation.check_data(bad, CFG, "train")  # C3DPO itself never needs them


def test_init_from_starts_a_run_from_another_runs_model(tmp_path):
    """train.init_from: a new run starts from the source's parameters (at a learning rate of
    1e-9 they stay), with the source's input scale; a model of another architecture is a
    one-line error naming the setting."""
    from c3dpo_jax import load, run_config
    from c3dpo_jax.data import auto_keypoint_rescale, load_splits

    source = str(tmp_path / "source")
    train.train_and_evaluate(_tiny_config(10), source)
    c = _tiny_config(1)
    c.train.init_from = source
    c.optim.lr = 1e-9
    c.data.synthetic.seed = 7  # other views: the data alone would give another input scale
    assert train.train_and_evaluate(c, str(tmp_path / "tuned"))["final"]["step"] == 1
    theirs, ours = (load(str(tmp_path / d)).variables for d in ("source", "tuned"))
    chex.assert_trees_all_close(ours["params"], theirs["params"], atol=1e-6)
    scales = [run_config.load_config(str(tmp_path / d))["model"]["keypoint_rescale"]
              for d in ("source", "tuned")]
    assert scales[0] == scales[1]
    assert auto_keypoint_rescale(load_splits(c.data)[0]) != scales[0]
    wider = _tiny_config(1)
    wider.model.n_fully_connected = 48
    wider.train.init_from = source
    with pytest.raises(ValueError, match=r"^config.train.init_from=.* another architecture"):
        train.train_and_evaluate(wider, str(tmp_path / "wider"))
    shutil.rmtree(source)  # a resumed run needs only its own workdir
    assert train.train_and_evaluate(c, str(tmp_path / "tuned"))["final"]["step"] == 1

"""Scoring a workdir's latest checkpoint without training (``--mode=eval``).

``evaluate_checkpoint(config, workdir)`` refuses a config whose model differs from the
one the run trained, scores the checkpoint on the test split with the config's inference
options and updates the workdir's ``eval_results.json``.
"""

import json

import jax
import jax.numpy as jnp
from absl import logging

from c3dpo_jax import checkpoint, lift, model, run_config, run_records, validation
from c3dpo_jax.data import load_splits
from c3dpo_jax.inference import evaluate_baselines, evaluate_split, with_views_mean
from c3dpo_jax.lift import InferenceConfig
from c3dpo_jax.resolve import resolve_from_data
from c3dpo_jax.train import RunSpec

# Model fields that may differ between a run and its scoring (``--mode=eval``): how the
# matmuls are done and what only training reads (the inference options are a config of
# their own, ``lift.InferenceConfig``).
_SCORING_OPTIONS = ("matmul_precision", "z_equivariance", "z_equivariance_rot_angle",
                    "n_rand_samples", "canonicalization_rot_angle", "weight_init_std")


def _check_model(saved: dict | None, model_cfg: model.ModelConfig, template,
                 workdir: str) -> None:
    """Refuses in one line to score a workdir's checkpoints with a config whose model
    differs from the one its run trained (other parameter shapes, or other settings such as
    the input scale, which would score another function of the same parameters), naming
    the fields that differ; ``matmul_precision`` and the fields only training reads
    (``_SCORING_OPTIONS``) may differ, and the inference options are not the model's (a
    saved model section that holds them, ``model.MOVED_TO_INFERENCE``, is read without
    them)."""
    if not saved or "model" not in saved:
        return

    def network(fields: dict) -> dict:
        return {k: v for k, v in fields.items()
                if k not in model.MOVED_TO_INFERENCE and k not in _SCORING_OPTIONS}

    now = json.loads(json.dumps(model_cfg.to_dict()))  # tuples as the saved JSON lists
    diffs = run_config.differences({"model": network(saved["model"])}, {"model": network(now)})
    if not diffs:
        return
    trained = model.variables_shape(model.ModelConfig.from_dict(saved["model"]))
    shaped = jax.tree.map(jnp.shape, trained) != jax.tree.map(jnp.shape, template)
    more = f"; and {len(diffs) - 3} more" if len(diffs) > 3 else ""
    what = "of another shape than" if shaped else "trained with other model settings than"
    raise ValueError(f"{workdir} holds a network {what} the config's ({'; '.join(diffs[:3])}"
                     f"{more}); evaluate it with the config it was trained with")


def _inference_options(options: InferenceConfig, saved: dict | None) -> dict:
    """The inference options of ``options`` that differ from the run's saved config's
    (``lift.saved_options``: an option the run's config predates counts as its default,
    which such a run used)."""
    if not saved or "model" not in saved:
        return {}
    now = json.loads(json.dumps(options.to_dict()))  # tuples as the saved JSON lists
    before = {**json.loads(json.dumps(InferenceConfig().to_dict())), **lift.saved_options(saved)}
    if options.handedness_reference == "views_mean":  # rows of the step scored, not options
        now.pop("handedness_body")
    return {k: v for k, v in now.items() if before[k] != v}


@model.single_precision
def evaluate_checkpoint(config, workdir: str, save: bool = True) -> dict:
    """``--mode=eval``: scores the latest checkpoint in ``workdir`` on the test split.

    Updates ``final`` and ``baselines`` of ``eval_results.json`` (``save=False``: returns
    them without writing, as the command does until it has printed them, so that a
    workdir it cannot write still shows its scores; not while a run trains there, nor over
    final scores of a later step: ``run_records.left_unwritten``); its training history stays,
    and the new ``final`` keeps the training clock of the latest record at or before the
    checkpoint's step (``run_records.clock_at``). Where the config's inference options
    (``config.inference``, checked against the model by ``lift.inference_config``) differ
    from the run's, ``final["inference"]`` records those that differ, since the history's
    records were made with the run's.
    """
    validation.check_workdir_is_a_folder(workdir)
    train_data, test_data = load_splits(config.data)
    validation.check_split_keypoints(train_data, test_data, config.model.n_keypoints)
    saved = run_config.load_config(workdir)
    config = resolve_from_data(config, train_data, saved)
    spec = RunSpec.from_config(config)
    model_cfg = spec.model
    options = lift.inference_config(model_cfg, spec.inference)
    template = model.variables_shape(model_cfg)
    _check_model(saved, model_cfg, template, workdir)
    variables, step = checkpoint.restore_variables(workdir, template)
    validation.check_data(test_data, model_cfg, "test")
    options = with_views_mean(options, variables, train_data, model_cfg)[0]  # the step's own
    final = evaluate_split(variables, test_data, model_cfg, options, config.data.protocol,
                           batch_size=config.train.eval_batch_size)
    before = run_records.read_results(workdir)
    clock = run_records.clock_at(before, step)
    final = dict(step=step, epoch=step // spec.steps_per_epoch,
                 **({} if clock is None else {"train_s": clock}), **final)
    inference = _inference_options(options, saved)
    if inference:
        final["inference"] = inference
    results = dict(before, final=final,
                   baselines=evaluate_baselines(train_data, test_data, config.data.protocol))
    if save:
        why = run_records.left_unwritten(workdir, step)
        if why is None:
            run_records.write_results(workdir, results)
        else:
            logging.warning("scores not written to %s/eval_results.json: %s", workdir, why)
    return results

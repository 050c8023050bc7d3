r"""Command line: trains C3DPO and scores it (or python -m c3dpo_jax.main ...).

  c3dpo-train --config=configs/synthetic.py --workdir=runs/synthetic     # built-in data
  c3dpo-train --config=configs/own_json.py --workdir=runs/mine \
      --config.data.train_path=A_train.json --config.data.test_path=A_test.json \
      --config.model.n_keypoints=K                                        # your keypoints

Trains (resuming from DIR when it holds checkpoints) and evaluates, or with --mode=eval
scores the latest checkpoint in DIR. Any config field can be set with
--config.section.field=value; --nofigures skips the pictures written after training.
configs/NAME.py is the package's bundled config when the working directory has no such
file. Errors in the input print as one line "error: ..." (exit status 2); --verbose logs
the resolved config and the loop's periodic metrics, and keeps tracebacks.
"""

import sys

from absl import flags, logging
from ml_collections import config_flags

from c3dpo_jax import cli, evaluate_workdir, evaluation, run_records, train, validation

_CONFIG = config_flags.DEFINE_config_file(
    "config", None, "Config file FILE[:ARGS], e.g. configs/synthetic.py:smoke (configs/NAME.py: "
    "the bundled config when the working directory has no such file).", lock_config=True
)
_WORKDIR = flags.DEFINE_string("workdir", None, "Directory for checkpoints, metrics and results.")
_MODE = flags.DEFINE_enum(
    "mode", "train", ["train", "eval"], "Train then evaluate, or evaluate only."
)
_FIGURES = flags.DEFINE_bool(
    "figures", True, "After training, write pictures into WORKDIR/figures (--nofigures: skip)."
)
_VERBOSE = flags.DEFINE_bool(
    "verbose", False, "Log the resolved config and the training loop's periodic metrics; "
    "show the traceback of input errors.")
flags.mark_flags_as_required(["config", "workdir"])


def _header(config) -> str:
    """What runs, in two or three lines (the whole resolved config is in WORKDIR/config.json)."""
    flag = flags.FLAGS[_CONFIG.name]
    d = config.data
    if d.train_path:
        data = f"{d.train_path} / {d.test_path}"
    elif d.source == "release" or d.name == d.source:
        data = d.name
    else:  # e.g. a release config's :smoke variant, which trains on generated data
        data = f"{d.source} (generated, in place of {d.name})"
    lines = [f"c3dpo_jax {_MODE.value}: {config_flags.get_config_filename(flag)} -> "
             f"{_WORKDIR.value}", f"  data: {data}, {config.model.n_keypoints} keypoints"]
    if _MODE.value == "train":
        spec = train.RunSpec.from_config(config)
        lines[-1] += f"; {spec.total_steps} steps of batch {spec.batch_size}"
    overrides = config_flags.get_override_values(flag)
    if overrides:
        lines.append("  overrides: " + ", ".join(f"{k}={v}" for k, v in overrides.items()))
    return "\n".join(lines)


def _method(config) -> str:
    """The results table's name for what was trained: C3DPO, one of the paper's ablations
    (C3DPO-base, C3DPO-equiv) or the network trained with the 3D truth, which is not C3DPO."""
    if config.loss.w_supervised > 0:
        return "3D-supervised network"
    if not config.model.canonicalization:
        return "C3DPO-equiv" if config.model.z_equivariance else "C3DPO-base"
    return "C3DPO"


def _unit_2d(config) -> str:
    """The unit of the data's 2D points (a data file's "unit", e.g. px; the built-in humans'
    m), '' when unknown."""
    from c3dpo_jax import visualise

    try:
        return visualise.run_style({"data": config.data.to_dict()})["unit"]
    except (OSError, ValueError):  # the scores are shown all the same
        return ""


def _write_figures(config, workdir):
    """A few pictures into workdir/figures; a plotting failure never fails the run."""
    try:
        from c3dpo_jax import visualise
        from c3dpo_jax.data import load_splits
        from c3dpo_jax.reconstruct import load, reconstruct_data

        verbosity = logging.get_verbosity()  # the data's warnings were given at training
        logging.set_verbosity(logging.ERROR)
        try:
            test = load_splits(config.data)[1]
        finally:
            logging.set_verbosity(verbosity)
        visualise.write_run_figures(workdir, test, reconstruct_data(load(workdir), test, 3))
    except Exception as err:  # noqa: BLE001 (pictures are optional)
        logging.warning("could not write figures to %s/figures: %r", workdir, err)


def main(argv):
    del argv
    config = _CONFIG.value
    validation.check_config(config)
    verbose = cli.is_verbose(_VERBOSE)
    # The bar shows the losses; the loop's "step N: {...}" lines (periodic metrics, test
    # scores: in metrics.jsonl and eval_results.json) would only repeat them at 16 digits.
    cli.setup_logging(hidden=() if verbose or not config.train.progress_bar else ("step %d:",))
    print(_header(config), flush=True)
    if verbose:
        logging.info("config:\n%s", config)
    if _MODE.value == "train":
        results = train.train_and_evaluate(config, _WORKDIR.value)  # cli.run: Ctrl-C, SIGTERM
        if _FIGURES.value:
            _write_figures(config, _WORKDIR.value)
    else:
        results = evaluate_workdir.evaluate_checkpoint(config, _WORKDIR.value, save=False)
    rows = {_method(config): results["final"], **results.get("baselines", {})}
    print(f"\nTest split ({results['final']['n_samples']} samples, protocol "
          f"'{config.data.protocol}'), step {results['final']['step']}:")
    print(evaluation.format_table(rows))
    if "inference" in results["final"]:
        options = ", ".join(f"inference.{k}={v}"
                            for k, v in results["final"]["inference"].items())
        print(f"{_method(config)} scored with inference options other than the training's: "
              f"{options}")
    if "mpjpe" in results["final"]:
        print("mpjpe_global: the 3D prediction as it is or every view mirrored, the better "
              "(what you get, up to one mirror flip of the whole set); mpjpe: per view the "
              "better of the prediction and its mirror image (the paper's protocol); "
              "mpjpe_orig: the prediction as it is; stress: the error of the distances between "
              "points")
    unit = _unit_2d(config) if "reprojection" in results["final"] else ""
    if unit:
        print(f"reprojection: the mean 2D distance of the visible points to their reprojection, "
              f"in {unit}")
    if "mirrored" in results["final"]:
        print("mirrored: the fraction of test views whose canonical shape, as the model "
              "lifts it before any handedness given at inference, has the other handedness "
              "than most (0: one for all; about 0.5: a coin toss per view, docs/inference.md)")
    if _MODE.value == "eval":  # after the table: a workdir it cannot write still shows it
        sys.stdout.flush()
        why = run_records.left_unwritten(_WORKDIR.value, results["final"]["step"])
        if why is not None:
            print(f"scores not written to {_WORKDIR.value}/eval_results.json: {why}")
            return
        run_records.write_results(_WORKDIR.value, results)
    print(f"results written to {_WORKDIR.value}/eval_results.json")
    sys.stdout.flush()


def cli_main():
    """The ``c3dpo-train`` console script."""
    cli.run(main, _VERBOSE, on_interrupt=(
        "the checkpoints written so far are kept, and the same command resumes from the "
        "latest (and scores it, if training had finished)"))


if __name__ == "__main__":
    cli_main()

"""Command line: ``python -m c3dpo_jax.main --config=configs/up3d.py --workdir=DIR``.

Trains (resuming from DIR when it holds checkpoints) and evaluates, or with
``--mode=eval`` scores the latest checkpoint in DIR. Any config field can be set with
``--config.section.field=value``; ``--nofigures`` skips the pictures written after training.
"""

import logging as py_logging
import sys

from absl import app, flags, logging
from ml_collections import config_flags

from c3dpo_jax import evaluation, train

_CONFIG = config_flags.DEFINE_config_file(
    "config", None, "Config file (FILE[:ARGS]).", lock_config=True
)
_WORKDIR = flags.DEFINE_string("workdir", None, "Directory for checkpoints, metrics and results.")
_MODE = flags.DEFINE_enum(
    "mode", "train", ["train", "eval"], "Train then evaluate, or evaluate only."
)
_FIGURES = flags.DEFINE_bool(
    "figures", True, "After training, write pictures into WORKDIR/figures (--nofigures: skip)."
)
flags.mark_flags_as_required(["config", "workdir"])


class _QuietLibraries(py_logging.Filter):
    """Drops the INFO chatter of orbax (dozens of lines per checkpoint)."""

    def filter(self, record):
        return record.levelno >= py_logging.WARNING or "/orbax/" not in record.pathname


def _write_figures(config, workdir):
    """A few pictures into workdir/figures; a plotting failure never fails the run."""
    try:
        from c3dpo_jax import visualise
        from c3dpo_jax.data import load_splits

        visualise.write_run_figures(workdir, load_splits(config.data)[1])
    except Exception as err:  # noqa: BLE001 (pictures are optional)
        logging.warning("could not write figures to %s/figures: %r", workdir, err)


def main(argv):
    del argv
    logging.get_absl_handler().addFilter(_QuietLibraries())
    config = _CONFIG.value
    logging.info("config:\n%s", config)
    if _MODE.value == "train":
        results = train.train_and_evaluate(config, _WORKDIR.value)
        if _FIGURES.value:
            _write_figures(config, _WORKDIR.value)
    else:
        results = train.evaluate_checkpoint(config, _WORKDIR.value)
    rows = {"C3DPO": results["final"], **results.get("baselines", {})}
    print(f"\nTest split ({results['final']['n_samples']} samples, protocol "
          f"'{config.data.protocol}'), step {results['final']['step']}:")
    print(evaluation.format_table(rows))
    print(f"results written to {_WORKDIR.value}/eval_results.json")
    sys.stdout.flush()


if __name__ == "__main__":
    app.run(main)

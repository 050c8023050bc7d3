"""Command line: ``python -m c3dpo_jax.main --config=configs/up3d.py --workdir=DIR``.

Trains (resuming from DIR when it holds checkpoints) and evaluates, or with
``--mode=eval`` scores the latest checkpoint in DIR. Any config field can be set with
``--config.section.field=value``.
"""

import logging as py_logging
import sys

from absl import app, flags, logging
from ml_collections import config_flags

from c3dpo_jax import evaluation, train

_CONFIG = config_flags.DEFINE_config_file("config", None, "Config file (FILE[:ARGS]).", lock_config=True)
_WORKDIR = flags.DEFINE_string("workdir", None, "Directory for checkpoints, metrics and results.")
_MODE = flags.DEFINE_enum("mode", "train", ["train", "eval"], "Train then evaluate, or evaluate only.")
flags.mark_flags_as_required(["config", "workdir"])


class _QuietLibraries(py_logging.Filter):
    """Drops the INFO chatter of orbax (dozens of lines per checkpoint)."""

    def filter(self, record):
        return record.levelno >= py_logging.WARNING or "/orbax/" not in record.pathname


def main(argv):
    del argv
    logging.get_absl_handler().addFilter(_QuietLibraries())
    config = _CONFIG.value
    logging.info("config:\n%s", config)
    if _MODE.value == "train":
        results = train.train_and_evaluate(config, _WORKDIR.value)
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

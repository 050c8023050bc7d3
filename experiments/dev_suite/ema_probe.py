"""Would an exponential moving average (EMA) of the parameters stop the degradation?

Trains one suite dataset with the library's loop and keeps, on the host, moving averages of
the parameters with several time constants (``tau`` steps: after every compiled chunk of
``n`` steps, ``ema <- d * ema + (1 - d) * params`` with ``d = exp(-n / tau)``). The averages
never feed back into training, so one run measures every ``tau`` against the same raw
curve. At each test evaluation every average is scored with the run's current BatchNorm
statistics; one JSON record per evaluation goes to ``OUT/ema.jsonl``::

  python experiments/dev_suite/ema_probe.py --dataset=humans --ema_out=runs/ema_humans
"""

import json
import math
import os
import sys

import jax
from absl import flags

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.normpath(os.path.join(HERE, "..", ".."))
sys.path.insert(0, ROOT)

import suite  # noqa: E402
from runner import run_main  # noqa: E402

from c3dpo_jax import inference, lift, resolve, train  # noqa: E402
from c3dpo_jax.data import json_dataset  # noqa: E402

FLAGS = flags.FLAGS
flags.DEFINE_string("dataset", "humans", "a dataset of the suite")
flags.DEFINE_integer("seed", 0, "training seed")
flags.DEFINE_list("taus", ["250", "1000", "2500"], "EMA time constants, in steps")
flags.DEFINE_string("ema_out", os.path.join(ROOT, "runs", "dev_suite_ema"),
                    "workdir of the run")


def main(argv):
    del argv
    c, info = suite.run_config(FLAGS.dataset, FLAGS.seed)
    test_data = json_dataset.load(info["test"])
    train_data = json_dataset.load(info["train"])
    c = resolve.resolve_from_data(c, train_data)  # once, before training
    spec = train.RunSpec.from_config(c)
    options = lift.inference_config(spec.model, spec.inference)
    taus = [float(t) for t in FLAGS.taus]
    emas, last = {}, {"step": 0}
    os.makedirs(FLAGS.ema_out, exist_ok=True)
    path = os.path.join(FLAGS.ema_out, "ema.jsonl")

    def after_chunk(step, state):
        # Copy to the host now: the next chunk donates the state's buffers.
        params = jax.device_get(state.params)
        n = step - last["step"]
        last["step"] = step
        for tau in taus:
            if tau not in emas:
                emas[tau] = params
            else:
                d = math.exp(-n / tau)
                emas[tau] = jax.tree.map(lambda e, p, d=d: d * e + (1 - d) * p, emas[tau], params)

    def after_evaluation(record, state):
        stats = jax.device_get(state.batch_stats)
        row = {"step": record["step"], "raw": record["mpjpe"],
               "raw_mirrored": record.get("mirrored")}
        for tau, params in emas.items():
            variables = {"params": params, "batch_stats": stats}
            used = inference.with_views_mean(options, variables, train_data, spec.model)[0]
            res = inference.evaluate_split(variables, test_data, spec.model, used,
                                           info["protocol"])
            row[f"ema{int(tau)}"] = res["mpjpe"]
        with open(path, "a") as f:
            f.write(json.dumps(row) + "\n")
        print(json.dumps(row), flush=True)

    train.train_and_evaluate(c, FLAGS.ema_out, train.Hooks(after_chunk=after_chunk,
                                                           after_evaluation=after_evaluation))


if __name__ == "__main__":
    run_main(main)

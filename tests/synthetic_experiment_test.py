"""experiments/synthetic/run.py: the table of the README's built-in-dataset results, from the
runs' records (made here by hand: the training itself is the CLI's, tested elsewhere)."""

import json

import pytest


def _run(folder, mpjpe, one_pass, no_flip):
    folder.mkdir(parents=True)
    final = {"step": 5000, "train_s": 120.0, "n_samples": 1000, "mpjpe": mpjpe,
             "mpjpe_orig": no_flip, "mpjpe_global": min(no_flip, 2 * mpjpe),
             "stress": 0.5 * mpjpe, "reprojection": 0.02,
             "mirrored": 0.25}
    baselines = {"fitted mean shape": {"mpjpe": 0.238, "mpjpe_orig": 0.242, "stress": 0.173,
                                       "mpjpe_global": 0.241}}
    (folder / "eval_results.json").write_text(json.dumps({"final": final,
                                                          "baselines": baselines}))
    (folder / "inference.json").write_text(json.dumps({
        "one_pass": dict(final, mpjpe=one_pass),
        "one_handedness": dict(final, mpjpe_orig=1.3, mirrored=0.0)}))


def test_the_table_gives_each_method_over_its_seeds_and_the_baselines(tmp_path, load_script):
    run = load_script("experiments/synthetic/run.py")
    _run(tmp_path / "runs" / "c3dpo__s0", 0.04, 0.07, 0.8)
    _run(tmp_path / "runs" / "c3dpo__s1", 0.06, 0.09, 0.4)
    _run(tmp_path / "runs" / "base__s0", 0.3, 0.31, 0.7)
    text = run.report(str(tmp_path), [0, 1], 2, [], ["--seeds=0,1"])
    rows = {line.split(" | ")[0].lstrip("| "): line for line in text.splitlines()
            if line.startswith("| ")}
    assert rows["C3DPO (`configs/synthetic.py`)"].startswith(
        "| C3DPO (`configs/synthetic.py`) | 2 | 0.100 ± 0.020 | 0.050 ± 0.010 | 0.080 ± 0.010 | "
        "0.600 ± 0.200 |")
    assert ("| C3DPO-base (`configs/synthetic.py:base`) | 1 | 0.600 ± 0.000 | 0.300 ± 0.000 |"
            in text)
    assert "C3DPO-equiv" not in text  # no finished run
    assert rows["fitted mean shape"].startswith(
        "| fitted mean shape | - | 0.241 | 0.238 | - | 0.242 |")
    assert "`python experiments/synthetic/run.py --seeds=0,1`" in text
    assert "Test split (1,000 views)" in text


@pytest.mark.parametrize("flag, want", [
    ("--config.train.num_steps=40", {"train.num_steps": 40}),
    ("--config.data.train_path=a.json", {"data.train_path": "a.json"}),
    ("--nofigures", {}),
])
def test_extra_flags_reach_the_rescoring_config(flag, want, load_script):
    assert load_script("experiments/synthetic/run.py")._overrides([flag]) == want
